"""The switching model of the path filter, written per metre travelled.

A generator matrix ``Q`` (K x K, 1/m) holds the rate ``Q[i, j]`` of switching from class ``i``
to class ``j`` per metre; each row sums to 0 and ``-Q[i, i]`` is the switching rate of class
``i``. The transition matrix over ``d`` metres is ``expm(Q * d)`` (:func:`transition_matrices`);
``d = 0`` gives the identity. Written per metre, not per frame, the model does not depend on
the rover's speed or the camera's frame rate. :func:`estimate_generator` learns ``Q`` from
labelled traverses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm

from rough_map import errors

__all__ = [
    "DISTANCE_DECIMALS",
    "consecutive_steps",
    "estimate_generator",
    "generator_from_counts",
    "switch_statistics",
    "transition_matrices",
]

#: Steps are rounded to this many decimals of a metre (1 mm) before ``expm``, so that repeated
#: frame spacings share one matrix exponential.
DISTANCE_DECIMALS = 3


def consecutive_steps(
    distance: NDArray[np.float64], group_codes: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Consecutive frame pairs within each group, in array order.

    Parameters
    ----------
    distance : ndarray, shape (n,)
        Cumulative distance travelled in m per frame.
    group_codes : ndarray of int, shape (n,)
        Traverse code per frame.

    Returns
    -------
    prev, next : ndarray of int
        Indices of the earlier and the later frame of each pair.
    step : ndarray
        Distance in m from ``prev`` to ``next`` (negative if the distance decreases).
    """
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
    counts, travelled = switch_statistics(yi, n_classes, dist, codes)
    return generator_from_counts(counts, travelled, switch_rate_prior, min_switch_rate)


def switch_statistics(
    y: NDArray[np.intp], n_classes: int, dist: NDArray[np.float64], codes: NDArray[np.intp]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Switch counts and metres travelled per class (see :func:`estimate_generator`).

    Parameters
    ----------
    y : ndarray of int, shape (n,)
        Class index per frame.
    n_classes : int
        K.
    dist : ndarray, shape (n,)
        Cumulative distance travelled in m per frame.
    codes : ndarray of int, shape (n,)
        Traverse code per frame.

    Returns
    -------
    counts : ndarray, shape (K, K)
        Switches ``i -> j``.
    travelled : ndarray, shape (K,)
        Metres travelled in each class.
    """
    prev, nxt, step = consecutive_steps(dist, codes)
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
    return counts, np.asarray(travelled, dtype=float)


def generator_from_counts(
    counts: NDArray[np.float64],
    travelled: NDArray[np.float64],
    switch_rate_prior: float,
    min_switch_rate: float,
) -> NDArray[np.float64]:
    """The generator ``Q`` in 1/m from :func:`switch_statistics` (see
    :func:`estimate_generator` for the priors; rates in 1/m)."""
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
