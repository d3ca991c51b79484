"""Cross-validated scores of a terrain model, raw and after the path filter.

The scores come from :mod:`sklearn.metrics` directly: the held-out posteriors of
:func:`~rough_map.classify.training.held_out_posteriors` give the raw class of each frame,
and a path filter fitted on the other folds' labels gives the filtered class
(:func:`filtered_held_out`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map.classify.evidence import emission_log_likelihood
from rough_map.classify.training import Folds, TrainingFrames

__all__ = ["cross_validated_report", "filtered_held_out", "scored_frames"]


def scored_frames(held_out: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Frames with a held-out posterior, the ones the cross-validation scores."""
    return np.asarray(np.isfinite(held_out).all(axis=1), dtype=bool)


def filtered_held_out(
    path_filter: Any,
    held_out: NDArray[np.float64],
    frames: TrainingFrames,
    folds: Folds,
    steps: NDArray[np.float64],
    evidence_per_m: float | None,
) -> NDArray[np.object_]:
    """The filtered class of every frame, fold by fold.

    Per fold, the path filter's switching model and class prior come from the other folds'
    labels (a fold whose other folds lack a class keeps ``path_filter`` as it is); the
    evidence per metre is the one given.

    Parameters
    ----------
    path_filter : fitted path filter or None
        None: no filter, the filtered class is the raw one.
    held_out : ndarray, shape (n, K)
        Held-out posteriors (NaN rows where there are none).
    frames : TrainingFrames
    folds : Folds
    steps : ndarray, shape (n,)
        Ground in m each frame adds (:func:`~rough_map.classify.evidence.frame_steps`).
    evidence_per_m : float or None
        Evidence per metre, 1/m (None without a filter).

    Returns
    -------
    ndarray of str, shape (n,)
        ``""`` for frames without a held-out posterior when there is no filter.
    """
    from sklearn.base import clone

    classes = np.unique(frames.y)
    scored = scored_frames(held_out)
    filtered = np.full(len(frames.y), "", dtype=object)
    if path_filter is None or evidence_per_m is None:
        filtered[scored] = classes[np.argmax(held_out[scored], axis=1)]
        return filtered
    y, d, g = frames.y, frames.distance, folds.groups
    for fit_idx, test_idx in folds.splits:
        if len(np.unique(y[fit_idx])) < len(classes):
            flt = path_filter  # a fold lacks a class: keep the full model's switching
        else:
            flt = clone(path_filter).fit(
                emission_log_likelihood(held_out[fit_idx], steps[fit_idx], 1.0),
                y[fit_idx],
                distance=d[fit_idx],
                groups=g[fit_idx],
            )
        filtered[test_idx] = flt.predict(
            emission_log_likelihood(held_out[test_idx], steps[test_idx], evidence_per_m),
            distance=d[test_idx],
            groups=g[test_idx],
            valid=scored[test_idx],
        )
    return filtered


def cross_validated_report(
    held_out: NDArray[np.float64],
    filtered: NDArray[np.object_],
    frames: TrainingFrames,
    folds: Folds,
    mode: str,
) -> dict[str, Any]:
    """Accuracy, macro-F1 and F1 per class of the raw and filtered held-out classes.

    Parameters
    ----------
    held_out : ndarray, shape (n, K)
        Held-out posteriors; the frames without one are not scored.
    filtered : ndarray of str, shape (n,)
        Filtered class per frame (:func:`filtered_held_out`).
    frames : TrainingFrames
    folds : Folds
    mode : str
        Filter mode, for the report.

    Returns
    -------
    dict
        ``scheme``, ``n_splits``, ``frames``, ``mode``; ``raw`` and ``filtered``, each with
        ``accuracy``, ``macro_f1`` and ``f1`` per class; ``per_fold`` (traverses, frames,
        raw and filtered macro-F1).
    """
    from sklearn.metrics import accuracy_score, f1_score

    classes = np.unique(frames.y)
    scored = scored_frames(held_out)
    y = frames.y
    per_fold = []
    for _, test_idx in folds.splits:
        ok = test_idx[scored[test_idx]]
        if len(ok) == 0:
            continue
        raw_f = classes[np.argmax(held_out[ok], axis=1)]
        traverses = {frames.names[int(i)] for i in np.unique(frames.traverse[ok])}
        per_fold.append(
            {
                "traverses": sorted(traverses) if folds.by_traverse else [],
                "frames": int(len(ok)),
                "raw_macro_f1": float(f1_score(y[ok], raw_f, average="macro")),
                "filtered_macro_f1": float(
                    f1_score(y[ok], filtered[ok].astype(str), average="macro")
                ),
            }
        )
    truth = y[scored]

    def summary(pred: NDArray[Any]) -> dict[str, Any]:
        f1 = f1_score(truth, pred, labels=classes, average=None, zero_division=0)
        return {
            "accuracy": float(accuracy_score(truth, pred)),
            "macro_f1": float(f1_score(truth, pred, average="macro")),
            "f1": {str(c): float(f) for c, f in zip(classes, f1, strict=True)},
        }

    raw = classes[np.argmax(np.nan_to_num(held_out[scored], nan=-1.0), axis=1)]
    return {
        "scheme": folds.scheme,
        "n_splits": int(folds.n_splits),
        "frames": int(scored.sum()),
        "mode": mode,
        "raw": summary(raw),
        "filtered": summary(filtered[scored].astype(str)),
        "per_fold": per_fold,
    }
