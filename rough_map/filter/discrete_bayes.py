"""Discrete Bayes filter in log space: small pure functions that return new arrays.

In the manner of ``filterpy.discrete_bayes``, written in log space so that long traverses
and confident classifiers do not underflow:

* :func:`predict` propagates a belief through one transition matrix;
* :func:`update` combines it with a measurement (Bayes' rule);
* :func:`forward` runs both along a sequence of frames (the online filter);
* :func:`smooth` is the forward-backward smoother (offline marginals);
* :func:`viterbi` gives the jointly most probable class sequence.

A frame without a measurement has a row of zeros in the log likelihood and so gets a predict
step only. The transition matrices come from :mod:`rough_map.filter.switching`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map import errors

__all__ = ["forward", "predict", "smooth", "update", "viterbi"]


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
    with np.errstate(divide="ignore"):
        for t in range(1, n):
            # predict() with the transition already exponentiated: log(exp(b - max) @ T) +
            # max; then update() with its normalisation written out (a frame's loop, 7,200
            # times for an hour of driving: half the time of the calls)
            m = belief.max()
            prior = np.log(np.exp(belief - m) @ trans[t - 1]) + m
            post = prior + ll[t]
            top = post.max()
            if not np.isfinite(top):
                update(prior, ll[t])  # raises, naming what is wrong
            belief = post - (np.log(np.exp(post - top).sum()) + top)
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
    with np.errstate(divide="ignore"):
        for t in range(n - 2, -1, -1):
            # beta_t(i) = sum_j T[i, j] l_{t+1}(j) beta_{t+1}(j), shifted to stay in range
            # (any constant per frame: the posterior is normalised at the end)
            v = ll[t + 1] + log_beta[t + 1]
            m = v.max()
            b = np.log(trans[t] @ np.exp(v - m))
            log_beta[t] = b - b.max()
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
