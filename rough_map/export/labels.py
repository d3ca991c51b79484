"""``labels.csv``: the raw and filtered class of every frame of a mapped traverse."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from rough_map._files import PathLike, atomic_output
from rough_map.classify import TerrainPrediction
from rough_map.features import FeatureTable
from rough_map.features.table import SMOOTH_COLUMNS

__all__ = ["LABEL_COLUMNS", "write_labels"]

#: Columns of ``labels.csv``, in order: frame index, time (s), position x, y (m, world),
#: distance along the path (m), valid patch, true label, raw class and its probability,
#: filtered class and its probability, roughness level, isolated defect, the novelty score
#: and its flag (ground unlike every trained class, :attr:`TerrainPrediction.novelty`; empty
#: without a valid patch or a score), and the roughness
#: smoothed along the path (R in m³/rad, w, standard deviations of ln R and w; empty when
#: the features were not smoothed), and the speed advice for a vehicle (``v_max``,
#: ``v_max_95`` in m/s; empty without one: :mod:`rough_map.features.driving`).
LABEL_COLUMNS = (
    "frame",
    "t",
    "x",
    "y",
    "distance",
    "valid",
    "label",
    "raw_class",
    "raw_p",
    "filtered_class",
    "filtered_p",
    "level",
    "defect",
    "novelty",
    "novel",
    *SMOOTH_COLUMNS,
    "v_max",
    "v_max_95",
)


def write_labels(features: FeatureTable, prediction: TerrainPrediction, path: PathLike) -> Path:
    """Write the classes of every frame as a plain CSV (atomic), columns
    :data:`LABEL_COLUMNS`.

    Parameters
    ----------
    features : FeatureTable
        The traverse's features (frame, t, x, y in m, true label).
    prediction : TerrainPrediction
        The model's classes for the same frames.
    path : str or Path
        The ``.csv`` file.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    f, pred = features, prediction
    raw_p = pred.raw_confidence
    filt_p = pred.filtered_confidence
    defect = pred.defect if pred.defect is not None else np.zeros(len(f), dtype=bool)
    nan = np.full(len(f), np.nan)
    novelty = np.asarray(pred.novelty if pred.novelty is not None else nan, dtype=float)
    smoothed = [
        np.asarray(f.columns.get(c, nan), dtype=float)
        for c in (*SMOOTH_COLUMNS, "v_max", "v_max_95")
    ]
    # a column at a time: the same text as formatting each value (tolist gives the same
    # floats; a str column's values are written as they are)
    t, x, y = (np.asarray(f[c]).tolist() for c in ("t", "x", "y"))
    columns = [
        [int(v) for v in np.asarray(f["frame"]).tolist()],
        [f"{v:.6g}" for v in t],
        [f"{v:.4f}" for v in x],
        [f"{v:.4f}" for v in y],
        [f"{v:.4f}" for v in np.asarray(pred.distance).tolist()],
        ["true" if v else "false" for v in np.asarray(pred.valid).tolist()],
        list(f["label"]),
        list(pred.raw_class),
        ["" if not math.isfinite(v) else f"{v:.4f}" for v in np.asarray(raw_p).tolist()],
        list(pred.filtered_class),
        ["" if not math.isfinite(v) else f"{v:.4f}" for v in np.asarray(filt_p).tolist()],
        list(pred.level),
        ["true" if v else "false" for v in np.asarray(defect).tolist()],
        ["" if not math.isfinite(v) else f"{v:.3f}" for v in novelty.tolist()],
        ["" if not math.isfinite(v) else ("true" if v > 1 else "false") for v in novelty.tolist()],
        *(["" if not math.isfinite(v) else f"{v:.6g}" for v in col.tolist()] for col in smoothed),
    ]
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LABEL_COLUMNS)
        w.writerows(zip(*columns, strict=True))
    return path
