"""The whole chain on one traverse: features -> classes -> filter -> map (+ near-to-far).

This module only composes the stages (:mod:`rough_map.features`, :mod:`rough_map.classify`,
:mod:`rough_map.map`, :mod:`rough_map.export`); the commands ``map``, ``report`` and
``demo`` call it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.errors import InputError

log = logging.getLogger(__name__)


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
    far : list
        Near-to-far predictions per frame (empty when not run).
    far_report : dict
        Area covered and far-field accuracy (when the world truth is known).
    """

    traverse: Any
    features: Any
    prediction: Any
    map: Any
    model: Any = None
    far: list = field(default_factory=list)
    far_report: dict = field(default_factory=dict)
    _truth: Any = field(default=None, init=False, repr=False)
    _truth_read: bool = field(default=False, init=False, repr=False)

    def truth(self) -> Any:
        """The simulator's world (:class:`~rough_map.types.HeightField` with its class map),
        read once from the traverse's ``height_field``; None when it has none."""
        if not self._truth_read:
            self._truth, self._truth_read = _world_truth(self.traverse), True
        return self._truth


def analyse(
    traverse: Any,
    model: Any = None,
    *,
    features: Any = None,
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
        Terrain model (``rough_map.io.model.load_terrain_model``); without one the map has
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
    from rough_map.features import traverse_features
    from rough_map.io.model import load_terrain_model
    from rough_map.io.traverse import Traverse, load_traverse
    from rough_map.map import fuse_traverse
    from rough_map.patch import Extraction

    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    if model is not None and not hasattr(model, "predict"):
        model = load_terrain_model(model)
    extraction = Extraction.from_dict(getattr(model, "extraction_", None))
    spec = extraction.patch
    if features is None:
        features = traverse_features(
            traverse,
            spec,
            use_imu=extraction.use_imu,
            method=extraction.method,
            subtract_noise=extraction.subtract_noise,
            progress=progress,
        )
    prediction = None
    probs = None
    names: tuple[str, ...] = ()
    if model is not None:
        prediction = model.predict(features)
        probs = prediction.filtered_proba
        names = tuple(str(c) for c in prediction.classes)
    levels = _levels(features, model)
    grid = fuse_traverse(
        features,
        probs,
        names,
        levels=levels,
        resolution=resolution,
        spec=spec,
        crs=traverse.spec.crs,
    )
    grid.attrs["traverse"] = traverse.name
    add_elevation(grid, traverse, progress=progress)
    result = TraverseAnalysis(traverse, features, prediction, grid, model)
    has_images = any(f.left is not None for f in traverse.frames)
    run_far = (near_far is True) or (near_far == "auto" and has_images and model is not None)
    if run_far:
        if not has_images:
            raise InputError(f"{traverse.name}: near-to-far needs stereo images in the frames")
        if prediction is None:
            raise InputError("near-to-far needs a terrain model to label the near field")
        result.far, result.far_report = _near_to_far(result, far_weight, progress)
    return result


def _levels_config(model: Any) -> Any:
    from rough_map.classify import load_roughness_levels

    return getattr(model, "levels_", None) or load_roughness_levels(None)


def level_edges(result: TraverseAnalysis) -> tuple[float, ...]:
    """R thresholds (m^3/rad) between the roughness levels used for ``result``."""
    return tuple(float(v) for v in _levels_config(result.model).values())


def _levels(features: Any, model: Any) -> np.ndarray:
    """Roughness level index per frame (0 low, 1 medium, 2 high; NaN invalid)."""
    from rough_map.classify import roughness_level

    levels_cfg = _levels_config(model)
    names = tuple(levels_cfg.levels)
    lv = roughness_level(features["R"], names, levels_cfg.values())
    lookup = {n: float(i) for i, n in enumerate(names)}
    return np.array([lookup.get(str(v), math.nan) for v in lv])


def add_elevation(
    grid: Any, traverse: Any, *, sample: int = 20_000, progress: bool = False
) -> None:
    """Elevation layer (m, world z): mean height of the frames' points per map cell.

    Points outside the map (it covers the patch footprints plus a margin) are left out.
    Reading the clouds again is one of the long steps of a map: ``progress`` shows a bar
    on stderr.
    """
    from tqdm import tqdm

    from rough_map.errors import RoughMapError

    geo = grid.geometry
    sums = np.zeros(geo.shape)
    counts = np.zeros(geo.shape)
    rng = np.random.default_rng(0)
    for i in tqdm(range(len(traverse)), desc="elevation", unit="frame", disable=not progress):
        if traverse.frames[i].cloud is None:
            continue
        try:
            pts = traverse.load_cloud(i, frame="world")
        except RoughMapError as exc:
            log.debug("elevation: frame %d skipped: %s", i, exc)
            continue
        if len(pts) > sample:
            pts = pts[rng.choice(len(pts), sample, replace=False)]
        rows, cols = geo.cell_of(pts[:, 0], pts[:, 1])
        ok = geo.inside(rows, cols) & np.isfinite(pts[:, 2])
        np.add.at(sums, (rows[ok], cols[ok]), pts[ok, 2])
        np.add.at(counts, (rows[ok], cols[ok]), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.where(counts > 0, sums / counts, np.nan)
    grid.add_layer("elevation", units="m", description="mean terrain height (world z)", data=elev)


def _near_to_far(result: TraverseAnalysis, weight: float, progress: bool):
    from rough_map.map import fuse_cell_probabilities
    from rough_map.map import near_far as n2f

    pred = result.prediction
    labels = np.where(pred.valid, pred.filtered_class, "")
    far = n2f.run_traverse(result.traverse, labels, classes=tuple(pred.classes), progress=progress)
    grid = result.map
    for fp in far:
        if len(fp) == 0:
            continue
        cells = grid.cells_at(fp.x, fp.y)
        fuse_cell_probabilities(
            grid, cells, fp.proba, weight=weight, group="far", t=getattr(fp, "t", None)
        )
    report = coverage_report(grid)
    world = result.truth()
    if world is not None and far:
        report["far_accuracy_by_distance"] = n2f.far_field_accuracy(far, world)
    return far, report


def coverage_report(grid: Any) -> dict:
    """Area (m^2) seen by the near field, by near + far, and their ratio."""
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


def _world_truth(traverse: Any):
    if traverse.spec.height_field is None:
        return None
    from rough_map.simulate.course import load_world

    path = traverse.resolve(traverse.spec.height_field)
    return load_world(path) if path.is_file() else None


def map_accuracy(grid: Any, world: Any, layer: str = "class") -> float:
    """Fraction of classified map cells whose class is the world's class at the cell centre.

    ``world`` is a :class:`rough_map.types.HeightField` with a class map (simulator truth).
    """
    names = grid.info(layer).categories or tuple(grid.attrs.get("class_names", ()))
    arr = grid[layer]
    rows, cols = np.nonzero(np.isfinite(arr))
    if rows.size == 0:
        return math.nan
    x, y = grid.geometry.cell_center(rows, cols)
    j = np.clip(
        np.round((x - world.origin[0]) / world.spacing).astype(int), 0, world.heights.shape[1] - 1
    )
    i = np.clip(
        np.round((y - world.origin[1]) / world.spacing).astype(int), 0, world.heights.shape[0] - 1
    )
    truth = np.asarray(world.class_names, dtype=object)[world.classes[i, j]]
    pred = np.asarray(names, dtype=object)[arr[rows, cols].astype(int)]
    return float(np.mean(truth == pred))


def truth_accuracy(result: TraverseAnalysis) -> dict[str, float]:
    """Map class accuracy against the simulator's truth, when the traverse has one.

    Returns ``near_class_accuracy`` (the ``class`` layer) and, with near-to-far,
    ``far_class_accuracy`` (the ``far_class`` layer): fractions of the classified cells
    whose class is the world's class at the cell centre (:func:`map_accuracy`). Empty
    without a model or without a ``height_field`` holding a class map.
    """
    world = result.truth()
    if world is None or world.classes is None or "class" not in result.map.layers:
        return {}
    out = {"near_class_accuracy": map_accuracy(result.map, world)}
    if "far_class" in result.map.layers:
        out["far_class_accuracy"] = map_accuracy(result.map, world, "far_class")
    return out


def write_tables(result: TraverseAnalysis, out_dir: str | Path) -> dict[str, Path]:
    """``features.csv`` with its metadata ``features.csv.json`` and, with a model,
    ``labels.csv`` (raw and filtered class per frame).

    Returns
    -------
    dict of str to Path
        ``"features"``, ``"features_metadata"`` and ``"labels"`` (with a model).
    """
    import csv

    from rough_map._files import atomic_output
    from rough_map.features import features_metadata_path, write_features

    out = Path(out_dir)
    features = write_features(result.features, out / "features.csv")
    paths = {"features": features, "features_metadata": features_metadata_path(features)}
    pred = result.prediction
    if pred is None:
        return paths
    f = result.features
    path = out / "labels.csv"
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
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
            ]
        )
        raw_p = pred.raw_confidence
        filt_p = pred.filtered_confidence
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
                    "true" if pred.defect[i] else "false",
                ]
            )
    paths["labels"] = path
    return paths
