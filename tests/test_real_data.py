"""Real measurements made by others (tests/data, with licences): honest checks."""

import re
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from rough_map.psd import patch_roughness

DATA = Path(__file__).parent / "data"


@lru_cache(maxsize=1)
def _texture_scan() -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) and depth (m) of the CAPTIF scan; blank dropouts are NaN."""
    path = DATA / "captif_aylesbury_station_0.dat"
    with open(path, encoding="latin-1") as fh:
        skip = next(i for i, line in enumerate(fh) if line.startswith("*****DATA")) + 2
    a = np.genfromtxt(path, delimiter="\t", skip_header=skip, usecols=(0, 1, 2), encoding="latin-1")
    depth = a[:, 2].copy()
    depth[np.isclose(depth, 47.5)] = np.nan  # the reference plates saturate the sensor
    return a[:, 1] / 1000.0, depth / 1000.0


def _bin(distance, depth, spacing, start=0.1, stop=1.85):
    edges = np.arange(start, stop, spacing)
    idx = np.digitize(distance, edges) - 1
    ok = (idx >= 0) & (idx < len(edges) - 1) & np.isfinite(depth)
    s = np.bincount(idx[ok], depth[ok], minlength=len(edges) - 1)
    c = np.bincount(idx[ok], minlength=len(edges) - 1)
    return np.where(c > 0, s / np.maximum(c, 1), np.nan)


def test_road_profile_is_iso_class_a():
    """A measured pavement profile: ISO 8608 (w fixed at -2) puts it in class A."""
    d = np.loadtxt(DATA / "road_profile_1.txt")
    assert d.shape == (2177, 2)
    assert np.allclose(np.diff(d[:, 0]), 0.25)
    iso = patch_roughness(d[:2176, 1].reshape(8, 272), 0.25, waviness=-2.0)
    assert iso.iso_class == "A"
    free = patch_roughness(d[:2176, 1].reshape(8, 272), 0.25)
    assert free.w < -2.0  # pavements fall faster than the ISO slope at long wavelengths


def test_texture_scan_at_half_a_millimetre_is_a_power_law():
    distance, depth = _texture_scan()
    h = _bin(distance, depth, 0.0005)
    r = patch_roughness(h[None], 0.0005, min_profiles=1, max_gap=0.01, max_gap_fraction=0.3)
    assert -2.4 < r.w < -1.7


def test_texture_scan_at_8_mm_is_flat_and_near_the_sensitivity_floor():
    """Chipseal texture is below the 8 mm grid: the spectrum is nearly white, rms ~2 mm."""
    distance, depth = _texture_scan()
    h = _bin(distance, depth, 0.008)
    r = patch_roughness(h[None], 0.008, min_profiles=1, max_gap=0.02)
    assert r.w > -1.2
    assert r.rms == pytest.approx(2.2e-3, abs=0.7e-3)


@pytest.mark.parametrize("name", ["ground_with_crs.las", "autzen_trim.laz"])
def test_a_georeferenced_lidar_file_says_where_it_lies(name: str, capsys) -> None:
    """The real LAS/LAZ files are in a projected CRS, hundreds of km from the vehicle frame's
    origin: the one line says how many points fell on the patch, where the patch was looked
    for and where the cloud is, and what to do (issue 30)."""
    from rough_map.cli.main import main

    assert main(["features", str(DATA / name)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "..." not in err and "…" not in err
    assert "0 of " in err and "points over the patch (x 0.552..1.45, y -0.448..0.448 m)" in err
    crs = {"ground_with_crs.las": "EPSG:32104",
           "autzen_trim.laz": "NAD_1983_HARN_Lambert_Conformal_Conic"}[name]  # fmt: skip
    assert re.search(rf"they lie around x \d{{6}}\.\d, y \d{{6}}\.\d m in {crs}: ", err), err
    assert err.rstrip().endswith("read it at a pose: --at X,Y[,YAW]")


def test_a_cloud_in_millimetres_and_a_frame_of_one_say_so() -> None:
    from rough_map.errors import PatchError
    from rough_map.features import cloud_roughness, frame_features

    rng = np.random.default_rng(0)
    mm = np.column_stack(
        [rng.uniform(500, 1500, 40_000), rng.uniform(-450, 450, 40_000), rng.normal(0, 1, 40_000)]
    )
    with pytest.raises(PatchError, match=r"they lie at x 500..1500, .*in millimetres\?"):
        cloud_roughness(mm)
    row, _, _ = frame_features(mm)  # a frame of a traverse: its reason, in features.csv
    assert not row["valid"] and "points over the patch" in row["reason"]
    assert "in millimetres?" in row["reason"]
