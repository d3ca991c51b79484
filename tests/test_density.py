"""The same ground reads the same from dense stereo or sparse lidar (issue 12).

Clouds of known continuous surfaces: an isotropic Gaussian field with a power-law spectrum
on a 4 m square at 2 mm (``surfaces.power_law_field``, much longer than the patch, so the
long wavelengths exist as on real ground), sampled at random points by cubic interpolation,
with 0.3 mm of sensor noise. Each cloud reading is compared with the same patch read
exactly: the field band-limited along the profiles to the 8 mm grid's Nyquist and sampled
at the cell centres, read with ``gridding="point"``.
"""

from __future__ import annotations

import math
from functools import cache, lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from surfaces import Field, power_law_field, sample_spline, spline_coefficients
from test_real_data import _texture_scan

from rough_map.errors import InputError, PatchError
from rough_map.features import cloud_roughness, frame_features
from rough_map.patch import (
    Extraction,
    PatchSpec,
    auto_spacing,
    grid_points,
    points_in_patch,
    pooled_rows,
    spacing_ladder,
)
from rough_map.psd import patch_roughness

SPEC = PatchSpec()
FINE = 0.002  # m, the field's grid
N_FINE = 2048  # 4.1 m square
NOISE = 0.0003  # m, sensor noise of every point
#: Patch positions (column, row offsets in fine cells) within a field: 12 apart.
OFFSETS = [(int(a), int(b)) for a in (0, 500, 1000, 1500) for b in (0, 640, 1280)]
#: Sparse clouds scatter more from patch to patch: their medians take 64 patches, on two
#: fields, half overlapping (their sampling noise is independent).
SPARSE = [
    (seed, (a, b)) for seed in (0, 1) for a in range(0, 2048, 256) for b in (0, 512, 1024, 1536)
]


def _band_R(w: float, rms: float = 0.003) -> float:
    """R (m^3/rad) of a power law with band rms ``rms`` m over the 8 mm patch's band."""
    o1, o2 = 2 * math.pi / (SPEC.n * SPEC.spacing), math.pi / SPEC.spacing
    return rms**2 * (w + 1) / (o2 ** (w + 1) - o1 ** (w + 1))


def _field(w: float, seed: int = 0) -> Field:
    return power_law_field(N_FINE, FINE, _band_R(w), w, seed=int(-w * 10) + 100 * seed)


@lru_cache(maxsize=4)
def _band_limited(w: float, seed: int = 0, spacing: float = SPEC.spacing) -> np.ndarray:
    """The field with every wavenumber along x above the Nyquist wavenumber of a grid of
    ``spacing`` m (8 mm by default) removed."""
    f = _field(w, seed).heights
    spec = np.fft.rfft(f, axis=1)
    kx = 2 * np.pi * np.fft.rfftfreq(N_FINE, FINE)
    spec[:, kx > math.pi / spacing] = 0
    return np.fft.irfft(spec, n=N_FINE, axis=1)


def _centres() -> tuple[np.ndarray, np.ndarray]:
    """x and y in m of the patch's cell centres."""
    k = np.arange(SPEC.n) + 0.5
    return SPEC.x0 + k * SPEC.spacing, SPEC.y0 + k * SPEC.spacing


def _origin(offset: tuple[int, int]) -> tuple[float, float]:
    """Field coordinates (m) of the vehicle origin for a patch offset: cell centres fall
    on the field's nodes."""
    x, y = _centres()
    return offset[0] * FINE - (x[0] - FINE / 2) + FINE / 2, offset[1] * FINE - y[0]


def exact(w: float, offset: tuple[int, int], field: int = 0):
    """The patch read exactly (point samples of the band-limited field)."""
    fx, fy = _origin(offset)
    x, y = _centres()
    ix = np.rint((x + fx) / FINE).astype(int) % N_FINE
    iy = np.rint((y + fy) / FINE).astype(int) % N_FINE
    return patch_roughness(_band_limited(w, field)[np.ix_(iy, ix)], SPEC.spacing)


def exact_at(w: float, offset: tuple[int, int], spec: PatchSpec, field: int = 0):
    """The patch read exactly on the coarser grid ``spec`` of the same square: the field
    band-limited to its Nyquist wavenumber, sampled (cubic interpolation) at its cell
    centres. What a sparse cloud gridded at that step can at best read."""
    fx, fy = _origin(offset)
    k = np.arange(spec.n) + 0.5
    x, y = spec.x0 + k * spec.spacing + fx, spec.y0 + k * spec.spacing + fy
    coords = np.stack(np.meshgrid(y, x, indexing="ij")) / FINE
    heights = sample_spline(band_limited_spline(w, field, spec.spacing), coords)
    return patch_roughness(heights, spec.spacing)


@lru_cache(maxsize=8)
def band_limited_spline(w: float, seed: int = 0, spacing: float = SPEC.spacing) -> np.ndarray:
    """Spline coefficients of :func:`_band_limited`, for cubic sampling of it."""
    return spline_coefficients(_band_limited(w, seed, spacing))


@cache
def band_errors(w: float, spec: PatchSpec) -> np.ndarray:
    """(ln(R / R_exact), w - w_exact) of the sparse rows' patches read exactly on the
    coarser grid ``spec``, against their exact 8 mm reading: what the band alone costs."""
    out = []
    for field, off in SPARSE:
        ref, r = exact(w, off, field), exact_at(w, off, spec, field)
        out.append((math.log(r.R / ref.R), r.w - ref.w))
    return np.array(out)


def random_places(rng: np.random.Generator, per_cell: float) -> tuple[np.ndarray, np.ndarray]:
    """x and y in m of random points over the patch (and 2 cm around it), ``per_cell``
    points per 8 mm cell on average."""
    margin = 0.02
    side = SPEC.n * SPEC.spacing + 2 * margin
    count = rng.poisson(per_cell * side**2 / SPEC.spacing**2)
    x = SPEC.x0 - margin + side * rng.random(count)
    y = SPEC.y0 - margin + side * rng.random(count)
    return x, y


def cloud(
    w: float,
    offset: tuple[int, int],
    per_cell: float,
    seed: int,
    field: int = 0,
    stretch: float = 1.0,
) -> np.ndarray:
    """A random cloud over the patch (and 2 cm around it): ``per_cell`` points per 8 mm
    cell on average, cubic interpolation of the field, 0.3 mm noise. With ``stretch`` the
    field is stretched across the profiles: the height at (x, y) is the field's at
    (x, stretch * y) (``tests/test_lateral.py``)."""
    rng = np.random.default_rng(seed)
    x, y = random_places(rng, per_cell)
    fx, fy = _origin(offset)
    z = _field(w, field).sample(x + fx, stretch * y + fy) + NOISE * rng.standard_normal(x.size)
    return np.column_stack([x, y, z])


def _read(points: np.ndarray, auto: bool = False):
    return cloud_roughness(points, Extraction(use_imu=False, auto_spacing=auto))


@cache
def errors(w: float, per_cell: float, auto: bool = False) -> np.ndarray:
    """(ln(R / R_exact), w - w_exact) of every patch, shape (patches, 2)."""
    out = []
    cases = SPARSE if auto else [(0, off) for off in OFFSETS]
    for i, (field, off) in enumerate(cases):
        ref = exact(w, off, field)
        pts = cloud(w, off, per_cell, seed=1000 * i + int(10 * per_cell), field=field)
        _, r = _read(pts, auto)
        out.append((math.log(r.R / ref.R), r.w - ref.w))
    return np.array(out)


WAVINESS = [-2.0, -2.4, -2.8]


@pytest.mark.parametrize("w", WAVINESS)
def test_exact_reading_is_unbiased(w):
    """The reference itself: the estimator on exact grids of these fields."""
    f = _field(w)
    lnr = [math.log(exact(w, off).R / f.R) for off in OFFSETS]
    dw = [exact(w, off).w - w for off in OFFSETS]
    assert abs(np.median(lnr)) < 0.2
    assert abs(np.median(dw)) < 0.05


@pytest.mark.parametrize("w", WAVINESS)
@pytest.mark.parametrize("per_cell", [50, 12, 4])
def test_dense_clouds_read_like_the_exact_patch(w, per_cell):
    """Stereo-like densities: the median ln(R / R_exact) and w - w_exact are within 0.15
    and 0.05, and so are the median absolute differences (the issue's figures).

    At 4 points per cell the sensor noise (0.3 mm / 2) buries the top of the band of steep
    ground (w -2.8) and 2 % of the cells are empty: the fit runs on into the noise with
    weights that follow its variance, and the floor and the terrain's power both allow
    for the cells the gap policy filled (``rough_map.psd._corrections.gap_filled_floor``).
    """
    e = errors(w, per_cell)
    assert abs(np.median(e[:, 0])) <= 0.15 and abs(np.median(e[:, 1])) <= 0.05
    assert np.median(np.abs(e[:, 0])) <= 0.15, np.median(np.abs(e), axis=0)
    assert np.median(np.abs(e[:, 1])) <= 0.05, np.median(np.abs(e), axis=0)


@pytest.mark.parametrize("w", WAVINESS)
def test_a_gappy_fixed_grid_reads_like_the_exact_patch(w):
    """2 points per cell on the 8 mm grid (--spacing 0.008 rather than auto): 13 % of the
    cells are empty and filled by interpolation, which takes up to half the terrain's power
    at the top of the band. Corrected for that, the patches read within 0.25 of the exact
    ones in median ln R (+0.11 at w -2.0, within 0.05 at w -2.4 and -2.8, over 64
    patches; runs of two empty cells, which the model does not describe, remain). Without
    the correction the median was +0.4 to +0.6."""
    out = []
    for i, off in enumerate(OFFSETS):
        ref = exact(w, off)
        _, r = _read(cloud(w, off, 2, seed=7000 + i))
        out.append((math.log(r.R / ref.R), r.w - ref.w))
    e = np.array(out)
    assert abs(np.median(e[:, 0])) <= 0.25 and abs(np.median(e[:, 1])) <= 0.07, e
    assert np.median(np.abs(e[:, 0])) <= 0.3, np.median(np.abs(e), axis=0)


@pytest.mark.parametrize("w", WAVINESS)
def test_4_and_50_points_per_cell_agree_within_15_percent(w):
    """The same patches at 4 and at 50 points per cell, each against the exact reading."""
    diff = np.median(errors(w, 4)[:, 0] - errors(w, 50)[:, 0])
    assert abs(diff) <= math.log(1.15)


@pytest.mark.parametrize("w", WAVINESS)
@pytest.mark.parametrize("per_cell", [2, 1, 0.5])
def test_sparse_clouds_with_auto_spacing_stay_comparable(w, per_cell):
    """Lidar-like densities: the grid coarsens and R stays within 25 %, w within 0.1, of
    the exact 8 mm reading (medians over the patches)."""
    e = errors(w, per_cell, auto=True)
    assert abs(np.median(e[:, 0])) <= math.log(1.25), np.median(e, axis=0)
    assert abs(np.median(e[:, 1])) <= 0.1, np.median(e, axis=0)


@cache
def truth_errors(w: float) -> np.ndarray:
    """(ln(R / R_exact), w - w_exact) of a reading that knew the ground: the field's own R
    and w, against each sparse patch's exact 8 mm reading."""
    out = []
    for field, off in SPARSE:
        ref, f = exact(w, off, field), _field(w, field)
        out.append((math.log(f.R / ref.R), f.w - ref.w))
    return np.array(out)


@pytest.mark.parametrize("w", WAVINESS)
def test_single_patches_scatter_about_the_ground_as_much_as_sparse_readings_do(w):
    """What "within 25 % of the exact reading" can mean for one patch. The exact 8 mm
    reading of a 0.9 m patch is itself a sample: it scatters about the ground's true R by a
    median |ln R| of 0.21-0.25 (and 0.04-0.05 in w), so even a reading that knew the true R
    and w would differ from single exact patches by that much, around ln 1.25 = 0.22. A
    sparse reading shares the exact one's low wavenumbers, so it is about as far from it as
    the truth is at 1 point per cell (within 0.05), and within 0.15 farther at 0.5 (0.07-0.12
    measured). The criterion holds as the median over patches (above), as the issue's own
    table is stated."""
    truth = truth_errors(w)
    assert abs(np.median(truth[:, 0])) <= 0.05 and abs(np.median(truth[:, 1])) <= 0.02
    spread = np.median(np.abs(truth[:, 0]))
    assert 0.15 <= spread <= 0.3, spread
    for per_cell, margin in ((1, 0.05), (0.5, 0.15)):
        sparse = np.median(np.abs(errors(w, per_cell, auto=True)[:, 0]))
        assert sparse <= spread + margin, (per_cell, sparse, spread)


@pytest.mark.parametrize("w", WAVINESS)
@pytest.mark.parametrize("step", [1, 2, 3])
def test_exact_patches_read_alike_on_every_step_of_the_ladder(w, step):
    """Spacing invariance on exact data: the same patches sampled exactly on the 11.2, 16
    and 22.4 mm grids read the R and w of their 8 mm reading (medians within 0.1 and
    0.03). Single patches differ more as the band shrinks (median |ln R| 0.08-0.12 at
    11.2 mm, 0.15-0.19 at 16 mm, 0.23-0.27 at 22.4 mm): the fit sees fewer ordinates
    and extrapolates further to 1 rad/m. That spread is about half of what separates a
    sparse cloud's reading from the exact 8 mm one (0.18-0.24 at 1 point per 8 mm cell,
    0.32-0.33 at 0.5); the rest is the coarse cells' sampling."""
    e = band_errors(w, spacing_ladder(SPEC)[step])
    assert abs(np.median(e[:, 0])) <= 0.1 and abs(np.median(e[:, 1])) <= 0.03, e
    assert np.median(np.abs(e[:, 0])) <= [0.15, 0.22, 0.3][step - 1]


def test_sparse_clouds_coarsen_the_grid_and_say_so(caplog):
    pts = cloud(-2.4, OFFSETS[0], 0.4, seed=3)
    with caplog.at_level("INFO", logger="rough_map.patch"):
        grid, r = _read(pts, auto=True)
    assert grid.spec.spacing == pytest.approx(0.0224)
    assert grid.spec.n * grid.spec.spacing == pytest.approx(SPEC.n * SPEC.spacing)
    assert r.omega[-1] == pytest.approx(math.pi / 0.0224)  # the band ends lower
    assert "22.4 mm grid" in caplog.text and "band" in caplog.text
    dense, _ = _read(cloud(-2.4, OFFSETS[0], 12, seed=3), auto=True)
    assert dense.spec == SPEC  # dense enough for the spacing asked for


def test_features_say_where_the_noise_takes_over(tmp_path, capsys):
    """Smooth ground from a sparse noisy sensor: ``rough-map features CLOUD`` says how far up
    the band the ground stays above the noise floor (``omega_noise``), and that is below
    the top of the fit; the dense cloud of rough ground keeps it to the top, unsaid."""
    import json

    from rough_map.cli.main import main

    rng = np.random.default_rng(5)
    pts = cloud(-2.8, OFFSETS[0], 1, seed=5)
    pts[:, 2] = 0.2 * pts[:, 2] + NOISE * rng.standard_normal(len(pts))  # 0.6 mm band rms
    np.save(tmp_path / "smooth.npy", pts)
    assert main(["features", str(tmp_path / "smooth.npy")]) == 0
    band = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("band"))
    assert "; ground above the noise floor to " in band
    assert main(["features", str(tmp_path / "smooth.npy"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert 7.0 < doc["omega_noise"] < doc["band_rad_per_m"][1]
    assert f"to {doc['omega_noise']:.1f} rad/m" in band
    np.save(tmp_path / "dense.npy", cloud(-2.4, OFFSETS[0], 12, seed=5))
    assert main(["features", str(tmp_path / "dense.npy"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["omega_noise"] > 380  # the top of the fit
    assert main(["features", str(tmp_path / "dense.npy")]) == 0
    assert "noise floor to" not in capsys.readouterr().out


def test_fixed_spacing_on_a_sparse_cloud_is_what_auto_avoids():
    """Without auto the 8 mm grid of a 0.5-point cloud has too many gaps to be read."""
    pts = cloud(-2.4, OFFSETS[0], 0.5, seed=3)
    with pytest.raises(PatchError, match="profiles are usable"):
        _read(pts)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), which=st.integers(0, len(OFFSETS) - 1))
def test_density_invariance_per_patch(seed, which):
    """Any patch, any sampling: 12 and 50 points per cell read the same ground alike."""
    off = OFFSETS[which]
    _, r12 = _read(cloud(-2.4, off, 12, seed))
    _, r50 = _read(cloud(-2.4, off, 50, seed + 1))
    assert abs(math.log(r12.R / r50.R)) < 0.5
    assert abs(r12.w - r50.w) < 0.12


# ---------------------------------------------------------------- the ladder and its API


def test_spacing_ladder_keeps_the_patch_and_its_wavenumbers():
    ladder = spacing_ladder(SPEC)
    assert [s.n for s in ladder] == [112, 80, 56, 40, 28]
    assert [round(s.spacing * 1e3, 1) for s in ladder] == [8.0, 11.2, 16.0, 22.4, 32.0]
    for s in ladder:
        assert s.n * s.spacing == pytest.approx(0.896)
        assert (s.ahead, s.lateral) == (SPEC.ahead, SPEC.lateral)


@pytest.mark.parametrize(
    ("per_cell", "spacing"),
    [
        (50, 0.008),
        (1.95, 0.008),
        (1.8, 0.0112),
        (1.0, 0.0112),
        (0.9, 0.016),
        (0.5, 0.016),
        (0.45, 0.0224),
    ],
)
def test_auto_spacing_picks_the_finest_step_with_enough_points(per_cell, spacing):
    assert auto_spacing(int(per_cell * 112**2), SPEC).spacing == pytest.approx(spacing)


def test_auto_spacing_refuses_a_cloud_too_sparse_for_any_step():
    with pytest.raises(PatchError, match=r"too sparse for any grid: 500 points.*32.0 mm cell"):
        auto_spacing(500, SPEC)
    with pytest.raises(InputError, match="min_points_per_cell must be > 0"):
        auto_spacing(5000, SPEC, min_points_per_cell=0)


def test_points_in_patch_counts_the_square_only():
    pts = np.array([[1.0, 0.0, 0.0], [1.44, 0.0, 0.0], [1.46, 0.0, 0.0], [1.0, -0.5, 0.0]])
    assert points_in_patch(pts, SPEC) == 2


def test_extraction_records_auto_spacing():
    ex = Extraction(auto_spacing=True)
    assert ex.to_dict()["spacing"] == "auto"
    assert Extraction.from_dict(ex.to_dict()) == ex
    fixed = ex.resolve(int(0.4 * 112**2))
    assert not fixed.auto_spacing and fixed.patch.spacing == pytest.approx(0.0224)
    assert Extraction().resolve(10) == Extraction()  # a fixed step is kept


def test_grid_of_a_cloud_is_always_read_as_cell_means():
    """Cell means of random points average to the cell's box mean at any density."""
    for per_cell in (0.5, 50):
        g = grid_points(cloud(-2.4, OFFSETS[0], per_cell, seed=1), SPEC)
        assert g.gridding == "cell_mean"


# ------------------------------------------------------------- real ground: the CAPTIF scan


def captif_cloud(start: float, per_cell: float, seed: int) -> np.ndarray:
    """The CAPTIF chipseal scan as the ground under the patch: z(x, y) is the scan's depth
    at distance ``start + x - x0`` (m), the same across the patch. Random points, linear
    interpolation between the scan's 0.037 mm samples, none where the laser dropped out,
    0.3 mm of noise."""
    distance, depth = _texture_scan()
    ok = np.isfinite(depth)
    rng = np.random.default_rng(seed)
    x, y = random_places(rng, per_cell)
    s = start + x - SPEC.x0
    seen = ok[np.clip(np.searchsorted(distance, s), 0, distance.size - 1)]
    z = -np.interp(s, distance[ok], depth[ok]) + NOISE * rng.standard_normal(x.size)
    return np.column_stack([x, y, z])[seen]


#: Where the patch starts along the scan (m): clear of the reference plates at both ends.
CAPTIF_STARTS = (0.10, 0.25, 0.40, 0.55, 0.70, 0.85)


@cache
def captif_readings(per_cell: float) -> np.ndarray:
    """(ln R, w, spacing and row width in m) of the scan's patches at ``per_cell`` points
    per 8 mm cell, spacing auto; 4 samplings of each of 6 patches."""
    out = []
    for start in CAPTIF_STARTS:
        for seed in range(4):
            pts = captif_cloud(start, per_cell, seed=100 * seed + int(10 * per_cell))
            grid, r = _read(pts, auto=True)
            out.append((math.log(r.R), r.w, grid.spec.spacing, grid.spec.row_step))
    return np.array(out)


@pytest.mark.parametrize("per_cell", [100, 20, 12, 8, 4])
def test_captif_scan_reads_alike_at_stereo_densities(per_cell):
    """Real chipseal: every stereo-like density reads the patches as 50 points per cell do
    (median differences within 0.15 in ln R and 0.05 in w).

    Chipseal is nearly white at these wavelengths (w about 0), so R at 1 rad/m is an
    extrapolation over a decade and a single patch's R moves 4.5 times as much as its w:
    the median |ln R difference| is 0.03 at 100 points per cell but 0.2-0.6 at 4-12.
    """
    ref = captif_readings(50)
    got = captif_readings(per_cell)
    assert np.all(got[:, 2] == SPEC.spacing)
    assert abs(np.median(got[:, 0] - ref[:, 0])) <= 0.15
    assert abs(np.median(got[:, 1] - ref[:, 1])) <= 0.05
    if per_cell >= 12:
        assert np.median(np.abs(got[:, 1] - ref[:, 1])) <= 0.05


def test_features_of_a_sparse_traverse_choose_one_coarser_grid(tmp_path):
    """`rough-map features TRAVERSE` with the default --spacing auto on lidar-like clouds:
    one step for every frame, reported with its band (stderr and --json)."""
    import json
    import subprocess
    import sys

    exe = [sys.executable, "-m", "rough_map"]
    run = tmp_path / "run"
    sim = ["simulate", "--out", str(run), "--course", "mixed", "--length", "3", "--seed", "2"]
    subprocess.run(
        [*exe, *sim, "--no-images", "--points-per-cell", "1.3", "-q"],
        check=True,
        capture_output=True,
    )
    out = subprocess.run(
        [*exe, "features", str(run), "--out", str(tmp_path / "f.csv"), "--json"],
        check=True,
        capture_output=True,
        text=True,
    )
    doc = json.loads(out.stdout)
    assert doc["spacing_m"] == pytest.approx(0.0112)
    assert doc["band_rad_per_m"][1] == pytest.approx(math.pi / 0.0112)
    assert "11.2 mm grid (auto), band 7.0 to 280.5 rad/m" in out.stderr
    fixed = subprocess.run(
        [
            *exe,
            "features",
            str(run),
            "--out",
            str(tmp_path / "g.csv"),
            "--json",
            "--spacing",
            "0.008",
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    assert json.loads(fixed.stdout)["spacing_m"] == pytest.approx(0.008)


# --------------------------------------- pooled rows: sparse clouds over ground alike across


def captif_exact_8mm() -> np.ndarray:
    """(ln R, w) of the CAPTIF patches read exactly on the 8 mm grid (``test_lateral``)."""
    from test_lateral import captif_exact

    return captif_exact()


@pytest.mark.parametrize("per_cell", [2, 1, 0.5])
def test_sparse_captif_clouds_keep_the_8_mm_band_in_pooled_rows(per_cell):
    """Real chipseal swept across the patch, at lidar densities: ``--spacing auto`` reads
    its lateral scale as 0, keeps the 8 mm step (and the band to 393 rad/m) and widens the
    cells across the track instead of coarsening the grid. R and w then stay within 25 %
    and 0.1 of the exact 8 mm scan (median differences) and of the dense clouds' reading,
    where the coarser square grids read -0.52 and -0.77 in ln R at 1 and 0.5 points per
    cell (the band alone costs that: ``test_lateral.py::
    test_captif_readings_depend_on_the_band``)."""
    ref, dense = captif_exact_8mm(), captif_readings(50)
    got = captif_readings(per_cell)
    assert np.median(got[:, 2]) == SPEC.spacing  # the step asked for, on most patches
    lnr = got[:, 0] - np.repeat(ref[:, 0], 4)
    dw = got[:, 1] - np.repeat(ref[:, 1], 4)
    assert abs(np.median(lnr)) <= math.log(1.25) and abs(np.median(dw)) <= 0.1, (lnr, dw)
    assert abs(np.median(got[:, 0] - dense[:, 0])) <= math.log(1.25)
    assert abs(np.median(got[:, 1] - dense[:, 1])) <= 0.1


def test_pooled_rows_are_logged_and_reported(caplog):
    """The widened rows are said (log) and kept in the grid's spec; the lateral scale is
    reported per step along the profiles."""
    pts = captif_cloud(CAPTIF_STARTS[1], 1.0, seed=7)
    with caplog.at_level("INFO", logger="rough_map.features"):
        grid, r = _read(pts, auto=True)
    assert grid.spec.spacing == SPEC.spacing
    assert grid.spec.row_step == pytest.approx(0.032)
    assert grid.heights.shape == (28, 112) and r.n_profiles <= 28
    assert r.omega[-1] == pytest.approx(math.pi / SPEC.spacing)  # the 8 mm band
    assert r.lateral_scale < 0.1
    assert "rows pooled" in caplog.text and "32.0 mm wide" in caplog.text


@pytest.mark.parametrize("per_cell", [1, 0.5])
def test_isotropic_sparse_clouds_are_not_pooled(per_cell):
    """Isotropic ground reads a lateral scale near 1 (0.8-1.3 on these clouds): widened
    rows would average away the band, so auto spacing keeps coarsening square cells."""
    for i, (field, off) in enumerate(SPARSE[::8]):
        pts = cloud(-2.4, off, per_cell, seed=1000 * i + int(10 * per_cell), field=field)
        grid, r = _read(pts, auto=True)
        assert grid.spec.row_spacing is None and grid.spec.spacing > SPEC.spacing
        assert r.lateral_scale > 0.6


@pytest.mark.parametrize("k", [2, 4])
def test_wide_rows_read_isotropic_ground_like_the_exact_patch(k):
    """Known answer for the lateral model: rows k cells wide over isotropic ground show its
    lateral scale times k, which the cell-mean correction takes, and the scale is reported
    per step: about 1. R and w stay near the exact patch (12 points per 8 mm cell)."""
    out = []
    ex = Extraction(use_imu=False, patch=PatchSpec(row_spacing=k * SPEC.spacing))
    for i, off in enumerate(OFFSETS[:8]):
        _, r = cloud_roughness(cloud(-2.4, off, 12, seed=i), ex)
        ref = exact(-2.4, off)
        out.append((r.lateral_scale, math.log(r.R / ref.R), r.w - ref.w))
    a, lnr, dw = np.median(out, axis=0)
    assert 0.8 <= a <= 1.4, out
    assert abs(lnr) <= 0.1 and abs(dw) <= 0.05, out


@pytest.mark.parametrize(
    ("n_points", "scale", "row_step"),
    [
        (12544 * 1.9, 0.0, 0.016),  # 1.9 points per 8 mm cell: rows 2 cells wide
        (12544 * 0.95, 0.0, 0.032),
        (12544 * 0.47, 0.02, 0.064),
        (12544 * 0.15, 0.0, 0.128),  # at most 16 cells wide
        (12544 * 0.1, 0.0, None),  # 16 cells wide would hold under 1.9 points
        (12544 * 1.0, 0.2, 0.016),  # 4 x 0.2 > 0.5: narrower rows
        (12544 * 3.0, 0.0, None),  # dense enough
        (12544 * 0.95, 1.0, None),  # isotropic
        (12544 * 0.47, 0.1, None),  # 4 cells wide would hold under 1.9 points
        (12544 * 0.95, math.nan, None),  # not read
    ],
)
def test_pooled_rows_width(n_points, scale, row_step):
    got = pooled_rows(int(n_points), SPEC, scale)
    if row_step is None:
        assert got is None
    else:
        assert got is not None and got.row_step == pytest.approx(row_step)
        assert (got.spacing, got.n, got.ahead) == (SPEC.spacing, SPEC.n, SPEC.ahead)
        assert got.rows * got.row_step == pytest.approx(SPEC.n * SPEC.spacing)


def test_pooled_rows_refuse_bad_arguments():
    with pytest.raises(InputError, match="lateral_scale must be a number"):
        pooled_rows(1000, SPEC, "flat")
    with pytest.raises(InputError, match="n_points"):
        pooled_rows(-1, SPEC, 0.0)
    with pytest.raises(InputError, match="spec must be a PatchSpec"):
        pooled_rows(1000, "8 mm", 0.0)


def test_frames_on_wide_rows_measure_both_directions():
    """The traverse path (``frame_features``) measures wide rows along the track with the
    step and across it with the row width, and agrees with ``cloud_roughness``."""
    pts = cloud(-2.4, OFFSETS[1], 4, seed=3)
    ex = Extraction(use_imu=False, patch=PatchSpec(row_spacing=0.032))
    row, omega, _ = frame_features(pts, ex, min_points=100)
    _, r = cloud_roughness(pts, ex)
    assert row["valid"], row["reason"]
    assert row["R"] == r.R and row["w"] == r.w
    assert omega[-1] == pytest.approx(math.pi / 0.008)
    # across the track: 28 samples of 32 mm, the same isotropic ground
    assert abs(math.log(row["R_lat"] / r.R)) < 1.0 and abs(row["w_lat"] - r.w) < 0.3


def test_a_frame_flat_across_the_track_is_measured_along_it():
    """Ground exactly the same across the track (the chipseal swept across the patch, no
    waves), 1 point per cell on the auto grid: across the track its profiles are flat to
    within the sensor's noise and have no roughness to read, so R_lat and w_lat are NaN,
    but the frame is valid and reads along the track what the cloud reads on that grid."""
    pts = captif_cloud(CAPTIF_STARTS[0], 1.0, seed=1)
    row, omega, _ = frame_features(pts, Extraction(use_imu=False, auto_spacing=True))
    assert row["valid"] and row["reason"] == "", row["reason"]
    assert math.isnan(row["R_lat"]) and math.isnan(row["w_lat"])
    assert row["lateral_scale"] == pytest.approx(0.0, abs=0.05)  # and says why
    square = auto_spacing(points_in_patch(pts, SPEC), SPEC)
    assert omega[-1] == pytest.approx(math.pi / square.spacing)
    one = cloud_roughness(pts, Extraction(patch=square, use_imu=False))[1]
    assert row["R"] == pytest.approx(one.R, rel=1e-9) and row["w"] == pytest.approx(one.w)


def test_a_sparse_traverse_over_swept_ground_pools_its_rows(tmp_path, caplog, capsys):
    """A traverse of lidar-like clouds (1 point per 8 mm cell) over ground whose profiles
    are the same across the track (the chipseal, with waves across it that only shift each
    profile): the frames that choose its step read a small lateral scale, so every frame
    keeps the 8 mm band in rows 32 mm wide, and reads as the single cloud does."""
    import json

    from rough_map.cli.main import main
    from rough_map.features import read_features, traverse_features, write_features

    def ground(start: float, seed: int) -> np.ndarray:
        pts = captif_cloud(start, 1.0, seed=seed)
        y = pts[:, 1]
        pts[:, 2] += 1e-3 * (np.sin(2 * np.pi * y / 0.31) + np.sin(2 * np.pi * y / 0.13 + 1))
        return pts

    (tmp_path / "clouds").mkdir()
    frames = []
    for i, start in enumerate(CAPTIF_STARTS):
        np.save(tmp_path / "clouds" / f"{i}.npy", ground(start, i))
        pose = {"x": 0.25 * i, "y": 0.0, "yaw": 0.0}
        frames.append({"t": 0.5 * i, "pose": pose, "cloud": f"clouds/{i}.npy"})
    doc = {"schema_version": "1.0", "name": "swept", "frames": frames}
    (tmp_path / "traverse.json").write_text(json.dumps(doc))
    with caplog.at_level("INFO", logger="rough_map.features"):
        table = traverse_features(tmp_path, Extraction(use_imu=False, auto_spacing=True))
    assert "8.0 mm grid in rows 32.0 mm wide" in caplog.text
    assert table.valid.all()
    assert table.omega[-1] == pytest.approx(math.pi / SPEC.spacing)
    one = _read(ground(CAPTIF_STARTS[2], 2), auto=True)[1]
    assert table.columns["R"][2] == pytest.approx(one.R, rel=1e-9)
    assert table.row_spacing == pytest.approx(0.032)
    assert (table["lateral_scale"] < 0.2).all()  # per step along: the rows show 4 times it
    back = read_features(write_features(table, tmp_path / "f.csv"))
    assert back.row_spacing == pytest.approx(0.032)
    np.testing.assert_allclose(back["lateral_scale"], table["lateral_scale"], rtol=1e-9)
    square = read_features(write_features(table.replace(name="x"), tmp_path / "g.parquet"))
    assert square.row_spacing == pytest.approx(0.032)  # replace and Parquet keep it too
    assert main(["features", str(tmp_path), "--out", str(tmp_path / "h.csv")]) == 0
    assert "8.0 mm grid in rows 32.0 mm wide (auto), band 7.0 to 392.7" in capsys.readouterr().err
    assert main(["features", str(tmp_path), "--out", str(tmp_path / "h.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["row_spacing_m"] == pytest.approx(0.032)
