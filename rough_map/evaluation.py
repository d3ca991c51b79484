"""Scores of a terrain model on labelled feature tables (raw and filtered classes)."""

from __future__ import annotations

from typing import Any

import numpy as np

from rough_map.errors import InputError


def evaluate_model(model: Any, tables: list[Any], mode: str | None = None) -> dict[str, Any]:
    """Confusion matrices, per-class precision/recall/F1, macro-F1 and accuracy.

    Frames without a label are skipped, and so are frames without a valid patch (they have
    no raw class); both are counted in ``frames``. Scores come from
    :func:`rough_map.classify.scores` (sklearn.metrics), for the raw classifier output and
    for the path-filtered classes.

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
        ``mode``, ``frames`` (total, scored, unlabelled, invalid), ``raw`` and ``filtered``
        (each with ``classes``, ``confusion_matrix``, ``confusion_matrix_normalized``,
        ``accuracy``, ``macro_f1``, per-class scores) and ``per_traverse``.
    """
    from rough_map.classify import scores

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
            r = scores(labels[scored], pred.raw_class[scored])
            f = scores(labels[scored], pred.filtered_class[scored])
            per_traverse.append(
                {
                    "name": tab.name,
                    "frames": int(scored.sum()),
                    "raw": {"accuracy": r["accuracy"], "macro_f1": r["macro_f1"]},
                    "filtered": {"accuracy": f["accuracy"], "macro_f1": f["macro_f1"]},
                }
            )
    if counts["scored"] == 0:
        raise InputError(
            f"no frame to score: of {counts['total']} frames, {counts['unlabelled']} have no "
            f"label and {counts['invalid']} no valid patch"
        )
    y = np.concatenate(truth)
    return {
        "mode": used_mode,
        "frames": counts,
        "raw": scores(y, np.concatenate(raw)),
        "filtered": scores(y, np.concatenate(filtered)),
        "per_traverse": per_traverse,
    }
