"""Example tests of rough_map.filter: known answers, accuracy on simulated paths, bad input."""

from __future__ import annotations

import itertools
import logging

import numpy as np
import pytest
from filterpy import discrete_bayes
from scipy.linalg import expm
from sklearn.base import clone
from sklearn.exceptions import NotFittedError as SklearnNotFittedError
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.utils.estimator_checks import parametrize_with_checks

from rough_map import errors
from rough_map.classify import load_terrain_model
from rough_map.filter import (
    PathFilter,
    Posteriors,
    estimate_generator,
    forward,
    isolated_spikes,
    predict,
    shipped_path_filter,
    smooth,
    transition_matrices,
    update,
    viterbi,
)

CLASSES = np.array(["asphalt", "grass", "gravel", "sand"])
SPACING_M = 0.25


# ------------------------------------------------------------------------- simulation helpers


def simulate_segments(
    rng: np.random.Generator, length_m: float = 500.0, seg_m: tuple[float, float] = (20, 80)
) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth: segment start positions (m) and class index per segment."""
    starts, labels = [0.0], [int(rng.integers(len(CLASSES)))]
    while starts[-1] < length_m:
        starts.append(starts[-1] + rng.uniform(*seg_m))
        labels.append(int((labels[-1] + rng.integers(1, len(CLASSES))) % len(CLASSES)))
    return np.array(starts), np.array(labels)


def sample_path(
    starts: np.ndarray, labels: np.ndarray, spacing_m: float, length_m: float = 500.0
) -> tuple[np.ndarray, np.ndarray]:
    """Frames every ``spacing_m`` metres: cumulative distance (m) and true class index."""
    d = np.arange(0.0, length_m, spacing_m)
    return d, labels[np.searchsorted(starts, d, side="right") - 1]


def noisy_posteriors(rng: np.random.Generator, y: np.ndarray, sigma: float = 0.7) -> np.ndarray:
    """Calibrated posteriors of a Gaussian classifier that confuses class c with c + 1.

    sigma = 0.7 gives ~65 % raw accuracy for 4 classes.
    """
    k = len(CLASSES)
    mu = np.eye(k) + 0.5 * np.roll(np.eye(k), 1, axis=1)
    z = mu[y] + sigma * rng.normal(size=(len(y), k))
    s = z @ mu.T / sigma**2
    p = np.exp(s - s.max(axis=1, keepdims=True))
    return p / p.sum(axis=1, keepdims=True)


def traverses(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` simulated 500 m traverses: posteriors, labels (str), distance (m), traverse id."""
    rng = np.random.default_rng(seed)
    parts = []
    for g in range(n):
        d, y = sample_path(*simulate_segments(rng), SPACING_M)
        parts.append((noisy_posteriors(rng, y), CLASSES[y], d, np.full(len(y), g)))
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))  # type: ignore[return-value]


@pytest.fixture(scope="module")
def train() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return traverses(seed=1, n=2)


@pytest.fixture(scope="module")
def test_path() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return traverses(seed=2, n=1)


# ------------------------------------------------------------------------- known answers


def test_update_two_class_hand_computed() -> None:
    # prior (0.2, 0.8), likelihood (0.9, 0.3): posterior (0.18, 0.24) / 0.42 = (3/7, 4/7)
    post = update(np.log([0.2, 0.8]), np.log([0.9, 0.3]))
    np.testing.assert_allclose(np.exp(post), [3 / 7, 4 / 7], rtol=1e-12)
    reference = discrete_bayes.update(np.array([0.9, 0.3]), np.array([0.2, 0.8]))
    np.testing.assert_allclose(np.exp(post), reference, rtol=1e-12)


def test_update_ignores_constant_in_likelihood_and_returns_new_array() -> None:
    b = np.log([0.5, 0.25, 0.25])
    ll = np.array([-1.0, 0.0, 2.0])
    out = update(b, ll)
    np.testing.assert_allclose(out, update(b, ll + 123.0), atol=1e-12)
    assert out is not b
    np.testing.assert_array_equal(b, np.log([0.5, 0.25, 0.25]))


def test_predict_two_class_hand_computed() -> None:
    t = np.array([[0.9, 0.1], [0.2, 0.8]])
    out = predict(np.log([0.5, 0.5]), np.log(t))
    np.testing.assert_allclose(np.exp(out), [0.55, 0.45], rtol=1e-12)


def test_forward_matches_linear_space_filterpy_reference() -> None:
    rng = np.random.default_rng(0)
    n, k = 30, 3
    like = rng.uniform(0.05, 1.0, size=(n, k))
    trans = transition_matrices(estimate_generator([0, 1, 2, 0], k, [0, 5, 9, 20]), 0.7)
    init = np.array([0.5, 0.3, 0.2])
    belief = discrete_bayes.update(like[0], init.copy())
    expected = [belief]
    for t in range(1, n):
        belief = discrete_bayes.update(like[t], trans.T @ belief)
        expected.append(belief)
    got = np.exp(forward(np.log(like), np.log(trans), np.log(init)))
    np.testing.assert_allclose(got, np.array(expected), rtol=1e-10)


def test_transition_matrix_rows_sum_to_one_and_semigroup() -> None:
    q = estimate_generator([0, 0, 1, 2, 2, 1, 0], 3, [0, 3, 4, 10, 12, 30, 31])
    np.testing.assert_allclose(q.sum(axis=1), 0.0, atol=1e-12)
    for d in (0.0, 0.25, 3.0, 250.0):
        p = transition_matrices(q, d)
        assert np.all(p >= 0)
        np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-12)
    a, b = 0.731, 2.4
    np.testing.assert_allclose(
        transition_matrices(q, a + b),
        transition_matrices(q, a) @ transition_matrices(q, b),
        atol=1e-12,
    )
    np.testing.assert_array_equal(transition_matrices(q, 0.0), np.eye(3))
    np.testing.assert_allclose(transition_matrices(q, a), expm(q * a), atol=1e-12)


def test_transition_matrix_two_state_closed_form() -> None:
    a, b, d = 0.05, 0.02, 7.5  # 1/m, 1/m, m
    q = np.array([[-a, a], [b, -b]])
    p00 = b / (a + b) + a / (a + b) * np.exp(-(a + b) * d)
    p11 = a / (a + b) + b / (a + b) * np.exp(-(a + b) * d)
    np.testing.assert_allclose(transition_matrices(q, d), [[p00, 1 - p00], [1 - p11, p11]])


def test_transition_matrices_batched_and_rounded_to_mm() -> None:
    q = np.array([[-0.1, 0.1], [0.3, -0.3]])
    steps = np.array([[0.25, 0.0], [0.2504, 1.0]])
    out = transition_matrices(q, steps)
    assert out.shape == (2, 2, 2, 2)
    np.testing.assert_array_equal(out[0, 0], out[1, 0])  # 0.2504 m rounds to 0.250 m
    np.testing.assert_array_equal(out[0, 1], np.eye(2))


def test_estimate_generator_hand_computed() -> None:
    # classes 0 0 0 1 1 0 at 0..5 m: 0->1 and 1->0 once each; metres in class 0: 1 + 1 + 0.5
    # + 0.5 = 3, in class 1: 0.5 + 1 + 0.5 = 2. Rates (1 + 1) / (L + 1 / 0.02).
    q = estimate_generator([0, 0, 0, 1, 1, 0], 2, np.arange(6.0), switch_rate_prior=0.02)
    np.testing.assert_allclose(q, [[-2 / 53, 2 / 53], [2 / 52, -2 / 52]])


def test_estimate_generator_does_not_count_across_traverses() -> None:
    y = [0, 0, 1, 1]
    d = [0.0, 1.0, 0.0, 1.0]  # distance restarts with the second traverse
    q = estimate_generator(y, 2, d, groups=["a", "a", "b", "b"], switch_rate_prior=0.02)
    np.testing.assert_allclose(-np.diag(q), [1 / 51, 1 / 51])  # no switch, 1 m in each class


def test_min_switch_rate_applies() -> None:
    q = estimate_generator(np.zeros(1000, int), 2, np.arange(1000.0), min_switch_rate=0.01)
    assert q[0, 1] == pytest.approx(0.01)


def test_generator_is_speed_invariant() -> None:
    """The same 2 km path at 1 frame/s and 0.3, 0.5, 0.7 m/s gives the same per-metre model."""
    starts, labels = simulate_segments(np.random.default_rng(5), length_m=2000.0)
    models = {}
    for speed in (0.3, 0.5, 0.7):
        d, y = sample_path(starts, labels, speed, 2000.0)
        models[speed] = PathFilter(inputs="proba").fit(np.eye(4)[y], CLASSES[y], distance=d)
    reference = models[0.3].generator_
    for model in models.values():  # every switch is seen at every speed
        np.testing.assert_array_equal(model.switch_counts_, models[0.3].switch_counts_)
    for speed, model in models.items():
        np.testing.assert_allclose(model.generator_, reference, rtol=0.01)
        # while the per-frame transition matrix adapts to the spacing
        np.testing.assert_allclose(
            model.transition_matrix(speed), expm(reference * speed), rtol=0.01
        )
    assert not np.allclose(models[0.3].transition_matrix(0.3), models[0.7].transition_matrix(0.7))


# ------------------------------------------------------------------------- filtering quality


def test_filter_raises_accuracy_on_noisy_path(train, test_path) -> None:
    X, y, d, g = train
    Xt, yt, dt, gt = test_path
    raw = np.mean(CLASSES[Xt.argmax(axis=1)] == yt)
    acc = {}
    for mode in ("forward", "smooth", "viterbi"):
        model = PathFilter(inputs="proba", mode=mode).fit(X, y, distance=d, groups=g)
        acc[mode] = np.mean(model.predict(Xt, distance=dt, groups=gt) == yt)
    assert 0.6 <= raw <= 0.7
    assert acc["forward"] >= 0.85
    assert acc["smooth"] >= acc["forward"]
    assert acc["viterbi"] >= 0.85


def test_filter_follows_a_class_change_within_3_m(train) -> None:
    X, y, d, g = train
    model = PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)
    dist = np.arange(0.0, 100.0, SPACING_M)
    truth = np.where(dist < 50.0, 1, 3)
    proba = np.full((len(dist), 4), 0.1 / 3)
    proba[np.arange(len(dist)), truth] = 0.9  # clear emissions
    pred = model.predict(proba, distance=dist)
    first_b = dist[np.argmax(pred == CLASSES[3])]
    assert np.all(pred[dist < 50.0][8:] == CLASSES[1])  # settled on the first class
    assert 50.0 <= first_b < 53.0
    assert np.all(pred[dist >= first_b] == CLASSES[3])


def test_invalid_frames_get_predict_step_only(train, test_path) -> None:
    X, y, d, g = train
    Xt, _, dt, _ = test_path
    Xt, dt = Xt[:200], dt[:200]
    model = PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)
    valid = np.ones(len(Xt), bool)
    valid[50:70] = False
    log_post = model.predict_log_proba(Xt, distance=dt, valid=valid)
    for t in range(50, 70):
        expected = predict(log_post[t - 1], np.log(model.transition_matrix(dt[t] - dt[t - 1])))
        np.testing.assert_allclose(log_post[t], expected, atol=1e-12)
    # NaN rows are invalid frames; their content does not matter when valid=False
    Xn = Xt.copy()
    Xn[50:70] = np.nan
    np.testing.assert_allclose(model.predict_log_proba(Xn, distance=dt), log_post, atol=1e-12)
    Xr = Xt.copy()
    Xr[50:70] = 123.0
    np.testing.assert_allclose(
        model.predict_log_proba(Xr, distance=dt, valid=valid), log_post, atol=1e-12
    )


def test_every_traverse_starts_from_the_class_prior(train) -> None:
    X, y, d, g = train
    model = PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)
    Xp = np.full((6, 4), np.nan)
    proba = model.predict_proba(Xp, distance=[0, 1, 2, 0, 1, 2.0], groups=[7, 7, 7, 3, 3, 3])
    np.testing.assert_allclose(proba[[0, 3]], [model.class_prior_] * 2)
    np.testing.assert_allclose(model.class_prior_.sum(), 1.0)


def test_zero_distance_step_is_identity(train) -> None:
    X, y, d, g = train
    model = PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)
    Xp = np.vstack([X[:1], np.full((1, 4), np.nan)])
    proba = model.predict_proba(Xp, distance=[3.0, 3.0])
    np.testing.assert_allclose(proba[1], proba[0], atol=1e-12)


def _joint_log_prob(path, ll, lt, init) -> float:
    return float(
        init[path[0]]
        + ll[0, path[0]]
        + sum(lt[t - 1][path[t - 1], path[t]] + ll[t, path[t]] for t in range(1, len(path)))
    )


def test_viterbi_and_smooth_match_brute_force() -> None:
    rng = np.random.default_rng(3)
    n, k = 6, 3
    ll = rng.normal(size=(n, k))
    q = estimate_generator([0, 1, 2, 1], k, [0, 1, 3, 4], switch_rate_prior=0.5)
    lt = np.log(transition_matrices(q, rng.uniform(0, 2, size=n - 1)))
    init = np.log([0.2, 0.5, 0.3])
    paths = np.array(list(itertools.product(range(k), repeat=n)))
    joint = np.array([_joint_log_prob(p, ll, lt, init) for p in paths])
    np.testing.assert_array_equal(viterbi(ll, lt, init), paths[np.argmax(joint)])
    w = np.exp(joint - joint.max())
    marginals = np.array([[w[paths[:, t] == c].sum() for c in range(k)] for t in range(n)])
    marginals /= marginals.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(np.exp(smooth(ll, lt, init)), marginals, atol=1e-12)
    # the last smoothed frame is the last filtered frame
    np.testing.assert_allclose(smooth(ll, lt, init)[-1], forward(ll, lt, init)[-1], atol=1e-12)


def test_viterbi_mode_gives_a_valid_path(train, test_path) -> None:
    X, y, d, g = train
    Xt, _, dt, _ = test_path
    model = PathFilter(inputs="proba", mode="viterbi").fit(X, y, distance=d, groups=g)
    path = model.predict(Xt, distance=dt)
    assert path.shape == (len(Xt),)
    assert set(path) <= set(model.classes_)
    # the Viterbi path is at least as probable as the smoothed argmax path
    # the scaled, floored, weighted log likelihood the estimator documents
    scaled = np.maximum(Xt / Xt.sum(axis=1, keepdims=True), model.floor) / model.class_prior_
    ll = model.emission_weight_ * np.log(scaled)
    lt = np.log(model.transition_matrix(np.diff(dt)))
    init = np.log(model.class_prior_)
    vit = np.searchsorted(model.classes_, path)
    marg = np.argmax(model.predict_proba(Xt, distance=dt), axis=1)
    assert _joint_log_prob(vit, ll, lt, init) >= _joint_log_prob(marg, ll, lt, init)


def test_string_labels_and_classes_from_y() -> None:
    y = np.array(["rock", "mud", "mud", "rock", "ice", "ice"])
    model = PathFilter(inputs="proba").fit(np.full((6, 3), 1 / 3), y)
    np.testing.assert_array_equal(model.classes_, ["ice", "mud", "rock"])
    np.testing.assert_allclose(model.class_prior_, [1 / 3, 1 / 3, 1 / 3])
    assert model.predict(np.eye(3)).dtype.kind == "U"


def test_log_likelihood_input_equals_proba_input(train, test_path) -> None:
    X, y, d, g = train
    Xt, _, dt, _ = test_path
    by_proba = PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)
    by_ll = PathFilter(inputs="log_likelihood").fit(X, y, distance=d, groups=g)
    # log p(x|c) = log p(c|x) - log p(c) + const
    ll = np.log(Xt) - np.log(by_proba.class_prior_)
    np.testing.assert_allclose(
        by_ll.predict_proba(ll, distance=dt), by_proba.predict_proba(Xt, distance=dt), atol=1e-9
    )


def test_classifier_and_auto_weight_in_a_pipeline() -> None:
    """A classifier before the filter in a Pipeline; the auto weight from held-out posteriors."""
    rng = np.random.default_rng(4)
    parts = []
    for g in range(5):
        d, yi = sample_path(*simulate_segments(rng, length_m=150.0), 0.5, 150.0)
        feats = np.eye(4)[yi] * 2.0 + rng.normal(size=(len(yi), 4)) * 1.5 + 10.0
        parts.append((feats, CLASSES[yi], d, np.full(len(yi), g)))
    X, y, d, g = (np.concatenate(p) for p in zip(*parts, strict=True))
    train, test = g < 4, g == 4
    pipe = make_pipeline(StandardScaler(), Posteriors(), PathFilter(emission_weight="auto"))
    pipe.fit(
        X[train],
        y[train],
        posteriors__groups=g[train],
        pathfilter__distance=d[train],
        pathfilter__groups=g[train],
    )
    model = pipe[-1]
    assert model.emission_weight_ in (0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)
    classifier = pipe.named_steps["posteriors"].classifier_
    raw = np.mean(classifier.predict(pipe[0].transform(X[test])) == y[test])
    filtered = np.mean(pipe.predict(X[test], distance=d[test]) == y[test])
    assert filtered > raw + 0.1


def test_missing_distance_logs_a_warning(caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="rough_map.filter"):
        PathFilter(inputs="proba").fit(np.eye(2)[[0, 1, 1]], [0, 1, 1])
    assert "assuming 1 m between frames" in caplog.text


# ------------------------------------------------------------------------- scikit-learn API

ORDER_DEPENDENT = (
    "a sequence filter's output for a frame depends, by design, on the frames before (and for "
    "smoothing after) it, so it cannot be invariant to sample order or to batching"
)


COLUMNS_ARE_CLASSES = (
    "the columns of X are the K classes' posteriors or log likelihoods; the check's X has "
    "another number of columns than y has classes, or values that are no posteriors "
    "(negative) or log likelihoods (chance accuracy); a classifier goes before the filter in "
    "a Pipeline (test_classifier_and_auto_weight_in_a_pipeline)"
)
COLUMNS_ARE_CLASSES_CHECKS = (
    "check_classifiers_classes",
    "check_classifiers_train",
    "check_dtype_object",
    "check_estimators_dtypes",
    "check_estimators_fit_returns_self",
    "check_estimators_overwrite_params",
    "check_estimators_pickle",
    "check_fit2d_1feature",
    "check_n_features_in_after_fitting",
    "check_pipeline_consistency",
    "check_positive_only_tag_during_fit",
    "check_readonly_memmap_input",
)
HELD_OUT = (
    "fit_transform gives held-out posteriors (cross_val_predict), transform those of the "
    "classifier fitted on every frame, by design (as scikit-learn's TargetEncoder)"
)


def _expected_failures(estimator) -> dict[str, str]:
    if isinstance(estimator, Posteriors):
        return dict.fromkeys(
            ("check_transformer_data_not_an_array", "check_transformer_general"), HELD_OUT
        )
    return {
        **dict.fromkeys(COLUMNS_ARE_CLASSES_CHECKS, COLUMNS_ARE_CLASSES),
        "check_methods_sample_order_invariance": ORDER_DEPENDENT,
        "check_methods_subset_invariance": ORDER_DEPENDENT,
    }


#: The path filter of the model that ships (models/default), unfitted.
SHIPPED_FILTER = clone(load_terrain_model("default").filter_)


def test_shipped_path_filter_is_the_one_that_ships() -> None:
    assert repr(shipped_path_filter("smooth").get_params()) == repr(SHIPPED_FILTER.get_params())


@parametrize_with_checks(
    # the default, the path filter of the shipped model and `rough-map train`, a classifier
    [PathFilter(), SHIPPED_FILTER, Posteriors()],
    expected_failed_checks=_expected_failures,
    xfail_strict=True,
)
def test_sklearn_compatible(estimator, check) -> None:
    check(estimator)


def test_posteriors_columns_and_frames_without_a_measurement() -> None:
    rng = np.random.default_rng(0)
    y = np.repeat(["a", "b", "c"], 20)
    X = rng.normal(size=(60, 2)) + np.repeat([[0, 0], [3, 0], [0, 3]], 20, axis=0)
    X[5] = np.nan
    y[5] = "z"  # a class seen on a frame without a measurement only
    step = Posteriors().fit(X, y)
    out = step.transform(X)
    assert list(step.classes_) == ["a", "b", "c", "z"]
    assert np.isnan(out[5]).all()
    np.testing.assert_allclose(np.delete(out, 5, axis=0).sum(axis=1), 1.0)
    assert np.all(np.delete(out, 5, axis=0)[:, 3] == 0.0)  # the classifier never saw 'z'
    held_out = Posteriors().fit_transform(X, y, groups=np.repeat([0, 1, 2, 3, 4], 12))
    assert held_out.shape == out.shape and np.isnan(held_out[5]).all()
    assert not np.allclose(np.delete(held_out, 5, 0), np.delete(out, 5, 0))


def test_not_fitted_error_is_both_kinds() -> None:
    with pytest.raises(errors.NotFittedError):
        PathFilter().predict(np.eye(2))
    with pytest.raises(SklearnNotFittedError):
        PathFilter().transition_matrix(1.0)


# ------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def fitted(train) -> PathFilter:
    X, y, d, g = train
    return PathFilter(inputs="proba").fit(X, y, distance=d, groups=g)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"distance": np.arange(5.0)}, r"distance must have one value \(m\) per frame"),
        ({"groups": np.zeros(5)}, "groups must have one traverse id per frame"),
        ({"valid": np.ones(5, bool)}, "valid must be a boolean array with one value per frame"),
        ({"distance": [0, 1, 2, 1.5, 3, 4.0]}, "distance must be non-decreasing within each"),
        ({"distance": [0, 1, np.inf, 2, 3, 4]}, r"distance \(m\) must be finite"),
    ],
)
def test_bad_path_arguments(fitted, kwargs, match) -> None:
    with pytest.raises(errors.InputError, match=match):
        fitted.predict_proba(np.full((6, 4), 0.25), **kwargs)


def test_decreasing_distance_is_fine_across_traverses(fitted) -> None:
    out = fitted.predict_proba(np.full((4, 4), 0.25), distance=[5, 6, 0, 1.0], groups=[1, 1, 2, 2])
    assert out.shape == (4, 4)
    with pytest.raises(errors.InputError, match="non-decreasing within each traverse"):
        fitted.predict_proba(np.full((4, 4), 0.25), distance=[5, 6, 0, 1.0], groups=[1, 1, 1, 2])


def test_bad_fit_arguments(train) -> None:
    X, y, d, _ = train
    with pytest.raises(errors.InputError, match="inconsistent numbers of samples"):
        PathFilter(inputs="proba").fit(X, y[:-1])
    with pytest.raises(errors.InputError, match="distance must have one value"):
        PathFilter(inputs="proba").fit(X, y, distance=d[:-1])
    with pytest.raises(errors.InputError, match="X has 3 columns but y has 4 classes"):
        PathFilter(inputs="proba").fit(X[:, :3], y)
    with pytest.raises(errors.InputError, match="at least 2 classes"):
        PathFilter(inputs="proba").fit(X[:, :1], np.full(len(X), "grass"))


def test_class_count_mismatch_between_fit_and_predict(fitted) -> None:
    with pytest.raises(errors.InputError, match="X has 3 features, but PathFilter is expecting 4"):
        fitted.predict(np.full((5, 3), 1 / 3))


def test_nan_posteriors_marked_valid(fitted) -> None:
    X = np.full((5, 4), 0.25)
    X[2, 1] = np.nan
    msg = r"NaN in frames marked valid=True \(first: frame 2"
    with pytest.raises(errors.InputError, match=msg):
        fitted.predict_proba(X, valid=np.ones(5, bool))


def test_bad_posteriors(fitted) -> None:
    X = np.full((5, 4), 0.25)
    X[1, 0] = -0.1
    with pytest.raises(errors.InputError, match="posteriors in X must be >= 0"):
        fitted.predict_proba(X)
    X[1] = 0.0
    with pytest.raises(errors.InputError, match="positive sum"):
        fitted.predict_proba(X)


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"emission_weight": 0.0}, "emission_weight must be in"),
        ({"emission_weight": 1.5}, "emission_weight must be in"),
        ({"mode": "backward"}, "mode must be one of"),
        ({"inputs": "scores"}, "inputs must be one of"),
        ({"floor": 0.0}, r"floor must be in \(0, 1\)"),
        ({"switch_rate_prior": -1.0}, "switch_rate_prior must be a positive number"),
    ],
)
def test_bad_parameters(params, match) -> None:
    with pytest.raises(errors.InputError, match=match):
        PathFilter(**{"inputs": "proba", **params}).fit(np.eye(2), [0, 1])


def test_pure_functions_reject_bad_shapes() -> None:
    with pytest.raises(errors.InputError, match="log_initial must have shape"):
        forward(np.zeros((3, 2)), np.zeros((2, 2)), np.zeros(3))
    with pytest.raises(errors.InputError, match="log_transitions must have shape"):
        smooth(np.zeros((3, 2)), np.zeros((5, 2, 2)), np.zeros(2))
    with pytest.raises(errors.InputError, match="no class with finite log probability"):
        update(np.array([0.0, -np.inf]), np.array([-np.inf, 0.0]))
    with pytest.raises(errors.InputError, match="steps_m must be finite and >= 0"):
        transition_matrices(np.zeros((2, 2)), -1.0)


# ------------------------------------------------------------------------ isolated defects


def _rough_path(rng: np.random.Generator, n: int = 120, spacing: float = 0.25):
    """R along a uniform stretch: log-normal drift (factor ~1.6) and frame noise, m^3/rad."""
    d = spacing * np.arange(n)
    drift = np.convolve(rng.normal(size=n + 8), np.ones(9) / 3.0, mode="valid")
    return 16e-6 * np.exp(0.5 * drift + 0.2 * rng.normal(size=n)), d


def test_isolated_spike_is_flagged_with_its_margin() -> None:
    rng = np.random.default_rng(0)
    R, d = _rough_path(rng)
    at = (d >= 10.0) & (d <= 11.0)  # a manhole seen by the patches of 1 m of path
    R[at] *= 40.0
    flagged = isolated_spikes(R, d)
    assert np.all(flagged[at])
    np.testing.assert_array_equal(np.flatnonzero(flagged), np.flatnonzero((d >= 9.5) & (d <= 11.5)))


def test_changes_of_terrain_are_not_defects() -> None:
    rng = np.random.default_rng(1)
    R, d = _rough_path(rng)
    step = R * np.where(d >= 15.0, 100.0, 1.0)  # concrete -> ploughed soil
    assert not isolated_spikes(step, d).any()
    long = R * np.where((d >= 10.0) & (d < 13.0), 30.0, 1.0)  # 3 m of rough ground
    assert not isolated_spikes(long, d).any()
    assert not isolated_spikes(R, d).any()  # nothing on a uniform stretch


def test_spikes_are_scale_and_translation_invariant_and_skip_missing_frames() -> None:
    rng = np.random.default_rng(2)
    R, d = _rough_path(rng)
    R[40:44] *= 50.0
    R[42] = np.nan  # a frame without a valid patch inside the spike
    base = isolated_spikes(R, d)
    assert base[40:44].all() and base.sum() == 4 + 2 * 2  # +-0.5 m: two frames each side
    np.testing.assert_array_equal(isolated_spikes(1e3 * R, d + 123.0), base)
    np.testing.assert_array_equal(isolated_spikes(R, d, ratio=1e4), np.zeros_like(base))


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        (([1.0, 2.0], [0.0]), {}, "same length"),
        (([1.0, 2.0, 3.0], [0.0, 1.0, 0.5]), {}, "non-decreasing"),
        (([1.0, 2.0, 3.0], [0.0, 1.0, np.nan]), {}, "finite"),
        (([1.0, 2.0, 3.0], [0.0, 1.0, 2.0]), {"ratio": 1.0}, "ratio must be"),
        (([1.0, 2.0, 3.0], [0.0, 1.0, 2.0]), {"window": -1.0}, "window must be"),
    ],
)
def test_isolated_spikes_bad_input(args, kwargs, match) -> None:
    with pytest.raises(errors.InputError, match=match):
        isolated_spikes(*args, **kwargs)
