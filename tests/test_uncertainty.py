"""Standard errors of a patch's ln R and w (``se_lnR``, ``se_w``): interval coverage on
patches cut from continuous isotropic surfaces (tests/surfaces.py), the model's parts, and
invariants (hypothesis)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import special
from surfaces import fold_spectrum, power_law_field

from rough_map import iso8608, psd
from rough_map.psd import _uncertainty

B = 0.008
N = 112
WAVINESS = (-2.0, -2.4, -2.8)
FIELDS_PER_W = 4  # 1024 x 1024 cells (8.2 m square): 81 patches each, 324 per waviness
#: ISO 8608 classes A to D: R from a quarter of A's centre to D's upper boundary.
R_RANGE = (iso8608.PHI0["A"] / 4, 2 * iso8608.PHI0["D"])

VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "fixed_w": {"waviness": None},  # set to the truth per field
    "paper": {"method": "paper"},
    "welch": {"nperseg": 56},
    "band_dropped": {},  # rows 40-75 lose 160 mm: 36 profiles dropped
}


def _occlude(patches: np.ndarray) -> np.ndarray:
    out = patches.copy()
    out[:, 40:76, 20:40] = np.nan
    return out


@pytest.fixture(scope="module")
def trials() -> dict[str, dict[str, np.ndarray]]:
    """Per variant: true w, errors of ln R and w, their se, and sigma / sqrt(m)."""
    rng = np.random.default_rng(2024)
    rows: dict[str, list[tuple[float, ...]]] = {v: [] for v in VARIANTS}
    for w in WAVINESS:
        for i in range(FIELDS_PER_W):
            R = float(np.exp(rng.uniform(*np.log(R_RANGE))))
            field = power_law_field(1024, B, R, w, seed=100 * i + int(-10 * w))
            patches = field.patches(N)
            for name, opts in VARIANTS.items():
                opts = {**opts, "waviness": w} if name == "fixed_w" else opts
                stack = _occlude(patches) if name == "band_dropped" else patches
                for e in psd.patch_roughness_batch(stack, B, **opts):
                    m = e.n_profiles
                    rows[name].append(
                        (w, math.log(e.R / R), e.w - w, e.se_lnR, e.se_w,
                         e.sigma_lnR / math.sqrt(m), e.sigma_w / math.sqrt(m), m)
                    )  # fmt: skip
    power_law_field.cache_clear()
    keys = ("w_true", "err_lnR", "err_w", "se_lnR", "se_w", "naive_lnR", "naive_w", "m")
    return {v: dict(zip(keys, np.array(r).T, strict=True)) for v, r in rows.items()}


def _coverage(err: np.ndarray, se: np.ndarray) -> tuple[float, float]:
    z = np.abs(err) / se
    return float(np.mean(z < 1.0)), float(np.mean(z < 1.96))


# --------------------------------------------------------------------------- coverage


@pytest.mark.parametrize("w", WAVINESS)
def test_the_estimator_is_unbiased_on_continuous_surfaces(trials, w):
    t = trials["default"]
    sel = t["w_true"] == w
    assert sel.sum() == 81 * FIELDS_PER_W
    assert abs(np.median(t["err_lnR"][sel])) < 0.1
    assert abs(np.median(t["err_w"][sel])) < 0.02


@pytest.mark.parametrize("w", WAVINESS)
@pytest.mark.parametrize("q", ["lnR", "w"])
def test_intervals_cover_the_truth(trials, q, w):
    """+-1 se covers the generating R (or w) 60-76 % of the time, +-1.96 se 90-98 %."""
    t = trials["default"]
    sel = t["w_true"] == w
    c68, c95 = _coverage(t[f"err_{q}"][sel], t[f"se_{q}"][sel])
    assert 0.60 <= c68 <= 0.76
    assert 0.90 <= c95 <= 0.98


@pytest.mark.parametrize("q", ["lnR", "w"])
def test_sigma_over_sqrt_m_is_far_too_small(trials, q):
    """Neighbouring profiles are correlated: the naive error covers less than half."""
    t = trials["default"]
    c68, c95 = _coverage(t[f"err_{q}"], t[f"naive_{q}"])
    assert c68 < 0.4 and c95 < 0.7
    assert np.all(t[f"se_{q}"] >= t[f"naive_{q}"])


def test_fixed_waviness(trials):
    t = trials["fixed_w"]
    assert np.all(t["se_w"] == 0) and np.all(np.abs(t["err_w"]) < 1e-12)
    c68, c95 = _coverage(t["err_lnR"], t["se_lnR"])
    assert 0.60 <= c68 <= 0.76 and 0.90 <= c95 <= 0.98
    # Only the level is estimated: a much smaller error than with the slope.
    assert np.median(t["se_lnR"]) < 0.25 * np.median(trials["default"]["se_lnR"])


def test_welch_segments(trials):
    t = trials["welch"]
    for q in ("lnR", "w"):
        c68, c95 = _coverage(t[f"err_{q}"], t[f"se_{q}"])
        assert 0.60 <= c68 <= 0.76 and 0.90 <= c95 <= 0.98


@pytest.mark.parametrize("q", ["lnR", "w"])
def test_the_paper_method_se_is_its_own_spread(trials, q):
    """The paper's fit is biased (R 44 % low), but its se is the spread about its mean."""
    t = trials["paper"]
    err = t[f"err_{q}"] - np.median(t[f"err_{q}"])
    c68, c95 = _coverage(err, t[f"se_{q}"])
    assert 0.60 <= c68 <= 0.76 and 0.90 <= c95 <= 0.98
    if q == "lnR":
        assert np.median(t["err_lnR"]) < -0.4


@pytest.mark.parametrize("q", ["lnR", "w"])
def test_dropped_profiles_keep_the_coverage(trials, q):
    """A band of occluded profiles is dropped; the rest are taken as adjacent, which can
    only overstate their correlation (the se may be a little large, never small)."""
    t = trials["band_dropped"]
    assert np.all(t["m"] == N - 36)
    c68, c95 = _coverage(t[f"err_{q}"], t[f"se_{q}"])
    assert 0.60 <= c68 <= 0.82 and 0.90 <= c95 <= 0.99
    assert np.median(t[f"se_{q}"]) > np.median(trials["default"][f"se_{q}"])


# --------------------------------------------------------------------------- the model's parts


def test_lateral_coherence_is_the_fourier_transform_of_the_2d_spectrum():
    w = -2.4
    u = np.linspace(-400, 400, 400_001)
    for nu in (0.1, 0.5, 2.0):
        spec = (nu**2 + u**2) ** ((w - 1) / 2)
        lags = np.array([1.0, 3.0, 8.0])
        ref = [(spec * np.cos(u * j)).sum() / spec.sum() for j in lags]
        got = _uncertainty._lateral_coherence(np.array([nu]), lags, w, "point")[:, 0]
        np.testing.assert_allclose(got, ref, atol=2e-4)


def test_cell_means_are_more_coherent_across_rows():
    nu, lags = np.array([0.5, 2.0, 2.8]), np.array([0.0, 1.0, 2.0])
    point = _uncertainty._lateral_coherence(nu, lags, -2.4, "point")
    cells = _uncertainty._lateral_coherence(nu, lags, -2.4, "cell_mean")
    np.testing.assert_allclose(cells[0], 1.0, rtol=1e-6)
    assert np.all(cells[1:] > point[1:])


def test_log_covariance_of_correlated_ordinates():
    """Li2(|rho|^2) for periodogram ordinates; the series for Welch averages (Monte Carlo)."""
    assert _uncertainty._log_covariance(np.array([1.0]), 1.0)[0] == pytest.approx(math.pi**2 / 6)
    for alpha in (2.0, 3.5):
        one = _uncertainty._log_covariance(np.array([1.0]), alpha)[0]
        assert one == pytest.approx(float(special.polygamma(1, alpha)))
    rng = np.random.default_rng(7)
    n, r = 400_000, 0.7

    def chi2_pair(dof: int) -> tuple[np.ndarray, np.ndarray]:
        z = rng.standard_normal((2, dof, n))
        x = z[0]
        y = r * z[0] + math.sqrt(1 - r * r) * z[1]
        return (x * x).sum(axis=0), (y * y).sum(axis=0)

    for dof, alpha in ((2, 1.0), (4, 2.0)):
        x, y = chi2_pair(dof)
        mc = np.cov(np.log(x), np.log(y))[0, 1]
        assert _uncertainty._log_covariance(np.array([r**2]), alpha)[0] == pytest.approx(
            mc, abs=0.01
        )


def test_design_effect():
    rho = np.zeros((1, 20))
    rho[0, 0] = 1.0
    assert _uncertainty.design_effect(rho, 10)[0] == 1.0  # independent profiles
    assert _uncertainty.design_effect(np.ones((1, 20)), 10)[0] == pytest.approx(10.0)
    rho[0, 1] = 0.5  # lag 1 only: 1 + 2 (1 - 1/m) 0.5
    assert _uncertainty.design_effect(rho, 10)[0] == pytest.approx(1.9)


def test_welch_degrees_of_freedom():
    assert _uncertainty.equivalent_alpha(-float(np.euler_gamma)) == 1.0
    bias = psd.log_bias("hann", 56, 28, 112)
    alpha = _uncertainty.equivalent_alpha(bias)
    assert special.digamma(alpha) - math.log(alpha) == pytest.approx(bias, abs=1e-9)
    assert 2 < alpha < 4  # three overlapping Hann segments


# --------------------------------------------------------------------------- the generator


def test_generated_rows_have_the_power_law_spectrum():
    n, w = 512, -2.6
    kx = 2 * np.pi * np.fft.rfftfreq(n, d=B)[1:]
    ky = 2 * np.pi * np.fft.fftfreq(n, d=B)
    const = 1.0 / (2 * iso8608.surface_constant(w))
    exact = 2 * const * fold_spectrum(kx, ky, B, w).sum(axis=0) * (2 * np.pi / (n * B))
    np.testing.assert_allclose(exact[1:] / kx[1:] ** w, 1.0, rtol=1e-4)  # up to pi / B
    f = power_law_field(n, B, 3e-5, w, seed=3)
    p = np.abs(np.fft.rfft(f.heights, axis=1)[:, 1:]) ** 2 * B / (np.pi * n)
    ratio = p.mean(axis=0) / (3e-5 * kx**w)
    assert np.mean(ratio[20:]) == pytest.approx(1.0, abs=0.03)
    # Spline sampling passes through the nodes, and wraps round the periodic domain.
    j = np.array([0, 7, 300])
    np.testing.assert_allclose(f.sample(j * B, j[::-1] * B), f.heights[j[::-1], j], atol=1e-12)
    np.testing.assert_allclose(f.sample(j * B + n * B, j * B), f.sample(j * B, j * B))
    assert not f.heights.flags.writeable


# --------------------------------------------------------------------------- the result


def test_single_and_batch_agree_and_the_dict_has_the_errors():
    f = power_law_field(512, B, 2e-5, -2.3, seed=5)
    stack = f.patches(N)[:3]
    batch = psd.patch_roughness_batch(stack, B)
    for patch, one in zip(stack, batch, strict=True):
        single = psd.patch_roughness(patch, B)
        assert single.se_lnR == pytest.approx(one.se_lnR, rel=1e-9)
        assert single.se_w == pytest.approx(one.se_w, rel=1e-9)
        d = single.as_dict()
        assert d["se_lnR"] == single.se_lnR and d["se_w"] == single.se_w


def test_one_profile_has_no_standard_error():
    f = power_law_field(512, B, 2e-5, -2.3, seed=5)
    r = psd.patch_roughness(f.heights[:1, :N], B, min_profiles=1)
    assert math.isnan(r.se_lnR) and math.isnan(r.se_w)


# --------------------------------------------------------------------------- invariants

options = st.fixed_dictionaries(
    {
        "method": st.sampled_from(["unbiased", "paper"]),
        "waviness": st.sampled_from([None, -2.0, -2.6]),
        "gridding": st.sampled_from(["point", "cell_mean"]),
        "nperseg": st.sampled_from([None, 56]),
    }
)


def _patch(row: int, col: int, dropped: int) -> np.ndarray:
    f = power_law_field(512, B, 2e-5, -2.3, seed=11)
    h = f.heights[row : row + N, col : col + N].copy()
    h[:dropped, 10:30] = np.nan  # the first `dropped` profiles lose 160 mm
    return h


@settings(max_examples=25, deadline=None)
@given(
    row=st.integers(0, 400),
    col=st.integers(0, 400),
    dropped=st.sampled_from([0, 0, 5, 60]),
    opts=options,
    offset=st.floats(-100, 100),
    slope=st.floats(-0.3, 0.3),
    lateral=st.floats(-0.3, 0.3),
    scale=st.floats(0.01, 100),
)
def test_se_ignores_planes_and_scale(row, col, dropped, opts, offset, slope, lateral, scale):
    h = _patch(row, col, dropped)
    x = np.arange(N) * B
    plane = offset + slope * x[None, :] + lateral * x[:, None]
    a = psd.patch_roughness(h, B, **opts)
    for b in (psd.patch_roughness(h + plane, B, **opts), psd.patch_roughness(scale * h, B, **opts)):
        assert math.isclose(a.se_lnR, b.se_lnR, rel_tol=2e-3)
        assert math.isclose(a.se_w, b.se_w, rel_tol=2e-3, abs_tol=1e-6)


@settings(max_examples=25, deadline=None)
@given(
    row=st.integers(0, 400),
    col=st.integers(0, 400),
    dropped=st.sampled_from([0, 5, 60, 107]),
    opts=options,
)
def test_se_is_at_least_sigma_over_sqrt_m(row, col, dropped, opts):
    r = psd.patch_roughness(_patch(row, col, dropped), B, **opts)
    assert r.n_profiles == N - dropped
    root_m = math.sqrt(r.n_profiles)
    assert r.se_lnR >= r.sigma_lnR / root_m * (1 - 1e-12)
    if opts["waviness"] is None:
        assert r.se_w >= r.sigma_w / root_m * (1 - 1e-12)
        assert r.se_w > 0
    else:
        assert r.se_w == 0


def test_contracted_design_effect_matches_the_lag_correlations():
    """The per-patch contraction equals the design effect of the interpolated lag
    correlations, for any weights (here a noise-weighted fit's)."""
    rng = np.random.default_rng(4)
    alpha, m = 1.0, 112
    t0, tw = _uncertainty._effect_tables(112, "hann", "cell_mean", alpha, m)
    v = rng.standard_normal((3, 56)) * (rng.random((3, 56)) > 0.3)
    got = _uncertainty._design_effects(v, t0, tw)[0]
    for row, d in zip(v, got, strict=True):
        rho = _uncertainty._lag_correlations(112, "hann", "cell_mean", alpha, row.tobytes())
        np.testing.assert_allclose(d, _uncertainty.design_effect(rho, m), rtol=1e-10)
