"""``labels.csv``: the raw and filtered class of every frame of a mapped traverse."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from rough_map._files import PathLike, atomic_output
from rough_map.classify import TerrainPrediction
from rough_map.features import FeatureTable
from rough_map.features.table import SMOOTH_COLUMNS

__all__ = ["LABEL_COLUMNS", "write_labels"]

#: Columns of ``labels.csv``, in order: frame index, time (s), position x, y (m, world),
#: distance along the path (m), valid patch, true label, raw class and its probability,
#: filtered class and its probability, roughness level, isolated defect, and the roughness
#: smoothed along the path (R in m³/rad, w, standard deviations of ln R and w; empty when
#: the features were not smoothed).
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
    *SMOOTH_COLUMNS,
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
    smoothed = [np.asarray(f.columns.get(c, nan), dtype=float) for c in SMOOTH_COLUMNS]
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(LABEL_COLUMNS)
        for i in range(len(f)):
            w.writerow(
                [
                    int(f["frame"][i]),
                    f"{f['t'][i]:.6g}",
                    f"{f['x'][i]:.4f}",
                    f"{f['y'][i]:.4f}",
                    f"{pred.distance[i]:.4f}",
                    "true" if pred.valid[i] else "false",
                    f["label"][i],
                    pred.raw_class[i],
                    "" if not np.isfinite(raw_p[i]) else f"{raw_p[i]:.4f}",
                    pred.filtered_class[i],
                    f"{filt_p[i]:.4f}",
                    pred.level[i],
                    "true" if defect[i] else "false",
                    *("" if not np.isfinite(v[i]) else f"{v[i]:.6g}" for v in smoothed),
                ]
            )
    return path
