"""Classification scores: confusion matrix, per-class and overall figures (sklearn.metrics)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rough_map import errors

__all__ = ["scores"]


def scores(
    y_true: ArrayLike, y_pred: ArrayLike, classes: Sequence[str] | None = None
) -> dict[str, Any]:
    """Confusion matrix and per-class and overall scores, from :mod:`sklearn.metrics`.

    The classes are ``classes`` if given (they must hold every true and predicted class),
    else those in ``y_true`` or ``y_pred`` (sorted), as scikit-learn's defaults take them,
    so every number equals the corresponding ``sklearn.metrics`` call on the same labels.
    The macro-F1 averages the F1 over the classes present in ``y_true`` only
    (``scored_classes``): a class predicted but never true is not averaged in.

    Parameters
    ----------
    y_true, y_pred : array_like of str, shape (n,)
        True and predicted class per scored frame.
    classes : sequence of str, optional
        Rows and columns of the confusion matrix, in this order (e.g. the same for raw and
        filtered predictions).

    Returns
    -------
    dict
        ``classes``; ``confusion_matrix`` (counts, rows true, columns predicted);
        ``confusion_matrix_normalized`` (rows divided by their sum, the recall on the
        diagonal; a class never true has a row of zeros); ``precision``, ``recall``,
        ``f1`` and ``support`` per class (dicts); ``accuracy``; ``macro_f1``;
        ``scored_classes`` (the true classes the macro-F1 averages); ``frames``.
    """
    from sklearn.metrics import (
        accuracy_score,
        confusion_matrix,
        f1_score,
        precision_recall_fscore_support,
    )
    from sklearn.utils.multiclass import unique_labels

    t = np.asarray(y_true).astype(str)
    p = np.asarray(y_pred).astype(str)
    if len(t) == 0:
        raise errors.InputError("no frames to score")
    present = unique_labels(t)
    if classes is None:
        labels = unique_labels(t, p)
    else:
        given = [str(c) for c in classes]
        missing = sorted({str(c) for c in unique_labels(t, p)} - set(given))
        if missing:
            raise errors.InputError(f"classes {given} lack the scored classes {missing}")
        labels = np.asarray(given)
    cm = confusion_matrix(t, p, labels=labels)
    rows = cm.sum(axis=1, keepdims=True)
    norm = np.divide(cm, rows, out=np.zeros(cm.shape), where=rows > 0)
    prec, rec, f1, sup = precision_recall_fscore_support(t, p, labels=labels, zero_division=0)
    names = [str(c) for c in labels]
    return {
        "classes": names,
        "confusion_matrix": cm.tolist(),
        "confusion_matrix_normalized": norm.tolist(),
        "precision": dict(zip(names, map(float, prec), strict=True)),
        "recall": dict(zip(names, map(float, rec), strict=True)),
        "f1": dict(zip(names, map(float, f1), strict=True)),
        "support": dict(zip(names, map(int, sup), strict=True)),
        "accuracy": float(accuracy_score(t, p)),
        "macro_f1": float(f1_score(t, p, labels=present, average="macro", zero_division=0)),
        "scored_classes": [str(c) for c in present],
        "frames": int(len(t)),
    }
