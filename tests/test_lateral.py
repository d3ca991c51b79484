"""Ground that is not isotropic: the lateral scale read from adjacent rows (issue 12).

The cell-mean tables take the ground as isotropic; a cell mean also averages across the
cell, and how much power that takes depends on how alike neighbouring rows are. Here
continuous surfaces of the family ``S(kx, ky / a)`` (an isotropic field stretched across
the profiles, ``tests/surfaces.py``; ``a = 0``: the same at every y, as the CAPTIF scan
swept across the patch) are read from clouds and compared with the same patch read
exactly, and the CAPTIF scan with its exact 8 mm reading.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
from surfaces import sample_spline
from test_density import (
    CAPTIF_STARTS,
    FINE,
    OFFSETS,
    SPARSE,
    SPEC,
    WAVINESS,
    _centres,
    _field,
    _origin,
    _read,
    band_limited_spline,
    captif_cloud,
    cloud,
)
from test_real_data import _texture_scan

from rough_map.patch import PatchSpec, spacing_ladder
from rough_map.psd import patch_roughness
from rough_map.psd._corrections import (
    A_NODES,
    lateral_log_gain,
    lateral_scale,
    lateral_scale_value,
    lateral_tables,
)
from rough_map.psd._uncertainty import W_NODES, _lateral_coherence

STRETCHES = [0.0, 0.3, 1.0]


def _sample(coefficients: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    coords = np.stack([np.asarray(y, float), np.asarray(x, float)]) / FINE
    return sample_spline(coefficients, coords)


def stretched_exact(w: float, offset, a: float):
    """The stretched patch read exactly: the band-limited field at the cell centres."""
    fx, fy = _origin(offset)
    x, y = _centres()
    yy, xx = np.meshgrid(a * y + fy, x + fx, indexing="ij")
    return patch_roughness(_sample(band_limited_spline(w), xx, yy), SPEC.spacing)


def read_with_scale(points: np.ndarray):
    """The cloud's reading (spacing auto off) and the lateral scale ``a`` it reports."""
    _, r = _read(points)
    return r, r.lateral_scale


# --------------------------------------------------------------------------- the tables


def test_isotropic_node_needs_no_correction_and_swept_ground_is_coherent():
    ratio, coherence = lateral_tables(112)
    iso = int(np.flatnonzero(A_NODES == 1.0)[0])
    assert ratio.shape == coherence.shape == (A_NODES.size, W_NODES.size, 56)
    assert np.all(ratio[iso] == 0.0)
    assert np.allclose(coherence[0], 1.0)  # the same at every y: rows are identical
    # ... and the lateral box then takes nothing: the gain is above the isotropic one.
    assert np.all(ratio[0] > 0) and np.all(np.diff(ratio[:, :, -1], axis=0) < 0)
    assert not ratio.flags.writeable and not coherence.flags.writeable


@pytest.mark.parametrize("w", [-2.0, -2.5, -3.0])
def test_isotropic_coherence_is_that_of_the_uncertainty_model(w):
    """At low wavenumbers (where nothing folds) the table's isotropic coherence is the
    triangle-averaged Matern coherence of ``rough_map.psd._uncertainty``."""
    _, coherence = lateral_tables(112)
    j = int(np.flatnonzero(np.isclose(W_NODES, w))[0])
    iso = int(np.flatnonzero(A_NODES == 1.0)[0])
    nu = 2 * math.pi * np.arange(1, 15) / 112
    expected = _lateral_coherence(nu, np.array([1]), w, "cell_mean")[0]
    assert np.allclose(coherence[iso, j, :14], expected, atol=0.01)


def test_log_gain_interpolates_between_nodes():
    ratio, _ = lateral_tables(112)
    j = 4  # a waviness node
    w = np.array([W_NODES[j]] * 3)
    got = lateral_log_gain(np.array([0.0, 6.0, 2.5]), w, 112)
    assert np.allclose(got[0], ratio[0, j]) and np.allclose(got[1], 0.0)
    assert np.allclose(got[2], 0.5 * (ratio[2, j] + ratio[3, j]))


def test_patches_without_usable_ordinates_are_taken_as_isotropic():
    psd = np.ones((2, 56))
    usable = np.zeros((2, 56), dtype=bool)
    pos = lateral_scale(psd, psd, np.zeros_like(psd), np.array([-2.0, -2.0]), usable, 112)
    assert np.all(lateral_scale_value(pos) == 1.0)


# ---------------------------------------------------------------- surfaces of known scale


def test_the_scale_is_read_only_for_cell_means():
    """Reported where the fit reads it (unbiased, cell means, one segment), NaN elsewhere
    (the CLI's ``lateral`` line is in the README transcripts that test_readme reruns)."""
    pts = cloud(-2.4, OFFSETS[0], 12, seed=5, stretch=0.0)
    r, scale = read_with_scale(pts)
    assert scale == r.as_dict()["lateral_scale"] and scale <= 0.2
    grid = _read(pts)[0]
    heights = grid.heights
    for kwargs in (
        {},  # point samples: no cell-mean correction
        {"method": "paper", "gridding": "cell_mean"},
        {"nperseg": 56, "gridding": "cell_mean"},  # Welch segments
    ):
        assert math.isnan(patch_roughness(heights, SPEC.spacing, **kwargs).lateral_scale)
    again = patch_roughness(
        heights, SPEC.spacing, gridding="cell_mean", noise_psd=grid.noise_psd, subtract_noise=True
    )
    assert again.lateral_scale == scale  # the library call the cloud's reading makes


@pytest.mark.parametrize("a", STRETCHES)
def test_the_lateral_scale_is_read_from_the_cloud(a):
    scales = [
        read_with_scale(cloud(-2.4, off, 12, seed=50 + i, stretch=a))[1]
        for i, off in enumerate(OFFSETS[:6])
    ]
    assert abs(np.median(scales) - a) <= 0.12, scales


@cache
def stretched_errors(w: float, per_cell: float, a: float) -> np.ndarray:
    out = []
    for i, off in enumerate(OFFSETS):
        ref = stretched_exact(w, off, a)
        _, r = _read(cloud(w, off, per_cell, seed=300 + i, stretch=a))
        out.append((math.log(r.R / ref.R), r.w - ref.w))
    return np.array(out)


@pytest.mark.parametrize("w", [-2.0, -2.8])
@pytest.mark.parametrize("per_cell", [50, 12, 4])
def test_stretched_ground_reads_like_the_exact_patch(w, per_cell):
    """Ground stretched across the profiles (a = 0.3): the issue's figures (median
    |ln(R / R_exact)| <= 0.15, |w - w_exact| <= 0.05) at 50 and 12 points per cell, and
    the medians within them at 4 (median |ln R| 0.17 at w -2.8, where the noise buries
    the top of the band). Taken as isotropic it read -0.40 to -0.55 in ln R and +0.11 to
    +0.15 in w at every density."""
    e = stretched_errors(w, per_cell, 0.3)
    assert abs(np.median(e[:, 0])) <= 0.15 and abs(np.median(e[:, 1])) <= 0.05, e
    if per_cell >= 12:
        assert np.median(np.abs(e[:, 0])) <= 0.15, np.median(np.abs(e), axis=0)
        assert np.median(np.abs(e[:, 1])) <= 0.05, np.median(np.abs(e), axis=0)


@pytest.mark.parametrize("w", [-2.0, -2.8])
@pytest.mark.parametrize(("per_cell", "bound"), [(50, 0.15), (12, 0.15), (4, 0.35)])
def test_swept_ground_reads_like_the_exact_patch(w, per_cell, bound):
    """Ground that is the same at every y (a = 0): median ln(R / R_exact) within 0.15 at
    50 and 12 points per cell (within 0.35 at 4: -0.29 at w -2.8) and w within 0.07.
    Taken as isotropic it read -0.44 to -0.69 in ln R and +0.12 to +0.19 in w. Single
    patches scatter more (median |ln R| 0.2-0.45): every row is the same profile, so the
    reading does not average over independent ones and one profile's folded power moves
    it."""
    e = stretched_errors(w, per_cell, 0.0)
    assert abs(np.median(e[:, 0])) <= bound and abs(np.median(e[:, 1])) <= 0.07, e


# ------------------------------------------------------------------- standard errors


@cache
def stretched_z(a: float, per_cell: float, auto: bool) -> np.ndarray:
    """|ln R - ln R_true| / se_lnR and |w - w_true| / se_w of clouds of ground stretched
    by ``a``, against the field's own R and w: the 64 sparse patches at each waviness."""
    out = []
    for w in WAVINESS:
        for i, (field, off) in enumerate(SPARSE):
            pts = cloud(w, off, per_cell, seed=500 + i, field=field, stretch=a)
            _, r = _read(pts, auto)
            truth = _field(w, field)
            out.append((math.log(r.R / truth.R) / r.se_lnR, (r.w - truth.w) / r.se_w))
    return np.abs(np.array(out))


@pytest.mark.parametrize(
    ("a", "per_cell", "auto"),
    [(0.3, 12, False), (0.0, 12, False), (0.0, 1, True)],
    ids=["stretched", "swept", "swept-lidar-pooled-rows"],
)
def test_intervals_cover_the_truth_on_ground_alike_across_the_track(a, per_cell, auto):
    """The design effect is that of the ground's lateral scale as the rows show it (read
    from the patch), so the 68 % and 95 % intervals keep their coverage on ground whose
    neighbouring profiles are more alike than isotropic ground's: 0.68-0.74 and 0.93-0.96
    measured (192 patches, w -2.0 to -2.8). On swept ground every row is the same profile
    and the spread between them says nothing; the model's variance of one profile takes
    over (``rough_map.psd._uncertainty._variance``). Taken as isotropic, the intervals
    covered 0.38-0.61 and 0.69-0.77 at a = 0.3, 0.05-0.20 and 0.08-0.31 on swept ground,
    and 0.17-0.27 and 0.27-0.44 in pooled rows at 1 point per cell (per waviness)."""
    z = stretched_z(a, per_cell, auto)
    for col, name in enumerate(("ln R", "w")):
        inside = np.mean(z[:, col] < 1.0), np.mean(z[:, col] < 1.96)
        assert 0.6 <= inside[0] <= 0.8 and 0.9 <= inside[1] <= 0.99, (name, inside)


# -------------------------------------------------------------------- the CAPTIF scan


@cache
def captif_exact(spec: PatchSpec = SPEC) -> np.ndarray:
    """(ln R, w) of the scan's patches read exactly on the grid ``spec``: the scan
    band-limited to its Nyquist wavenumber and sampled at the cell centres (every row
    alike)."""
    distance, depth = _texture_scan()
    ok = np.isfinite(depth)
    s = np.arange(0.0, 1.91, 0.0005)
    z = -np.interp(s, distance[ok], depth[ok])
    dft = np.fft.rfft(z)
    dft[2 * np.pi * np.fft.rfftfreq(s.size, 0.0005) > math.pi / spec.spacing] = 0
    band = np.fft.irfft(dft, n=s.size)
    rng = np.random.default_rng(0)
    out = []
    for start in CAPTIF_STARTS:
        x = start + (np.arange(spec.n) + 0.5) * spec.spacing
        grid = np.tile(np.interp(x, s, band), (spec.n, 1))
        grid += 1e-7 * rng.standard_normal(grid.shape)  # rows not bit-identical
        r = patch_roughness(grid, spec.spacing)
        out.append((math.log(r.R), r.w))
    return np.array(out)


def test_captif_readings_depend_on_the_band():
    """Why auto spacing cannot keep the chipseal's R: sampled exactly on the 16 mm grid
    (band to 196 rad/m) the scan reads R more than 1.6 times away from its exact 8 mm
    reading (band to 393 rad/m) on median. Its spectrum is not a power law there."""
    coarse = captif_exact(spacing_ladder(SPEC)[2])
    assert np.median(np.abs(coarse[:, 0] - captif_exact()[:, 0])) > math.log(1.6)


@pytest.mark.parametrize("per_cell", [50, 12, 4, 2])
def test_captif_clouds_read_near_the_exact_scan(per_cell):
    """Real chipseal swept across the patch: the clouds' lateral scale reads 0 and their
    R and w come near the scan's exact 8 mm reading (median differences within 0.3 in
    ln R and 0.1 in w), down to 2 points per cell, where auto spacing keeps the 8 mm
    grid. Taken as isotropic they read -0.9 to -1.1 in ln R and +0.33 to
    +0.38 in w at every density. What is left is the chipseal's spectrum, which falls
    as Omega^-2.3 above the band where the cell-mean tables extend the power law."""
    ref = captif_exact()
    e, scales = [], []
    for i, start in enumerate(CAPTIF_STARTS):
        for seed in range(2):
            pts = captif_cloud(start, per_cell, seed=100 * seed + int(10 * per_cell))
            r, scale = read_with_scale(pts)
            e.append((math.log(r.R) - ref[i, 0], r.w - ref[i, 1]))
            scales.append(scale)
    d = np.median(np.array(e), axis=0)
    assert abs(d[0]) <= 0.3 and abs(d[1]) <= 0.1, d
    assert np.median(scales) <= 0.1, scales
