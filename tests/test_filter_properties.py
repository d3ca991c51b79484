"""Invariants of rough_map.filter, checked with hypothesis."""

from __future__ import annotations

import functools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from rough_map.filter import (
    PathFilter,
    estimate_generator,
    forward,
    isolated_spikes,
    smooth,
    transition_matrices,
    viterbi,
)

K = 3
SETTINGS = settings(max_examples=40, deadline=None)

finite = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)


@st.composite
def sequences(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random HMM problem: log likelihood (n, K), log transitions (n-1, K, K), log prior."""
    n = draw(st.integers(1, 25))
    ll = draw(arrays(float, (n, K), elements=finite))
    invalid = draw(arrays(bool, n))
    ll[invalid] = 0.0  # frames with a predict step only
    labels = draw(arrays(np.int64, 12, elements=st.integers(0, K - 1)))
    spacing = draw(arrays(float, 12, elements=st.floats(0.0, 20.0)))
    q = estimate_generator(
        labels, K, np.cumsum(spacing), switch_rate_prior=draw(st.floats(1e-3, 1.0))
    )
    steps = draw(arrays(float, n - 1, elements=st.floats(0.0, 100.0)))
    with np.errstate(divide="ignore"):
        lt = np.log(transition_matrices(q, steps))
    prior = draw(arrays(float, K, elements=st.floats(0.01, 1.0)))
    return ll, lt, np.log(prior / prior.sum())


@SETTINGS
@given(sequences())
def test_belief_sums_to_one_and_stays_finite(problem) -> None:
    for run in (forward, smooth):
        log_post = run(*problem)
        assert np.all(np.isfinite(log_post))
        np.testing.assert_allclose(np.exp(log_post).sum(axis=1), 1.0, rtol=1e-9)
    path = viterbi(*problem)
    assert path.shape == (len(problem[0]),)
    assert np.all((path >= 0) & (path < K))


@SETTINGS
@given(sequences(), st.data())
def test_constant_per_frame_in_log_likelihood_changes_nothing(problem, data) -> None:
    ll, lt, init = problem
    shift = data.draw(arrays(float, (len(ll), 1), elements=finite))
    for run in (forward, smooth):
        np.testing.assert_allclose(run(ll + shift, lt, init), run(ll, lt, init), atol=1e-8)


def _joint(path: np.ndarray, ll: np.ndarray, lt: np.ndarray, init: np.ndarray) -> float:
    steps = lt[np.arange(len(path) - 1), path[:-1], path[1:]]
    return float(init[path[0]] + ll[np.arange(len(path)), path].sum() + steps.sum())


@SETTINGS
@given(sequences(), st.permutations(range(K)))
def test_permuting_classes_permutes_output(problem, perm) -> None:
    ll, lt, init = problem
    p = np.array(perm)
    permuted = (ll[:, p], lt[:, p][:, :, p], init[p])
    for run in (forward, smooth):
        np.testing.assert_allclose(run(*permuted), run(ll, lt, init)[:, p], atol=1e-8)
    # Viterbi: ties may break differently, but the best path's probability is the same
    best = _joint(viterbi(ll, lt, init), ll, lt, init)
    best_permuted = _joint(viterbi(*permuted), *permuted)
    np.testing.assert_allclose(best_permuted, best, rtol=1e-9, atol=1e-8)


# ------------------------------------------------------------------------- the estimator

_RNG = np.random.default_rng(0)
_Y_TRAIN = np.repeat([0, 1, 2, 1, 0, 2], [40, 25, 30, 10, 35, 20])
_X_TRAIN = _RNG.dirichlet(np.ones(K), size=len(_Y_TRAIN))
_D_TRAIN = np.cumsum(_RNG.uniform(0.1, 0.6, size=len(_Y_TRAIN)))
NAMES = np.array(["grass", "gravel", "sand"])  # sorted: label i is column i


@functools.cache
def fitted(mode: str = "forward", perm: tuple[int, ...] = (0, 1, 2)) -> PathFilter:
    """A model fitted once on the training path, with class i renamed NAMES[perm[i]]."""
    inv = np.argsort(perm)
    y = NAMES[np.array(perm)[_Y_TRAIN]]
    return PathFilter(inputs="proba", mode=mode).fit(_X_TRAIN[:, inv], y, distance=_D_TRAIN)


@st.composite
def frames(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """Posteriors (n, K), some rows NaN, and a non-decreasing distance in m."""
    n = draw(st.integers(1, 30))
    proba = draw(arrays(float, (n, K), elements=st.floats(1e-9, 1.0)))
    proba[draw(arrays(bool, n))] = np.nan
    steps = draw(arrays(float, n, elements=st.floats(0.0, 5.0)))
    return proba, np.cumsum(steps)


@SETTINGS
@given(frames(), st.sampled_from(["forward", "smooth"]), st.data())
def test_scaling_posteriors_per_frame_changes_nothing(fr, mode, data) -> None:
    proba, dist = fr
    model = fitted(mode)
    scale = data.draw(arrays(float, (len(proba), 1), elements=st.floats(1e-3, 1e3)))
    out = model.predict_proba(proba, distance=dist)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out.sum(axis=1), 1.0, rtol=1e-9)
    np.testing.assert_allclose(model.predict_proba(proba * scale, distance=dist), out, atol=1e-9)


@SETTINGS
@given(frames(), st.permutations(range(K)))
def test_renaming_classes_permutes_estimator_output(fr, perm) -> None:
    """Relabel classes so that their sorted order is permuted: the output follows."""
    proba, dist = fr
    p = np.array(perm)
    base = fitted()
    # class i of the base model is called NAMES[p[i]]; sorted, column j of the new model is the
    # base class inv[j]
    inv = np.argsort(p)
    renamed = fitted("forward", tuple(perm))
    np.testing.assert_array_equal(renamed.classes_, NAMES)
    np.testing.assert_allclose(renamed.generator_, base.generator_[np.ix_(inv, inv)], atol=1e-12)
    np.testing.assert_allclose(
        renamed.predict_proba(proba[:, inv], distance=dist),
        base.predict_proba(proba, distance=dist)[:, inv],
        atol=1e-9,
    )


@st.composite
def rough_paths(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """R along a path (m^3/rad, within a factor of 2.5 of 1e-4) at dyadic frame spacings (m)."""
    n = draw(st.integers(3, 60))
    steps = draw(arrays(np.int64, n - 1, elements=st.integers(0, 4)))
    d = np.concatenate([[0.0], np.cumsum(steps * 0.125)])
    R = 1e-4 * 2.5 ** draw(arrays(float, n, elements=st.floats(-1.0, 1.0)))
    return R, d


@SETTINGS
@given(rough_paths(), st.integers(-400, 400))
def test_defect_frames_do_not_depend_on_where_the_path_starts(path, shift) -> None:
    R, d = path
    np.testing.assert_array_equal(isolated_spikes(R, d + 0.25 * shift), isolated_spikes(R, d))


@SETTINGS
@given(rough_paths())
def test_ground_within_a_factor_of_2_5_has_no_defect(path) -> None:
    R, d = path
    assert not isolated_spikes(R, d).any()  # no two frames differ by more than 6.25 < 8


@SETTINGS
@given(rough_paths(), st.floats(0.0, 1.0), st.floats(100.0, 1e4))
def test_a_short_strong_spike_is_always_found(path, start, factor) -> None:
    R, d = path
    spiked = np.where((d >= d[-1] * start) & (d <= d[-1] * start + 0.5), factor * R, R)
    hit = spiked > R
    if hit.sum() and (~hit).sum() >= 2 * hit.sum() + 1:  # the median stays on the ground
        flagged = isolated_spikes(spiked, d, window=1e3)
        assert flagged[hit].all()
