"""The whole chain on one traverse: features -> classes -> filter -> map (+ near-to-far).

This module only wires the stages together: :mod:`rough_map.features` (the features, with
the model's :class:`~rough_map.patch.Extraction`), :mod:`rough_map.classify` (classes and
path filter), :mod:`rough_map.map` (fusion, elevation, near-to-far),
:mod:`rough_map.evaluation.truth` (scores against the simulator's world) and
:mod:`rough_map.export.labels`. The commands ``map``, ``report`` and ``demo`` call it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import PathLike
from rough_map.classify import (
    RoughnessLevels,
    TerrainModel,
    TerrainPrediction,
    load_roughness_levels,
    load_terrain_model,
    roughness_level,
)
from rough_map.errors import InputError
from rough_map.evaluation.near_far import far_field_accuracy
from rough_map.evaluation.truth import truth_accuracy
from rough_map.export.labels import write_labels
from rough_map.features import (
    FeatureTable,
    features_metadata_path,
    traverse_features,
    write_features,
)
from rough_map.io.traverse import Traverse, load_traverse
from rough_map.io.truth import traverse_truth
from rough_map.map import GridMap, fuse_cell_probabilities, fuse_traverse
from rough_map.map import near_far as n2f
from rough_map.map.elevation import add_elevation
from rough_map.patch import Extraction
from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = [
    "TraverseAnalysis",
    "analyse",
    "coverage_report",
    "level_edges",
    "write_tables",
]


@dataclass
class TraverseAnalysis:
    """Everything rough_map learned about one traverse.

    Attributes
    ----------
    traverse : Traverse
        The input.
    features : FeatureTable
        Per-frame roughness features.
    prediction : TerrainPrediction or None
        Raw and filtered classes (None without a model).
    map : GridMap
        The fused map (R, w, sigma, level, class probabilities, count, last seen,
        elevation; far-field layers with near-to-far).
    model : TerrainModel or None
        The terrain model used.
    extraction : Extraction
        The patch and estimator options of the features (the model's).
    far : list of FarPrediction
        Near-to-far predictions per frame (empty when not run).
    far_report : dict
        Area covered (m²) and far-field accuracy (when the world truth is known).
    """

    traverse: Traverse
    features: FeatureTable
    prediction: TerrainPrediction | None
    map: GridMap
    model: TerrainModel | None = None
    extraction: Extraction = field(default_factory=Extraction)
    far: list[n2f.FarPrediction] = field(default_factory=list)
    far_report: dict[str, Any] = field(default_factory=dict)
    _truth: HeightField | None = field(default=None, init=False, repr=False)
    _truth_read: bool = field(default=False, init=False, repr=False)

    def truth(self) -> HeightField | None:
        """The simulator's world (:class:`~rough_map.types.HeightField` with its class map),
        read once from the traverse's ``height_field``; None when it has none."""
        if not self._truth_read:
            self._truth, self._truth_read = traverse_truth(self.traverse), True
        return self._truth

    def truth_accuracy(self) -> dict[str, float]:
        """Map class accuracy against the simulator's truth, when the traverse has one
        (:func:`rough_map.evaluation.truth.truth_accuracy`): ``near_class_accuracy`` and,
        with near-to-far, ``far_class_accuracy``; empty without a model or a truth."""
        return truth_accuracy(self.map, self.truth())


def analyse(
    traverse: Traverse | PathLike,
    model: TerrainModel | PathLike | None = None,
    *,
    features: FeatureTable | None = None,
    resolution: float = 0.1,
    near_far: str | bool = "auto",
    far_weight: float = 0.3,
    progress: bool = False,
) -> TraverseAnalysis:
    """Run the chain on a traverse.

    Parameters
    ----------
    traverse : Traverse or path
        The traverse.
    model : TerrainModel or path, optional
        Terrain model (or its name or file, read by
        :func:`rough_map.classify.load_terrain_model`); without one the map has
        roughness layers only.
    features : FeatureTable, optional
        Precomputed features (else computed with the model's extraction settings).
    resolution : float
        Map cell size in m.
    near_far : {"auto", True, False}
        Learn appearance near the rover and predict far away ("auto": when the frames have
        images and there is a model).
    far_weight : float
        Weight of a far-field prediction relative to a near-field observation.
    progress : bool
        Progress bars on stderr.
    """
    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    terrain_model: TerrainModel | None = (
        model if model is None or isinstance(model, TerrainModel) else _load_model(model)
    )
    extraction = Extraction.from_dict(
        terrain_model.extraction_ if terrain_model is not None else None
    )
    if features is None:
        features = traverse_features(traverse, extraction, progress=progress)
    prediction = terrain_model.predict(features) if terrain_model is not None else None
    grid = fuse_traverse(
        features,
        prediction.filtered_proba if prediction is not None else None,
        tuple(str(c) for c in prediction.classes) if prediction is not None else (),
        levels=_levels(features, terrain_model),
        resolution=resolution,
        spec=extraction.patch,
        crs=traverse.spec.crs,
    )
    grid.attrs["traverse"] = traverse.name
    add_elevation(grid, traverse, progress=progress)
    result = TraverseAnalysis(traverse, features, prediction, grid, terrain_model, extraction)
    has_images = any(f.left is not None for f in traverse.frames)
    run_far = near_far is True or (near_far == "auto" and has_images and prediction is not None)
    if run_far:
        if not has_images:
            raise InputError(f"{traverse.name}: near-to-far needs stereo images in the frames")
        if prediction is None:
            raise InputError("near-to-far needs a terrain model to label the near field")
        result.far, result.far_report = _near_to_far(result, prediction, far_weight, progress)
    return result


def _load_model(name: PathLike) -> TerrainModel:
    model: TerrainModel = load_terrain_model(Path(name))
    return model


def _levels_config(model: TerrainModel | None) -> RoughnessLevels:
    return model.levels_ if model is not None else load_roughness_levels(None)


def level_edges(result: TraverseAnalysis) -> tuple[float, ...]:
    """R thresholds (m³/rad) between the roughness levels used for ``result``."""
    return tuple(float(v) for v in _levels_config(result.model).values())


def _levels(features: FeatureTable, model: TerrainModel | None) -> np.ndarray:
    """Roughness level index per frame (0 low, 1 medium, 2 high; NaN invalid)."""
    levels_cfg = _levels_config(model)
    names = tuple(levels_cfg.levels)
    lv = roughness_level(features["R"], names, levels_cfg.values())
    lookup = {n: float(i) for i, n in enumerate(names)}
    return np.array([lookup.get(str(v), math.nan) for v in lv])


def _near_to_far(
    result: TraverseAnalysis, pred: TerrainPrediction, weight: float, progress: bool
) -> tuple[list[n2f.FarPrediction], dict[str, Any]]:
    """Near-to-far along the traverse, fused into the map's far layers; the predictions
    and the coverage report (with the far-field accuracy when the world is known)."""
    labels = np.where(pred.valid, pred.filtered_class, "")
    far = n2f.run_traverse(
        result.traverse,
        labels,
        patch=result.extraction,
        classes=tuple(pred.classes),
        progress=progress,
    )
    grid = result.map
    for fp in far:
        if len(fp) == 0:
            continue
        cells = grid.cells_at(fp.x, fp.y)
        fuse_cell_probabilities(grid, cells, fp.proba, weight=weight, group="far", t=fp.t)
    report: dict[str, Any] = coverage_report(grid)
    world = result.truth()
    if world is not None and far:
        report["far_accuracy_by_distance"] = far_field_accuracy(far, world)
    return far, report


def coverage_report(grid: GridMap) -> dict[str, float]:
    """Area (m²) seen by the near field, by near + far, and their ratio."""
    near = np.isfinite(grid["class"]) if "class" in grid.layers else np.isfinite(grid["R"])
    total = near.copy()
    if "far_class" in grid.layers:
        total |= np.isfinite(grid["far_class"])
    cell = grid.geometry.resolution**2
    a_near, a_all = float(near.sum() * cell), float(total.sum() * cell)
    return {
        "near_area_m2": a_near,
        "near_far_area_m2": a_all,
        "area_ratio": a_all / a_near if a_near else math.nan,
    }


def write_tables(result: TraverseAnalysis, out_dir: PathLike) -> dict[str, Path]:
    """``features.csv`` with its metadata ``features.csv.json`` and, with a model,
    ``labels.csv`` (raw and filtered class per frame,
    :func:`rough_map.export.labels.write_labels`).

    Returns
    -------
    dict of str to Path
        ``"features"``, ``"features_metadata"`` and ``"labels"`` (with a model).
    """
    out = Path(out_dir)
    features = write_features(result.features, out / "features.csv")
    paths = {"features": features, "features_metadata": features_metadata_path(features)}
    if result.prediction is not None:
        paths["labels"] = write_labels(result.features, result.prediction, out / "labels.csv")
    return paths
