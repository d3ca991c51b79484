"""The near-to-far estimator: learn the look of the near field, classify the far field.

See :mod:`rough_map.map.near_far` for the method; this module holds :class:`NearToFar`, which
ties the tiles (:mod:`~rough_map.map.near_far.tiles`), the appearance model
(:mod:`~rough_map.map.near_far.looks`) and the ground cells
(:mod:`~rough_map.map.near_far.cells`) together, frame by frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from numbers import Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator

from rough_map.config import Pose, StereoCalibration
from rough_map.errors import InputError, NotFittedError
from rough_map.geometry import pose_matrix
from rough_map.map.near_far.cells import GroundCells, NearField, cells_in_view
from rough_map.map.near_far.looks import DEFAULT_MIN_STD, Looks, LooksClassifier
from rough_map.map.near_far.prediction import FarPrediction
from rough_map.map.near_far.tiles import (
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
    :class:`~rough_map.map.near_far.looks.LooksClassifier` it builds (``appearance_``, the
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
        :data:`~rough_map.map.near_far.tiles.FEATURE_NAMES`), see
        :data:`~rough_map.map.near_far.looks.DEFAULT_MIN_STD`.
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
        Cells whose largest class probability is below this are left out of the
        predictions: unknown (NaN in a map) rather than a near-uniform row, which a map's
        evidence fusion would count as seen. 0 keeps every cell in view.

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
        min_confidence: float = 0.5,
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
        self._recall_checked = 0

    def _check_numbers(self, near: NearField) -> None:
        def integer(value: Any, low: int) -> bool:
            return (
                isinstance(value, int | np.integer)
                and not isinstance(value, bool)
                and bool(value >= low)
            )

        def positive(value: Any) -> bool:
            number = isinstance(value, int | float | np.number) and not isinstance(value, bool)
            return number and bool(value > 0)

        if not integer(self.tile_px, 4):
            raise InputError(f"tile_px must be an integer >= 4 px, got {self.tile_px!r}")
        if not (positive(self.max_range) and self.max_range > near.ahead[1]):
            raise InputError(
                f"max_range ({self.max_range!r} m) must exceed the end of the near field "
                f"({near.ahead[1]:g} m)"
            )
        if not positive(self.ground_step):
            raise InputError(f"ground_step must be positive (m), got {self.ground_step!r}")
        if not integer(self.min_near_tiles, 1):
            raise InputError(f"min_near_tiles must be an integer >= 1, got {self.min_near_tiles!r}")
        if not integer(self.memory_cells, 0):
            raise InputError(f"memory_cells must be an integer >= 0, got {self.memory_cells!r}")
        if not isinstance(self.recall, bool | np.bool_):
            raise InputError(f"recall must be true or false, got {self.recall!r}")
        if not (isinstance(self.min_confidence, Real) and 0.0 <= self.min_confidence <= 1.0):
            raise InputError(f"min_confidence must be in [0, 1], got {self.min_confidence!r}")

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
        classes = self.classes_
        k = len(classes)
        if isinstance(near_label, str):
            if near_label not in classes:
                raise InputError(f"unknown class label {near_label!r}; expected one of {classes}")
            return np.eye(k)[classes.index(near_label)]
        arr = np.asarray(near_label)
        if arr.ndim == 0:
            if not np.issubdtype(arr.dtype, np.integer) or not 0 <= int(arr) < k:
                raise InputError(
                    f"unknown class label {near_label!r}; expected a class name or an index "
                    f"0..{k - 1}"
                )
            return np.eye(k)[int(arr)]
        try:
            p = arr.astype(float)
        except (TypeError, ValueError):
            p = np.full(0, np.nan)
        if p.shape != (k,) or not np.all(np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
            raise InputError(
                f"near probabilities must be {k} non-negative finite numbers (one per class "
                f"{classes}), got {arr!r}"
            )
        return p / p.sum()

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
    ) -> NearToFar:
        """:meth:`update` from the image's :func:`~rough_map.map.near_far.tiles.tile_features`
        (of ``tile_px`` px), e.g. computed once for :meth:`predict_tiles` and this."""
        self._start()
        target = self._target(near_label)
        near = self.near_tiles(calib)
        if near.sum() < self.min_near_tiles:
            raise InputError(
                f"only {int(near.sum())} tiles of {self.tile_px} px see the near field "
                f"{self.near_field_.ahead} m ahead; check the calibration or use smaller tiles"
            )
        first = not hasattr(self.appearance_, "looks_")
        self.appearance_.learn(tiles[near], target, classes=self.classes_ if first else None)
        return self

    # ------------------------------------------------------------------------ prediction

    def predict_proba_features(self, features: ArrayLike) -> NDArray[np.float64]:
        """Class probabilities of tile feature rows
        (:meth:`~rough_map.map.near_far.looks.LooksClassifier.predict_proba`).

        Parameters
        ----------
        features : array_like, shape (N, 6)
            Tile features (:func:`~rough_map.map.near_far.tiles.tile_features`).

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
        :func:`~rough_map.map.near_far.tiles.tile_features` (of ``tile_px`` px)."""
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
        proba, familiar = self._proba(cells.features)
        recalled = np.zeros(len(cells.x), dtype=bool)
        if self.recall:
            old = self._recall(cells, familiar, transform)
            if len(old.x):
                old_proba, _ = self._proba(old.features)
                cells = GroundCells.concat(cells, old)
                proba = np.concatenate([proba, old_proba])
                recalled = np.concatenate([recalled, np.ones(len(old.x), dtype=bool)])
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
        ).select(proba.max(axis=1, initial=0.0) >= self.min_confidence)

    def _proba(
        self, features: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Probabilities (N, K) and whether each row is familiar (N,)."""
        if not len(features):
            return np.zeros((0, len(self.classes_))), np.zeros(0, dtype=bool)
        appearance = self.appearance_
        proba = appearance.predict_proba(features)
        if appearance.novelty_alpha == 0:
            return proba, np.ones(len(features), dtype=bool)
        return proba, appearance.familiarity(features) >= appearance.novelty_alpha

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
        _, now_familiar = self._proba(rows[:, 5:])
        out = [key for key, ok in zip(candidates, now_familiar, strict=True) if ok]
        for key in out:
            del memory[key]
        log.debug("near-to-far recall: %d cells became familiar", len(out))
        return GroundCells.from_rows(np.array(out, dtype=np.int64), rows[now_familiar])
