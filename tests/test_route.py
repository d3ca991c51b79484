"""A route over a height raster (rough_map.io.route, rough_map.patch.surface, `features` and
`map` with --route) and the road it measured as OpenCRG (`map --crg`): frames on the survey's
windows read what the survey reads, any heading reads the same isotropic ground, the CRG
reads back to the map's elevation exactly and surveys as the grid it holds, and bad routes
get one-line errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from surfaces import write_height_geotiff

from rough_map.errors import FileFormatError, InputError
from rough_map.features import read_features, traverse_features
from rough_map.io.crg import read_crg
from rough_map.io.raster import open_height_raster
from rough_map.io.route import read_route, route_traverse
from rough_map.io.traverse import load_traverse, save_traverse
from rough_map.iso8608 import synthesize_surface
from rough_map.patch import PatchSpec
from rough_map.patch.surface import cut_patch, surface_patch_spec
from rough_map.psd import patch_roughness_each
from rough_map.survey import roughness_raster

B = 0.008  # m
X0, Y0 = 500_000.0, 4_100_000.0  # UTM 33N, m: the DEM's north-west corner
GROUND = 250.0  # m above the datum, as a real DEM's heights are


def _dem(path: Path, z: np.ndarray, crs: str = "EPSG:32633", cell: float = B) -> Path:
    return write_height_geotiff(path, z, crs, Affine(cell, 0.0, X0, 0.0, -cell, Y0), "float64")


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> Path:
    z = synthesize_surface((640, 896), B, 64e-6, -2.5, seed=5) + GROUND
    return _dem(tmp_path_factory.mktemp("route") / "dem.tif", z)


@pytest.fixture(scope="module")
def survey(dem: Path):
    return roughness_raster(open_height_raster(dem))


def _csv(path: Path, poses: list[tuple[float, float, float]]) -> Path:
    lines = ["x,y,yaw"] + [f"{float(x)!r},{float(y)!r},{float(a)!r}" for x, y, a in poses]
    path.write_text("\n".join(lines) + "\n")
    return path


def _window_centre(grid, row: int, col: int) -> tuple[float, float]:
    west, south = grid.geometry.origin
    res = grid.geometry.resolution
    return west + (col + 0.5) * res, south + (row + 0.5) * res


def _survey_at(grid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    rows, cols = grid.geometry.cell_of(x, y)
    return grid["R"][rows, cols]


def test_frames_on_the_windows_read_what_the_survey_reads(dem: Path, survey, tmp_path: Path):
    # each vehicle stands 1 m behind a window's centre, heading east: its patch is the window
    poses = []
    for row in (2, 5, 8):
        for col in range(1, survey.shape[1] - 3):
            x, y = _window_centre(survey, row, col)
            poses.append((x - 1.0, y, 0.0))
    feats = traverse_features(route_traverse(dem, _csv(tmp_path / "r.csv", poses)))
    assert feats.valid.all()
    centre = _survey_at(survey, feats["patch_x"], feats["patch_y"])
    assert np.abs(np.log(feats["R"] / centre)).max() < 1e-4  # the fit converges to ~1e-6
    assert np.allclose(feats["patch_x"], [p[0] + 1.0 for p in poses])


def test_a_linestring_every_stride_walks_the_windows(dem: Path, survey, tmp_path: Path):
    """`features DEM --route LINE.geojson`: from 1 m behind a window's centre, a frame every
    0.448 m (the default, the survey's stride) puts each patch on the next window."""
    x, y = _window_centre(survey, 4, 1)
    line = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "LineString", "coordinates": [[x - 1.0, y], [x + 3.5, y]]},
    }
    route = tmp_path / "line.geojson"
    route.write_text(json.dumps(line))
    out = tmp_path / "f.csv"
    proc = subprocess.run(
        [sys.executable, "-m", "rough_map", "features", str(dem), "--route", str(route)]
        + ["--out", str(out), "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["frames"] == 11
    feats = read_features(out)
    ratio = np.log(feats["R"] / _survey_at(survey, feats["patch_x"], feats["patch_y"]))
    assert np.median(np.abs(ratio)) <= 0.05
    assert np.allclose(np.diff(feats["x"]), 0.448)


def _isotropic(shape: tuple[int, int], w: float, seed: int) -> np.ndarray:
    """A Gaussian surface with the same spectrum in every direction: white noise shaped by
    |k|^((w - 1) / 2), so that its straight profiles have PSD ~ Omega^w."""
    rng = np.random.default_rng(seed)
    k = np.hypot(np.fft.fftfreq(shape[0])[:, None], np.fft.rfftfreq(shape[1])[None, :])
    k[0, 0] = np.inf
    noise = rng.normal(size=k.shape) + 1j * rng.normal(size=k.shape)
    z = np.fft.irfft2(noise * k ** ((w - 1) / 2), shape)
    return z / z.std() * 0.004


@pytest.mark.parametrize("yaw", [0.3, math.pi / 4, 2.0])
def test_any_heading_reads_isotropic_ground_as_along_the_rows(tmp_path: Path, yaw: float):
    """Turned patches are resampled by Fourier interpolation: on three isotropic surfaces
    the same 120 places read within 0.2 of the patches along the rows in median ln R (the
    ground's own spread between directions: 0.03-0.13; cubic splines read +0.6 to +0.9)."""
    differences = []
    for seed in (1, 2, 3):
        z = _isotropic((640, 896), -2.5, seed)
        raster = open_height_raster(_dem(tmp_path / f"iso{seed}.tif", z))
        spec = surface_patch_spec(raster, PatchSpec(ahead=0.0))
        rng = np.random.default_rng(3)
        places = [(X0 + rng.uniform(1.2, 5.9), Y0 - rng.uniform(1.2, 3.9)) for _ in range(40)]
        ln_r = {}
        for heading in (0.0, yaw):
            cuts = [cut_patch(raster, (x, y, heading), spec)[0].heights for x, y in places]
            out = patch_roughness_each(np.stack(cuts), spec.spacing, gridding="point")
            ln_r[heading] = np.log([r.R for r in out])
        differences.append(ln_r[yaw] - ln_r[0.0])
    assert abs(np.median(np.concatenate(differences))) < 0.2


def test_a_patch_across_the_rows_is_the_transposed_grid(dem: Path) -> None:
    raster = open_height_raster(dem)
    spec = surface_patch_spec(raster, PatchSpec(ahead=0.0))
    x, y = X0 + 375 * B, Y0 - 312 * B  # a cell's corner: the even patch's nodes on centres
    east, _ = cut_patch(raster, (x, y, 0.0), spec)
    north, _ = cut_patch(raster, (x, y, math.pi / 2), spec)
    nudged, _ = cut_patch(raster, (x, y, math.pi / 2 + 1e-6), spec)  # resampled
    # heading north, the profiles are the raster's columns run northwards, and row 0 (the
    # rightmost) is the easternmost column: north[i, j] = east[j, n - 1 - i]
    assert np.array_equal(north.heights, east.heights.T[::-1])
    assert np.abs(nudged.heights - north.heights).max() < 1e-5


@settings(max_examples=8, deadline=None)
@given(dx=st.floats(-1e4, 1e4), dy=st.floats(-1e4, 1e4))
def test_moving_raster_and_route_together_reads_the_same(dx: float, dy: float) -> None:
    import tempfile

    z = synthesize_surface((160, 320), B, 64e-6, -2.5, seed=2)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        readings = []
        for shift in ((0.0, 0.0), (round(dx / B) * B, round(dy / B) * B)):
            grid = base / f"z{len(readings)}.npy"
            np.save(grid, z)
            origin = (shift[0], shift[1])
            poses = [(origin[0] + 0.103 + 0.3 * k, origin[1] - 0.643, 0.0) for k in range(4)]
            route = _csv(base / f"r{len(readings)}.csv", poses)
            t = route_traverse(grid, route, spacing=B, origin=origin)
            readings.append(traverse_features(t)["R"])
        assert np.allclose(readings[0], readings[1], rtol=1e-9, equal_nan=True)


def test_a_route_traverse_saves_and_loads_and_leaves_the_surface(dem: Path, tmp_path: Path):
    poses = [(X0 + 0.2 + 0.5 * k, Y0 - 2.0, 0.0) for k in range(4)] + [(X0 + 9.0, Y0 - 2.0, 0.0)]
    traverse = route_traverse(dem, _csv(tmp_path / "r.csv", poses))
    save_traverse(traverse, dem.parent)  # beside the raster its surface names
    again = load_traverse(dem.parent)
    assert again.spec.surface is not None and again.spec.surface.path == "dem.tif"
    a, b = traverse_features(traverse), traverse_features(again)
    assert np.array_equal(a["R"], b["R"], equal_nan=True)
    # the last patch lies beyond the raster's east edge (7.17 m): invalid, saying why
    assert list(a.valid) == [True, True, True, True, False]
    assert "off the surface" in str(a["reason"][-1])


def _map_with_crg(dem: Path, route: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rough_map", "map", str(dem), "--route", str(route)]
        + ["--out", str(out), "--crg", "--resolution", "0.02", "--no-png", "--json"],
        capture_output=True,
        text=True,
        timeout=900,
    )


def _elevation_at(map_tif: Path, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    with rasterio.open(map_tif) as ds:
        band = list(ds.descriptions).index("elevation") + 1
        elevation = ds.read(band, masked=True).astype(np.float64).filled(np.nan)
        rows, cols = rasterio.transform.rowcol(ds.transform, x.ravel(), y.ravel(), op=math.floor)
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    inside = (rows >= 0) & (rows < elevation.shape[0]) & (cols >= 0) & (cols < elevation.shape[1])
    z = np.full(rows.shape, np.nan)
    z[inside] = elevation[rows[inside], cols[inside]]
    return z.reshape(x.shape)


@pytest.mark.parametrize("bend", [False, True])
def test_the_map_writes_the_road_it_measured_as_crg(dem: Path, tmp_path: Path, bend: bool):
    """`map DEM --route ROUTE --crg`: the elevation layer along the path as OpenCRG; read
    back, every node holds the elevation of map.tif's cell under it (max |dz| <= 1e-6 m),
    the reference line is curved where the path turns, and the road surveys as the grid it
    holds."""
    coords = [[X0 + 0.3, Y0 - 2.0], [X0 + 3.3, Y0 - 2.0]]
    coords += [[X0 + 5.0, Y0 - 3.0]] if bend else [[X0 + 5.0, Y0 - 2.0]]
    route = tmp_path / "route.geojson"
    route.write_text(json.dumps({"type": "LineString", "coordinates": coords}))
    out = tmp_path / "m"
    proc = _map_with_crg(dem, route, out)
    assert proc.returncode == 0, proc.stderr
    road = read_crg(out / "map_road.crg")
    assert (road.phi is not None) == bend
    x, y = road.node_xy()
    expected = _elevation_at(out / "map.tif", x, y)
    measured = np.isfinite(road.z)
    assert np.array_equal(measured, np.isfinite(expected))  # NaN where unmeasured
    assert measured.mean() > 0.5
    assert np.abs(road.z[measured] - expected[measured]).max() <= 1e-6
    assert np.nanmedian(road.z) == pytest.approx(GROUND, abs=0.1)
    # the road's features are those of the grid it holds
    grid = tmp_path / "road.npy"
    np.save(grid, road.z.T[::-1])  # rows: v from the left, north first; columns: u
    from_crg = roughness_raster(open_height_raster(out / "map_road.crg"))
    from_grid = roughness_raster(open_height_raster(grid, spacing=road.du))
    assert np.array_equal(from_crg["R"], from_grid["R"], equal_nan=True)


def test_bad_routes_get_one_line(dem: Path, tmp_path: Path) -> None:
    cases = {
        "empty.csv": ("", "empty"),
        "noxy.csv": ("a,b\n1,2\n", "no column x, y"),
        "text.csv": ("x,y\n1,2\nfoo,3\n", "line 3, column x: not a number"),
        "nan.csv": ("x,y\n1,2\nnan,3\n", "line 3, column x: NaN or infinite"),
        "back.csv": ("t,x,y,yaw\n0,1,2,0\n0,2,2,0\n", "line 3, column t: time does not increase"),
        "still.csv": ("x,y\n1,2\n1,2\n", "line 3: the pose repeats"),
        "bad.geojson": ("{", "not JSON"),
        "point.geojson": ('{"type": "Point", "coordinates": [1, 2]}', "not Point"),
        "two.geojson": (
            json.dumps(
                {
                    "type": "FeatureCollection",
                    "features": [
                        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": c}}
                        for c in ([[0, 0], [1, 0]], [[0, 1], [1, 1]])
                    ],
                }
            ),
            "one LineString, found 2",
        ),
        "short.geojson": ('{"type": "LineString", "coordinates": [[1, 2]]}', "2 or more"),
        "inf.geojson": ('{"type": "LineString", "coordinates": [[0, 0], [1e999, 0]]}', "NaN or"),
        "flat.geojson": ('{"type": "LineString", "coordinates": [[0, 0], [0, 0]]}', "no length"),
        "far.geojson": ('{"type": "LineString", "coordinates": [[0, 0], [1e12, 0]]}', "beyond"),
        "far.csv": ("x,y\n1,2\n1e15,3\n", "line 3, column x: beyond"),
        "route.kml": ("<kml/>", "a route is a .geojson LineString or a .csv"),
    }
    for name, (text, message) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(FileFormatError, match=message) as err:
            read_route(path)
        assert "\n" not in str(err.value) and name in str(err.value)
    huge = tmp_path / "huge.geojson"
    huge.write_text('{"type": "LineString", "coordinates": [[0, 0], [1e7, 0]]}')
    with pytest.raises(FileFormatError, match="frames; give a larger --every"):
        read_route(huge, every=0.001)
    elsewhere = tmp_path / "wgs84.geojson"
    elsewhere.write_text(
        json.dumps(
            {
                "type": "LineString",
                "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::4326"}},
                "coordinates": [[0, 0], [1, 0]],
            }
        )
    )
    with pytest.raises(InputError, match="the route is in EPSG:4326, the raster in EPSG:32633"):
        route_traverse(dem, elsewhere)
    feet = _dem(tmp_path / "feet.tif", np.zeros((64, 64)), crs="EPSG:2263", cell=0.05)
    with pytest.raises(InputError, match="a route needs a raster in metres"):
        route_traverse(feet, _csv(tmp_path / "ok.csv", [(0.0, 0.0, 0.0)]))


def test_the_command_says_what_is_wrong_in_one_line(dem: Path, tmp_path: Path) -> None:
    route = tmp_path / "bad.csv"
    route.write_text("x,y\n1,2\n")
    proc = subprocess.run(
        [sys.executable, "-m", "rough_map", "features", str(dem), "--route", str(route)]
        + ["--out", str(tmp_path / "f.csv")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "one pose without yaw" in lines[0], proc.stderr
