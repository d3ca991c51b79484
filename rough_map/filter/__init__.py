"""Discrete Bayes (HMM) filter of terrain classes along the rover's path.

A per-frame classifier says how likely each of K terrain classes is for the patch ahead. Terrain
does not change class every frame, so these posteriors are smoothed along the path with a
hidden Markov model whose state is the terrain class under the patch.

The model is written **per metre travelled**, not per frame, so that it does not depend on the
rover's speed or the camera's frame rate:

* A generator matrix ``Q`` (K x K, 1/m) holds the rate ``Q[i, j]`` of switching from class ``i``
  to class ``j`` per metre; each row sums to 0 and ``-Q[i, i]`` is the switching rate of class
  ``i``. The transition matrix over ``d`` metres is ``expm(Q * d)``; ``d = 0`` gives identity.
* The emission of a frame is the classifier posterior divided by the class prior (a *scaled
  likelihood*, proportional to p(x | c)), floored so one over-confident frame cannot lock the
  filter, and raised to the power ``emission_weight`` because overlapping patches are not
  independent observations.

The small pure functions (:func:`predict`, :func:`update`, :func:`forward`, :func:`smooth`,
:func:`viterbi`, :func:`estimate_generator`, :func:`transition_matrices`) work in log space and
return new arrays, in the manner of ``filterpy.discrete_bayes``; :class:`PathFilter` is the
scikit-learn estimator whose ``fit`` learns the generator from labelled traverses.
"""

from __future__ import annotations

import logging
from numbers import Integral, Real
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm
from sklearn.base import BaseEstimator, ClassifierMixin, clone
from sklearn.exceptions import NotFittedError as _SklearnNotFittedError
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

from rough_map import errors

__all__ = [
    "PathFilter",
    "estimate_generator",
    "forward",
    "isolated_spikes",
    "predict",
    "smooth",
    "transition_matrices",
    "update",
    "viterbi",
]

logger = logging.getLogger(__name__)

#: Steps are rounded to this many decimals of a metre (1 mm) before ``expm``, so that repeated
#: frame spacings share one matrix exponential.
DISTANCE_DECIMALS = 3

#: Candidate emission weights tried by ``PathFilter(emission_weight="auto")``.
EMISSION_WEIGHT_GRID = (0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)

_MODES = ("forward", "smooth", "viterbi")
_INPUTS = ("features", "proba", "log_likelihood")


class _NotFittedError(errors.NotFittedError, _SklearnNotFittedError):
    """Raised before ``fit``; is both rough_map's and scikit-learn's ``NotFittedError``."""


# --------------------------------------------------------------------------------------------
# Pure functions, log space
# --------------------------------------------------------------------------------------------


def _logsumexp(a: NDArray[np.float64], axis: int | None = None) -> NDArray[np.float64]:
    # Same max-shift formula as scipy.special.logsumexp, which costs ~15x more per call on the
    # K-element arrays of a per-frame loop (array-API dispatch); the filter calls this per frame.
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        s = np.log(np.sum(np.exp(a - m), axis=axis, keepdims=True))
    out = s + m
    return out if axis is None else np.squeeze(out, axis=axis)


def predict(log_belief: ArrayLike, log_transition: ArrayLike) -> NDArray[np.float64]:
    """Propagate a belief through one transition (the HMM *predict* step).

    Parameters
    ----------
    log_belief : array_like, shape (K,)
        Log probability of each class before the step.
    log_transition : array_like, shape (K, K)
        Log transition matrix, ``log_transition[i, j] = log P(class j after | class i before)``;
        rows must be log probability vectors.

    Returns
    -------
    ndarray, shape (K,)
        ``log sum_i exp(log_belief[i] + log_transition[i, j])`` for each ``j``: the log prior
        belief after the step. A new array.
    """
    b = np.asarray(log_belief, dtype=float)
    t = np.asarray(log_transition, dtype=float)
    return _logsumexp(b[:, None] + t, axis=0)


def update(log_belief: ArrayLike, log_likelihood: ArrayLike) -> NDArray[np.float64]:
    """Combine a belief with a measurement (the HMM *update* step, Bayes' rule).

    The log space twin of ``filterpy.discrete_bayes.update``: ``normalize(prior * likelihood)``.

    Parameters
    ----------
    log_belief : array_like, shape (K,)
        Log prior probability of each class.
    log_likelihood : array_like, shape (K,)
        Log likelihood of the measurement under each class, up to an additive constant.

    Returns
    -------
    ndarray, shape (K,)
        Log posterior, normalised so that ``exp`` of it sums to 1. A new array.

    Raises
    ------
    InputError
        If no class has both a non-zero prior and a non-zero likelihood.
    """
    post = np.asarray(log_belief, dtype=float) + np.asarray(log_likelihood, dtype=float)
    norm = _logsumexp(post)
    if not np.isfinite(norm):
        raise errors.InputError(
            "update: belief and likelihood leave no class with finite log probability "
            f"(log_belief={np.asarray(log_belief)}, log_likelihood={np.asarray(log_likelihood)})"
        )
    return post - norm


def _step_transitions(log_transitions: ArrayLike, n: int, k: int) -> NDArray[np.float64]:
    t = np.asarray(log_transitions, dtype=float)
    if t.shape == (k, k):
        return np.broadcast_to(t, (max(n - 1, 0), k, k))
    if t.shape != (max(n - 1, 0), k, k):
        raise errors.InputError(
            f"log_transitions must have shape ({k}, {k}) or ({max(n - 1, 0)}, {k}, {k}) "
            f"for {n} frames of {k} classes; got {t.shape}"
        )
    return t


def _check_sequence(
    log_likelihood: ArrayLike, log_initial: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    ll = np.asarray(log_likelihood, dtype=float)
    if ll.ndim != 2:
        raise errors.InputError(f"log_likelihood must be 2-D (frames, classes); got {ll.shape}")
    init = np.asarray(log_initial, dtype=float)
    if init.shape != (ll.shape[1],):
        raise errors.InputError(
            f"log_initial must have shape ({ll.shape[1]},) to match log_likelihood; "
            f"got {init.shape}"
        )
    return ll, init


def forward(
    log_likelihood: ArrayLike, log_transitions: ArrayLike, log_initial: ArrayLike
) -> NDArray[np.float64]:
    """Forward (online) filter over one sequence of frames.

    Frame 0 is ``update(log_initial, log_likelihood[0])``; frame ``t > 0`` is
    ``update(predict(belief[t-1], log_transitions[t-1]), log_likelihood[t])``. A frame without a
    measurement has a row of zeros in ``log_likelihood`` and so gets a predict step only.

    Parameters
    ----------
    log_likelihood : array_like, shape (n, K)
        Log likelihood of each frame under each class, up to an additive constant per frame.
    log_transitions : array_like, shape (n - 1, K, K) or (K, K)
        Log transition matrix from frame ``t`` to frame ``t + 1``; one matrix is used for all
        steps if 2-D.
    log_initial : array_like, shape (K,)
        Log belief before frame 0 (the class prior).

    Returns
    -------
    ndarray, shape (n, K)
        Log filtered posterior ``log P(class at t | frames 0..t)``; each row is normalised.
    """
    ll, init = _check_sequence(log_likelihood, log_initial)
    n, k = ll.shape
    trans = np.exp(_step_transitions(log_transitions, n, k))
    out = np.empty((n, k))
    if n == 0:
        return out
    belief = update(init, ll[0])
    out[0] = belief
    for t in range(1, n):
        # predict() with the transition already exponentiated: log(exp(b - max) @ T) + max
        m = belief.max()
        with np.errstate(divide="ignore"):
            prior = np.log(np.exp(belief - m) @ trans[t - 1]) + m
        belief = update(prior, ll[t])
        out[t] = belief
    return out


def smooth(
    log_likelihood: ArrayLike, log_transitions: ArrayLike, log_initial: ArrayLike
) -> NDArray[np.float64]:
    """Forward-backward smoother over one sequence of frames (offline).

    Parameters
    ----------
    log_likelihood, log_transitions, log_initial
        As for :func:`forward`.

    Returns
    -------
    ndarray, shape (n, K)
        Log smoothed posterior ``log P(class at t | all frames)``; each row is normalised.
    """
    ll, init = _check_sequence(log_likelihood, log_initial)
    n, k = ll.shape
    log_alpha = forward(ll, log_transitions, init)
    if n == 0:
        return log_alpha
    trans = np.exp(_step_transitions(log_transitions, n, k))
    log_beta = np.zeros((n, k))
    for t in range(n - 2, -1, -1):
        # beta_t(i) = sum_j T[i, j] l_{t+1}(j) beta_{t+1}(j), renormalised to stay in range
        v = ll[t + 1] + log_beta[t + 1]
        m = v.max()
        with np.errstate(divide="ignore"):
            b = np.log(trans[t] @ np.exp(v - m)) + m
        log_beta[t] = b - _logsumexp(b)
    post = log_alpha + log_beta
    return post - _logsumexp(post, axis=1)[:, None]


def viterbi(
    log_likelihood: ArrayLike, log_transitions: ArrayLike, log_initial: ArrayLike
) -> NDArray[np.intp]:
    """Most probable class sequence (Viterbi), in log space.

    Parameters
    ----------
    log_likelihood, log_transitions, log_initial
        As for :func:`forward`.

    Returns
    -------
    ndarray of int, shape (n,)
        Class index per frame of the jointly most probable path; ties go to the lower index.
    """
    ll, init = _check_sequence(log_likelihood, log_initial)
    n, k = ll.shape
    steps = _step_transitions(log_transitions, n, k)
    path = np.zeros(n, dtype=np.intp)
    if n == 0:
        return path
    back = np.zeros((n, k), dtype=np.intp)
    delta = init + ll[0]
    for t in range(1, n):
        scores = delta[:, None] + steps[t - 1]
        back[t] = np.argmax(scores, axis=0)
        delta = scores[back[t], np.arange(k)] + ll[t]
        delta = delta - delta.max()  # a constant shift keeps the numbers in range
    path[-1] = int(np.argmax(delta))
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


def _segments(
    distance: NDArray[np.float64], group_codes: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Consecutive frame pairs (prev, next, step in m) within each group, in array order."""
    order = np.argsort(group_codes, kind="stable")
    same = group_codes[order][1:] == group_codes[order][:-1]
    prev, nxt = order[:-1][same], order[1:][same]
    return prev, nxt, distance[nxt] - distance[prev]


def estimate_generator(
    y: ArrayLike,
    n_classes: int,
    distance: ArrayLike,
    groups: ArrayLike | None = None,
    *,
    switch_rate_prior: float = 0.02,
    min_switch_rate: float = 1e-3,
) -> NDArray[np.float64]:
    """Learn the per-metre switching model from labelled traverses.

    For consecutive frames of one traverse ``d`` metres apart, a pair with the same class ``i``
    adds ``d`` to the distance travelled in ``i``; a switch ``i -> j`` counts one switch and adds
    ``d / 2`` to each class (the boundary is somewhere in between). Then, per class,

    * switching rate ``lambda_i = (n_i + 1) / (L_i + 1 / switch_rate_prior)`` in 1/m, i.e. one
      pseudo-switch over ``1 / switch_rate_prior`` pseudo-metres (a Gamma prior with mean
      ``switch_rate_prior``), and at least ``min_switch_rate``;
    * destinations ``q_ij = (n_ij + 1) / (n_i + K - 1)`` for ``j != i`` (Laplace smoothing).

    Counts and distances come from positions, not frames, so the estimate does not depend on
    the frame spacing as long as frames are dense compared with the class segments.

    Parameters
    ----------
    y : array_like of int, shape (n,)
        Class index per frame, in ``[0, n_classes)``.
    n_classes : int
        K, the number of classes.
    distance : array_like, shape (n,)
        Cumulative distance travelled in m per frame; non-decreasing within each group.
    groups : array_like, shape (n,), optional
        Traverse id per frame; switches are never counted across traverses. Frames of a group
        are taken in array order. Default: one traverse.
    switch_rate_prior : float, default 0.02
        Prior switching rate in 1/m (one switch per 50 m).
    min_switch_rate : float, default 1e-3
        Lower bound on each class's switching rate in 1/m, so that the filter can always leave a
        class.

    Returns
    -------
    ndarray, shape (K, K)
        Generator ``Q`` in 1/m: ``Q[i, j] = lambda_i * q_ij`` off the diagonal, rows sum to 0.
    """
    yi = np.asarray(y, dtype=np.intp)
    dist = np.asarray(distance, dtype=float)
    codes = (
        np.zeros(len(yi), dtype=np.intp)
        if groups is None
        else np.unique(np.asarray(groups), return_inverse=True)[1].ravel()
    )
    if not (len(yi) == len(dist) == len(codes)):
        raise errors.InputError(
            f"y, distance and groups must have the same length; got {len(yi)}, {len(dist)}, "
            f"{len(codes)}"
        )
    counts, travelled = _switch_statistics(yi, n_classes, dist, codes)
    return _generator(counts, travelled, switch_rate_prior, min_switch_rate)


def _switch_statistics(
    y: NDArray[np.intp], n_classes: int, dist: NDArray[np.float64], codes: NDArray[np.intp]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Switch counts (K, K) and metres travelled per class (K,); see estimate_generator."""
    prev, nxt, step = _segments(dist, codes)
    if np.any(step < 0):
        raise errors.InputError("distance must be non-decreasing within each group")
    a, b = y[prev], y[nxt]
    stay = a == b
    travelled = (
        np.bincount(a[stay], step[stay], minlength=n_classes)
        + np.bincount(a[~stay], step[~stay] / 2, minlength=n_classes)
        + np.bincount(b[~stay], step[~stay] / 2, minlength=n_classes)
    )
    counts = np.zeros((n_classes, n_classes))
    np.add.at(counts, (a[~stay], b[~stay]), 1.0)
    return counts, travelled


def _generator(
    counts: NDArray[np.float64],
    travelled: NDArray[np.float64],
    switch_rate_prior: float,
    min_switch_rate: float,
) -> NDArray[np.float64]:
    k = len(travelled)
    if k == 1:
        return np.zeros((1, 1))
    n_out = counts.sum(axis=1)
    rate = np.maximum((n_out + 1.0) / (travelled + 1.0 / switch_rate_prior), min_switch_rate)
    dest = (counts + 1.0) / (n_out + k - 1.0)[:, None]
    np.fill_diagonal(dest, 0.0)
    q = rate[:, None] * dest
    np.fill_diagonal(q, -rate)
    return q


def isolated_spikes(
    values: ArrayLike,
    distance: ArrayLike,
    *,
    ratio: float = 8.0,
    window: float = 3.0,
    max_length: float = 1.5,
    margin: float = 0.5,
) -> NDArray[np.bool_]:
    """Frames that see an isolated defect: a short spike of R along the path.

    A manhole, a pothole or a rock in otherwise uniform ground lifts the overall energy R of
    the few patches that contain it by an order of magnitude, and R falls back once they
    have passed (paper section 5.1, Fig. 13). Those frames say little about what the ground
    around the defect is made of, and a classifier reads them as rougher terrain. A frame is
    *above* when its value exceeds ``ratio`` times the median over the frames within
    ``window`` m along the path; a run of frames above that spans at most ``max_length`` m
    is a spike, and the frames within ``margin`` m of it (which see the defect only in
    part) are flagged with it. A longer run is a change of terrain and is not flagged.

    The test looks ahead of each frame as well as behind it, so it suits recorded traverses
    (the smoother and Viterbi), not the online filter.

    Parameters
    ----------
    values : array_like, shape (n,)
        Per-frame R in m^3/rad (any positive quantity that scales like it); NaN or <= 0 for
        frames without one (never above; inside a run, or within ``margin`` of one, they
        are flagged with it).
    distance : array_like, shape (n,)
        Distance travelled along the path in m, non-decreasing.
    ratio : float
        How many times the local median a frame must exceed (> 1).
    window : float
        Half-width in m of the neighbourhood of the local median.
    max_length : float
        Longest run in m that still counts as one isolated defect.
    margin : float
        Distance in m around a spike within which frames are flagged with it.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    v = np.asarray(values, dtype=float)
    s = np.asarray(distance, dtype=float)
    if v.ndim != 1 or s.shape != v.shape:
        raise errors.InputError(
            f"values and distance must be 1-D of the same length; got {v.shape} and {s.shape}"
        )
    if not np.all(np.isfinite(s)) or np.any(np.diff(s) < 0):
        raise errors.InputError("distance must be finite and non-decreasing (m)")
    for name, value, low in (
        ("ratio", ratio, 1.0),
        ("window", window, 0.0),
        ("max_length", max_length, 0.0),
        ("margin", margin, -np.inf),
    ):
        if not (isinstance(value, Real) and np.isfinite(value) and value > low):
            raise errors.InputError(f"{name} must be a finite number > {low:g}; got {value!r}")
    if margin < 0:
        raise errors.InputError(f"margin must be >= 0 (m); got {margin!r}")
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_v = np.where(np.isfinite(v) & (v > 0), np.log(v), np.nan)
    known = np.isfinite(ln_v)
    n = len(v)
    flagged = np.zeros(n, dtype=bool)
    if known.sum() < 3:
        return flagged
    lo = np.searchsorted(s, s - window, side="left")
    hi = np.searchsorted(s, s + window, side="right")
    above = np.zeros(n, dtype=bool)
    for i in np.flatnonzero(known):
        local = ln_v[lo[i] : hi[i]]
        above[i] = ln_v[i] - np.median(local[np.isfinite(local)]) > np.log(ratio)
    # runs of frames above, bridging frames without a value
    i = 0
    while i < n:
        if not above[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and (above[j + 1] or not known[j + 1]):
            j += 1
        last = j
        while not above[last]:  # the run ends at its last frame above
            last -= 1
        if s[last] - s[i] <= max_length:
            flagged |= (s >= s[i] - margin) & (s <= s[last] + margin)
        i = j + 1
    return flagged


def transition_matrices(generator: ArrayLike, steps_m: ArrayLike) -> NDArray[np.float64]:
    """Transition matrices ``expm(Q * d)`` for steps of ``d`` metres.

    Steps are rounded to 1 mm and each distinct step is exponentiated once.

    Parameters
    ----------
    generator : array_like, shape (K, K)
        Generator ``Q`` in 1/m (rows sum to 0, off-diagonal entries >= 0).
    steps_m : array_like, shape (...)
        Distances travelled in m, >= 0.

    Returns
    -------
    ndarray, shape (..., K, K)
        Row-stochastic transition matrices; exactly the identity where the step is 0.
    """
    q = np.asarray(generator, dtype=float)
    d = np.round(np.asarray(steps_m, dtype=float), DISTANCE_DECIMALS)
    if np.any(~np.isfinite(d)) or np.any(d < 0):
        raise errors.InputError("steps_m must be finite and >= 0 (m)")
    uniq, inverse = np.unique(d, return_inverse=True)
    mats = expm(q[None, :, :] * uniq[:, None, None]) if len(uniq) else np.empty((0, *q.shape))
    # expm can leave round-off of either sign; clip and renormalise the rows
    mats = np.clip(mats, 0.0, None)
    mats /= mats.sum(axis=2, keepdims=True)
    mats[uniq == 0] = np.eye(q.shape[0])
    return mats[inverse.reshape(d.shape)]


# --------------------------------------------------------------------------------------------
# The estimator
# --------------------------------------------------------------------------------------------


class PathFilter(ClassifierMixin, BaseEstimator):
    """HMM filter of terrain classes along the path, with a per-metre switching model.

    ``fit`` learns the classes, their prior and the per-metre generator from labelled traverses
    (and, by default, a classifier from features to posteriors); ``predict_proba`` runs the
    filter over each traverse, starting from the class prior.

    What ``X`` holds is set by ``inputs``:

    * ``"features"`` (default): arbitrary per-frame features. ``classifier`` (default
      ``LogisticRegression()``) is fitted on them in ``fit`` and maps them to posteriors. This
      makes the estimator a self-contained scikit-learn classifier (it passes
      ``check_estimator``, with the two order-invariance checks marked as expected failures
      since the output of a sequence filter depends, by design, on the neighbouring frames).
    * ``"proba"``: the columns of ``X`` are posteriors p(c | x) of an upstream classifier for
      ``classes_`` in sorted order (``np.unique(y)``). Only ratios within a row matter: rows
      are normalised. For ``emission_weight="auto"`` they must be held-out posteriors.
    * ``"log_likelihood"``: the columns are finite log p(x | c), up to an additive constant per
      frame.

    Rows of ``X`` containing NaN are frames without a measurement: they get a predict step
    only (in ``fit`` they are left out of the classifier but still count for the switching
    model).

    Parameters
    ----------
    switch_rate_prior : float, default 0.02
        Prior switching rate in 1/m (one class change per 50 m), worth one pseudo-switch; see
        :func:`estimate_generator`.
    min_switch_rate : float, default 1e-3
        Lower bound on each class's switching rate in 1/m.
    emission_weight : float in (0, 1] or "auto", default 0.5
        Exponent applied to each frame's likelihood (a temperature). Consecutive patches
        overlap (~70 % at 0.25 m frame spacing), so their classifier errors are partly shared
        and a frame carries less than one frame's worth of new evidence; with fully shared
        errors the right weight would be about ``1 - overlap`` = 0.3, with independent errors
        1. The default 0.5 was chosen on simulated 500 m traverses (4 classes, 65 % raw
        accuracy, frames every 0.25 m; forward filter accuracy on 4 test traverses at weights
        0.3 / 0.5 / 1.0): independent errors 0.95 / 0.96 / 0.95; half the error variance
        shared over 3 frames 0.93 / 0.94 / 0.91; all of it shared 0.88 / 0.86 / 0.79. The
        weight is per frame: if you know the errors are mostly shared, use about
        ``spacing / patch length``; or use ``"auto"``, which picks the value from
        :data:`EMISSION_WEIGHT_GRID` that maximises the mean log posterior of the true class on
        the training traverses (posteriors from ``cross_val_predict`` for ``"features"``).
    mode : {"forward", "smooth", "viterbi"}, default "forward"
        ``"forward"``: online filter, each frame uses only past frames. ``"smooth"``:
        forward-backward marginals using all frames of the traverse. ``"viterbi"``:
        ``predict`` returns the jointly most probable class sequence and ``predict_proba`` the
        smoothed marginals (whose argmax may differ from that sequence).
    floor : float, default 1e-6
        Posteriors are clipped from below at ``floor`` (after row normalisation), and
        log-likelihoods at ``log(floor)`` below the row maximum, so that no single frame can
        rule a class out.
    inputs : {"features", "proba", "log_likelihood"}, default "features"
        What the columns of ``X`` are; see above.
    classifier : classifier, default None
        scikit-learn classifier with ``predict_proba`` used when ``inputs="features"``; cloned
        in ``fit``. None means ``LogisticRegression()``.
    cv : int, default 5
        Folds for ``cross_val_predict`` when ``emission_weight="auto"`` and
        ``inputs="features"``. Folds are whole traverses if ``groups`` has at least ``cv``
        traverses, else contiguous blocks of frames.

    Attributes
    ----------
    classes_ : ndarray, shape (K,)
        Class labels, ``np.unique(y)``.
    class_prior_ : ndarray, shape (K,)
        Class frequencies in the training labels; the initial belief of every traverse and the
        divisor that turns posteriors into scaled likelihoods.
    generator_ : ndarray, shape (K, K)
        Generator ``Q`` in 1/m; ``transition_matrix(d)`` is ``expm(Q * d)``.
    switch_counts_ : ndarray, shape (K, K)
        Class switches ``i -> j`` counted in the training traverses.
    distance_per_class_ : ndarray, shape (K,)
        Metres travelled in each class in the training traverses.
    emission_weight_ : float
        The emission weight in use (equal to ``emission_weight`` unless "auto").
    classifier_ : classifier
        Fitted classifier (``inputs="features"`` only).
    n_features_in_ : int
        Number of columns of ``X``.

    Notes
    -----
    ``fit``, ``predict_proba``, ``predict`` and ``predict_log_proba`` take keyword-only
    ``distance`` (cumulative distance in m per frame; default 1 m per frame, with a logged
    warning) and ``groups`` (traverse id per frame; frames of a traverse are taken in array
    order). The prediction methods also take ``valid`` (bool per frame; False means predict
    step only).
    """

    def __init__(
        self,
        switch_rate_prior: float = 0.02,
        min_switch_rate: float = 1e-3,
        emission_weight: float | Literal["auto"] = 0.5,
        mode: Literal["forward", "smooth", "viterbi"] = "forward",
        floor: float = 1e-6,
        inputs: Literal["features", "proba", "log_likelihood"] = "features",
        classifier: Any = None,
        cv: int = 5,
    ) -> None:
        self.switch_rate_prior = switch_rate_prior
        self.min_switch_rate = min_switch_rate
        self.emission_weight = emission_weight
        self.mode = mode
        self.floor = floor
        self.inputs = inputs
        self.classifier = classifier
        self.cv = cv

    def __sklearn_tags__(self):  # type: ignore[no-untyped-def]
        tags = super().__sklearn_tags__()
        # NaN marks a frame without a measurement (predict step only)
        tags.input_tags.allow_nan = True
        return tags

    # ---------------------------------------------------------------- validation helpers

    def _check_params(self) -> None:
        def number(value: Any) -> bool:
            return isinstance(value, Real) and not isinstance(value, bool) and np.isfinite(value)

        for name in ("switch_rate_prior", "min_switch_rate"):
            value = getattr(self, name)
            if not (number(value) and value > 0):
                raise errors.InputError(f"{name} must be a positive number (1/m); got {value!r}")
        if not (isinstance(self.cv, Integral) and self.cv >= 2):
            raise errors.InputError(f"cv must be an integer >= 2; got {self.cv!r}")
        if not (number(self.floor) and 0 < self.floor < 1):
            raise errors.InputError(f"floor must be in (0, 1); got {self.floor!r}")
        w = self.emission_weight
        if not (w == "auto" or (number(w) and 0 < w <= 1)):
            raise errors.InputError(f"emission_weight must be in (0, 1] or 'auto'; got {w!r}")
        if self.mode not in _MODES:
            raise errors.InputError(f"mode must be one of {_MODES}; got {self.mode!r}")
        if self.inputs not in _INPUTS:
            raise errors.InputError(f"inputs must be one of {_INPUTS}; got {self.inputs!r}")

    def _validate_X(self, X: ArrayLike, y: Any = "no_validation", *, reset: bool) -> Any:
        # y="no_validation" is scikit-learn's own sentinel for "X only"; y=None in fit must
        # reach validate_data so that it raises its standard "requires y" message.
        try:
            return validate_data(self, X, y, reset=reset, ensure_all_finite="allow-nan")
        except errors.RoughMapError:
            raise
        except ValueError as err:
            raise errors.InputError(str(err)) from err

    @staticmethod
    def _check_path(
        n: int, distance: ArrayLike | None, groups: ArrayLike | None
    ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        if distance is None:
            logger.warning("PathFilter: no distance given; assuming 1 m between frames")
            dist = np.arange(n, dtype=float)
        else:
            dist = np.asarray(distance, dtype=float)
            if dist.shape != (n,):
                raise errors.InputError(
                    f"distance must have one value (m) per frame, shape ({n},); got {dist.shape}"
                )
            if not np.all(np.isfinite(dist)):
                raise errors.InputError("distance (m) must be finite")
        if groups is None:
            codes = np.zeros(n, dtype=np.intp)
        else:
            g = np.asarray(groups)
            if g.shape != (n,):
                raise errors.InputError(
                    f"groups must have one traverse id per frame, shape ({n},); got {g.shape}"
                )
            codes = np.unique(g, return_inverse=True)[1].ravel().astype(np.intp)
        prev, _, step = _segments(dist, codes)
        bad = np.flatnonzero(step < 0)
        if len(bad):
            i = int(prev[bad[0]])
            raise errors.InputError(
                f"distance must be non-decreasing within each traverse (group); it decreases "
                f"after frame {i} ({dist[i]} m -> {dist[i] - abs(step[bad[0]])} m)"
            )
        return dist, codes

    # ---------------------------------------------------------------- emissions

    def _log_likelihood(
        self, X: NDArray[np.float64], valid: NDArray[np.bool_], weight: float
    ) -> NDArray[np.float64]:
        """Weighted, floored log likelihood per frame (n, K); zero rows where not valid."""
        k = len(self.classes_)
        ll = np.zeros((len(X), k))
        if not valid.any():
            return ll
        log_floor = np.log(self.floor)
        xv = X[valid]
        if self.inputs == "log_likelihood":
            lv = xv - xv.max(axis=1, keepdims=True)
            lv = np.maximum(lv, log_floor)
        else:
            if self.inputs == "features":
                proba = np.full((len(xv), k), 0.0)
                cols = np.searchsorted(self.classes_, self.classifier_.classes_)
                proba[:, cols] = self.classifier_.predict_proba(xv)
            else:
                proba = xv
                if np.any(proba < 0):
                    raise errors.InputError("posteriors in X must be >= 0 (inputs='proba')")
            total = proba.sum(axis=1, keepdims=True)
            if np.any(total <= 0):
                raise errors.InputError(
                    "each valid row of posteriors must have a positive sum; mark frames without "
                    "a measurement with NaN or valid=False"
                )
            lv = np.log(np.maximum(proba / total, self.floor)) - np.log(self.class_prior_)
        ll[valid] = weight * lv
        return ll

    def _valid_mask(self, X: NDArray[np.float64], valid: ArrayLike | None) -> NDArray[np.bool_]:
        finite_rows = ~np.isnan(X).any(axis=1)
        if valid is None:
            return finite_rows
        v = np.asarray(valid)
        if v.shape != (len(X),) or v.dtype != bool:
            raise errors.InputError(
                f"valid must be a boolean array with one value per frame, shape ({len(X)},); "
                f"got dtype {v.dtype} shape {v.shape}"
            )
        bad = np.flatnonzero(v & ~finite_rows)
        if len(bad):
            raise errors.InputError(
                f"X has NaN in frames marked valid=True (first: frame {bad[0]}); mark them "
                "valid=False or leave valid=None to skip NaN frames"
            )
        return v

    # ---------------------------------------------------------------- fit

    def fit(
        self,
        X: ArrayLike,
        y: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
    ) -> PathFilter:
        """Learn classes, class prior, switching generator (and classifier) from traverses.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features)
            Per-frame features, posteriors or log-likelihoods (see ``inputs``).
        y : array_like, shape (n_frames,)
            True class label per frame (any labels ``np.unique`` can sort, e.g. strings).
        distance : array_like, shape (n_frames,), optional
            Cumulative distance travelled along the path in m per frame, non-decreasing within
            each traverse. Default: 1 m between frames (a warning is logged).
        groups : array_like, shape (n_frames,), optional
            Traverse id per frame; switches are not counted across traverses.

        Returns
        -------
        PathFilter
            ``self``, fitted.

        Raises
        ------
        InputError
            Bad parameters, mismatched lengths, decreasing distance, fewer than two classes,
            or (``inputs`` "proba"/"log_likelihood") a column count other than the number of
            classes.
        """
        self._check_params()
        X, y = self._validate_X(X, y, reset=True)
        check_classification_targets(y)
        self.classes_, y_idx = np.unique(y, return_inverse=True)
        y_idx = y_idx.ravel()
        k = len(self.classes_)
        if k < 2:
            raise errors.InputError(
                f"PathFilter needs at least 2 classes in y to filter between; got {k} class"
            )
        if self.inputs != "features" and X.shape[1] != k:
            raise errors.InputError(
                f"with inputs={self.inputs!r} the columns of X are the classes "
                f"{list(self.classes_)} (sorted); X has {X.shape[1]} columns but y has {k} classes"
            )
        dist, codes = self._check_path(len(X), distance, groups)

        self.class_prior_ = np.bincount(y_idx, minlength=k) / len(y_idx)
        self.switch_counts_, self.distance_per_class_ = _switch_statistics(y_idx, k, dist, codes)
        self.generator_ = _generator(
            self.switch_counts_,
            self.distance_per_class_,
            self.switch_rate_prior,
            self.min_switch_rate,
        )

        finite_rows = ~np.isnan(X).any(axis=1)
        if self.inputs == "features":
            if not finite_rows.any():
                raise errors.InputError("X has NaN in every row; nothing to train the classifier")
            self.classifier_ = clone(self._default_classifier()).fit(
                X[finite_rows], self.classes_[y_idx[finite_rows]]
            )

        if self.emission_weight == "auto":
            self.emission_weight_ = self._choose_emission_weight(X, y_idx, finite_rows, dist, codes)
        else:
            self.emission_weight_ = float(self.emission_weight)
        logger.info(
            "PathFilter fitted: %d classes, switching rates %s 1/m, emission weight %.2f",
            k,
            np.array2string(-np.diag(self.generator_), precision=4),
            self.emission_weight_,
        )
        return self

    def _default_classifier(self) -> Any:
        if self.classifier is not None:
            return self.classifier
        from sklearn.linear_model import LogisticRegression

        return LogisticRegression()

    def _choose_emission_weight(
        self,
        X: NDArray[np.float64],
        y_idx: NDArray[np.intp],
        finite_rows: NDArray[np.bool_],
        dist: NDArray[np.float64],
        codes: NDArray[np.intp],
    ) -> float:
        """Emission weight from the grid maximising the mean log posterior of the true class."""
        if self.inputs == "features":
            from sklearn.model_selection import GroupKFold, KFold, cross_val_predict

            n_groups = len(np.unique(codes[finite_rows]))
            # whole traverses per fold if possible, else contiguous blocks (no shuffling), so
            # that overlapping neighbouring patches do not leak between train and test folds
            by_traverse = n_groups >= self.cv
            held_out = cross_val_predict(
                clone(self._default_classifier()),
                X[finite_rows],
                self.classes_[y_idx[finite_rows]],
                groups=codes[finite_rows] if by_traverse else None,
                cv=GroupKFold(self.cv) if by_traverse else KFold(self.cv),
                method="predict_proba",
            )
            Xh = np.full((len(X), len(self.classes_)), np.nan)
            Xh[finite_rows] = 0.0
            cols = np.searchsorted(self.classes_, self.classifier_.classes_)
            Xh[np.ix_(finite_rows, cols)] = held_out
            inputs = "proba"
        else:
            Xh, inputs = X, self.inputs
        scorer = clone(self).set_params(inputs=inputs)
        scorer.classes_, scorer.class_prior_ = self.classes_, self.class_prior_
        scorer.generator_ = self.generator_
        scores = []
        for w in EMISSION_WEIGHT_GRID:
            log_post = scorer._run(Xh, dist, codes, finite_rows, w)[0]
            scores.append(float(np.mean(log_post[np.arange(len(y_idx)), y_idx])))
        best = EMISSION_WEIGHT_GRID[int(np.argmax(scores))]
        logger.info(
            "PathFilter emission_weight='auto': mean log posterior of the true class %s for %s; "
            "chose %.2f",
            np.round(scores, 4).tolist(),
            list(EMISSION_WEIGHT_GRID),
            best,
        )
        return float(best)

    # ---------------------------------------------------------------- inference

    def transition_matrix(self, d_m: ArrayLike) -> NDArray[np.float64]:
        """Class transition matrix over a distance travelled.

        Parameters
        ----------
        d_m : float or array_like
            Distance travelled in m, >= 0 (rounded to 1 mm).

        Returns
        -------
        ndarray, shape (K, K) or (..., K, K)
            ``expm(generator_ * d_m)``: ``[i, j]`` is the probability of being in class
            ``classes_[j]`` after ``d_m`` metres when starting in ``classes_[i]``.
        """
        self._check_fitted()
        return transition_matrices(self.generator_, d_m)

    def _check_fitted(self) -> None:
        try:
            check_is_fitted(self, ["classes_", "generator_"])
        except _SklearnNotFittedError as err:
            raise _NotFittedError(str(err)) from err

    def _run(
        self,
        X: NDArray[np.float64],
        dist: NDArray[np.float64],
        codes: NDArray[np.intp],
        valid: NDArray[np.bool_],
        weight: float,
        decode: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
        """Filter every traverse: log posteriors (n, K) and, if ``decode``, the Viterbi path."""
        ll = self._log_likelihood(X, valid, weight)
        _, nxt, step = _segments(dist, codes)
        trans = transition_matrices(self.generator_, step)
        with np.errstate(divide="ignore"):
            log_trans = np.log(trans)
        # index of the step arriving at each frame (-1 for the first frame of a traverse)
        step_into = np.full(len(X), -1, dtype=np.intp)
        step_into[nxt] = np.arange(len(nxt))
        log_init = np.log(self.class_prior_)
        log_post = np.empty_like(ll)
        path = np.empty(len(X), dtype=np.intp) if decode else None
        run = forward if self.mode == "forward" else smooth
        for g in np.unique(codes):
            idx = np.flatnonzero(codes == g)
            lt = log_trans[step_into[idx[1:]]]
            log_post[idx] = run(ll[idx], lt, log_init)
            if path is not None:
                path[idx] = viterbi(ll[idx], lt, log_init)
        return log_post, path

    def _filter(
        self,
        X: ArrayLike,
        distance: ArrayLike | None,
        groups: ArrayLike | None,
        valid: ArrayLike | None,
        decode: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
        self._check_fitted()
        Xv = self._validate_X(X, reset=False)
        dist, codes = self._check_path(len(Xv), distance, groups)
        mask = self._valid_mask(Xv, valid)
        return self._run(Xv, dist, codes, mask, self.emission_weight_, decode)

    def predict_log_proba(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """Log of :meth:`predict_proba`.

        Parameters
        ----------
        X, distance, groups, valid
            As for :meth:`predict_proba`.

        Returns
        -------
        ndarray, shape (n_frames, K)
            Log posterior per frame and class.
        """
        return self._filter(X, distance, groups, valid)[0]

    def predict_proba(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """Filtered (mode "forward") or smoothed (other modes) class posteriors per frame.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features)
            As in ``fit``; rows with NaN are frames without a measurement.
        distance : array_like, shape (n_frames,), optional
            Cumulative distance in m per frame, non-decreasing within each traverse. Default:
            1 m between frames (a warning is logged).
        groups : array_like, shape (n_frames,), optional
            Traverse id per frame. Each traverse starts from ``class_prior_``.
        valid : array_like of bool, shape (n_frames,), optional
            False for frames that get a predict step only. Default: rows of ``X`` without NaN.

        Returns
        -------
        ndarray, shape (n_frames, K)
            Posterior per frame over ``classes_``; rows sum to 1.

        Raises
        ------
        InputError
            Shape mismatches, decreasing distance, NaN in a frame marked valid, bad posteriors.
        """
        return np.exp(self.predict_log_proba(X, distance=distance, groups=groups, valid=valid))

    def predict(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[Any]:
        """Class per frame: argmax of :meth:`predict_proba`, or the Viterbi path.

        Parameters
        ----------
        X, distance, groups, valid
            As for :meth:`predict_proba`.

        Returns
        -------
        ndarray, shape (n_frames,)
            Labels from ``classes_``.
        """
        log_post, path = self._filter(X, distance, groups, valid, self.mode == "viterbi")
        return self.classes_[path if path is not None else np.argmax(log_post, axis=1)]
