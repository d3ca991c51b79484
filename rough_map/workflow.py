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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import near_far as n2f
from rough_map._files import PathLike, output_set
from rough_map.classify import (
    RoughnessLevels,
    TerrainModel,
    TerrainPrediction,
    load_roughness_levels,
    load_terrain_model,
)
from rough_map.errors import InputError, ModelError
from rough_map.evaluation.near_far import far_field_accuracy
from rough_map.evaluation.truth import truth_accuracy
from rough_map.export import export_map, import_writers
from rough_map.export.costmap import CostmapSettings, cost_layer, write_costmap
from rough_map.export.labels import write_labels
from rough_map.export.png import write_pngs
from rough_map.export.road_crg import write_road_crg
from rough_map.export.vector import write_path_geojson
from rough_map.features import (
    FeatureTable,
    FramePass,
    FrameStream,
    features_metadata_path,
    frame_jobs,
    iter_frames,
    write_features,
)
from rough_map.features.driving import speed_advice, speed_table
from rough_map.features.traverse import start_frame_pass, traverse_pass
from rough_map.filter import smooth_table
from rough_map.io.traverse import Traverse
from rough_map.io.truth import World, traverse_truth
from rough_map.map import GridMap, fuse_cell_probabilities
from rough_map.map.fusion import log_fused
from rough_map.map.grid_geometry import check_map_memory
from rough_map.map.tiles import is_accumulator
from rough_map.online import OnlineMapper
from rough_map.patch import Extraction, options_of
from rough_map.vehicle import SpeedTable, Vehicle

log = logging.getLogger(__name__)

#: Names ``rough-map map`` writes in its folder (glob patterns): an old file of these
#: names that a run does not write again is dropped from the folder (see
#: :func:`write_outputs`); any other file there is the user's and is kept.
MAP_OUTPUTS = (
    "map.tif",
    "map_*.tif",
    "map_*.tif.aux.xml",
    "map_*.qml",
    "map_*.png",
    "map_path.geojson",
    "map_gridmap",
    "features.csv",
    "features.csv.json",
    "labels.csv",
    "labels.csv.json",
    "map_state.npz",
    "map_road.crg",
    "map_costmap.pgm",
    "map_costmap.yaml",
)

#: What the map's roughness layers fuse (:func:`analyse`'s ``roughness``).
ROUGHNESS_SOURCES = ("raw", "smoothed")

__all__ = [
    "MAP_OUTPUTS",
    "ROUGHNESS_SOURCES",
    "AnalysisOptions",
    "TraverseAnalysis",
    "add_speed_layers",
    "analyse",
    "analyse_model_file",
    "coverage_report",
    "level_edges",
    "summary",
    "write_outputs",
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
    mapper : OnlineMapper or None
        The mapper that fused the map, holding its sums (``map_state.npz``).
    vehicle : Vehicle or None
        The vehicle of the speed advice (``v_max``), if any.
    """

    traverse: Traverse
    features: FeatureTable
    prediction: TerrainPrediction | None
    map: GridMap
    model: TerrainModel | None = None
    extraction: Extraction = field(default_factory=Extraction)
    far: list[n2f.FarPrediction] = field(default_factory=list)
    far_report: dict[str, Any] = field(default_factory=dict)
    mapper: OnlineMapper | None = field(default=None, repr=False)
    vehicle: Vehicle | None = None
    _truth: World | None = field(default=None, init=False, repr=False)
    _truth_read: bool = field(default=False, init=False, repr=False)

    def truth(self) -> World | None:
        """The simulator's world (:class:`~rough_map.types.HeightField` with its class map,
        or for a long world a :class:`~rough_map.io.truth.TiledWorld` read a tile at a
        time), read once from the traverse's ``height_field``; None when it has none."""
        if not self._truth_read:
            self._truth, self._truth_read = traverse_truth(self.traverse), True
        return self._truth

    def truth_accuracy(self) -> dict[str, float]:
        """Map class accuracy against the simulator's truth, when the traverse has one
        (:func:`rough_map.evaluation.truth.truth_accuracy`): ``near_class_accuracy`` and,
        with near-to-far, ``far_class_accuracy``; empty without a model or a truth."""
        return truth_accuracy(self.map, self.truth())


@dataclass(frozen=True)
class AnalysisOptions:
    """Options of :func:`analyse`, checked when made (:class:`InputError`).

    Attributes
    ----------
    resolution : float
        Map cell size in m.
    near_far : {"auto", True, False}
        Learn appearance near the rover and predict far away ("auto": when the frames have
        images and there is a model).
    near_far_settings : NearFarSettings, optional
        Tile size, range, weight, confidence threshold and label settling of near-to-far;
        default the shipped ``configs/near_far.yaml``.
    roughness : {"raw", "smoothed"}
        The R and w the map fuses: each frame's own (``"raw"``, the default), or those
        smoothed along the path (:class:`rough_map.filter.RoughnessSmoother`, the
        features' ``R_smooth`` ... columns), fused in the second pass with the classes.
        Raw is the default because the map already averages the ~70 % overlapping patches
        of consecutive frames in each cell; fusing smoothed values would count that
        along-track correlation twice (and make the map's sigma too small). The features
        table gets the smoothed columns either way.
    n_jobs : int
        Worker processes for the frames (-1: every core); the result is the same for any.
    progress : bool
        Progress bars on stderr.
    vehicle : Vehicle, optional
        A vehicle (:func:`rough_map.vehicle.load_vehicle`): the features get its speed
        advice (:func:`rough_map.features.driving.speed_advice`) and the map a ``v_max``
        layer (m/s) from each cell's fused R and w.
    speed : float, optional
        With ``vehicle``: the speed in m/s of the features' response columns.
    """

    resolution: float = 0.1
    near_far: str | bool = "auto"
    near_far_settings: n2f.NearFarSettings | None = None
    roughness: str = "raw"
    n_jobs: int = 1
    progress: bool = False
    vehicle: Vehicle | None = None
    speed: float | None = None

    def __post_init__(self) -> None:
        if self.roughness not in ROUGHNESS_SOURCES:
            raise InputError(f"roughness must be 'raw' or 'smoothed'; got {self.roughness!r}")
        if self.near_far not in ("auto", True, False):
            raise InputError(f"near_far must be 'auto', True or False; got {self.near_far!r}")


def analyse(
    traverse: Traverse,
    model: TerrainModel | None = None,
    options: AnalysisOptions | None = None,
    *,
    frames: FrameStream | None = None,
    **changes: Any,
) -> TraverseAnalysis:
    """Run the chain on a traverse.

    One pass over the frames (each cloud read once, on ``n_jobs`` processes) gives the
    features and the heights; an :class:`~rough_map.online.OnlineMapper` fuses them into a
    tiled map kept in bounded memory; the model classifies the frames and filters the
    classes over the whole path, and their posteriors are fused in a second pass over the
    poses (no cloud is read again).

    Parameters
    ----------
    traverse : Traverse
        The traverse (:func:`rough_map.io.traverse.load_traverse` reads one).
    model : TerrainModel, optional
        Terrain model (:func:`rough_map.classify.load_terrain_model` reads one); without
        one the map has roughness layers only.
    options : AnalysisOptions, optional
        The options (:class:`AnalysisOptions`, each with its unit); default the defaults.
    frames : FrameStream, optional
        The frame pass, already started on this traverse from the model's card
        (:func:`rough_map.features.traverse.start_frame_pass`), as ``rough-map map`` does
        before it imports scikit-learn and loads the model (``benchmarks/bench_startup.py``);
        checked against the model. Default: started here.
    **changes
        Fields of ``options`` changed by keyword (``near_far=False``).

    Raises
    ------
    InputError
        Bad options, a traverse or model of another type, ``frames`` set up for another
        traverse; see also the stages.
    ModelError
        ``frames`` started with another feature extraction than the model's (its card's,
        which is not covered by the model file's sha256, edited or of another model).
    """
    try:  # a frame pass given is closed on any error
        opt = options_of(AnalysisOptions, options, changes, "analyse")
        if not isinstance(traverse, Traverse):
            raise InputError(
                f"analyse takes a Traverse (rough_map.io.traverse.load_traverse reads one), "
                f"got {type(traverse).__name__}"
            )
        if model is not None and not isinstance(model, TerrainModel):
            raise InputError(
                f"analyse takes a TerrainModel or None (rough_map.classify.load_terrain_model "
                f"reads one), got {type(model).__name__}"
            )
        resolution, progress = opt.resolution, opt.progress
        check_map_memory(traverse.poses()[:, :2], resolution)
        extraction = Extraction.from_dict(model.extraction_ if model is not None else None)
        reading = extraction if model is None else model.reading()
        if frames is not None and frames.settings.requested != reading:
            raise ModelError(
                f"{frames.card or 'the model'}: {_card_differs(frames.settings, reading)}"
            )
        mapper = OnlineMapper(
            model,
            resolution=resolution,
            crs=traverse.spec.crs,
            calibration=traverse.spec.calibration,
            extraction=extraction,
            name=traverse.name,
        )
        _frame_pass(traverse, mapper, reading, opt, frames)
    except BaseException:
        if frames is not None:
            frames.close()
        raise
    features = mapper.features().require_valid()
    prediction = model.predict(features) if model is not None else None
    # the frames the class filter leaves out as isolated defects stay out of the smoothing
    defect = None if prediction is None or prediction.mode == "forward" else prediction.defect
    features = smooth_table(features, defect=defect)
    if opt.vehicle is not None:
        features = speed_advice(features, opt.vehicle, opt.speed)
    grid = mapper.finish(
        late=True,
        proba=prediction.filtered_proba if prediction is not None else None,
        roughness=_smoothed(features) if opt.roughness == "smoothed" else None,
        novelty=prediction.novelty if prediction is not None else None,
    )
    grid.attrs["traverse"] = traverse.name
    if opt.vehicle is not None:
        add_speed_layers(grid, speed_table(features, opt.vehicle), opt.speed)
    log_fused(len(features), np.asarray(features.valid, dtype=bool), grid, resolution)
    result = TraverseAnalysis(traverse, features, prediction, grid, model, extraction)
    result.mapper = mapper
    result.vehicle = opt.vehicle
    has_images = any(f.left is not None for f in traverse.frames)
    near_far = opt.near_far
    run_far = near_far is True or (near_far == "auto" and has_images and prediction is not None)
    if run_far:
        if not has_images:
            raise InputError(f"{traverse.name}: near-to-far needs stereo images in the frames")
        if prediction is None:
            raise InputError("near-to-far needs a terrain model to label the near field")
        settings = opt.near_far_settings or n2f.load_near_far_settings()
        result.far, result.far_report = _near_to_far(result, prediction, settings, progress)
        far_sums = [n for n in grid.layers if n.startswith("far_") and is_accumulator(grid, n)]
        mapper.tiles.add_group("far")
        mapper.tiles.add_layers_from(grid, far_sums)
    return result


def add_speed_layers(grid: GridMap, speeds: SpeedTable, speed: float | None) -> None:
    """The map's speed advice from each cell's fused R and w: ``v_max`` (m/s), the speed
    ``v_max_95`` that holds with 95 % confidence from the cell's spread of R and w (its
    ``sigma_R`` and ``sigma_w``: the frames' standard errors and their scatter) and, at
    ``speed``, the rms responses."""
    name = speeds.vehicle.name
    R, w = grid["R"], grid["w"]
    grid.add_layer(
        "v_max",
        units="m/s",
        description=f"highest speed keeping the {name}'s limits",
        data=speeds.v_max(R, w),
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        se_ln_r = grid["sigma_R"] / R
    grid.add_layer(
        "v_max_95",
        units="m/s",
        description=f"speed keeping the {name}'s limits with 95 % confidence",
        data=speeds.v_max(R, w, se_ln_r, grid["sigma_w"]),
    )
    if speed is None:
        return
    at = speeds.response(R, w, speed)
    responses = (
        ("weighted_acceleration", "m/s^2", "ISO 2631-1 Wk-weighted rms acceleration"),
        ("suspension_travel", "m", "rms suspension travel"),
        ("dynamic_load_ratio", "1", "rms dynamic tyre load over the static load"),
    )
    for layer, units, what in responses:
        grid.add_layer(
            layer,
            units=units,
            description=f"{what} of the {name} at {speed:g} m/s",
            data=getattr(at, layer),
        )


def analyse_model_file(
    traverse: Traverse, model_file: PathLike, options: AnalysisOptions | None = None
) -> TraverseAnalysis:
    """:func:`analyse` with the model in a file: with more than one process, the frame pass
    starts from the model's card (:func:`~rough_map.features.traverse.start_frame_pass`)
    while the model loads, and :func:`analyse` checks the card against it."""
    opt = options or AnalysisOptions()
    frames = start_frame_pass(
        traverse, model_file, resolution=opt.resolution, n_jobs=opt.n_jobs, progress=opt.progress
    )
    try:
        model = _load_model(model_file)
    except BaseException:
        if frames is not None:
            frames.close()
        raise
    return analyse(traverse, model, opt, frames=frames)


def _frame_pass(
    traverse: Traverse,
    mapper: OnlineMapper,
    reading: Extraction,
    opt: AnalysisOptions,
    frames: FrameStream | None,
) -> None:
    """Every frame through the mapper: features (read as ``reading`` says) and heights,
    classes later; ``frames``: the pass, already started (checked to be this one)."""
    settings = traverse_pass(
        traverse, reading, height_resolution=mapper.tiles.resolution, features=True
    )
    if frames is not None and (frames.settings != settings or len(frames.jobs) != len(traverse)):
        raise InputError(f"{traverse.name}: the frame pass given was set up for another traverse")
    jobs = frames.jobs if frames is not None else frame_jobs(traverse)
    outputs = (
        frames
        if frames is not None
        else iter_frames(
            jobs, settings, n_jobs=opt.n_jobs, progress=opt.progress, desc=traverse.name
        )
    )
    for out in outputs:
        mapper.add(out, jobs[out.index].pose, classes=False, roughness=opt.roughness == "raw")


def _card_differs(started: FramePass, model: Extraction) -> str:
    """Why a model's card is refused: the settings where the extraction the frames started
    on (from the card) differs from the model's."""
    a, b = (replace(x, auto_spacing=False).to_dict() for x in (started.requested, model))
    diff = ", ".join(
        f"{k} {a.get(k)!r} against {b.get(k)!r}" for k in a | b if a.get(k) != b.get(k)
    )
    return (
        f"the feature extraction on its card is not the model's ({diff}): the card was edited "
        "or belongs to another model; refusing it"
    )


def _smoothed(features: FeatureTable) -> dict[str, np.ndarray]:
    """The smoothed roughness of the features table, as :meth:`OnlineMapper.finish`
    takes it (sigma_R in m³/rad from the standard deviation of ln R)."""
    R = np.asarray(features["R_smooth"], dtype=float)
    return {
        "R": R,
        "w": np.asarray(features["w_smooth"], dtype=float),
        "sigma_R": R * np.asarray(features["sigma_lnR_smooth"], dtype=float),
        "sigma_w": np.asarray(features["sigma_w_smooth"], dtype=float),
    }


def _load_model(name: PathLike) -> TerrainModel:
    model: TerrainModel = load_terrain_model(Path(name))
    return model


def _levels_config(model: TerrainModel | None) -> RoughnessLevels:
    return model.levels_ if model is not None else load_roughness_levels(None)


def level_edges(result: TraverseAnalysis) -> tuple[float, ...]:
    """R thresholds (m³/rad) between the roughness levels used for ``result``."""
    return tuple(float(v) for v in _levels_config(result.model).values())


def _near_to_far(
    result: TraverseAnalysis,
    pred: TerrainPrediction,
    settings: n2f.NearFarSettings,
    progress: bool,
) -> tuple[list[n2f.FarPrediction], dict[str, Any]]:
    """Near-to-far along the traverse, fused into the map's far layers; the predictions
    and the coverage report (with the far-field accuracy when the world is known). Only
    settled, confident near labels teach it (:func:`rough_map.near_far.run_traverse`)."""
    labels = np.where(pred.valid, pred.filtered_class, "")
    calib = result.traverse.spec.calibration
    far = n2f.run_traverse(
        result.traverse,
        labels,
        patch=result.extraction,
        classes=tuple(pred.classes),
        settle=settings.settle_frames,
        min_posterior=settings.min_posterior,
        posterior=np.nan_to_num(np.max(np.asarray(pred.filtered_proba, dtype=float), axis=1)),
        defect=None if pred.mode == "forward" else pred.defect,
        progress=progress,
        tile_px=settings.tile_px(calib, result.extraction) if calib is not None else 32,
        max_range=settings.max_range_m,
        min_confidence=settings.min_confidence,
        recall_min_confidence=settings.recall_min_confidence,
        calibrate=settings.calibrate,
    )
    weight = settings.weight
    grid = result.map
    grid.attrs["far_min_confidence"] = float(settings.min_confidence)
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
    """``features.csv`` with its metadata ``features.csv.json``, with a model ``labels.csv``
    (raw and filtered class per frame, :func:`rough_map.export.labels.write_labels`), and
    ``map_path.geojson``, the path and the frames (:mod:`rough_map.export.vector`).

    Returns
    -------
    dict of str to Path
        ``"features"``, ``"features_metadata"``, ``"labels"`` (with a model) and
        ``"path_geojson"``.
    """
    out = Path(out_dir)
    features = write_features(result.features, out / "features.csv")
    paths = {"features": features, "features_metadata": features_metadata_path(features)}
    if result.prediction is not None:
        paths["labels"] = write_labels(result.features, result.prediction, out / "labels.csv")
    paths["path_geojson"] = write_path_geojson(
        result.features, result.map.crs, out / "map_path.geojson", result.prediction
    )
    return paths


def write_outputs(
    result: TraverseAnalysis,
    out_dir: PathLike,
    *,
    png: bool = True,
    gridmap_bag: bool = False,
    state: bool = True,
    progress: bool = False,
    as_set: bool = True,
    crg: bool = False,
    costmap: CostmapSettings | None = None,
) -> dict[str, Path]:
    """Everything ``rough-map map`` writes for a traverse, into ``out_dir``.

    ``map.tif`` and ``map_<class layer>.tif`` (:func:`rough_map.export.export_map`), one
    PNG per layer, the tables (:func:`write_tables`) and, with ``state``,
    ``map_state.npz``: the map's sums, which ``rough-map batch`` adds to other traverses'
    (:meth:`rough_map.map.tiles.TiledMap.add_saved`). With ``crg``, ``map_road.crg``:
    the elevation layer along the path as an OpenCRG road
    (:func:`rough_map.export.road_crg.write_road_crg`). With a vehicle
    (:attr:`TraverseAnalysis.vehicle`), ``map_costmap.pgm`` and ``.yaml``: the speed advice
    as a map_server costmap (:func:`rough_map.export.costmap.write_costmap`, ``costmap``
    its settings), also in the grid_map bag as a ``nav_msgs/OccupancyGrid``.

    With ``as_set`` (the default) they are written as a set
    (:func:`rough_map._files.output_set`): in a staging folder beside ``out_dir``
    swapped in whole when all are written, so that ``out_dir`` holds either the old outputs
    or the new ones, never a mix; the user's own files in ``out_dir`` are kept, outputs of
    an earlier run that this one does not write (:data:`MAP_OUTPUTS`) are dropped.

    Returns
    -------
    dict of str to Path
        What was written, by kind (paths in ``out_dir``).

    Raises
    ------
    FileFormatError
        Writing failed (full disk, read-only folder); ``out_dir`` is as it was.
    """
    out = Path(out_dir)
    if not as_set:
        out.mkdir(parents=True, exist_ok=True)
        return _write_outputs(result, out, png, gridmap_bag, state, progress, crg, costmap)
    with output_set(out, owned=MAP_OUTPUTS) as stage:
        written = _write_outputs(result, stage, png, gridmap_bag, state, progress, crg, costmap)
    return {k: out / p.relative_to(stage) for k, p in written.items()}


def _write_outputs(
    result: TraverseAnalysis,
    out: Path,
    png: bool,
    gridmap_bag: bool,
    state: bool,
    progress: bool,
    crg: bool,
    costmap: CostmapSettings | None,
) -> dict[str, Path]:
    grid = result.map
    top = result.vehicle.limits.top_speed if result.vehicle is not None else None
    cost = None if top is None else cost_layer(grid, top, costmap)
    # The GeoTIFFs on a second thread beside the PNGs, compressing on that one thread:
    # for an hour of driving, 1.8 s for both against 2.2 s one after the other (and 2.0 s
    # with two GDAL threads, three busy threads then sharing the two cores).
    import_writers(gridmap_bag)  # here, not on the thread (see there)
    pool = ThreadPoolExecutor(1)
    try:
        files = pool.submit(
            export_map,
            grid,
            out,
            name="map",
            png=False,
            gridmap_bag=gridmap_bag,
            threads=1 if png else 2,
            # the bag replays the map as it grew, one message per frame fused
            gridmap_updates=result.mapper.replay() if gridmap_bag and result.mapper else (),
            occupancy=cost,
        )
        pngs = write_pngs(grid, out, "map", progress=progress) if png else {}
        written = files.result()
    except BaseException:
        # a Ctrl-C or a failure here: do not wait for the GeoTIFFs, the set is not written
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    written.update({f"png_{name}": path for name, path in pngs.items()})
    written.update(write_tables(result, out))
    if state and result.mapper is not None:
        written["state"] = result.mapper.save_state(out / "map_state.npz")
    if top is not None:
        written.update(write_costmap(grid, out, top, settings=costmap))
    if crg:
        x, y = result.features["x"], result.features["y"]
        written["crg"] = write_road_crg(grid, x, y, out / "map_road.crg")
    return written


def summary(result: TraverseAnalysis, resolution: float) -> dict[str, Any]:
    """The figures of a traverse's map: frames, valid frames, map shape, near-to-far
    coverage and, with the simulator's truth, class accuracy."""
    return {
        "traverse": result.traverse.name,
        "frames": len(result.features),
        "valid": int(result.features.valid.sum()),
        "map_shape": list(result.map.shape),
        "resolution_m": resolution,
        "band_rad_m": [float(result.features.omega[0]), float(result.features.omega[-1])]
        if result.features.omega.size > 1
        else None,
        **result.far_report,
        **result.truth_accuracy(),
    }
