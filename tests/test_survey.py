"""Roughness rasters of a whole surface (rough_map.survey, rough_map.io.raster, `survey`):
known answers on synthetic ISO surfaces, the window cells where the windows are, nodata
where the survey has none, the same numbers from a GeoTIFF, a .npy grid and any -j, and
one-line errors on hostile rasters."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from surfaces import write_height_geotiff

from rough_map.config import Crs
from rough_map.errors import FileFormatError, InputError
from rough_map.io.raster import open_height_raster
from rough_map.io.truth_raster import write_dem_geotiff
from rough_map.iso8608 import synthesize_surface
from rough_map.survey import SurveySpec, roughness_raster, survey_geometry
from rough_map.types import HeightField

B = 0.008  # m, the paper's grid step
PHI0, W = 64e-6, -2.5  # ISO class D, a steep spectrum
X0, Y0 = 500_000.0, 4_100_000.0  # UTM 33N, m


def _surface(shape: tuple[int, int] = (768, 896), seed: int = 1) -> np.ndarray:
    return synthesize_surface(shape, B, PHI0, W, seed=seed)


def _north_up(west: float, north: float, cell: float) -> Affine:
    return Affine(cell, 0.0, west, 0.0, -cell, north)


def _geotiff(
    path: Path, z: np.ndarray, *, crs: str | None = "EPSG:32633", transform: Affine | None = None
) -> Path:
    return write_height_geotiff(path, z, crs, transform or _north_up(X0, Y0, B))


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    z = _surface()
    z[:150, :250] = np.nan  # a corner the survey did not reach
    return _geotiff(tmp_path_factory.mktemp("dem") / "dem.tif", z), z


def test_windows_read_the_surface_they_were_made_from(dem: tuple[Path, np.ndarray]) -> None:
    path, _ = dem
    grid = roughness_raster(open_height_raster(path))
    ok = grid["valid"] > 0
    assert ok.sum() > 0.8 * ok.size
    assert abs(np.log(np.median(grid["R"][ok]) / PHI0)) < 0.15
    assert abs(np.median(grid["w"][ok]) - W) < 0.08
    assert grid.geometry.crs.code == "EPSG:32633"
    # ISO class D is index 3; a steep -2.5 surface at D reads within a class of it
    assert set(np.unique(grid["iso_class"][ok])) <= {2.0, 3.0, 4.0}


def test_each_window_cell_sits_on_its_window(dem: tuple[Path, np.ndarray]) -> None:
    """Window (i, j) of 112 cells every 56 spans raster rows 56 i .. 56 i + 111: its cell's
    centre is the window's centre, and the nodata corner is nodata in the output."""
    path, z = dem
    raster = open_height_raster(path)
    geo = survey_geometry(raster, SurveySpec())
    assert geo.resolution == pytest.approx(56 * B) and geo.shape == (
        (768 - 112) // 56 + 1,
        (896 - 112) // 56 + 1,
    )
    grid = roughness_raster(raster)
    rows, cols = geo.shape
    for i, j in ((0, 0), (3, 7), (rows - 1, cols - 1)):
        x, y = geo.cell_center([rows - 1 - i], [j])  # map rows run north
        assert x[0] == pytest.approx(X0 + (56 * j + 56) * B)
        assert y[0] == pytest.approx(Y0 - (56 * i + 56) * B)
        window = z[56 * i : 56 * i + 112, 56 * j : 56 * j + 112]
        unread = np.isnan(window).all(axis=1).mean() > 0.5
        assert (grid["valid"][rows - 1 - i, j] == 0) == unread, (i, j)


def test_geotiff_npy_and_jobs_give_the_same_numbers(
    dem: tuple[Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Also with a strip per band of windows: this process then measures some of them
    itself while the worker has its queue, and the strips still come in order."""
    import rough_map.survey as survey

    path, z = dem
    one = roughness_raster(open_height_raster(path))
    two = roughness_raster(open_height_raster(path), n_jobs=2)
    monkeypatch.setattr(survey, "_STRIP_ROWS", 1)
    many = roughness_raster(open_height_raster(path), n_jobs=2)
    for name in one.layers:
        assert np.array_equal(one[name], two[name], equal_nan=True), name
        assert np.array_equal(one[name], many[name], equal_nan=True), name
    np.save(tmp_path / "dem.npy", z.astype(np.float32))
    grid = roughness_raster(
        open_height_raster(tmp_path / "dem.npy", spacing=B, origin=(X0, Y0), crs="EPSG:32633")
    )
    assert grid.geometry == one.geometry
    ok = one["valid"] > 0
    np.testing.assert_array_equal(grid["valid"], one["valid"])
    np.testing.assert_allclose(grid["R"][ok], one["R"][ok], rtol=1e-9)


def test_profiles_along_the_columns_are_the_rows_of_the_transpose(tmp_path: Path) -> None:
    z = _surface((448, 448), seed=4)
    np.save(tmp_path / "z.npy", z)
    np.save(tmp_path / "t.npy", np.ascontiguousarray(z.T))
    cols = roughness_raster(
        open_height_raster(tmp_path / "z.npy", spacing=B), SurveySpec(direction="columns")
    )
    rows = roughness_raster(open_height_raster(tmp_path / "t.npy", spacing=B))
    # window (i, j) of z is window (j, i) of its transpose; the map's rows run north
    a = cols["R"][::-1]
    b = rows["R"][::-1].T
    np.testing.assert_allclose(a, b, rtol=1e-12)
    both = roughness_raster(
        open_height_raster(tmp_path / "z.npy", spacing=B), SurveySpec(both_directions=True)
    )
    ok = both["valid"] > 0
    # an isotropic surface: the same roughness either way, about
    assert abs(np.median(both["anisotropy"][ok])) < 0.3
    np.testing.assert_allclose(both["R_across"][::-1], cols["R"][::-1], rtol=1e-12)


@settings(max_examples=8, deadline=None)
@given(
    a=st.floats(-0.2, 0.2),
    b=st.floats(-0.2, 0.2),
    c=st.floats(-100.0, 100.0),
)
def test_a_tilted_or_raised_survey_reads_the_same(a: float, b: float, c: float) -> None:
    """Every profile is detrended: a plane under the surface changes no window's R or w."""
    z = _surface((224, 224), seed=2)
    yy, xx = np.mgrid[0:224, 0:224] * B
    with tempfile.TemporaryDirectory() as tmp:
        np.save(Path(tmp) / "z.npy", z)
        np.save(Path(tmp) / "p.npy", z + a * xx + b * yy + c)
        flat = roughness_raster(open_height_raster(Path(tmp) / "z.npy", spacing=B))
        tilted = roughness_raster(open_height_raster(Path(tmp) / "p.npy", spacing=B))
    # to rounding: a plane of tens of cm leaves the mm of roughness ~14 digits
    np.testing.assert_allclose(tilted["R"], flat["R"], rtol=1e-4)
    np.testing.assert_allclose(tilted["w"], flat["w"], atol=1e-4)


def test_the_command_writes_the_rasters_as_a_set(dem: tuple[Path, np.ndarray], tmp_path: Path):
    path, _ = dem
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    proc = subprocess.run(
        [sys.executable, "-m", "rough_map", "survey", str(path), "--out", str(out), "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["crs"] == "EPSG:32633" and summary["window_m"] == pytest.approx(0.896)
    assert summary["stride_m"] == pytest.approx(0.448)
    assert (out / "notes.txt").read_text() == "mine"
    with rasterio.open(out / "roughness.tif") as ds:
        assert ds.crs.to_epsg() == 32633
        assert ds.transform.a == pytest.approx(0.448)
        assert ds.transform.c == pytest.approx(X0 + 28 * B)  # the first cell's west edge
        assert ds.transform.f == pytest.approx(Y0 - 28 * B)
        bands = {d: i + 1 for i, d in enumerate(ds.descriptions)}
        R = ds.read(bands["R"], masked=True)
        assert R.mask[0, 0] and not R.mask[-1, -1]  # nodata where the survey has none
    with rasterio.open(out / "roughness_class.tif") as ds:
        assert ds.dtypes[0] == "uint8" and ds.nodata == 255
        assert len(ds.colormap(1)) >= 8
        assert ds.tags(1)["CLASS_3"] == "D"
    lines = (out / "roughness.csv").read_text().splitlines()
    assert lines[0].startswith("x,y,R,w,") and len(lines) - 1 == summary["windows_read"]
    assert (out / "roughness_R.png").stat().st_size > 1000


def test_a_raster_in_feet_reads_in_metres_and_writes_in_feet(tmp_path: Path) -> None:
    """A DEM in US survey feet (cells and heights): the estimator sees metres, the output
    is in the DEM's CRS and units."""
    foot = 1200 / 3937
    z = _surface((336, 336), seed=6)
    metres = roughness_raster(open_height_raster(_geotiff(tmp_path / "m.tif", z)))
    ft = open_height_raster(
        _geotiff(
            tmp_path / "ft.tif",
            z / foot,
            crs="EPSG:2229",
            transform=_north_up(6_000_000.0, 2_000_000.0, B / foot),
        )
    )
    assert ft.spacing == pytest.approx(B) and ft.unit_m == pytest.approx(foot)
    feet = roughness_raster(ft)
    np.testing.assert_allclose(feet["R"], metres["R"], rtol=1e-4)
    assert feet.geometry.resolution == pytest.approx(56 * B / foot)
    assert feet.geometry.origin[0] == pytest.approx(6_000_000.0 + 28 * B / foot)


def test_hostile_rasters_get_one_line(tmp_path: Path) -> None:
    z = _surface((128, 128), seed=3)
    geo = _geotiff(tmp_path / "deg.tif", z, crs="EPSG:4326", transform=_north_up(10, 45, 1e-7))
    with pytest.raises(FileFormatError, match=r"deg\.tif \[crs\]: in a geographic CRS \(degrees\)"):
        open_height_raster(geo)
    rotated = Affine(B, 0.001, X0, 0.0, -B, Y0)
    with pytest.raises(FileFormatError, match=r"rot\.tif \[transform\]: not a north-up raster"):
        open_height_raster(_geotiff(tmp_path / "rot.tif", z, transform=rotated))
    oblong = Affine(B, 0.0, X0, 0.0, -2 * B, Y0)
    with pytest.raises(FileFormatError, match=r"long\.tif \[transform\]: cells of 0.008 x 0.016"):
        open_height_raster(_geotiff(tmp_path / "long.tif", z, transform=oblong))
    good = _geotiff(tmp_path / "good.tif", z).read_bytes()
    (tmp_path / "cut.tif").write_bytes(good[: len(good) // 2])
    with pytest.raises(FileFormatError, match=r"cut\.tif: not a readable raster"):
        roughness_raster(open_height_raster(tmp_path / "cut.tif"))
    (tmp_path / "empty.tif").write_bytes(b"")
    with pytest.raises(FileFormatError, match=r"empty\.tif"):
        open_height_raster(tmp_path / "empty.tif")
    np.save(tmp_path / "cube.npy", np.zeros((4, 4, 4)))
    with pytest.raises(FileFormatError, match=r"cube\.npy \[shape\]: expected a 2-D numeric"):
        open_height_raster(tmp_path / "cube.npy", spacing=B)
    np.save(tmp_path / "z.npy", z)
    with pytest.raises(InputError, match=r"z\.npy: a \.npy height grid needs its spacing"):
        open_height_raster(tmp_path / "z.npy")
    with pytest.raises(InputError, match=r"spacing must be a cell size in m > 0, got nan"):
        open_height_raster(tmp_path / "z.npy", spacing=float("nan"))
    with pytest.raises(InputError, match=r"good\.tif: a GDAL raster gives its own cell size"):
        open_height_raster(tmp_path / "good.tif", spacing=B)
    raster = open_height_raster(tmp_path / "z.npy", spacing=B)
    with pytest.raises(InputError, match=r"holds 5 cells of 0.008 m; the estimator needs"):
        roughness_raster(raster, SurveySpec(window=0.04))
    with pytest.raises(InputError, match=r"z\.npy: 128 x 128 cells of 0.008 m hold no window"):
        roughness_raster(raster, SurveySpec(window=2.0))
    with pytest.raises(InputError, match=r"direction must be one of"):
        SurveySpec(direction="diagonal")


@pytest.mark.parametrize(
    "crs",
    [
        {"code": "local"},
        {"code": "local", "origin": {"lat": 40.3515, "lon": 18.175}},
        {"code": "EPSG:32633"},
    ],
)
def test_a_crs_reads_back_from_its_raster_form(crs: dict) -> None:
    value = Crs.from_any(crs)
    assert Crs.from_rasterio(value.rasterio()) == value


def test_the_simulated_dem_is_the_world_every_8_mm(tmp_path: Path) -> None:
    """``simulate --dem``: the world's heights every 4th cell of 2 mm, placed where they are
    (cell centres on the world's), read back by the survey in the traverse's CRS."""
    rng = np.random.default_rng(0)
    heights = rng.normal(0, 1e-3, size=(301, 481))
    world = HeightField(heights, 0.002, origin=(-0.4, -0.3))
    crs = Crs.from_any({"code": "local", "origin": {"lat": 40.0, "lon": 18.0}})
    path = write_dem_geotiff(world, tmp_path / "dem.tif", crs.rasterio(), 0.008)
    raster = open_height_raster(path)
    assert raster.shape == (76, 121) and raster.spacing == pytest.approx(0.008)
    assert raster.crs == crs
    dem = raster.rows(0, raster.shape[0])
    np.testing.assert_allclose(dem[::-1], heights[::4, ::4].astype(np.float32), rtol=0, atol=0)
    # the west edge is half a DEM cell west of the world's first centre
    assert raster.origin[0] == pytest.approx(-0.4 - 0.004)
    assert raster.origin[1] == pytest.approx(-0.3 + 300 * 0.002 + 0.004)


def test_integer_heights_with_scale_and_offset_and_an_ascii_grid(tmp_path: Path) -> None:
    """Integer heights are read through the band's scale and offset (mm steps here), with
    their nodata as missing cells; an Esri ASCII grid reads the same heights."""
    z = _surface((240, 240), seed=5)
    steps = np.round((z - 0.0) / 0.0001).astype(np.int16)
    steps[:10, :10] = -32768
    with rasterio.open(
        tmp_path / "int.tif",
        "w",
        driver="GTiff",
        width=240,
        height=240,
        count=1,
        dtype="int16",
        crs="EPSG:32633",
        transform=_north_up(X0, Y0, B),
        nodata=-32768,
    ) as ds:
        ds.write(steps, 1)
        ds.scales = (0.0001,)
        ds.offsets = (100.0,)
    got = open_height_raster(tmp_path / "int.tif").rows(0, 240)
    assert np.isnan(got[:10, :10]).all()
    np.testing.assert_allclose(got[10:], 100.0 + steps[10:] * 0.0001, rtol=0, atol=1e-9)
    with rasterio.open(
        tmp_path / "z.asc",
        "w",
        driver="AAIGrid",
        width=240,
        height=240,
        count=1,
        dtype="float32",
        transform=_north_up(X0, Y0, B),
    ) as ds:
        ds.write(z.astype(np.float32), 1)
    asc = open_height_raster(tmp_path / "z.asc")
    assert asc.crs.code == "local" and asc.spacing == pytest.approx(B)
    np.testing.assert_allclose(asc.rows(0, 240), z.astype(np.float32), rtol=0, atol=1e-6)


def test_a_header_declaring_more_cells_than_the_file_holds_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "sparse.tif"
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=200_000,
        height=200_000,
        count=1,
        dtype="float32",
        crs="EPSG:32633",
        transform=_north_up(X0, Y0, B),
        tiled=True,
        sparse_ok=True,
    ):
        pass
    assert path.stat().st_size < 16 << 20  # 4e10 cells declared, none written
    with pytest.raises(FileFormatError, match=r"sparse\.tif \[size\]: declares 200000 x 200000"):
        open_height_raster(path)


@pytest.mark.slow
def test_a_survey_on_a_dask_cluster_reads_as_one_process(
    dem: tuple[Path, np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two worker processes of a local cluster measure the strips (in this process
    measuring is made to fail) and give the numbers of one process; an unreachable
    scheduler is one line."""
    distributed = pytest.importorskip("distributed")
    import rough_map.survey as survey_mod

    path, _ = dem
    raster = open_height_raster(path)
    one = roughness_raster(raster)

    def not_here(*args: object) -> None:
        raise AssertionError("measured in the client, not on a worker")

    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        monkeypatch.setattr(survey_mod, "_band", not_here)
        grid = roughness_raster(raster, scheduler=cluster.scheduler_address)
    for name in one.layers:
        assert np.array_equal(grid[name], one[name], equal_nan=True), name
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        roughness_raster(raster, scheduler="tcp://127.0.0.1:9")


DATA = Path(__file__).parent / "data"


@pytest.mark.parametrize(
    ("name", "epsg", "spacing"),
    [("ground_with_crs.las", 32104, 0.21), ("autzen_trim.laz", 2994, 1.8)],
)
def test_real_airborne_lidar_gives_rasters_in_its_own_crs(
    name: str, epsg: int, spacing: float, tmp_path: Path
) -> None:
    """Real airborne clouds in feet (one with an EPSG code, one with only a WKT): their
    ground points are gridded at the spacing their density supports (2 points per cell),
    the window is 32 such cells, and the rasters lie over the cloud, in its CRS."""
    import laspy

    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "rough_map", "survey", str(DATA / name), "--out", str(out)]
        + ["--json", "--no-png"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["spacing_m"] == pytest.approx(spacing)
    assert summary["window_m"] == pytest.approx(32 * spacing)
    assert summary["gridding"] == "cell_mean" and "ground (class 2) points" in summary["gridded"]
    assert summary["windows_read"] >= 5
    header = laspy.read(DATA / name).header
    with rasterio.open(out / "roughness.tif") as ds:
        assert ds.crs.to_epsg() == epsg
        b = ds.bounds
        assert header.mins[0] <= b.left < b.right <= header.maxs[0]
        assert header.mins[1] <= b.bottom < b.top <= header.maxs[1]
        R = ds.read(ds.descriptions.index("R") + 1, masked=True)
        assert np.all((R.compressed() > 0) & np.isfinite(R.compressed()))
    with rasterio.open(out / "roughness_class.tif") as ds:
        assert ds.crs.to_epsg() == epsg


def test_a_world_frame_cloud_is_gridded_by_its_density(tmp_path: Path) -> None:
    """Any cloud in a world frame (here .npy of N x 3 points and the same as .ply), in the
    CRS given: gridded at sqrt(2 / density) rounded up, read on that grid, the same numbers
    from either file; a .npy with a spacing is still a grid of heights."""
    from rough_map.io.pointcloud import write_cloud

    rng = np.random.default_rng(4)
    n = 120_000  # over 12 m x 6 m: 1,667 points per m^2, 2 per 3.5 cm cell
    x, y = X0 + rng.uniform(0, 12, n), Y0 - rng.uniform(0, 6, n)
    fine = synthesize_surface((600, 1200), 0.01, PHI0, W, seed=3)
    rows, cols = ((Y0 - y) / 0.01).astype(int), ((x - X0) / 0.01).astype(int)
    z = fine[rows.clip(0, 599), cols.clip(0, 1199)]
    points = np.column_stack([x, y, z])
    np.save(tmp_path / "cloud.npy", points)
    write_cloud(tmp_path / "cloud.ply", points)
    readings = []
    for name in ("cloud.npy", "cloud.ply"):
        raster = open_height_raster(tmp_path / name, crs="EPSG:32633")
        assert raster.crs.code == "EPSG:32633" and raster.gridding == "cell_mean"
        assert raster.spacing == pytest.approx(0.035)  # sqrt(2 / 1667) = 0.0346 m
        assert "gridded at 0.035 m" in raster.note
        readings.append(roughness_raster(raster)["R"])
    assert np.array_equal(readings[0], readings[1], equal_nan=True)
    assert np.isfinite(readings[0]).mean() > 0.8
    grid = tmp_path / "three_columns.npy"
    np.save(grid, np.zeros((64, 3)))
    assert open_height_raster(grid, spacing=0.01).shape == (64, 3)
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n1,2,3\n4,5,nan\n")
    with pytest.raises(FileFormatError, match=r"bad\.csv"):
        open_height_raster(bad)
