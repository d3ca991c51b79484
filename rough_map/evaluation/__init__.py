"""Scores of a terrain model on labelled feature tables (raw and filtered classes)."""

from __future__ import annotations

from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.evaluation.metrics import scores


def evaluate_model(model: Any, tables: list[Any], mode: str | None = None) -> dict[str, Any]:
    """Confusion matrices, per-class precision/recall/F1, macro-F1 and accuracy.

    Frames without a label are skipped, and so are frames without a valid patch (they have
    no raw class); both are counted in ``frames``. Scores come from
    :func:`rough_map.evaluation.metrics.scores` (sklearn.metrics), for the raw classifier output and
    for the path-filtered classes.

    Raw and filtered results have the same ``classes``, in the same order: every class that
    is true or predicted (raw or filtered) on a scored frame, sorted. The macro-F1 is the
    mean F1 over the classes present in the truth, ``scored_classes``; a class the model
    predicts but that is never true lowers the recall of the true classes, not the average.

    Parameters
    ----------
    model : TerrainModel
        A fitted model.
    tables : list of FeatureTable
        Labelled traverses.
    mode : {"forward", "smooth", "viterbi"}, optional
        Filter mode; default the model's.

    Returns
    -------
    dict
        ``mode``, ``frames`` (total, scored, unlabelled, invalid), ``scored_classes``,
        ``raw`` and ``filtered`` (each with ``classes``, ``confusion_matrix``,
        ``confusion_matrix_normalized``, ``accuracy``, ``macro_f1``, ``scored_classes``,
        per-class scores) and ``per_traverse``.
    """

    truth, raw, filtered, per_traverse = [], [], [], []
    counts = {"total": 0, "scored": 0, "unlabelled": 0, "invalid": 0}
    used_mode = mode
    for tab in tables:
        labels = np.array([str(v) for v in tab.columns["label"]], dtype=object)
        model.check_labels(labels, where=f"traverse {tab.name!r}")
        pred = model.predict(tab, mode=mode)
        used_mode = pred.mode
        labelled = labels != ""
        scored = labelled & pred.valid
        counts["total"] += len(tab)
        counts["unlabelled"] += int((~labelled).sum())
        counts["invalid"] += int((labelled & ~pred.valid).sum())
        counts["scored"] += int(scored.sum())
        truth.append(labels[scored])
        raw.append(pred.raw_class[scored])
        filtered.append(pred.filtered_class[scored])
        if scored.any():
            cls = _classes(labels[scored], pred.raw_class[scored], pred.filtered_class[scored])
            r = scores(labels[scored], pred.raw_class[scored], cls)
            f = scores(labels[scored], pred.filtered_class[scored], cls)
            per_traverse.append(
                {
                    "name": tab.name,
                    "frames": int(scored.sum()),
                    "scored_classes": r["scored_classes"],
                    "raw": {"accuracy": r["accuracy"], "macro_f1": r["macro_f1"]},
                    "filtered": {"accuracy": f["accuracy"], "macro_f1": f["macro_f1"]},
                }
            )
    if counts["scored"] == 0:
        raise InputError(
            f"no frame to score: of {counts['total']} frames, {counts['unlabelled']} have no "
            f"label and {counts['invalid']} no valid patch"
        )
    y_all = np.concatenate(truth)
    raw_all, filtered_all = np.concatenate(raw), np.concatenate(filtered)
    cls = _classes(y_all, raw_all, filtered_all)
    raw_scores = scores(y_all, raw_all, cls)
    return {
        "mode": used_mode,
        "frames": counts,
        "raw": raw_scores,
        "filtered": scores(y_all, filtered_all, cls),
        "per_traverse": per_traverse,
        "scored_classes": raw_scores["scored_classes"],
    }


def _classes(*labels: np.ndarray) -> list[str]:
    """Every class in ``labels`` (true, raw, filtered), sorted: one order for all matrices."""
    return sorted({str(v) for lab in labels for v in lab})
