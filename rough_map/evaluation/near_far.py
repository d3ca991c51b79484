"""Scores of near-to-far against a known world (the simulator's truth): far-field accuracy
by distance, and the ground area covered with and without the far field.

The world is a :class:`~rough_map.types.HeightField` with a class map or a
:class:`~rough_map.io.truth.TiledWorld` (a long world, read a tile at a time), e.g. from
:func:`rough_map.io.truth.traverse_truth` on a simulated traverse; the predictions come
from :func:`rough_map.near_far.run_traverse`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.geometry import pose_matrix
from rough_map.io.truth import TiledWorld, World
from rough_map.near_far import FarPrediction, NearField
from rough_map.patch import Extraction, PatchSpec

__all__ = [
    "DEFAULT_BINS",
    "AccuracyTable",
    "Coverage",
    "area_coverage",
    "class_remap",
    "far_field_accuracy",
    "world_class",
]

#: Accuracy-table bin edges (m of distance from the vehicle).
DEFAULT_BINS = (1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0)


def world_class(world: World, x: ArrayLike, y: ArrayLike) -> NDArray[np.int64]:
    """Class index (into ``world.class_names``) of the world's nearest cell at (x, y), m;
    -1 outside the world or where it has no height.

    Raises
    ------
    InputError
        The world has no class map.
    """
    if not isinstance(world, TiledWorld) and world.classes is None:
        raise InputError("the world has no class map")
    ny, nx = world.shape
    col = np.rint((np.asarray(x) - world.origin[0]) / world.spacing).astype(np.int64)
    row = np.rint((np.asarray(y) - world.origin[1]) / world.spacing).astype(np.int64)
    ok = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    out = np.full(col.shape, -1, dtype=np.int64)
    if not ok.any():
        return out
    if isinstance(world, TiledWorld):
        classes, finite = world.lookup(row[ok], col[ok])
    else:
        assert world.classes is not None
        classes = world.classes[row[ok], col[ok]]
        finite = np.isfinite(world.heights[row[ok], col[ok]])
    out[ok] = np.where(finite, classes, -1)
    return out


def class_remap(classes: Sequence[str], world: World) -> NDArray[np.int64]:
    """Index in ``classes`` of each of ``world.class_names`` (-1 if absent): maps the world's
    class indices to those of predictions over ``classes``."""
    lookup = {name: i for i, name in enumerate(classes)}
    return np.array([lookup.get(name, -1) for name in world.class_names], dtype=np.int64)


@dataclass(frozen=True)
class AccuracyTable:
    """Far-field accuracy against distance (:func:`far_field_accuracy`).

    Attributes
    ----------
    edges : ndarray, shape (B + 1,)
        Bin edges of distance from the vehicle, m (the first is 0).
    n : ndarray of int, shape (B,)
        Predictions on classified world cells per bin.
    n_confident : ndarray of int, shape (B,)
        Of those, predictions with confidence >= ``threshold``.
    accuracy : ndarray, shape (B,)
        Share of confident predictions whose class is the world's; NaN for empty bins.
    accuracy_all : ndarray, shape (B,)
        Share of all predictions whose class is the world's; NaN for empty bins.
    threshold : float
        Confidence threshold.
    n_abstained : ndarray of int, shape (B,)
        Cells in view that the model left unknown per bin (whatever the world holds there;
        :attr:`~rough_map.near_far.FarPrediction.abstained`).
    """

    edges: NDArray[np.float64]
    n: NDArray[np.int64]
    n_confident: NDArray[np.int64]
    accuracy: NDArray[np.float64]
    accuracy_all: NDArray[np.float64]
    threshold: float
    n_abstained: NDArray[np.int64] | None = None

    def abstained_fraction(self) -> NDArray[np.float64]:
        """Share of the cells in view left unknown per bin: abstained / (abstained +
        predicted); NaN for empty bins."""
        ab = np.zeros_like(self.n) if self.n_abstained is None else self.n_abstained
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(ab + self.n > 0, ab / (ab + self.n), np.nan)

    def overall(self, max_distance: float = np.inf) -> float:
        """Accuracy of the confident predictions up to ``max_distance`` m (bin edges)."""
        sel = self.edges[1:] <= max_distance + 1e-9
        n = self.n_confident[sel]
        acc = np.nan_to_num(self.accuracy[sel])
        return float((acc * n).sum() / n.sum()) if n.sum() else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The table as plain Python types, for JSON: the threshold, the overall accuracy
        and one dict per bin (``from_m``, ``to_m``, ``cells``, ``confident``, ``accuracy``,
        ``accuracy_all``; accuracies None for empty bins)."""

        def number(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        ab = np.zeros_like(self.n) if self.n_abstained is None else self.n_abstained
        fraction = self.abstained_fraction()

        return {
            "threshold": float(self.threshold),
            "overall": number(self.overall()),
            "abstained_fraction": number(
                float(ab.sum() / (ab.sum() + self.n.sum())) if ab.sum() + self.n.sum() else np.nan
            ),
            "bins": [
                {
                    "from_m": float(self.edges[k]),
                    "to_m": float(self.edges[k + 1]),
                    "cells": int(self.n[k]),
                    "confident": int(self.n_confident[k]),
                    "accuracy": number(self.accuracy[k]),
                    "accuracy_all": number(self.accuracy_all[k]),
                    "abstained": int(ab[k]),
                    "abstained_fraction": number(fraction[k]),
                }
                for k in range(len(self.n))
            ],
        }

    def to_text(self) -> str:
        """The table as aligned text (a Markdown table)."""
        lines = [
            f"| distance (m) | cells | confident (p >= {self.threshold:g}) | accuracy "
            "(confident) | accuracy (all) | abstained |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        fraction = self.abstained_fraction()
        for k in range(len(self.n)):
            lines.append(
                f"| {self.edges[k]:g}-{self.edges[k + 1]:g} | {self.n[k]} | "
                f"{self.n_confident[k]} | {self.accuracy[k]:.3f} | {self.accuracy_all[k]:.3f} | "
                f"{fraction[k]:.3f} |"
            )
        return "\n".join(lines)


def far_field_accuracy(
    predictions: Sequence[FarPrediction],
    world: World,
    bins: Sequence[float] = DEFAULT_BINS,
    *,
    threshold: float = 0.0,
) -> AccuracyTable:
    """Compare far-field predictions with the world's class map, by distance.

    Parameters
    ----------
    predictions : sequence of FarPrediction
        E.g. from :func:`rough_map.near_far.run_traverse`.
    world : HeightField or TiledWorld
        The true world, with ``classes`` and ``class_names``; predictions are compared with
        the class of the world cell nearest to their (x, y). Cells outside the world (or of a
        class the predictions do not know) are not counted.
    bins : sequence of float
        Upper edges of the distance bins, m, increasing; the first bin starts at 0.
    threshold : float
        Confidence (largest class probability) a prediction needs to count in ``accuracy``.

    Returns
    -------
    AccuracyTable
    """
    edges = np.concatenate([[0.0], np.asarray(bins, dtype=float)])
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
        raise InputError(f"bins must be positive increasing distances (m), got {bins!r}")
    if not 0.0 <= threshold <= 1.0:
        raise InputError(f"threshold must be in [0, 1], got {threshold}")
    n_bins = len(edges) - 1
    n = np.zeros(n_bins, dtype=np.int64)
    n_conf = np.zeros(n_bins, dtype=np.int64)
    hits = np.zeros(n_bins)
    hits_all = np.zeros(n_bins)
    n_abstained = np.zeros(n_bins, dtype=np.int64)
    for pred in predictions:
        ab = np.searchsorted(edges, np.asarray(pred.abstained), side="right") - 1
        np.add.at(n_abstained, ab[(ab >= 0) & (ab < n_bins)], 1)
        if not len(pred):
            continue
        remap = class_remap(pred.classes, world)
        truth = world_class(world, pred.x, pred.y)
        truth = np.where(truth >= 0, remap[np.maximum(truth, 0)], -1)
        b = np.searchsorted(edges, pred.distance, side="right") - 1
        ok = (truth >= 0) & (b >= 0) & (b < n_bins)
        correct = pred.label_index == truth
        conf = pred.confidence >= threshold
        np.add.at(n, b[ok], 1)
        np.add.at(hits_all, b[ok], correct[ok])
        sel = ok & conf
        np.add.at(n_conf, b[sel], 1)
        np.add.at(hits, b[sel], correct[sel])
    with np.errstate(invalid="ignore", divide="ignore"):
        accuracy = np.where(n_conf > 0, hits / n_conf, np.nan)
        accuracy_all = np.where(n > 0, hits_all / n, np.nan)
    return AccuracyTable(edges, n, n_conf, accuracy, accuracy_all, float(threshold), n_abstained)


@dataclass(frozen=True)
class Coverage:
    """Ground covered by the near field alone and with near-to-far (:func:`area_coverage`).

    Attributes
    ----------
    cell : float
        Side of the counting grid, m.
    near_area : float
        Area of the cells covered by near-field patches, m^2.
    far_area : float
        Area of the cells covered by confident far-field predictions and not by the near
        field, m^2.
    total_area : float
        ``near_area + far_area``, m^2.
    ratio : float
        ``total_area / near_area``.
    accuracy : float
        Share of the far-only cells whose fused class (mean of the confident probabilities
        predicted for the cell over all frames) is the world's.
    threshold : float
        Confidence threshold of the far predictions counted.
    """

    cell: float
    near_area: float
    far_area: float
    total_area: float
    ratio: float
    accuracy: float
    threshold: float


def area_coverage(
    predictions: Sequence[FarPrediction],
    poses: ArrayLike,
    world: World,
    patch: PatchSpec | Extraction,
    *,
    cell: float = 0.1,
    threshold: float = 0.0,
) -> Coverage:
    """Ground area covered by the near-field patches, and with the far-field cells added.

    Parameters
    ----------
    predictions : sequence of FarPrediction
        Far-field predictions, e.g. from :func:`rough_map.near_far.run_traverse`.
    poses : array_like, shape (F, 6)
        Poses of every frame whose near-field patch geometry classified, ``(x, y, z, roll,
        pitch, yaw)`` in m and rad (:meth:`Traverse.poses`).
    world : HeightField or TiledWorld
        The true world: only cells inside it with a class count (the simulated world is a
        strip; what lies beyond cannot be checked), and it gives the truth for ``accuracy``.
    patch : PatchSpec or Extraction
        The near-field patch (that of the near-to-far model).
    cell : float
        Side of the counting grid, m.
    threshold : float
        Confidence a far prediction needs to count.

    Returns
    -------
    Coverage
    """
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise InputError(f"poses must have shape (F, 6), got {poses.shape}")
    if not cell > 0:
        raise InputError(f"cell must be positive (m), got {cell}")
    near_keys = _near_cells(poses, world, NearField.of(patch), cell)
    sums, classes = _far_cells(predictions, world, cell, threshold)
    far_keys = [k for k in sums if k not in near_keys]
    accuracy = float("nan")
    if far_keys:
        xs = (np.array([k[0] for k in far_keys]) + 0.5) * cell
        ys = (np.array([k[1] for k in far_keys]) + 0.5) * cell
        truth = world_class(world, xs, ys)
        remap = class_remap(classes, world)
        truth = np.where(truth >= 0, remap[np.maximum(truth, 0)], -1)
        fused = np.array([np.argmax(sums[k]) for k in far_keys])
        ok = truth >= 0
        accuracy = float(np.mean(fused[ok] == truth[ok])) if ok.any() else float("nan")
    near_area = len(near_keys) * cell * cell
    far_area = len(far_keys) * cell * cell
    total = near_area + far_area
    return Coverage(
        cell=cell,
        near_area=near_area,
        far_area=far_area,
        total_area=total,
        ratio=total / near_area if near_area else float("inf"),
        accuracy=accuracy,
        threshold=float(threshold),
    )


def _near_cells(
    poses: NDArray[np.float64], world: World, near: NearField, cell: float
) -> set[tuple[int, int]]:
    """Counting cells (inside the world) hit by the near field of any pose: each patch is
    sampled at a quarter cell."""
    step = cell / 4.0
    ax = np.arange(near.ahead[0] + step / 2, near.ahead[1], step)
    ay = np.arange(near.lateral[0] + step / 2, near.lateral[1], step)
    gx, gy = np.meshgrid(ax, ay)
    samples = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    keys: set[tuple[int, int]] = set()
    for pose in poses:
        pw = samples @ pose_matrix(pose)[:3, :3].T + pose[:3]
        ok = world_class(world, pw[:, 0], pw[:, 1]) >= 0
        keys.update(_keys(pw[ok, 0], pw[ok, 1], cell))
    return keys


def _far_cells(
    predictions: Sequence[FarPrediction], world: World, cell: float, threshold: float
) -> tuple[dict[tuple[int, int], NDArray[np.float64]], tuple[str, ...]]:
    """Sums of the confident probabilities predicted for each counting cell inside the
    world, and the class names of the predictions."""
    sums: dict[tuple[int, int], NDArray[np.float64]] = {}
    classes: tuple[str, ...] = ()
    for pred in predictions:
        if not len(pred):
            continue
        classes = pred.classes
        ok = (pred.confidence >= threshold) & (world_class(world, pred.x, pred.y) >= 0)
        for key, p in zip(_keys(pred.x[ok], pred.y[ok], cell), pred.proba[ok], strict=True):
            if key in sums:
                sums[key] = sums[key] + p
            else:
                sums[key] = p.copy()
    return sums, classes


def _keys(x: NDArray, y: NDArray, cell: float) -> list[tuple[int, int]]:
    """Counting-cell keys ``(floor(x / cell), floor(y / cell))`` of points in m."""
    i = np.floor(np.asarray(x) / cell).astype(np.int64)
    j = np.floor(np.asarray(y) / cell).astype(np.int64)
    return list(zip(i.tolist(), j.tolist(), strict=True))
