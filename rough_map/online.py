"""Streaming: frames in one at a time; roughness, class posterior and map update out at once.

:class:`OnlineMapper` is what a robot runs while it drives (a ROS 2 node's callback, or any
loop): give it each frame's cloud (or stereo pair), pose and optional IMU attitude, and
:meth:`OnlineMapper.update` returns the patch's roughness, the class posterior filtered
along the path so far (the forward filter of the model's path filter) and the map around
the patch as it now stands. The map lives in lattice tiles
(:class:`rough_map.map.tiles.TiledMap`): those farther than ``window`` m from the vehicle go
to disk, so memory stays flat over any length of drive; :meth:`OnlineMapper.finish` merges
them into one :class:`~rough_map.map.grid.GridMap`.

>>> mapper = OnlineMapper("default", resolution=0.1)                  # doctest: +SKIP
>>> for t, pose, cloud in frames:                                      # doctest: +SKIP
...     up = mapper.update(pose, cloud=cloud, t=t)
...     print(up.features["R"], up.label, up.map["R"].shape)
>>> grid = mapper.finish()                                             # doctest: +SKIP

``rough-map map`` and :func:`rough_map.workflow.analyse` run the same mapper on recorded
traverses, with the frames processed in parallel (:func:`rough_map.features.iter_frames`)
and the classes smoothed over the whole path before they are fused (:meth:`OnlineMapper.add`
then :meth:`OnlineMapper.finish` with ``late``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map._blas import one_blas_thread
from rough_map.classify import (
    TerrainModel,
    emission_log_likelihood,
    load_roughness_levels,
    load_terrain_model,
    roughness_level,
)
from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.features import FeatureTable, FrameJob, FrameOutput, FramePass
from rough_map.features.extract import feature_table
from rough_map.features.frames import process_points
from rough_map.features.traverse import FeatureCollector
from rough_map.filter import discrete_bayes
from rough_map.geometry import pose_matrix
from rough_map.map.grid import GridMap
from rough_map.map.layers import OBSERVED
from rough_map.map.tiles import TiledMap
from rough_map.patch import Extraction
from rough_map.stereo import stereo_to_cloud

log = logging.getLogger(__name__)

__all__ = ["FrameUpdate", "OnlineMapper"]


@dataclass(frozen=True)
class FrameUpdate:
    """What one frame changed.

    Attributes
    ----------
    index : int
        Frame number (0, 1, ... in the order given).
    features : dict
        The patch's roughness: ``valid``, ``reason``, ``R`` (m³/rad), ``w``, ``sigma_R``,
        ``sigma_w``, ``iso_class``, ... (:func:`rough_map.features.frame_features`).
    raw_proba : ndarray or None
        The classifier's class probabilities for this patch alone (None without a model or
        a valid patch).
    posterior : ndarray or None
        Class posterior filtered along the path up to this frame (None without a model).
    label : str
        The likeliest class under ``posterior`` ("" none).
    level : str
        Roughness level of the patch ("" invalid).
    map : GridMap or None
        The map around the patch as it now stands (estimate layers, lattice-aligned; None
        when the frame fused nothing).
    """

    index: int
    features: dict[str, Any]
    raw_proba: NDArray[np.float64] | None
    posterior: NDArray[np.float64] | None
    label: str
    level: str
    map: GridMap | None


class OnlineMapper:
    """Roughness, terrain class and a rolling map from frames given one at a time.

    Parameters
    ----------
    model : TerrainModel, str, path or None
        The terrain model, its name (``"default"``) or file; None: roughness only.
    resolution : float
        Map cell size, m.
    crs : optional
        CRS of the world frame of the poses (a traverse's ``spec.crs``, ``"EPSG:32633"``).
    calibration : StereoCalibration, optional
        The stereo rig, for frames given as stereo pairs.
    extraction : Extraction, optional
        Patch and estimator (default: the model's, else the paper's).
    window : float
        Radius in m around the vehicle of the map kept in memory; tiles beyond go to disk.
    tile_cells : int
        Side of a map tile, cells.
    spill_dir : path, optional
        Folder for the tiles on disk (default: a temporary folder, removed at the end).
    min_points, min_fill
        Validity of a patch (:func:`rough_map.features.frame_features`).
    name : str
        Name of the run (the features table's and the map's).

    Notes
    -----
    Memory: the tiles within ``window`` of the vehicle, plus each frame's feature row (about
    2 KB, for :meth:`features`). BLAS is held to one thread while a frame is processed.
    """

    def __init__(
        self,
        model: TerrainModel | str | Path | None = "default",
        *,
        resolution: float = 0.1,
        crs: Any = None,
        calibration: StereoCalibration | None = None,
        extraction: Extraction | None = None,
        window: float = 20.0,
        tile_cells: int = 128,
        spill_dir: str | Path | None = None,
        min_points: int = 2000,
        min_fill: float = 0.7,
        name: str = "online",
    ) -> None:
        if not (isinstance(window, int | float) and math.isfinite(window) and window > 0):
            raise InputError(f"window must be a radius > 0 in m, got {window!r}")
        self.model: TerrainModel | None = (
            model if model is None or isinstance(model, TerrainModel) else load_terrain_model(model)
        )
        if extraction is None:
            extraction = Extraction.from_dict(
                self.model.extraction_ if self.model is not None else None
            )
        self.extraction = extraction
        self.settings = FramePass(
            extraction,
            "auto",
            calibration,
            min_points=min_points,
            min_fill=min_fill,
            height_resolution=resolution,
        )
        levels = self.model.levels_ if self.model is not None else load_roughness_levels(None)
        self.level_names = tuple(levels.levels)
        self.level_thresholds = tuple(float(v) for v in levels.values())
        self.classes = tuple(str(c) for c in self.model.classes_) if self.model is not None else ()
        self.window = float(window)
        self.name = name
        self._collect = FeatureCollector(name, extraction)
        self.tiles = TiledMap(
            resolution,
            self.classes,
            crs=crs,
            spec=extraction.patch,
            tile_cells=tile_cells,
            level_names=self.level_names,
            spill_dir=spill_dir,
        )
        self._track: list[tuple[float, float]] = []
        self._log_belief: NDArray[np.float64] | None = None
        self._last_xy: tuple[float, float] | None = None
        self._late: tuple[Any, Any, dict[str, NDArray[Any]]] | None = None

    # -- one frame ---------------------------------------------------------------------

    def update(
        self,
        pose: Any,
        *,
        cloud: ArrayLike | None = None,
        left: NDArray[Any] | None = None,
        right: NDArray[Any] | None = None,
        imu: tuple[float, float] | None = None,
        t: float = math.nan,
        label: str | None = None,
    ) -> FrameUpdate:
        """Process one frame and fuse it into the map.

        Parameters
        ----------
        pose : Pose, 6 floats or 4x4
            Vehicle pose in the world: ``(x, y, z, roll, pitch, yaw)`` in m and rad, a
            :class:`~rough_map.config.Pose` or a 4x4 matrix
            (:func:`rough_map.geometry.pose_matrix`).
        cloud : array_like, shape (N, 3), optional
            Points in the vehicle frame, m.
        left, right : ndarray, optional
            A rectified stereo pair (instead of ``cloud``; needs ``calibration``).
        imu : (roll, pitch), optional
            IMU attitude in rad, for tilt compensation when the extraction asks for it.
        t : float
            Time, s.
        label : str, optional
            True class, if known (kept in the features table).
        """
        job = self._job(pose, t, label, imu)
        # Small matrices per frame: BLAS threads would only get in each other's way.
        with one_blas_thread():
            points = self._points(cloud, left, right)
            out = process_points(points, job, self.settings, "no cloud or stereo pair given")
            return self.add(out, job.pose, classes=True)

    def _job(self, pose: Any, t: float, label: str | None, imu: Any) -> FrameJob:
        m = pose_matrix(pose)
        rot = m[:3, :3]
        yaw = math.atan2(rot[1, 0], rot[0, 0])
        pitch = math.asin(max(-1.0, min(1.0, -rot[2, 0])))
        roll = math.atan2(rot[2, 1], rot[2, 2])
        if imu is not None:
            imu = (float(imu[0]), float(imu[1]))
        xyz = (float(m[0, 3]), float(m[1, 3]), float(m[2, 3]))
        return FrameJob(
            len(self._collect.rows), float(t), (*xyz, roll, pitch, yaw), label or "", imu=imu
        )

    def _points(
        self, cloud: ArrayLike | None, left: NDArray[Any] | None, right: NDArray[Any] | None
    ) -> NDArray[np.float64] | None:
        if cloud is not None:
            return np.asarray(cloud, dtype=float)
        if left is None or right is None:
            return None
        if self.settings.calibration is None:
            raise InputError("a stereo pair needs the rig's calibration (calibration=...)")
        return stereo_to_cloud(left, right, self.settings.calibration, patch=self.extraction.patch)

    def add(
        self,
        out: FrameOutput,
        pose: Sequence[float],
        *,
        classes: bool = True,
        roughness: bool = True,
    ) -> FrameUpdate:
        """Fuse a frame already processed (:func:`rough_map.features.iter_frames`).

        Parameters
        ----------
        out : FrameOutput
            The frame's features and height sample.
        pose : 6 floats
            ``(x, y, z, roll, pitch, yaw)``, m and rad.
        classes : bool
            Classify the frame, filter forward and fuse its posterior now (False: fuse only
            the roughness and heights, and the classes later: :meth:`finish` with ``late``).
        roughness : bool
            Fuse the patch's R and w now (False: the patch is counted but its roughness
            comes later, e.g. smoothed along the whole path, with
            :meth:`finish`'s ``roughness``).
        """
        index = len(self._collect.rows)
        self._collect.add(out)
        x, y, yaw = float(pose[0]), float(pose[1]), float(pose[5])
        self._track.append((x, y))
        row = out.row
        raw = posterior = None
        novelty = math.nan
        if classes and self.model is not None:
            raw, posterior, novelty = self._classify(out, x, y)
        level = self._level(row) if classes else math.nan
        observation = None
        if row["valid"]:
            observation = _observation(row, posterior if classes else None, level, novelty)
            if not roughness:
                observation["R"] = math.nan  # fused later (finish, late)
        h = out.heights
        touched, area = self.tiles.add_frame(
            x,
            y,
            yaw,
            observation,
            None if h is None else (h.rows, h.cols, h.sums, h.counts),
            keep_box=not classes,
            window=self.window,
            margin=0.0 if classes else None,
        )
        label = "" if posterior is None else self.classes[int(np.argmax(posterior))]
        area = area if touched else None
        name = self.level_names[int(level)] if math.isfinite(level) else ""
        return FrameUpdate(index, row, raw, posterior, label, name, area)

    def _level(self, row: dict[str, Any]) -> float:
        return float(self._levels([row["R"]])[0]) if row["valid"] else math.nan

    def _levels(self, R: ArrayLike) -> NDArray[np.float64]:
        """Level index per value of R (m³/rad; NaN: none), as :meth:`_level` of each."""
        index: dict[str, float] = {}
        for i, name in enumerate(self.level_names):
            index.setdefault(name, float(i))
        names = roughness_level(R, self.level_names, self.level_thresholds)
        return np.array([index[n] if n else math.nan for n in names], dtype=float)

    def _classify(
        self, out: FrameOutput, x: float, y: float
    ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64], float]:
        """The classifier's probabilities of the frame, the forward-filtered posterior and
        the frame's novelty (NaN: none)."""
        model = self.model
        assert model is not None
        step = (
            math.hypot(x - self._last_xy[0], y - self._last_xy[1])
            if self._last_xy is not None
            else self.extraction.patch.size  # the first patch is all new ground
        )
        self._last_xy = (x, y)
        table = feature_table(
            [out.row],
            [out.psd],
            out.omega,
            self.extraction.patch,
            self.name,
        )
        raw_all, valid, novelties = model.frame_scores(table)  # the features read once
        raw = raw_all[0] if valid[0] else None
        novelty = float(novelties[0]) if raw is not None else math.nan
        flt = model.filter_
        if flt is None or model.evidence_per_m_ is None:
            if raw is None:
                return None, np.full(len(self.classes), 1.0 / len(self.classes)), novelty
            return raw, raw, novelty
        if self._log_belief is None:
            belief = np.log(flt.class_prior_)
        else:
            with np.errstate(divide="ignore"):
                log_t = np.log(flt.transition_matrix(step))
            belief = discrete_bayes.predict(self._log_belief, log_t)
        if raw is not None:
            ll = emission_log_likelihood(raw[None, :], [step], model.evidence_per_m_)[0]
            belief = discrete_bayes.update(belief, ll)
        self._log_belief = belief
        return raw, np.exp(belief), novelty

    # -- the whole run -----------------------------------------------------------------

    def features(self) -> FeatureTable:
        """The features table of the frames so far."""
        return self._collect.table()

    def _fuse_late(
        self,
        proba: ArrayLike | None,
        roughness: Mapping[str, ArrayLike] | None,
        novelty: ArrayLike | None,
    ) -> None:
        """Fuse what the frames added with ``classes=False`` held back (:meth:`finish`'s
        ``late``): their classes, levels, and roughness and novelty when given."""
        rows = self._collect.rows
        extra = _per_frame(roughness, len(rows))
        if novelty is not None:
            extra["novelty"] = np.asarray(novelty, dtype=float)
            if extra["novelty"].shape != (len(rows),):
                raise InputError(f"novelty needs one value per frame ({len(rows)},)")
        p = (
            np.full((len(rows), len(self.classes)), np.nan)
            if proba is None
            else (np.asarray(proba, dtype=float))
        )
        if p.shape != (len(rows), len(self.classes)):
            raise InputError(
                f"proba must have shape ({len(rows)}, {len(self.classes)}), got {p.shape}"
            )
        # the frames' levels and which rows of p are whole, for all frames at once
        known = np.all(np.isfinite(p), axis=1) if self.classes else np.zeros(len(rows), bool)
        level_of = np.full(len(rows), math.nan)
        if rows:
            valid = np.array([bool(row["valid"]) for row in rows])
            R = extra["R"] if "R" in extra else [r["R"] if r["valid"] else math.nan for r in rows]
            level_of = np.where(valid, self._levels(R), math.nan)
        # kept for replay(): each frame's classes, level, roughness and novelty as fused here
        self._late = (np.where(known[:, None], p, np.nan), level_of, extra)
        for i, row in enumerate(rows):
            if not row["valid"]:
                continue
            x, y, yaw = row["x"], row["y"], row["yaw"]
            probs = p[i] if known[i] else None
            rough = {k: float(v[i]) for k, v in extra.items()}
            level = float(level_of[i])
            if probs is None and not math.isfinite(level) and not rough:
                continue
            fused: dict[str, Any] = {"probs": probs, "level": level, "count": False, **rough}
            self.tiles.add_frame(x, y, yaw, fused, window=self.window)

    def replay(self, *, margin: float = 0.2) -> Iterator[tuple[float, GridMap]]:
        """The map as it grew: after each valid frame, in order, the map around its patch
        (its box plus ``margin`` m) as it then stood, with every observation of the frames
        so far fused at once (roughness, the classes and levels fused late by :meth:`finish`),
        as ``(t, window)``; the heights (``elevation``) are not replayed.

        The frames are fused again into tiles of their own (kept within :attr:`window` of
        the vehicle, the rest on disk), so the map itself is left as it is; after the last
        frame, the replayed sums are those of the map.
        """
        rows = self._collect.rows
        p, level_of, extra = self._late if self._late is not None else (None, None, {})
        replayed = TiledMap(
            self.tiles.resolution,
            self.classes,
            crs=self.tiles.geometry.crs,
            spec=self.extraction.patch,
            tile_cells=self.tiles.tile_cells,
            level_names=self.level_names,
        )
        try:
            for i, row in enumerate(rows):
                if not row["valid"]:
                    continue
                x, y, yaw = row["x"], row["y"], row["yaw"]
                obs = _observation(
                    row,
                    None if p is None or not np.isfinite(p[i]).all() else p[i],
                    math.nan if level_of is None else float(level_of[i]),
                    math.nan,  # or the frame's, in extra
                )
                obs.update({k: float(v[i]) for k, v in extra.items()})
                _, area = replayed.add_frame(x, y, yaw, obs, window=self.window, margin=margin)
                if area is not None:
                    yield float(row.get("t", math.nan)), area
        finally:
            replayed.close()

    def finish(
        self,
        *,
        late: bool = False,
        proba: ArrayLike | None = None,
        roughness: Mapping[str, ArrayLike] | None = None,
        novelty: ArrayLike | None = None,
        margin: float = 1.0,
    ) -> GridMap:
        """The whole map: estimate layers and ``elevation``, over every patch seen plus
        ``margin`` m. The sums stay in :attr:`tiles` (for :meth:`save_state`) until
        :meth:`close`.

        With ``late``, what the frames added with ``classes=False`` held back is fused
        first: the class probabilities computed over the whole run (``proba``, e.g.
        smoothed; one row per frame, NaN rows: none; None: no classes) and the frames'
        roughness levels. ``roughness`` gives the roughness of each frame computed over the
        whole run, for frames added with ``roughness=False``: arrays ``R`` (m³/rad), ``w``,
        ``sigma_R`` (m³/rad) and ``sigma_w``, one value per frame (e.g. smoothed along the
        path, :class:`rough_map.filter.RoughnessSmoother`); the levels then come from this
        R. ``novelty`` gives each frame's novelty score (NaN: none;
        :attr:`rough_map.classify.TerrainPrediction.novelty`), fused with its classes.
        """
        if late:
            self._fuse_late(proba, roughness, novelty)
        valid = [r["valid"] for r in self._collect.rows]
        attrs = {
            "name": self.name,
            "track": np.asarray(self._track, dtype=float).reshape(-1, 2),
            "n_frames": len(valid),
            "n_valid": int(sum(valid)),
            "patch": {
                "ahead": self.extraction.patch.ahead,
                "size": self.extraction.patch.size,
                "lateral": self.extraction.patch.lateral,
            },
        }
        return self.tiles.merged(margin=margin, attrs=attrs)

    def save_state(self, path: str | Path) -> Path:
        """Write the map's sums (:meth:`rough_map.map.tiles.TiledMap.save`), which
        ``rough-map batch`` adds up across traverses."""
        return self.tiles.save(path, attrs={"name": self.name})

    def close(self) -> None:
        """Remove the tiles kept on disk."""
        self.tiles.close()


def _per_frame(roughness: Mapping[str, ArrayLike] | None, n: int) -> dict[str, NDArray[Any]]:
    """The arrays ``R``, ``w``, ``sigma_R``, ``sigma_w`` of ``roughness``, checked (n each)."""
    if roughness is None:
        return {}
    keys = ("R", "w", "sigma_R", "sigma_w")
    missing = [k for k in keys if k not in roughness]
    if missing:
        raise InputError(f"roughness needs the arrays {list(keys)}; missing {missing}")
    out = {k: np.asarray(roughness[k], dtype=float) for k in keys}
    bad = [k for k, v in out.items() if v.shape != (n,)]
    if bad:
        raise InputError(f"roughness {bad[0]!r} needs one value per frame ({n},)")
    return out


def _observation(
    row: dict[str, Any], probs: NDArray[np.float64] | None, level: float, novelty: float
) -> dict:
    """A frame's observation for the map (:func:`rough_map.map.fuse_patch`): the fields of
    :data:`rough_map.map.layers.OBSERVED` from its features row, its novelty, classes and
    level."""
    obs: dict[str, Any] = {k: float(row.get(k, math.nan)) for k in OBSERVED}
    obs.update(t=float(row.get("t", math.nan)), probs=probs, level=level, novelty=novelty)
    return obs
