"""Near-to-far on the path band, against the nearest-near-field-cell baseline.

The ground the rover will drive over matters most, and there a trivial rule is hard to
beat: give a far cell the class of the nearest ground the near field has already labelled
(terrain continues). :func:`path_band_accuracy` scores near-to-far's labelled cells that
lie on the path band (within ``half_width`` of the rover's track) and, on the same cells,
that baseline, built from the near labels of the frames up to the predicting one only.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rough_map.errors import InputError
from rough_map.evaluation.near_far import class_remap, world_class
from rough_map.geometry import pose_matrix
from rough_map.io.truth import World
from rough_map.near_far import FarPrediction, NearField
from rough_map.patch import Extraction, PatchSpec

__all__ = ["PathBand", "path_band_accuracy"]


@dataclass(frozen=True)
class PathBand:
    """Scores on the path band (:func:`path_band_accuracy`).

    Attributes
    ----------
    n : int
        Labelled far cells on the band with a known true class (counted once per frame).
    accuracy : float
        Share of them near-to-far got right (NaN without any).
    baseline_accuracy : float
        Share of the same cells the nearest-near-field-cell baseline got right.
    half_width : float
        Half width of the band, m.
    """

    n: int
    accuracy: float
    baseline_accuracy: float
    half_width: float

    def to_dict(self) -> dict[str, Any]:
        """Plain types for JSON (NaN as None)."""

        def number(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "cells": self.n,
            "accuracy": number(self.accuracy),
            "baseline_accuracy": number(self.baseline_accuracy),
            "half_width_m": self.half_width,
        }


def path_band_accuracy(
    predictions: Sequence[FarPrediction],
    world: World,
    poses: ArrayLike,
    near_labels: Sequence[str | None],
    patch: PatchSpec | Extraction,
    *,
    half_width: float | None = None,
) -> PathBand:
    """Accuracy of near-to-far and of the nearest-near-field-cell baseline on the path band.

    Parameters
    ----------
    predictions : sequence of FarPrediction
        With ``frame`` set (:func:`rough_map.near_far.run_traverse`); recalled cells
        are left out.
    world : HeightField or TiledWorld
        The true world, with a class map.
    poses : array_like, shape (F, 6)
        Pose of every frame of the traverse, ``(x, y, z, roll, pitch, yaw)`` in m and rad:
        the track (the band) and where each frame's near field lay.
    near_labels : sequence of str or None, length F
        The near-field class of each frame (None: unknown), as the near-to-far model got it.
    patch : PatchSpec or Extraction
        The near-field patch.
    half_width : float, optional
        Half width of the band, m; default half the patch width.

    Returns
    -------
    PathBand
    """
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise InputError(f"poses must have shape (F, 6), got {poses.shape}")
    if len(near_labels) != len(poses):
        raise InputError(f"near_labels has {len(near_labels)} entries, poses {len(poses)}")
    near = NearField.of(patch)
    half = 0.5 * (near.lateral[1] - near.lateral[0]) if half_width is None else half_width
    # the track, sampled every 2 cm, and each frame's near-field centre in the world
    track = _densify(poses[:, :2], 0.02)
    centre_vehicle = np.array([np.mean(near.ahead), np.mean(near.lateral), 0.0])
    centres = np.array([pose_matrix(p)[:3, :3] @ centre_vehicle + p[:3] for p in poses])[:, :2]
    known = np.array([x is not None for x in near_labels])
    n = right = base = 0
    for pred in predictions:
        if not len(pred) or pred.frame is None:
            continue
        remap = class_remap(pred.classes, world)
        truth = world_class(world, pred.x, pred.y)
        truth = np.where(truth >= 0, remap[np.maximum(truth, 0)], -1)
        xy = np.column_stack([pred.x, pred.y])
        on_band = _distance_to(track, xy) <= half
        sel = on_band & (truth >= 0) & ~np.asarray(pred.recalled, dtype=bool)
        upto = np.flatnonzero(known[: pred.frame + 1])
        if not sel.any() or not len(upto):
            continue
        nearest = upto[np.argmin(_squared(xy[sel], centres[upto]), axis=1)]
        lookup = {c: i for i, c in enumerate(pred.classes)}
        baseline = np.array([lookup.get(str(near_labels[k]), -1) for k in nearest])
        n += int(sel.sum())
        right += int(np.sum(pred.label_index[sel] == truth[sel]))
        base += int(np.sum(baseline == truth[sel]))
    return PathBand(
        n=n,
        accuracy=right / n if n else float("nan"),
        baseline_accuracy=base / n if n else float("nan"),
        half_width=float(half),
    )


def _densify(xy: np.ndarray, step: float) -> np.ndarray:
    """Points along the polyline ``xy`` (N, 2) every ``step`` m or closer."""
    out = [xy[:1]]
    for a, b in itertools.pairwise(xy):
        k = max(1, int(np.ceil(np.hypot(*(b - a)) / step)))
        out.append(a + (b - a) * (np.arange(1, k + 1) / k)[:, None])
    return np.concatenate(out)


def _squared(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances (len(a), len(b)) between 2-D points."""
    return np.asarray(((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=-1))


def _distance_to(track: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance (m) from each point of ``xy`` to the nearest track point."""
    from scipy.spatial import cKDTree

    return np.asarray(cKDTree(track).query(xy)[0])
