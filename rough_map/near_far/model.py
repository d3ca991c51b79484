"""The near-to-far estimator: learn the look of the near field, classify the far field.

See :mod:`rough_map.near_far` for the method; this module holds :class:`NearToFar`, which
ties the tiles (:mod:`~rough_map.near_far.tiles`), the appearance model
(:mod:`~rough_map.near_far.looks`) and the ground cells
(:mod:`~rough_map.near_far.cells`) together, frame by frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator

from rough_map.config import Pose, StereoCalibration
from rough_map.errors import InputError, NotFittedError
from rough_map.geometry import pose_matrix
from rough_map.near_far.calibration import DistanceCalibration, apply_confidence, top_logit
from rough_map.near_far.cells import GroundCells, NearField, cells_in_view
from rough_map.near_far.checks import check_numbers, class_weights
from rough_map.near_far.looks import DEFAULT_MIN_STD, Looks, LooksClassifier
from rough_map.near_far.prediction import FarPrediction
from rough_map.near_far.tiles import (
    FEATURE_NAMES,
    TileGeometry,
    check_image,
    tile_features,
    tile_geometry,
)
from rough_map.patch import Extraction, PatchSpec

log = logging.getLogger(__name__)

__all__ = ["NearToFar"]


class NearToFar(BaseEstimator):
    """Online appearance model: learn near-field tiles, classify far-field ground cells.

    A scikit-learn estimator (``get_params``, ``set_params``, :func:`sklearn.base.clone`):
    the constructor only stores its arguments; they are checked at the first
    :meth:`update`, and the appearance parameters (``novelty_alpha``, ``outlier_k``,
    ``min_std``, ``min_support``, ``max_looks``) are read then, by the
    :class:`~rough_map.near_far.looks.LooksClassifier` it builds (``appearance_``, the
    model's X, y interface on tile features). The others are read at every frame.

    Parameters
    ----------
    classes : sequence of str
        Terrain class names, in the order of the probability vectors in and out.
    patch : PatchSpec or Extraction
        The patch that geometry classifies (an extraction's patch): the near field whose
        tiles are learnt, and which predictions leave out. Take it from the terrain model
        that labels the near field (``Extraction.from_dict(model.extraction_)``).
    tile_px : int
        Side of the square image tiles, px.
    max_range : float
        Largest horizontal distance from the vehicle of a predicted cell, m.
    ground_step : float
        Spacing of the ground cells the predictions are given on, m.
    novelty_alpha : float
        A tile whose squared Mahalanobis distance to the nearest look in use has a
        chi-square tail probability ``q`` below this is unfamiliar: its probabilities are
        mixed with the uniform distribution, with weight ``1 - q / novelty_alpha``. 0
        disables the gate. A near-field batch joins a look of its class if its mean passes
        the same test, and starts a new look otherwise.
    outlier_k : float
        Near-field tiles further than this many robust standard deviations (normal-consistent
        MAD) from the batch median in some feature are not learnt; ``inf`` learns them all.
    min_near_tiles : int
        Fewest near-field tiles an update needs; fewer (the patch out of view) raises.
    min_std : sequence of 6 float
        Lowest standard deviation of each feature within a class (units of
        :data:`~rough_map.near_far.tiles.FEATURE_NAMES`), see
        :data:`~rough_map.near_far.looks.DEFAULT_MIN_STD`.
    recall : bool
        Remember the appearance of the cells that were unfamiliar when seen (at their
        closest sighting) and predict them, once, as soon as an update makes them familiar:
        terrain of a new class is mostly seen far ahead before the rover drives onto it and
        learns it. Only images and labels up to the current frame are used.
    memory_cells : int
        Most cells remembered for ``recall`` (the oldest are forgotten first; cells more
        than ``2 * max_range`` from the vehicle are forgotten too).
    min_support : float
        Updates (frames, weighted by the label's probability) a look needs before it is
        used: a look learnt once may be a wrong geometric label.
    max_looks : int
        Most looks kept per class; the least supported goes first.
    min_confidence : float
        Cells whose largest (calibrated) class probability is below this are left out of
        the predictions: the model abstains, and they stay unknown (NaN in a map) rather
        than take the likeliest class or a near-uniform row, which a map's evidence fusion
        would count as seen. 0 keeps every cell in view. Their distances are kept
        (:attr:`FarPrediction.abstained`).
    calibrate : bool
        Calibrate the confidence on checked predictions: near-field batches scored before
        they are learnt, and far cells scored once the near field labels them (by the
        distance they were predicted from; :mod:`~rough_map.near_far.calibration`).
        The far cells are checked only when :meth:`update_tiles` gets the frame's pose
        (:meth:`update`, :func:`~rough_map.near_far.run_traverse` pass it).
    recall_min_confidence : float
        A remembered cell is recalled only if its calibrated probability reaches this
        (and ``min_confidence``): a recall labels ground that is no longer in view, all at
        once, so it needs strong evidence.

    Attributes
    ----------
    classes_ : tuple of str
        The class names (after the first :meth:`update`).
    near_field_ : NearField
        The near field of ``patch`` in the vehicle frame, m.
    appearance_ : LooksClassifier
        The appearance model of the tile features.
    looks_ : Looks
        The learnt looks (once an update has learnt a tile; ``hasattr(model, "looks_")``
        says whether the model can predict).
    n_updates_ : int
        Number of updates that learnt tiles.
    seen_ : ndarray of bool, shape (K,)
        Classes with at least one look in use.
    """

    def __init__(
        self,
        classes: Sequence[str],
        patch: PatchSpec | Extraction,
        *,
        tile_px: int = 32,
        max_range: float = 8.0,
        ground_step: float = 0.1,
        novelty_alpha: float = 1e-3,
        outlier_k: float = 4.0,
        min_near_tiles: int = 8,
        min_std: Sequence[float] = DEFAULT_MIN_STD,
        recall: bool = True,
        memory_cells: int = 50_000,
        min_support: float = 2.0,
        max_looks: int = 8,
        min_confidence: float = 0.8,
        calibrate: bool = True,
        recall_min_confidence: float = 0.9,
    ) -> None:
        self.classes = classes
        self.patch = patch
        self.tile_px = tile_px
        self.max_range = max_range
        self.ground_step = ground_step
        self.novelty_alpha = novelty_alpha
        self.outlier_k = outlier_k
        self.min_near_tiles = min_near_tiles
        self.min_std = min_std
        self.recall = recall
        self.memory_cells = memory_cells
        self.min_support = min_support
        self.max_looks = max_looks
        self.min_confidence = min_confidence
        self.calibrate = calibrate
        self.recall_min_confidence = recall_min_confidence

    # ------------------------------------------------------------------------ validation

    def _start(self) -> None:
        """Check the parameters and set up the fitted state (at the first update)."""
        if hasattr(self, "classes_"):
            return
        classes = tuple(str(c) for c in self.classes)
        if len(classes) < 2:
            raise InputError(f"classes must name at least two classes, got {classes}")
        if len(set(classes)) != len(classes):
            raise InputError(f"classes must be distinct, got {classes}")
        if not isinstance(self.patch, PatchSpec | Extraction):
            raise InputError(
                f"patch must be a PatchSpec or an Extraction, got {type(self.patch).__name__}"
            )
        near = NearField.of(self.patch)
        if not 0.0 <= near.ahead[0]:
            raise InputError(
                f"the patch must lie ahead of the vehicle; its x range is {near.ahead} m"
            )
        self._check_numbers(near)
        self.classes_ = classes
        self.near_field_ = near
        # checks its parameters when it learns its first batch, in this update
        self.appearance_ = LooksClassifier(
            novelty_alpha=self.novelty_alpha,
            outlier_k=self.outlier_k,
            min_std=self.min_std,
            min_support=self.min_support,
            max_looks=self.max_looks,
        )
        self._memory: dict[tuple[int, int], tuple[float, NDArray[np.float64]]] = {}
        # far-field scores per cell, (distance, scores), until the near field labels it
        self._pending: dict[tuple[int, int], list[tuple[float, float, int]]] = {}
        self.distance_calibration_ = DistanceCalibration()
        self._recall_checked = 0

    def _check_numbers(self, near: NearField) -> None:
        check_numbers(self, near)

    # ------------------------------------------------------------------------ fitted state

    @property
    def looks_(self) -> Looks:
        """The learnt looks (AttributeError before an update has learnt a tile)."""
        appearance = getattr(self, "appearance_", None)
        if appearance is None or getattr(appearance, "n_updates_", 0) == 0:
            raise AttributeError("NearToFar has learnt nothing yet: no looks_")
        return appearance.looks_

    @property
    def n_updates_(self) -> int:
        """Number of updates that learnt tiles (AttributeError before the first)."""
        return int(self.appearance_.n_updates_) if hasattr(self, "looks_") else self._not_fitted()

    @property
    def seen_(self) -> NDArray[np.bool_]:
        """Classes with at least one look in use (``min_support`` reached), shape (K,)."""
        seen = np.zeros(len(self.classes_ if hasattr(self, "classes_") else self.classes), bool)
        if hasattr(self, "looks_"):
            looks = self.looks_
            seen[looks.cls[looks.support >= self.appearance_.min_support]] = True
        return seen

    def _not_fitted(self) -> Any:
        raise NotFittedError("NearToFar has learnt nothing yet: call update() first")

    # ------------------------------------------------------------------------ helpers

    def tile_geometry(self, calib: StereoCalibration) -> TileGeometry:
        """The tiles of ``tile_px`` px of ``calib``'s left image and their ground points
        (cached for the last calibration)."""
        key = (calib.model_dump_json(), self.tile_px)
        cache = getattr(self, "_tile_cache", None)
        if cache is None or cache[0] != key:
            cache = (key, tile_geometry(calib, self.tile_px))
            self._tile_cache = cache
        return cache[1]

    def near_tiles(self, calib: StereoCalibration) -> NDArray[np.bool_]:
        """Which tiles of ``calib``'s left image see the near field, shape (T,)."""
        geometry = self.tile_geometry(calib)
        near = self.near_field_ if hasattr(self, "near_field_") else NearField.of(self.patch)
        return np.asarray(near.contains(geometry.ground[:, 0], geometry.ground[:, 1]))

    def _target(self, near_label: str | int | ArrayLike) -> NDArray[np.float64]:
        """Class weights (K,) of a near label: name, index or probability vector."""
        return class_weights(self.classes_, near_label)

    # ------------------------------------------------------------------------ learning

    def update(
        self,
        image_bgr: ArrayLike,
        calib: StereoCalibration,
        pose: Pose | ArrayLike,
        near_label: str | int | ArrayLike,
    ) -> NearToFar:
        """Learn the look of the near field of one frame.

        Parameters
        ----------
        image_bgr : array_like of uint8, shape (H, W, 3)
            Left image, 8-bit BGR, of the size of ``calib``.
        calib : StereoCalibration
            The rig.
        pose : Pose or array_like
            Vehicle pose in the world (see :func:`~rough_map.geometry.pose_matrix`). The
            near field is defined in the vehicle frame, so the pose is only checked; it is
            taken for symmetry with :meth:`predict`.
        near_label : str, int or array_like of float, shape (K,)
            Geometric class of the near-field patch: a class name, a class index, or class
            probabilities (weights of the tiles per class).

        Returns
        -------
        NearToFar
            ``self``.

        Raises
        ------
        InputError
            Bad parameters (at the first update), wrong image size or type, an unknown
            class label, or a near field not in view.
        """
        self._start()
        image = check_image(image_bgr, calib)
        pose_matrix(pose)
        self._target(near_label)  # checked before the features are computed
        return self.update_tiles(tile_features(image, self.tile_px), calib, near_label)

    def update_tiles(
        self,
        tiles: NDArray[np.float64],
        calib: StereoCalibration,
        near_label: str | int | ArrayLike,
        pose: Pose | ArrayLike | None = None,
        *,
        check: bool = True,
    ) -> NearToFar:
        """:meth:`update` from the image's :func:`~rough_map.near_far.tiles.tile_features`
        (of ``tile_px`` px), e.g. computed once for :meth:`predict_tiles` and this. With
        ``check``, :meth:`check_tiles` first."""
        near = self._near_batch(calib)
        target = self._target(near_label)
        if check:
            self.check_tiles(tiles, calib, near_label, pose)
        first = not hasattr(self.appearance_, "looks_")
        self.appearance_.learn(tiles[near], target, classes=self.classes_ if first else None)
        return self

    def check_tiles(
        self,
        tiles: NDArray[np.float64],
        calib: StereoCalibration,
        near_label: str | int | ArrayLike,
        pose: Pose | ArrayLike | None = None,
    ) -> NearToFar:
        """Check the model against a near label without learning it (the calibration):
        the near-field tiles are scored before they are learnt (held out) and, with the
        ``pose``, the far-field predictions made earlier of the cells under the near field
        are scored against the label. Any label may check, a settled one or not
        (:func:`~rough_map.near_far.run_traverse` checks every frame and learns only
        the settled ones)."""
        near = self._near_batch(calib)
        target = self._target(near_label)
        if not (self.calibrate and target.max() >= 0.5 and hasattr(self, "looks_")):
            return self
        raw = self.appearance_.predict_proba(tiles[near])
        right = np.argmax(raw, axis=1) == np.argmax(target)
        self.distance_calibration_.near.add(top_logit(raw), right, int(np.argmax(target)))
        if pose is not None:
            self._check_far(pose_matrix(pose), target)
        return self

    def _near_batch(self, calib: StereoCalibration) -> NDArray[np.bool_]:
        """The near-field tiles (checked to be enough), after starting the model."""
        self._start()
        near = self.near_tiles(calib)
        if near.sum() < self.min_near_tiles:
            raise InputError(
                f"only {int(near.sum())} tiles of {self.tile_px} px see the near field "
                f"{self.near_field_.ahead} m ahead; check the calibration or use smaller tiles"
            )
        return near

    def _check_far(self, transform: NDArray[np.float64], target: NDArray[np.float64]) -> None:
        """Calibration rows: earlier far-field scores of the cells under the near field."""
        if not self._pending:
            return
        near = self.near_field_
        step = self.ground_step / 2.0
        ax = np.arange(near.ahead[0] + step / 2, near.ahead[1], step)
        ay = np.arange(near.lateral[0] + step / 2, near.lateral[1], step)
        gx, gy = np.meshgrid(ax, ay)
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
        world = pts @ transform[:3, :3].T + transform[:3, 3]
        keys = np.unique(np.floor(world[:, :2] / self.ground_step).astype(np.int64), axis=0)
        rows = [r for key in map(tuple, keys.tolist()) for r in self._pending.pop(key, [])]
        if rows:
            arr = np.array(rows)
            right = arr[:, 2].astype(np.intp) == int(np.argmax(target))
            self.distance_calibration_.add_far(arr[:, 1], right, arr[:, 0], int(np.argmax(target)))

    # ------------------------------------------------------------------------ prediction

    def predict_proba_features(self, features: ArrayLike) -> NDArray[np.float64]:
        """Class probabilities of tile feature rows
        (:meth:`~rough_map.near_far.looks.LooksClassifier.predict_proba`).

        Parameters
        ----------
        features : array_like, shape (N, 6)
            Tile features (:func:`~rough_map.near_far.tiles.tile_features`).

        Returns
        -------
        ndarray, shape (N, K)
            Probabilities, rows summing to 1.

        Raises
        ------
        NotFittedError
            Before the first :meth:`update`.
        """
        if not hasattr(self, "looks_"):
            self._not_fitted()
        x = np.asarray(features, dtype=float)
        if x.ndim != 2 or x.shape[1] != len(FEATURE_NAMES):
            raise InputError(f"features must have shape (N, {len(FEATURE_NAMES)}), got {x.shape}")
        return self.appearance_.predict_proba(x)

    def predict(
        self,
        image_bgr: ArrayLike,
        calib: StereoCalibration,
        pose: Pose | ArrayLike,
        *,
        t: float | None = None,
        frame: int | None = None,
    ) -> FarPrediction:
        """Class probabilities of the ground cells in view beyond the near field.

        Parameters
        ----------
        image_bgr : array_like of uint8, shape (H, W, 3)
            Left image, 8-bit BGR, of the size of ``calib``.
        calib : StereoCalibration
            The rig.
        pose : Pose or array_like
            Vehicle pose in the world (see :func:`~rough_map.geometry.pose_matrix`).
        t : float, optional
            Frame time, s, copied to the prediction.
        frame : int, optional
            Frame index, copied to the prediction.

        Returns
        -------
        FarPrediction
            Cells on the ``ground_step`` world lattice within ``max_range`` m, outside the
            near field, seen by a tile whose ray meets the ground, with a confidence of at
            least ``min_confidence``; with ``recall``, followed by the remembered cells that
            became familiar (``recalled`` true).

        Raises
        ------
        InputError
            Wrong image size or type, or a bad pose.
        NotFittedError
            Before the first :meth:`update`.
        """
        image = check_image(image_bgr, calib)
        transform = pose_matrix(pose)
        if not hasattr(self, "looks_"):
            self._not_fitted()
        tiles = tile_features(image, self.tile_px)
        return self.predict_tiles(tiles, calib, transform, t=t, frame=frame)

    def predict_tiles(
        self,
        tiles: NDArray[np.float64],
        calib: StereoCalibration,
        pose: Pose | ArrayLike,
        *,
        t: float | None = None,
        frame: int | None = None,
    ) -> FarPrediction:
        """:meth:`predict` from the image's
        :func:`~rough_map.near_far.tiles.tile_features` (of ``tile_px`` px)."""
        transform = pose_matrix(pose)
        if not hasattr(self, "looks_"):
            self._not_fitted()
        geometry = self.tile_geometry(calib)
        # Tiles whose centre is a little beyond max_range still cover cells within it.
        with np.errstate(invalid="ignore"):
            usable = np.isfinite(geometry.distance) & (geometry.distance <= self.max_range + 1.0)
        features = np.where(usable[:, None], tiles, np.nan)
        cells = cells_in_view(
            calib,
            geometry,
            self.tile_px,
            transform,
            usable,
            features,
            step=self.ground_step,
            max_range=self.max_range,
            near=self.near_field_,
        )
        proba, familiar = self._proba(cells.features, cells.distance, cells.keys)
        recalled = np.zeros(len(cells.x), dtype=bool)
        if self.recall:
            old = self._recall(cells, familiar, transform)
            if len(old.x):
                old_proba, _ = self._proba(old.features, old.distance)
                strong = old_proba.max(axis=1) >= self.recall_min_confidence
                old = GroundCells.from_rows(old.keys[strong], _rows(old)[strong])
                cells = GroundCells.concat(cells, old)
                proba = np.concatenate([proba, old_proba[strong]])
                recalled = np.concatenate([recalled, np.ones(len(old.x), dtype=bool)])
        confident = proba.max(axis=1, initial=0.0) >= self.min_confidence
        return FarPrediction(
            x=cells.x,
            y=cells.y,
            ahead=cells.ahead,
            lateral=cells.lateral,
            distance=cells.distance,
            proba=proba,
            classes=self.classes_,
            t=t,
            frame=frame,
            recalled=recalled,
            abstained=cells.distance[~confident & ~recalled],
        ).select(confident)

    def _proba(
        self,
        features: NDArray[np.float64],
        distance: NDArray[np.float64],
        keys: NDArray[np.int64] | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Probabilities (N, K), calibrated, and whether each row is familiar (N,), of cells
        ``distance`` m away; with their ``keys``, the raw predictions are remembered until
        the near field checks them."""
        k = len(self.classes_)
        if not len(features):
            return np.zeros((0, k)), np.zeros(0, dtype=bool)
        appearance = self.appearance_
        proba = appearance.predict_proba(features)
        if self.calibrate:
            s = top_logit(proba)
            if keys is not None:
                self._remember(keys, distance, s, np.argmax(proba, axis=1))
            # calibration only lowers a confidence: the curve is extrapolated where few
            # checked rows lie (a uniform row of unfamiliar ground must stay uniform); and
            # nothing is confident before checks of two classes or more exist
            q = self.distance_calibration_.confidence(s, distance)
            q = np.where(np.isfinite(q), np.fmin(q, proba.max(axis=1)), 1.0 / k)
            if self.seen_.sum() < 2:
                # one class in use: every familiar tile is that class, whatever it is
                q[:] = 1.0 / k
            proba = apply_confidence(proba, q)
        if appearance.novelty_alpha == 0:
            return proba, np.ones(len(features), dtype=bool)
        return proba, appearance.familiarity(features) >= appearance.novelty_alpha

    def _remember(
        self,
        keys: NDArray[np.int64],
        distance: NDArray[np.float64],
        s: NDArray[np.float64],
        top: NDArray[np.intp],
    ) -> None:
        pending = self._pending
        rows = zip(
            map(tuple, keys.tolist()), distance.tolist(), s.tolist(), top.tolist(), strict=True
        )
        for key, d, logit, c in rows:
            pending.setdefault(key, []).append((d, logit, c))
        while len(pending) > self.memory_cells:
            del pending[next(iter(pending))]

    def _recall(
        self, cells: GroundCells, familiar: NDArray[np.bool_], transform: NDArray[np.float64]
    ) -> GroundCells:
        """Update the memory of unfamiliar cells; return those that are familiar now."""
        memory = self._memory
        for k, key in enumerate(map(tuple, cells.keys.tolist())):
            if familiar[k]:
                memory.pop(key, None)
            elif key not in memory or memory[key][0] > cells.distance[k]:
                memory[key] = (float(cells.distance[k]), cells.row(k))
        # Forget cells far behind, and the oldest beyond the cap.
        here = transform[:2, 3]
        stale = [
            key
            for key, (_, row) in memory.items()
            if math.hypot(row[0] - here[0], row[1] - here[1]) > 2.0 * self.max_range
        ]
        for key in stale:
            del memory[key]
        while len(memory) > self.memory_cells:
            del memory[next(iter(memory))]
        n_updates = self.n_updates_
        if self._recall_checked == n_updates or not memory:
            return GroundCells.empty(len(FEATURE_NAMES))
        self._recall_checked = n_updates
        in_view = set(map(tuple, cells.keys.tolist()))
        candidates = [key for key in memory if key not in in_view]
        if not candidates:
            return GroundCells.empty(len(FEATURE_NAMES))
        rows = np.array([memory[key][1] for key in candidates])
        _, now_familiar = self._proba(rows[:, 5:], rows[:, 4])
        out = [key for key, ok in zip(candidates, now_familiar, strict=True) if ok]
        for key in out:
            del memory[key]
        log.debug("near-to-far recall: %d cells became familiar", len(out))
        return GroundCells.from_rows(np.array(out, dtype=np.int64), rows[now_familiar])


def _rows(cells: GroundCells) -> NDArray[np.float64]:
    """The :meth:`GroundCells.row` arrays of all cells, shape (N, 5 + F)."""
    head = np.column_stack([cells.x, cells.y, cells.ahead, cells.lateral, cells.distance])
    return np.concatenate([head, cells.features], axis=1)
