"""The classifier's evidence for the path filter, weighted by the ground each frame adds.

Consecutive patches overlap, so a frame brings new evidence in proportion to the ground it
adds: :func:`emission_log_likelihood` weighs each frame's log posterior by
``min(1, evidence_per_m * step)``, with the step from :func:`frame_steps`, so that the
evidence per metre does not depend on the speed. :func:`choose_evidence_per_m` picks the
weight per metre from :data:`EVIDENCE_GRID` on held-out posteriors.
"""

from __future__ import annotations

import copy
import logging
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

log = logging.getLogger(__name__)

__all__ = ["EVIDENCE_GRID", "choose_evidence_per_m", "emission_log_likelihood", "frame_steps"]

#: Candidate evidence per metre travelled (1/m) that :meth:`TerrainModel.fit` chooses from.
EVIDENCE_GRID: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)


def frame_steps(distance: ArrayLike, groups: ArrayLike | None = None) -> NDArray[np.float64]:
    """Distance in m from each frame to the previous frame of its traverse.

    The first frame of a traverse gets the traverse's median step.

    Parameters
    ----------
    distance : array_like, shape (n,)
        Cumulative distance along the path in m, non-decreasing within a traverse.
    groups : array_like, shape (n,), optional
        Traverse id per frame (frames of a traverse in order). Default: one traverse.

    Returns
    -------
    ndarray, shape (n,)
        Steps in m.
    """
    d = np.asarray(distance, dtype=float)
    g = np.zeros(len(d), dtype=np.intp) if groups is None else np.asarray(groups)
    steps = np.zeros(len(d))
    for value in np.unique(g):
        idx = np.flatnonzero(g == value)
        if len(idx) > 1:
            step = np.diff(d[idx])
            steps[idx[1:]] = step
            steps[idx[0]] = float(np.median(step))
    return steps


def emission_log_likelihood(
    proba: ArrayLike,
    steps: ArrayLike,
    evidence_per_m: float,
    prior: ArrayLike | None = None,
    floor: float = 1e-6,
) -> NDArray[np.float64]:
    """Scaled log likelihoods for the path filter, weighted by the distance each frame adds.

    Consecutive patches overlap (a 0.9 m patch, a frame every 0.15 to 0.35 m at 0.3 to 0.7
    m/s and 2 Hz), so a frame brings new evidence in proportion to the ground it adds:
    its emission is ``min(1, evidence_per_m * step) * (log p(c | x) - log prior(c))``. The
    evidence per metre is then the same whatever the speed, where a fixed weight per frame
    would over-trust slow traverses and under-trust fast ones.

    Parameters
    ----------
    proba : array_like, shape (n, K)
        Classifier posteriors (rows are normalised); NaN rows for frames without one.
    steps : array_like, shape (n,)
        Ground in m each frame adds (:func:`frame_steps`).
    evidence_per_m : float
        Weight per metre travelled, 1/m.
    prior : array_like, shape (K,), optional
        Class prior the posteriors were trained under; default uniform (a classifier
        trained with balanced class weights, as :func:`make_classifier` builds it).
    floor : float
        Posteriors are clipped from below at this value.

    Returns
    -------
    ndarray, shape (n, K)
        Log likelihood per frame up to a constant; NaN rows where ``proba`` has NaN.
    """
    p = np.asarray(proba, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = p / p.sum(axis=1, keepdims=True)
        ll = np.log(np.maximum(p, floor))
        if prior is not None:
            ll = ll - np.log(np.asarray(prior, dtype=float))
    weight = np.minimum(1.0, evidence_per_m * np.asarray(steps, dtype=float))
    ll = ll * weight[:, None]
    ll[np.isnan(p).any(axis=1)] = np.nan
    return ll


def choose_evidence_per_m(
    path_filter: Any,
    held_out: NDArray[np.float64],
    steps: NDArray[np.float64],
    y: NDArray[Any],
    *,
    distance: NDArray[np.float64],
    groups: NDArray[Any],
    scored: NDArray[np.bool_],
) -> float:
    """The evidence per metre of :data:`EVIDENCE_GRID` with the best filtered macro-F1.

    The score is the mean of the forward filter's and the smoother's macro-F1 on the
    held-out posteriors: too little evidence makes the forward filter lag behind a change
    of class; too much lets a run of wrong frames flip it.

    Parameters
    ----------
    path_filter : fitted path filter
        Takes log likelihoods; ``predict(X, distance=, groups=, valid=)`` and a ``mode``
        parameter (``set_params``). Left unchanged (a shallow copy is probed).
    held_out : ndarray, shape (n, K)
        Held-out classifier posteriors; NaN rows where there are none.
    steps : ndarray, shape (n,)
        Ground in m each frame adds (:func:`frame_steps`).
    y : ndarray, shape (n,)
        True class per frame.
    distance : ndarray, shape (n,)
        Distance along the path in m.
    groups : ndarray, shape (n,)
        Traverse per frame.
    scored : ndarray of bool, shape (n,)
        Frames with held-out posteriors, the ones scored.

    Returns
    -------
    float
        Evidence per metre, 1/m.
    """
    from sklearn.metrics import f1_score

    probe = copy.copy(path_filter)
    tried = []
    for per_m in EVIDENCE_GRID:
        ll = emission_log_likelihood(held_out, steps, per_m)
        f1 = []
        for mode in ("forward", "smooth"):
            probe.set_params(mode=mode)
            pred = probe.predict(ll, distance=distance, groups=groups, valid=scored)
            f1.append(f1_score(y[scored], pred[scored].astype(str), average="macro"))
        tried.append(float(np.mean(f1)))
    best = float(EVIDENCE_GRID[int(np.argmax(tried))])
    log.info(
        "evidence per metre: held-out filtered macro-F1 %s for %s 1/m; chose %.2f 1/m",
        np.round(tried, 3).tolist(),
        list(EVIDENCE_GRID),
        best,
    )
    return best
