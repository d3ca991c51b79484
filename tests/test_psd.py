"""The estimator of section 4: known answers, the synthesis round trip, gaps, bad input."""

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from rough_map import iso8608, psd
from rough_map.errors import InputError, PatchError
from rough_map.psd import _corrections, _fit, _spectra
from rough_map.psd._corrections import compute_lateral_tables

B = 0.008
N = 112


def test_matches_scipy_welch():
    rng = np.random.default_rng(1)
    h = rng.standard_normal((7, N)) * 1e-3 + np.linspace(0, 0.05, N)
    omega, p = psd.profile_psd(h, B)
    f, ref = signal.welch(
        signal.detrend(h, axis=1), fs=1 / B, window="hann", nperseg=N, detrend=False
    )
    np.testing.assert_allclose(omega, 2 * np.pi * f[1:])
    np.testing.assert_allclose(p, ref[:, 1:] / (2 * np.pi), rtol=2e-4)


def test_sinusoid_peak_has_its_power():
    k, amp = 10, 2e-3
    x = np.arange(N) * B
    omega_k = 2 * np.pi * k / (N * B)
    h = amp * np.sin(omega_k * x + 0.3)
    omega, p = psd.profile_psd(h, B)
    peak = int(np.argmax(p))
    assert omega[peak] == pytest.approx(omega_k)
    d_omega = omega[1] - omega[0]
    power = p[peak - 1 : peak + 2].sum() * d_omega  # Hann spreads a tone over 3 ordinates
    assert power == pytest.approx(amp**2 / 2, rel=0.02)


def test_parseval_with_rectangular_window():
    rng = np.random.default_rng(2)
    h = np.cumsum(rng.standard_normal((5, N)), axis=1) * 1e-4
    omega, p = psd.profile_psd(h, B, window="boxcar")
    var = signal.detrend(h, axis=1).var(axis=1)
    np.testing.assert_allclose(p.sum(axis=1) * (omega[1] - omega[0]), var, rtol=1e-4)


CASES = [(c, w) for c in "BCDEFG" for w in (-2.0, -2.4, -2.6)]


@pytest.mark.parametrize(("cls", "w"), CASES)
def test_round_trip_surfaces(cls, w):
    """Median over 20 patches cut from larger surfaces: ln R within 0.15, w within 0.05."""
    phi0 = iso8608.PHI0[cls]
    seed = 1000 * "BCDEFG".index(cls) + int(-10 * w)
    patches = np.stack(
        [
            iso8608.synthesize_surface((4 * N, 2 * N), B, phi0, w, seed=seed + i)[:N, :N]
            for i in range(20)
        ]
    )
    est = psd.patch_roughness_batch(patches, B)
    assert abs(np.median([math.log(e.R / phi0) for e in est])) < 0.15
    assert abs(np.median([e.w - w for e in est])) < 0.05


@pytest.mark.parametrize("w", [-1.8, -2.2, -2.6, -3.0])
@pytest.mark.parametrize("cls", ["A", "D", "H"])
def test_round_trip_profiles(cls, w):
    phi0 = iso8608.PHI0[cls]
    h = np.stack(
        [iso8608.synthesize_profile(N, B, phi0, w, n_profiles=N, seed=s) for s in range(10)]
    )
    est = psd.patch_roughness_batch(h, B)
    assert abs(np.median([math.log(e.R / phi0) for e in est])) < 0.1
    assert abs(np.median([e.w - w for e in est])) < 0.04


def test_paper_method_is_biased_low_by_about_gamma():
    h = np.stack(
        [iso8608.synthesize_profile(N, B, 64e-6, -2.0, n_profiles=N, seed=s) for s in range(10)]
    )
    paper = psd.patch_roughness_batch(h, B, method="paper")
    unbiased = psd.patch_roughness_batch(h, B)
    gap = np.median([math.log(u.R / p.R) for u, p in zip(unbiased, paper, strict=True)])
    assert 0.35 < gap < 0.75  # exp(-gamma): 44 % low, plus the window/detrend offsets


@pytest.mark.parametrize("shape", [(N, N), (7, 90), (N, 111)])
def test_single_and_batch_agree(shape):
    """A patch reads bit for bit the same alone and in a batch of any size (the online
    mapper reads frames alone, a traverse in chunks)."""
    h = np.stack([iso8608.synthesize_surface(shape, B, "E", -2.3, seed=s) for s in range(37)])
    batch = psd.patch_roughness_batch(h, B)
    for k in (0, 1, 5, 36):
        single = psd.patch_roughness(h[k], B)
        part = psd.patch_roughness_batch(h[k : k + 3], B)[0]
        for other in (single, part):
            assert (other.R, other.w, other.rms) == (batch[k].R, batch[k].w, batch[k].rms)
            assert np.array_equal(other.psd, batch[k].psd)


def test_results_built_fast_are_the_constructors():
    """``PatchRoughness.from_fields`` (the estimator's constructor) makes what the
    dataclass's own would, and refuses a missing or unknown field as it does."""
    r = psd.patch_roughness(iso8608.synthesize_surface((N, N), B, "D", -2.1, seed=2), B)
    values = {f.name: getattr(r, f.name) for f in dataclasses.fields(r)}
    fast, slow = psd.PatchRoughness.from_fields(values), psd.PatchRoughness(**values)
    assert fast.as_dict() == slow.as_dict() == r.as_dict()
    assert np.array_equal(fast.psd, slow.psd) and np.array_equal(fast.fit_mask, r.fit_mask)
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.R = 1.0
    with pytest.raises(TypeError, match=r"missing \['w'\], unknown \['x'\]"):
        psd.PatchRoughness.from_fields({**{k: v for k, v in values.items() if k != "w"}, "x": 1})


def test_uncertainty_is_the_profile_spread():
    h = iso8608.synthesize_surface((N, N), B, "E", -2.3, seed=5)
    r = psd.patch_roughness(h, B)
    assert r.n_profiles == N and r.profile_R.shape == (N,)
    assert r.sigma_w == pytest.approx(np.std(r.profile_w, ddof=1))
    assert r.sigma_R == pytest.approx(r.R * np.std(np.log(r.profile_R), ddof=1))
    assert r.R == pytest.approx(math.exp(np.mean(np.log(r.profile_R))))
    assert r.iso_class == iso8608.iso_class(r.R)
    assert r.rms > 0 and r.omega[0] == pytest.approx(2 * math.pi / (N * B))


def test_welch_segments_are_unbiased_too():
    h = np.stack(
        [iso8608.synthesize_profile(2 * N, B, 64e-6, -2.4, n_profiles=N, seed=s) for s in range(10)]
    )
    est = psd.patch_roughness_batch(h, B, nperseg=N)
    assert abs(np.median([math.log(e.R / 64e-6) for e in est])) < 0.15
    assert abs(np.median([e.w + 2.4 for e in est])) < 0.06


def test_cell_mean_gridding_is_corrected():
    """Cell means of a fine surface: the box filter is undone by gridding='cell_mean'."""
    fine = 0.001
    lr, dw = [], []
    for s in range(6):
        f = iso8608.synthesize_surface((896, 1792), fine, 1e-4, -2.4, seed=s)
        means = f.reshape(112, 8, 224, 8).mean(axis=(1, 3))[:, :112]
        r = psd.patch_roughness(means, B, gridding="cell_mean")
        plain = psd.patch_roughness(means, B)
        lr.append(math.log(r.R / 1e-4))
        dw.append(r.w + 2.4)
        assert plain.w < r.w  # the box filter steepens the spectrum
    assert abs(np.mean(lr)) < 0.35
    assert abs(np.mean(dw)) < 0.08


# --------------------------------------------------------------------------- noise


def test_noise_floor_subtraction_moves_back_to_the_truth():
    rng = np.random.default_rng(3)
    phi0, w = iso8608.PHI0["B"], -2.0
    clean = np.stack(
        [iso8608.synthesize_surface((2 * N, 2 * N), B, phi0, w, seed=s)[:N, :N] for s in range(10)]
    )
    sigma = 1.0e-4  # noise of a cell mean, m
    noisy = clean + rng.normal(0, sigma, clean.shape)
    floor = sigma**2 * B / math.pi
    raw = psd.patch_roughness_batch(noisy, B)
    fixed = psd.patch_roughness_batch(noisy, B, noise_psd=floor, subtract_noise=True)
    err_raw = abs(np.median([math.log(e.R / phi0) for e in raw]))
    err_fixed = abs(np.median([math.log(e.R / phi0) for e in fixed]))
    assert err_fixed < err_raw
    assert err_fixed < 0.2
    assert np.median([e.w for e in raw]) > np.median([e.w for e in fixed])  # noise flattens


def test_omega_noise_is_where_the_ground_meets_the_floor():
    """``omega_noise``: the wavenumber where the ground's R Omega^w falls to the floor F,
    (R / F)^(-1 / w); the top of the fit without noise; 0 where the floor is above the
    ground over the whole band; NaN when no floor is subtracted."""
    rng = np.random.default_rng(4)
    phi0, w = iso8608.PHI0["B"], -2.0
    clean = np.stack(
        [iso8608.synthesize_surface((2 * N, 2 * N), B, phi0, w, seed=s)[:N, :N] for s in range(6)]
    )
    for crossing in (60.0, 150.0):  # rad/m
        floor = phi0 * crossing**w
        noisy = clean + rng.normal(0, math.sqrt(floor * math.pi / B), clean.shape)
        got = psd.patch_roughness_batch(noisy, B, noise_psd=floor, subtract_noise=True)
        reach = np.median([r.omega_noise for r in got])
        assert abs(math.log(reach / crossing)) < 0.15, (crossing, reach)
    exact = psd.patch_roughness(clean[0], B, noise_psd=0.0, subtract_noise=True)
    assert exact.omega_noise == exact.omega[exact.fit_mask][-1]
    assert math.isnan(psd.patch_roughness(clean[0], B).omega_noise)
    low = phi0 * exact.omega[1] ** w  # the ground's power at the fit's first ordinate
    buried = clean[0] + rng.normal(0, math.sqrt(3 * low * math.pi / B), clean[0].shape)
    assert psd.patch_roughness(buried, B, noise_psd=3 * low, subtract_noise=True).omega_noise == 0


def test_subtract_noise_needs_a_floor():
    h = iso8608.synthesize_surface((N, N), B, "C", seed=0)
    with pytest.raises(InputError, match="noise_psd"):
        psd.patch_roughness(h, B, subtract_noise=True)


def test_noise_above_the_signal_everywhere_is_an_error():
    h = iso8608.synthesize_surface((N, N), B, "A", seed=0)
    with pytest.raises(PatchError, match="noise floor"):
        psd.patch_roughness(h, B, noise_psd=1.0, subtract_noise=True)


# --------------------------------------------------------------------------- gaps


def test_short_gaps_are_filled_and_counted():
    h = iso8608.synthesize_surface((N, N), B, "E", -2.4, seed=7)
    ref = psd.patch_roughness(h, B)
    holed = h.copy()
    rng = np.random.default_rng(0)
    holed[rng.random(h.shape) < 0.03] = np.nan  # scattered single cells
    holed[5, 20:40] = np.nan  # a 160 mm gap: profile 5 is dropped
    holed[9, :] = np.nan  # an empty profile
    r = psd.patch_roughness(holed, B)
    assert r.n_dropped == 2 and r.n_profiles == N - 2
    assert math.log(r.R / ref.R) == pytest.approx(0, abs=0.15)
    assert r.w == pytest.approx(ref.w, abs=0.05)


def test_fill_gaps_interpolates_linearly():
    h = np.array([[0.0, np.nan, 2.0, 3.0, np.nan, np.nan, 6.0, 7.0, np.nan]])
    filled, keep = psd.fill_gaps(h, 0.01, max_gap=0.02, max_gap_fraction=0.5)
    np.testing.assert_allclose(filled[0], [0, 1, 2, 3, 4, 5, 6, 7, 7])
    assert keep.all()


def test_all_nan_patch_raises():
    with pytest.raises(PatchError, match="profiles are usable"):
        psd.patch_roughness(np.full((N, N), np.nan), B)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("heights", "spacing", "match"),
    [
        (np.zeros((0, 0)), B, "empty"),
        (np.zeros((4, 4, 4, 4)), B, "2-D grid"),
        (np.zeros((10, 4)), B, "at least 8 samples"),
        (np.full((10, 16), np.inf), B, "infinite"),
        (np.zeros((10, 16)), 0.0, "spacing"),
        (np.zeros((10, 16)), -1.0, "spacing"),
        (np.zeros((10, 16)), float("nan"), "spacing"),
        (np.array([["a"] * 16] * 10), B, "numeric"),
    ],
)
def test_bad_input(heights, spacing, match):
    with pytest.raises(InputError, match=match):
        psd.patch_roughness(heights, spacing)


def test_bad_options():
    h = np.zeros((10, 16))
    with pytest.raises(InputError, match="method"):
        psd.patch_roughness(h, B, method="magic")
    with pytest.raises(InputError, match="gridding"):
        psd.patch_roughness(h, B, gridding="nearest")
    with pytest.raises(InputError, match="noverlap"):
        psd.patch_roughness(np.random.default_rng(0).random((10, 64)), B, nperseg=16, noverlap=16)
    with pytest.raises(PatchError, match="need at least 3"):
        psd.patch_roughness(np.random.default_rng(0).random((2, 64)), B)


def test_shipped_tables_are_up_to_date():
    with np.load(_corrections.SHIPPED_TABLES) as data:
        for g in psd.GRIDDINGS:
            np.testing.assert_allclose(
                data[f"hann_112_{g}"], _corrections.compute_leakage_table(112, "hann", g), atol=1e-9
            )
        for name, table in zip(("ratio", "coherence"), compute_lateral_tables(112), strict=True):
            np.testing.assert_allclose(data[f"lateral_{name}_112"], table, atol=1e-9)


# --------------------------------------------------------------------------- one call, one type


def test_a_stack_goes_to_the_batch_function():
    h = np.stack([iso8608.synthesize_surface((N, N), B, "C", seed=s) for s in range(2)])
    assert psd.patch_roughness_batch(h[:0], B) == []
    with pytest.raises(InputError, match="stack"):
        psd.patch_roughness_batch(h[0], B)
    with pytest.raises(InputError, match="empty"):
        psd.patch_roughness_batch(np.zeros((2, 5, 0)), B)
    with pytest.raises(TypeError, match="windw"):
        psd.patch_roughness_batch(h, B, windw="hann")
    with pytest.raises(InputError, match="method"):
        psd.patch_roughness_batch(h, B, method="magic")
    with pytest.raises(InputError, match="use patch_roughness_batch for a stack"):
        psd.patch_roughness(h, B)
    assert [r.R for r in psd.patch_roughness_batch(h, B)] == [
        psd.patch_roughness(x, B).R for x in h
    ]


# --------------------------------------------------------------------------- cached plans


def test_cached_plans_cannot_be_changed():
    """The lru_cache'd plans and tables are shared by every later call: read-only."""
    h = iso8608.synthesize_surface((N, N), B, "E", -2.3, seed=4)
    before = psd.patch_roughness(h, B)
    win, basis, _ = _spectra.hann_plan(N, "hann")
    plan = _fit.fit_plan(N // 2, N, "unbiased", B, 1.0, "hann", "point")
    arrays = [win, basis, _corrections.leakage_table(N, "hann", "point"), _corrections.W_GRID]
    arrays += [getattr(plan, f) for f in ("mask", "x", "xc", "avg", "proj", "leak_x", "leak_a")]
    for a in arrays:
        assert not a.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            a[..., 0] = 0
    with pytest.raises(ValueError, match="read-only"):
        before.fit_mask[0] = not before.fit_mask[0]  # a view of the plan's mask
    again = psd.patch_roughness(h, B)
    assert (again.R, again.w) == (before.R, before.w)


def test_each_patch_takes_its_own_floor_or_one_for_all() -> None:
    h = np.stack(
        [iso8608.synthesize_surface((32, 64), 0.008, 64e-6, -2.3, seed=s) for s in range(3)]
    )
    with pytest.raises(InputError, match=r"noise_psd has shape \(2,\); give one floor"):
        psd.patch_roughness_each(h, 0.008, noise_psd=[1e-9, 1e-9], subtract_noise=True)
    with pytest.raises(InputError, match="noise_psd must be finite floors"):
        psd.patch_roughness_each(h, 0.008, noise_psd=[1e-9, np.nan, 1e-9], subtract_noise=True)
    with pytest.raises(InputError, match="unexpected keyword"):
        psd.patch_roughness_each(h, 0.008, windows="hann")
    # a floor above the whole spectrum refuses that patch only
    out = psd.patch_roughness_each(h, 0.008, noise_psd=[1e-9, 1.0, 1e-9], subtract_noise=True)
    assert isinstance(out[1], PatchError) and "noise floor 1 m^3/rad" in str(out[1])
    assert [type(r).__name__ for r in out] == ["PatchRoughness", "PatchError", "PatchRoughness"]
    assert out[0].noise_psd == 1e-9 and out[0].noise_subtracted


def test_one_options_object_for_every_entry_point() -> None:
    """The four entry points take the same :class:`rough_map.psd.Options`, whole or as
    keyword changes of it, and read a patch alike whichever way it is given."""
    h = iso8608.synthesize_surface((24, 112), B, 64e-6, -2.3, seed=4)
    opts = psd.Options(method="paper", window="hamming")

    def key(r: psd.PatchRoughness | PatchError) -> tuple[float, ...]:
        assert isinstance(r, psd.PatchRoughness)
        return (r.R, r.w, r.se_lnR, r.se_w)

    whole = key(psd.patch_roughness(h, B, opts))
    assert whole == key(psd.patch_roughness(h, B, method="paper", window="hamming"))
    assert whole == key(psd.patch_roughness(h, B, psd.Options(method="paper"), window="hamming"))
    assert whole == key(psd.patch_roughness_batch(h[None], B, opts)[0])
    assert whole == key(psd.patch_roughness_each(h[None], B, opts)[0])
    assert whole != key(psd.patch_roughness(h, B))
    _, p = psd.profile_psd(h, B, opts)
    assert np.array_equal(p, psd.profile_psd(h, B, window="hamming")[1])
    assert psd.Options() == psd.Options.of(None, {}, "f")
    for f in (psd.patch_roughness, psd.profile_psd):
        with pytest.raises(psd.UnknownOptionError, match=rf"{f.__name__}\(\) got unexpected"):
            f(h, B, windows="hann")
    with pytest.raises(InputError, match=r"options must be a rough_map.psd.Options"):
        psd.patch_roughness(h, B, {"method": "paper"})  # type: ignore[arg-type]
    with pytest.raises(InputError, match="method"):
        psd.patch_roughness(h, B, opts, method="exact")


def test_fill_gaps_in_place_fills_the_array_given_and_checks_heights_as_before():
    """``copy=False`` (the estimator's own stacks) gives the copy's result in the array."""
    from rough_map.psd import fill_gaps
    from rough_map.psd._spectra import check_heights

    rng = np.random.default_rng(2)
    h = rng.normal(0.0, 1e-3, (6, 64))
    h[1, 10:13] = np.nan
    h[4, 5:40] = np.nan  # too long: dropped, left as it was
    copied, keep = fill_gaps(h, 0.008)
    assert np.isnan(h).sum() == 38  # the default copies
    own = h.copy()
    filled, keep2 = fill_gaps(own, 0.008, copy=False)
    assert filled is own and np.array_equal(filled, copied, equal_nan=True)
    assert np.array_equal(keep, keep2) and keep.tolist() == [1, 1, 1, 1, 0, 1]
    with pytest.raises(InputError, match="copy must be"):
        fill_gaps(h, 0.008, copy="no")
    for bad, match in ((np.inf, "infinite"), (-np.inf, "infinite"), (2e6, "wrong units")):
        g = h.copy()
        g[0, 0] = bad
        with pytest.raises(InputError, match=match):
            check_heights(g)
    assert check_heights(np.full((2, 8), np.nan)).shape == (2, 8)  # all missing passes


# ------------------------------------------------------------------ gaps under a noise floor


def _filled_white(share: float, seed: int, rows: int = 20000, n: int = 112):
    """White profiles (sd 1e-4 m) with a share of isolated cells filled by the gap policy:
    the heights, the mask of the filled cells."""
    rng = np.random.default_rng(seed)
    h = rng.normal(0.0, 1e-4, (rows, n))
    pick = rng.random((rows, n)) < share
    pick[:, 1:] &= ~pick[:, :-1]  # isolated cells only
    pick[:, [0, -1]] = False
    holed = np.where(pick, np.nan, h)
    filled, keep = psd.fill_gaps(holed, B, max_gap=B, max_gap_fraction=0.5)
    assert keep.all()
    return filled, pick


@pytest.mark.parametrize(("share", "rtol"), [(0.05, 0.04), (0.15, 0.08)])
def test_gap_filled_floor_is_the_spectrum_of_filled_noise(share, rtol):
    """A closed form against Monte Carlo: white noise whose gaps were filled has the floor
    ``N g + f (1 - f) v B / pi`` (g the terrain's gain), not the flat ``N``. (The model
    takes the filled cells as independent; only isolated ones are filled here, which
    leaves a few per cent at 12 % filled.)"""
    from rough_map.psd._corrections import gap_filled_floor, gap_statistics

    filled, pick = _filled_white(share, seed=int(share * 100))
    omega, p, _ = _spectra.periodogram(filled, B, "hann")
    measured = p.mean(axis=0)
    stats = gap_statistics(filled, pick)
    assert stats[0] == pytest.approx(pick.mean())
    assert stats[1] == pytest.approx(1.5e-8, rel=0.03)  # E[(A y)^2] = 1.5 s^2 for white y
    floor, gain = gap_filled_floor(
        np.array([1e-8 * B / math.pi]), np.array([stats]), omega.size, filled.shape[1], B
    )
    inner = slice(2, -1)  # the detrending takes most of the first ordinates
    np.testing.assert_allclose(measured[inner], floor[0, inner], rtol=rtol)
    flat = np.full(omega.size, 1e-8 * B / math.pi)
    top = slice(-9, -1)  # below the Nyquist ordinate, which has half the density
    assert (
        np.abs(measured[top] / flat[top] - 1).mean()
        > 3 * np.abs(measured[top] / floor[0, top] - 1).mean()
    )  # the flat floor is what the model corrects
    assert gain[0, -1] == pytest.approx((1 - 2 * stats[0]) ** 2)


def test_gap_statistics_of_a_grid_without_gaps_or_of_a_ramp():
    from rough_map.psd._corrections import gap_filled_floor, gap_statistics

    ramp = np.tile(np.linspace(0.0, 0.1, 50), (4, 1))
    none = np.zeros(ramp.shape, dtype=bool)
    assert gap_statistics(ramp, none) == (0.0, 0.0)
    some = none.copy()
    some[1, 10] = True
    share, resid = gap_statistics(ramp, some)
    assert share == pytest.approx(1 / 200) and resid == pytest.approx(0.0, abs=1e-20)
    floor, gain = gap_filled_floor(np.array([2.0]), None, 5, 10, B)
    np.testing.assert_array_equal(floor, np.full((1, 5), 2.0))
    np.testing.assert_array_equal(gain, np.ones((1, 5)))
