"""Near-to-far: learn the look of the terrain near the rover, classify it far away.

Geometry (stereo or range clouds, :mod:`rough_map.psd`, :mod:`rough_map.classify`) is only
trustworthy in the patch of interest, about 1 m ahead. Appearance reaches further: every
frame, the image tiles that see the patch are labelled with the geometric class of the patch
and teach an online appearance model; the model then classifies the tiles that see the ground
beyond, and their class probabilities are handed to the map as ground-cell predictions
(the conclusion of the paper names this "near-to-far" extension as future work).

Steps, per frame
----------------
1. *Tiles*: the left image is cut into square tiles of ``tile_px`` px. The ray through each
   tile centre is intersected with the vehicle's ground plane ``z = 0`` (flat-ground
   assumption, :func:`pixel_to_ground`); tiles that see no ground within reach are dropped.
2. *Features* (:func:`tile_features`): per tile the mean CIE L*a*b* colour and the log of the
   standard deviation of each L*a*b* channel (six numbers). L*a*b* separates brightness
   from chroma, so a grey surface and a brown one differ in a*, b* whatever the exposure of
   their texture, and a tile's mean colour hardly depends on how far away it is. Texture
   descriptors at a fixed pixel scale (LBP, gradient energy) were left out: the same ground
   seen 3 m away shows its texture at half the pixel scale with its fine detail blurred, so
   they drift with distance and, learnt at 1 m only, mislead the far field
   (``benchmarks/bench_near_far.py`` measures both). The log-stds drift too (fine texture
   fades), so they only get a weak say (``min_std``).
3. *Update* (:meth:`NearToFar.update`): the tiles whose ground point lies in the patch are
   one batch. Outliers within it (more than ``outlier_k`` robust standard deviations from
   the batch median in some feature: a manhole rim) are dropped, and a patch across a class
   boundary keeps only its main look (:func:`_main_look`: a two-component Gaussian mixture
   chosen by BIC). The batch then joins the nearest familiar *look* of its class, or starts
   a new one (:class:`Looks`: running means and variances, Chan's parallel update). A look
   is used only once ``min_support`` frames fed it: a wrong geometric label starts a look
   of its own that stays unused, or light, instead of corrupting the class's main look. A
   probability vector as the near label feeds every class with its weight.
4. *Prediction* (:meth:`NearToFar.predict`): ``p(class | tile)`` is proportional to the sum
   over the class's looks in use of ``n_look * N(features; look)``, ``n_look`` the tiles the
   look learnt: a mixture over all looks, so a look taught by a few wrong labels weighs
   little against the same look learnt by its own class (and the class priors follow how
   much of each class the rover drove over). Then an *unfamiliarity* gate: a tile far from
   every look in use (its smallest squared Mahalanobis distance has a chi-square tail
   probability below ``novelty_alpha``) has its probabilities pulled towards uniform.
   Terrain of a class the rover has not driven over yet thus comes out as "unknown", not as
   the nearest known class; with ``recall`` its look is remembered and it is predicted once
   the class is learnt (new terrain is always seen far ahead first).
5. *Ground cells*: predictions are returned on the world lattice of cell centres
   ``((i + 0.5) * ground_step, (j + 0.5) * ground_step)`` (the lattice of
   :class:`rough_map.map.grid.GridMap` maps of that resolution), for cells in view within
   ``max_range`` of the vehicle and outside the patch: a cell averages the tiles whose
   centres fall in it, or takes the tile its centre projects into when none does (far away
   one tile covers several cells).

Frames and units
----------------
Vehicle frame x forward, y left, z up; camera frame OpenCV (x right, y down, z forward); world
frame as the poses, ``p_world = Rz(yaw) Ry(pitch) Rx(roll) p_vehicle + t``; all in m and rad.
Pixel ``(u, v)`` = (column, row), integer coordinates at pixel centres.

Limits
------
Only classes the rover has driven over can be predicted, and a far cell of another class is
"unknown" (uniform) at best. Flat ground: a tile's ground point is where its ray meets the
vehicle's ``z = 0`` plane, so slopes and steps displace far predictions (by
``dz / tan(elevation angle)``, about 3 cm per cm of height at 3 m). Classes that look alike
in colour (different roughness of the same material) cannot be told apart by this model;
the near field is then the only source of their class.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.config import StereoCalibration
from rough_map.errors import FileFormatError, InputError, NotFittedError
from rough_map.geometry import ground_to_pixel, pixel_to_ground, pose_matrix

if TYPE_CHECKING:
    from rough_map.config import Pose
    from rough_map.io.traverse import Traverse
    from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = [
    "FEATURE_NAMES",
    "AccuracyTable",
    "Coverage",
    "FarPrediction",
    "Looks",
    "NearToFar",
    "area_coverage",
    "far_field_accuracy",
    "run_traverse",
    "tile_features",
]

#: Names of the per-tile features of :func:`tile_features`, in column order.
FEATURE_NAMES: tuple[str, ...] = (
    "L_mean",
    "a_mean",
    "b_mean",
    "log_L_std",
    "log_a_std",
    "log_b_std",
)
#: Added to the standard deviations before the log (L* and a*, b* units): keeps the log of a
#: flat tile finite without mattering for textured ground (L* std 2-10 on rendered terrain).
_STD_FLOOR = 0.05
#: Default lowest standard deviation of a class per feature (units of
#: :data:`FEATURE_NAMES`). Measured on rendered terrain, a class's far-field tile means stay
#: within about 0.5 L*, 0.05 a* and 0.1 b* of its near-field means, and its log-stds drift
#: by up to 0.4 (L*, fine texture fading with distance) and 0.08 (a*, b*).
DEFAULT_MIN_STD: tuple[float, ...] = (1.0, 0.1, 0.2, 0.25, 0.15, 0.15)
#: Accuracy-table bin edges (m of distance from the vehicle).
DEFAULT_BINS = (1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0)


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _TileGeometry:
    """Tile layout of one calibration: centres (px) and their ground points (vehicle, m)."""

    n_rows: int
    n_cols: int
    ground: NDArray[np.float64]  # (n_rows * n_cols, 3), NaN where the ray misses the ground
    distance: NDArray[np.float64]  # horizontal distance of the ground point from the vehicle


def _tile_geometry(calib: StereoCalibration, tile_px: int) -> _TileGeometry:
    n_rows, n_cols = calib.height // tile_px, calib.width // tile_px
    centre = 0.5 * (tile_px - 1)
    u = tile_px * np.arange(n_cols) + centre
    v = tile_px * np.arange(n_rows) + centre
    ground = pixel_to_ground(calib, u[None, :], v[:, None]).reshape(-1, 3)
    return _TileGeometry(n_rows, n_cols, ground, np.hypot(ground[:, 0], ground[:, 1]))


# --------------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------------


def _check_image(image: ArrayLike, calib: StereoCalibration) -> NDArray[np.uint8]:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InputError(f"image must be 8-bit (uint8) BGR, got dtype {image.dtype}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(
            f"image must be a colour (height, width, 3) BGR array, got shape {image.shape}"
        )
    if image.shape[:2] != (calib.height, calib.width):
        raise InputError(
            f"image is {image.shape[1]}x{image.shape[0]} px but the calibration is for "
            f"{calib.width}x{calib.height} px"
        )
    return image


def tile_features(image_bgr: ArrayLike, tile_px: int = 32) -> NDArray[np.float64]:
    """Colour features of the square tiles of an image.

    Parameters
    ----------
    image_bgr : array_like of uint8, shape (H, W, 3)
        8-bit BGR image (OpenCV order).
    tile_px : int
        Side of a tile, px. Tiles are laid from the top-left corner; the last
        ``W % tile_px`` columns and ``H % tile_px`` rows are not used.

    Returns
    -------
    ndarray, shape (H // tile_px * W // tile_px, 6)
        One row per tile, row-major over the tile grid; columns :data:`FEATURE_NAMES`: mean
        L* (0-100), a*, b* (about -128..127) of CIE L*a*b* (OpenCV's conversion of BGR
        scaled to [0, 1]) and ``log(std + 0.05)`` of each of the three channels (log of
        L*a*b* units).

    Raises
    ------
    InputError
        Not an 8-bit BGR image, or smaller than one tile.
    """
    import cv2

    image = np.asarray(image_bgr)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise InputError(
            f"image must be 8-bit BGR, shape (height, width, 3); got {image.dtype} {image.shape}"
        )
    if tile_px < 2:
        raise InputError(f"tile_px must be at least 2 px, got {tile_px}")
    n_rows, n_cols = image.shape[0] // tile_px, image.shape[1] // tile_px
    if n_rows == 0 or n_cols == 0:
        raise InputError(f"image {image.shape[1]}x{image.shape[0]} px is smaller than one tile")
    crop = image[: n_rows * tile_px, : n_cols * tile_px]
    lab = cv2.cvtColor(crop.astype(np.float32) * np.float32(1.0 / 255.0), cv2.COLOR_BGR2Lab)
    # Block means by area resampling (exact for whole tiles); centred first so that the
    # float32 second moments keep their precision.
    centre = np.array(cv2.mean(lab)[:3])
    lab = cv2.subtract(lab, (*centre, 0.0))
    size = (n_cols, n_rows)
    mean = cv2.resize(lab, size, interpolation=cv2.INTER_AREA).astype(np.float64)
    square = cv2.resize(lab * lab, size, interpolation=cv2.INTER_AREA).astype(np.float64)
    var = np.maximum(square - mean * mean, 0.0)
    out = np.concatenate([mean + centre, np.log(np.sqrt(var) + _STD_FLOOR)], axis=-1)
    return out.reshape(n_rows * n_cols, 6)


# --------------------------------------------------------------------------------------------
# Predictions
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FarPrediction:
    """Class probabilities of ground cells seen in one image, beyond the near field.

    Attributes
    ----------
    x, y : ndarray, shape (N,)
        World coordinates of the cell centres, m.
    ahead, lateral : ndarray, shape (N,)
        The same points in the vehicle frame (x forward, y left), m.
    distance : ndarray, shape (N,)
        Horizontal distance from the vehicle origin, m.
    proba : ndarray, shape (N, K)
        Class probabilities (rows sum to 1), columns in the order of ``classes``.
    classes : tuple of str
        Class names.
    t : float or None
        Time of the frame, s.
    frame : int or None
        Index of the frame in its traverse.
    recalled : ndarray of bool, shape (N,)
        Cells predicted from their look in an earlier image (:class:`NearToFar` ``recall``);
        their ``ahead``, ``lateral`` and ``distance`` are those of that sighting. All false
        by default.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    ahead: NDArray[np.float64]
    lateral: NDArray[np.float64]
    distance: NDArray[np.float64]
    proba: NDArray[np.float64]
    classes: tuple[str, ...]
    t: float | None = None
    frame: int | None = None
    recalled: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        n = np.shape(self.x)
        for name in ("y", "ahead", "lateral", "distance"):
            if np.shape(getattr(self, name)) != n:
                raise InputError(f"FarPrediction.{name} must have shape {n} like x")
        if np.shape(self.proba) != (*n, len(self.classes)):
            raise InputError(
                f"FarPrediction.proba must have shape {(*n, len(self.classes))} (cells, classes)"
            )
        if self.recalled is None:
            object.__setattr__(self, "recalled", np.zeros(n, dtype=bool))
        elif np.shape(self.recalled) != n:
            raise InputError(f"FarPrediction.recalled must have shape {n} like x")

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def label_index(self) -> NDArray[np.intp]:
        """Most probable class index per cell, shape (N,)."""
        return np.argmax(self.proba, axis=1) if len(self) else np.zeros(0, dtype=np.intp)

    @property
    def label(self) -> NDArray[np.str_]:
        """Most probable class name per cell, shape (N,)."""
        return np.asarray(self.classes)[self.label_index]

    @property
    def confidence(self) -> NDArray[np.float64]:
        """Probability of the most probable class per cell, shape (N,)."""
        return self.proba.max(axis=1) if len(self) else np.zeros(0)

    def select(self, mask: ArrayLike) -> FarPrediction:
        """The cells where the boolean ``mask`` (shape (N,)) is true."""
        m = np.asarray(mask, dtype=bool)
        if m.shape != self.x.shape:
            raise InputError(f"mask must have shape {self.x.shape}, got {m.shape}")
        return FarPrediction(
            self.x[m],
            self.y[m],
            self.ahead[m],
            self.lateral[m],
            self.distance[m],
            self.proba[m],
            self.classes,
            self.t,
            self.frame,
            self.recalled[m],  # type: ignore[index]
        )


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


class NearToFar:
    """Online appearance model: learn near-field tiles, classify far-field ground cells.

    Parameters
    ----------
    classes : sequence of str
        Terrain class names, in the order of the probability vectors in and out.
    tile_px : int
        Side of the square image tiles, px.
    max_range : float
        Largest horizontal distance from the vehicle of a predicted cell, m.
    near : (float, float)
        The near field, i.e. the patch that geometry classifies: ``near[0] <= x <= near[1]``
        ahead of the vehicle, m.
    near_half_width : float, optional
        Half width of the near field across the vehicle (``|y| <=``), m; by default half of
        ``near[1] - near[0]`` (a square patch).
    ground_step : float
        Spacing of the ground cells the predictions are given on, m.
    novelty_alpha : float
        A tile whose squared Mahalanobis distance to the nearest look in use has a
        chi-square tail probability ``q`` below this is unfamiliar: its probabilities are
        mixed with the uniform distribution, with weight ``1 - q / novelty_alpha``. 0
        disables the gate. A near-field batch joins a look of its class if its mean passes
        the same test, and starts a new look otherwise.
    outlier_k : float
        Near-field tiles further than this many robust standard deviations (1.4826 MAD) from
        the batch median in some feature are not learnt; ``inf`` learns them all.
    min_near_tiles : int
        Fewest near-field tiles an update needs; fewer (the patch out of view) raises.
    min_std : sequence of 6 float
        Lowest standard deviation of each feature within a class (units of
        :data:`FEATURE_NAMES`), see :data:`DEFAULT_MIN_STD`.
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
    looks_ : Looks
        The learnt looks (after the first :meth:`update`).
    n_updates_ : int
        Number of updates made.
    """

    def __init__(
        self,
        classes: Sequence[str],
        tile_px: int = 32,
        max_range: float = 8.0,
        near: tuple[float, float] = (0.55, 1.45),
        *,
        near_half_width: float | None = None,
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
        self.classes = tuple(str(c) for c in classes)
        self.tile_px = int(tile_px)
        self.max_range = float(max_range)
        self.near = (float(near[0]), float(near[1]))
        self.near_half_width = (
            0.5 * (self.near[1] - self.near[0]) if near_half_width is None else near_half_width
        )
        self.ground_step = float(ground_step)
        self.novelty_alpha = float(novelty_alpha)
        self.outlier_k = float(outlier_k)
        self.min_near_tiles = int(min_near_tiles)
        self.min_std = tuple(float(v) for v in min_std)
        self.recall = bool(recall)
        self.memory_cells = int(memory_cells)
        self.min_support = float(min_support)
        self.max_looks = int(max_looks)
        self.min_confidence = float(min_confidence)
        self._check_params()
        self._min_var = np.square(np.asarray(self.min_std))[None, :]
        self._geometry_key: tuple[str, int] | None = None
        self._geometry: _TileGeometry | None = None

    def _check_params(self) -> None:
        if len(self.classes) < 2:
            raise InputError(f"classes must name at least two classes, got {self.classes}")
        if len(set(self.classes)) != len(self.classes):
            raise InputError(f"classes must be distinct, got {self.classes}")
        if self.tile_px < 4:
            raise InputError(f"tile_px must be at least 4 px, got {self.tile_px}")
        if not 0.0 <= self.near[0] < self.near[1]:
            raise InputError(f"near must be (start, end) m with 0 <= start < end, got {self.near}")
        if not self.near_half_width > 0:
            raise InputError(f"near_half_width must be positive (m), got {self.near_half_width}")
        if not self.max_range > self.near[1]:
            raise InputError(
                f"max_range ({self.max_range} m) must exceed the end of the near field "
                f"({self.near[1]} m)"
            )
        if not self.ground_step > 0:
            raise InputError(f"ground_step must be positive (m), got {self.ground_step}")
        if len(self.min_std) != len(FEATURE_NAMES) or not all(v > 0 for v in self.min_std):
            raise InputError(
                f"min_std must be {len(FEATURE_NAMES)} positive numbers (units of "
                f"{FEATURE_NAMES}), got {self.min_std}"
            )
        if not 0.0 <= self.novelty_alpha < 1.0:
            raise InputError(f"novelty_alpha must be in [0, 1), got {self.novelty_alpha}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise InputError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.max_looks < 1:
            raise InputError(f"max_looks must be at least 1, got {self.max_looks}")

    # ------------------------------------------------------------------------------ helpers

    def _tiles(self, calib: StereoCalibration) -> _TileGeometry:
        key = (calib.model_dump_json(), self.tile_px)
        if self._geometry is None or self._geometry_key != key:
            self._geometry = _tile_geometry(calib, self.tile_px)
            self._geometry_key = key
        return self._geometry

    def _in_near(self, ahead: NDArray[np.float64], lateral: NDArray[np.float64]) -> NDArray:
        with np.errstate(invalid="ignore"):
            return (
                (ahead >= self.near[0])
                & (ahead <= self.near[1])
                & (np.abs(lateral) <= self.near_half_width)
            )

    def _target(self, near_label: str | int | ArrayLike) -> NDArray[np.float64]:
        """Class weights (K,) of a near label: name, index or probability vector."""
        k = len(self.classes)
        if isinstance(near_label, str):
            if near_label not in self.classes:
                raise InputError(
                    f"unknown class label {near_label!r}; expected one of {self.classes}"
                )
            return np.eye(k)[self.classes.index(near_label)]
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
                f"{self.classes}), got {arr!r}"
            )
        return p / p.sum()

    # ------------------------------------------------------------------------------ learning

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
            Vehicle pose in the world (see :func:`pose_matrix`). The near field is defined in
            the vehicle frame, so the pose is only checked; it is taken for symmetry with
            :meth:`predict`.
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
            Wrong image size or type, an unknown class label, or a near field not in view.
        """
        image = _check_image(image_bgr, calib)
        pose_matrix(pose)
        target = self._target(near_label)
        return self._update_features(tile_features(image, self.tile_px), calib, target)

    def _update_features(
        self, tiles: NDArray[np.float64], calib: StereoCalibration, target: NDArray[np.float64]
    ) -> NearToFar:
        """:meth:`update` from the image's :func:`tile_features`."""
        geometry = self._tiles(calib)
        near = self._in_near(geometry.ground[:, 0], geometry.ground[:, 1])
        if near.sum() < self.min_near_tiles:
            raise InputError(
                f"only {int(near.sum())} tiles of {self.tile_px} px see the near field "
                f"{self.near} m ahead; check the calibration or use smaller tiles"
            )
        features = tiles[near]
        features = _main_look(features[_inliers(features, self.outlier_k)], self._min_var)
        if not len(features):
            log.debug("near-to-far update skipped: no near-field tile left to learn")
            return self
        if not hasattr(self, "looks_"):
            self.looks_ = Looks.empty(len(FEATURE_NAMES))
            self.n_updates_ = 0
            self._memory: dict[tuple[int, int], tuple[float, NDArray[np.float64]]] = {}
            self._recall_checked = 0
        for c in np.flatnonzero(target > 1e-3):
            self._learn(int(c), features, float(target[c]))
        self.n_updates_ += 1
        log.debug(
            "near-to-far update %d: %d near tiles of %d learnt as %s; %d looks",
            self.n_updates_,
            len(features),
            int(near.sum()),
            {self.classes[c]: round(float(target[c]), 3) for c in np.flatnonzero(target)},
            len(self.looks_.cls),
        )
        return self

    def _learn(self, c: int, x: NDArray[np.float64], weight: float) -> None:
        """Merge a batch of tiles (weight per tile) into the nearest familiar look of class
        ``c``, or start a new look."""
        from scipy.stats import chi2

        looks = self.looks_
        n = weight * len(x)
        mean = x.mean(axis=0)
        m2 = weight * ((x - mean) ** 2).sum(axis=0)
        mine = np.flatnonzero(looks.cls == c)
        if len(mine):
            var = np.maximum(looks.var[mine], self._min_var)
            d2 = (((mean - looks.mean[mine]) ** 2) / var).sum(axis=1)
            best = int(np.argmin(d2))
            if chi2.sf(d2[best], df=x.shape[1]) >= max(self.novelty_alpha, 1e-12):
                looks.merge(int(mine[best]), n, mean, m2, weight)
                return
        looks.add(c, n, mean, m2, weight)
        if len(mine) + 1 > self.max_looks:
            weakest = mine[np.argmin(looks.support[mine])]
            looks.drop(int(weakest))

    # ------------------------------------------------------------------------------ prediction

    @property
    def seen_(self) -> NDArray[np.bool_]:
        """Classes with at least one look in use (``min_support`` reached), shape (K,)."""
        seen = np.zeros(len(self.classes), dtype=bool)
        if hasattr(self, "looks_"):
            seen[self.looks_.cls[self.looks_.support >= self.min_support]] = True
        return seen

    def _distances(
        self, x: NDArray[np.float64]
    ) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:
        """Looks in use, squared Mahalanobis distances (N, L) and variances (L, F).

        Each look's variances are floored at ``min_std ** 2``: a few frames of near field
        underestimate how much a class varies elsewhere (shading with the viewing angle,
        fine texture fading with distance), and Gaussians of very different spreads
        extrapolate wildly between them.
        """
        looks = self.looks_
        used = np.flatnonzero(looks.support >= self.min_support)
        var = np.maximum(looks.var[used], self._min_var)
        d2 = (((x[:, None, :] - looks.mean[used][None]) ** 2) / var[None]).sum(axis=-1)
        return used, d2, var

    def _nearest_class(
        self, x: NDArray[np.float64]
    ) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
        """Class of the nearest look in use of feature rows, and the chi-square tail
        probability of the distance to it (-1 and 0 when no look is in use)."""
        from scipy.stats import chi2

        used, d2, _ = self._distances(x)
        if not len(used):
            return np.full(len(x), -1, dtype=np.intp), np.zeros(len(x))
        best = np.argmin(d2, axis=1)
        tail = chi2.sf(d2[np.arange(len(x)), best], df=x.shape[1])
        return self.looks_.cls[used][best], tail

    def predict_proba_features(self, features: ArrayLike) -> NDArray[np.float64]:
        """Class probabilities of feature rows (:func:`tile_features`).

        The looks in use form one Gaussian mixture weighted by the tiles each learnt
        (variances floored at ``min_std ** 2``); a class's probability is the share of its
        looks in the mixture's density, zero for classes without a look in use. Unfamiliar
        rows are pulled towards uniform over all classes (see ``novelty_alpha``). Uniform
        before any look is in use.

        Parameters
        ----------
        features : array_like, shape (N, 6)
            Tile features.

        Returns
        -------
        ndarray, shape (N, K)
            Probabilities, rows summing to 1.

        Raises
        ------
        NotFittedError
            Before the first :meth:`update`.
        """
        from scipy.special import logsumexp
        from scipy.stats import chi2

        if not hasattr(self, "looks_"):
            raise NotFittedError("NearToFar has learnt nothing yet: call update() first")
        x = np.asarray(features, dtype=float)
        if x.ndim != 2 or x.shape[1] != len(FEATURE_NAMES):
            raise InputError(f"features must have shape (N, {len(FEATURE_NAMES)}), got {x.shape}")
        k = len(self.classes)
        used, d2, var = self._distances(x)
        if not len(used):
            return np.full((len(x), k), 1.0 / k)
        cls = self.looks_.cls[used]
        n = self.looks_.n[used]
        loglik = (
            np.log(n / n.sum())[None]
            - 0.5 * d2
            - 0.5 * np.log(2.0 * np.pi * var).sum(axis=-1)[None]
        )
        classes = np.unique(cls)
        per_class = np.stack(
            [logsumexp(loglik[:, cls == c], axis=1) for c in classes], axis=1
        )  # (N, C)
        post = np.zeros((len(x), k))
        post[:, classes] = np.exp(per_class - logsumexp(per_class, axis=1, keepdims=True))
        if self.novelty_alpha > 0:
            tail = chi2.sf(d2.min(axis=1), df=x.shape[1])
            known = np.clip(tail / self.novelty_alpha, 0.0, 1.0)[:, None]
            post = known * post + (1.0 - known) / len(self.classes)
        return post

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
            Vehicle pose in the world (see :func:`pose_matrix`).
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
        image = _check_image(image_bgr, calib)
        transform = pose_matrix(pose)
        if not hasattr(self, "looks_"):
            raise NotFittedError("NearToFar has learnt nothing yet: call update() first")
        return self._predict_features(
            tile_features(image, self.tile_px), calib, transform, t=t, frame=frame
        )

    def _predict_features(
        self,
        tiles: NDArray[np.float64],
        calib: StereoCalibration,
        transform: NDArray[np.float64],
        *,
        t: float | None,
        frame: int | None,
    ) -> FarPrediction:
        """:meth:`predict` from the image's :func:`tile_features` and the 4x4 pose."""
        geometry = self._tiles(calib)
        # Tiles whose centre is a little beyond max_range still cover cells within it.
        with np.errstate(invalid="ignore"):
            usable = np.isfinite(geometry.distance) & (geometry.distance <= self.max_range + 1.0)
        features = np.where(usable[:, None], tiles, np.nan)
        keys, ahead, lateral, wx, wy, cell_features = self._cells(
            calib, geometry, transform, usable, features
        )
        proba, familiar = self._proba(cell_features)
        cells = _Cells(keys, wx, wy, ahead, lateral, np.hypot(ahead, lateral), cell_features)
        recalled = np.zeros(len(wx), dtype=bool)
        if self.recall:
            old = self._recall(cells, familiar, transform)
            if len(old.x):
                old_proba, _ = self._proba(old.features)
                cells = _Cells.concat(cells, old)
                proba = np.concatenate([proba, old_proba])
                recalled = np.concatenate([recalled, np.ones(len(old.x), dtype=bool)])
        return FarPrediction(
            x=cells.x,
            y=cells.y,
            ahead=cells.ahead,
            lateral=cells.lateral,
            distance=cells.distance,
            proba=proba,
            classes=self.classes,
            t=t,
            frame=frame,
            recalled=recalled,
        ).select(proba.max(axis=1, initial=0.0) >= self.min_confidence)

    def _proba(
        self, features: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Probabilities (N, K) and whether each row is familiar (N,)."""
        if not len(features):
            return np.zeros((0, len(self.classes))), np.zeros(0, dtype=bool)
        proba = self.predict_proba_features(features)
        if self.novelty_alpha == 0:
            return proba, np.ones(len(features), dtype=bool)
        _, tail = self._nearest_class(features)
        return proba, tail >= self.novelty_alpha

    def _recall(
        self, cells: _Cells, familiar: NDArray[np.bool_], transform: NDArray[np.float64]
    ) -> _Cells:
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
        if self._recall_checked == self.n_updates_ or not memory:
            return _Cells.empty(len(FEATURE_NAMES))
        self._recall_checked = self.n_updates_
        in_view = set(map(tuple, cells.keys.tolist()))
        candidates = [key for key in memory if key not in in_view]
        if not candidates:
            return _Cells.empty(len(FEATURE_NAMES))
        rows = np.array([memory[key][1] for key in candidates])
        _, now_familiar = self._proba(rows[:, 5:])
        out = [key for key, ok in zip(candidates, now_familiar, strict=True) if ok]
        for key in out:
            del memory[key]
        rows = rows[now_familiar]
        log.debug("near-to-far recall: %d cells became familiar", len(out))
        return _Cells(
            np.array(out, dtype=np.int64).reshape(-1, 2),
            rows[:, 0],
            rows[:, 1],
            rows[:, 2],
            rows[:, 3],
            rows[:, 4],
            rows[:, 5:],
        )

    def _cells(
        self,
        calib: StereoCalibration,
        geometry: _TileGeometry,
        transform: NDArray[np.float64],
        usable: NDArray[np.bool_],
        features: NDArray[np.float64],
    ) -> tuple[NDArray[Any], ...]:
        """Ground cells in view and their features (see the module notes, step 5).

        Returns the cell keys (N, 2) (lattice indices along world x and y), vehicle-frame
        ahead and lateral (m), world x and y (m), and features (N, F).
        """
        step = self.ground_step
        rot, trans = transform[:3, :3], transform[:3, 3]
        # World bounding box of the vehicle-frame area in reach, on the cell lattice.
        reach = self.max_range
        corners = np.array([[x, y, 0.0] for x in (0.0, reach) for y in (-reach, reach)])
        world = corners @ rot.T + trans
        i0 = math.floor(world[:, 0].min() / step)
        i1 = math.ceil(world[:, 0].max() / step)
        j0 = math.floor(world[:, 1].min() / step)
        j1 = math.ceil(world[:, 1].max() / step)
        gi, gj = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1))
        keys = np.column_stack([gi.ravel(), gj.ravel()])
        wx, wy = (keys[:, 0] + 0.5) * step, (keys[:, 1] + 0.5) * step
        # The point of the vehicle's z = 0 plane above/below each world (x, y).
        try:
            inv = np.linalg.inv(rot[:2, :2])
        except np.linalg.LinAlgError:
            raise InputError("the pose tilts the vehicle's ground plane vertical") from None
        vxy = np.column_stack([wx - trans[0], wy - trans[1]]) @ inv.T
        ahead, lateral = vxy[:, 0], vxy[:, 1]
        keep = (
            (ahead > 0)
            & (np.hypot(ahead, lateral) <= self.max_range)
            & ~self._in_near(ahead, lateral)
        )
        u, v = ground_to_pixel(
            calib, np.column_stack([ahead[keep], lateral[keep], np.zeros(int(keep.sum()))])
        )
        t_px = self.tile_px
        with np.errstate(invalid="ignore"):
            col = np.floor((u + 0.5) / t_px)
            row = np.floor((v + 0.5) / t_px)
            inside = (col >= 0) & (col < geometry.n_cols) & (row >= 0) & (row < geometry.n_rows)
        tile = np.full(u.shape, -1, dtype=np.int64)
        tile[inside] = row[inside].astype(np.int64) * geometry.n_cols + col[inside].astype(np.int64)
        inside[inside] = usable[tile[inside]]
        keep[keep] = inside
        keys, ahead, lateral, wx, wy = (a[keep] for a in (keys, ahead, lateral, wx, wy))
        cell_features = features[tile[inside]]
        # Cells holding tile centres take the mean of those tiles instead (near the rover a
        # cell spans many tiles).
        centres = geometry.ground[usable] @ rot.T + trans
        centre_keys = np.floor(centres[:, :2] / step).astype(np.int64)
        if len(keys):
            _, inverse = np.unique(np.concatenate([keys, centre_keys]), axis=0, return_inverse=True)
            inverse = inverse.ravel()
            n_cells = len(keys)
            sums = np.zeros((int(inverse.max()) + 1, features.shape[1]))
            counts = np.zeros(len(sums))
            np.add.at(sums, inverse[n_cells:], features[usable])
            np.add.at(counts, inverse[n_cells:], 1.0)
            hits = counts[inverse[:n_cells]]
            filled = hits > 0
            cell_features[filled] = sums[inverse[:n_cells]][filled] / hits[filled, None]
        return keys, ahead, lateral, wx, wy, cell_features


@dataclass(frozen=True)
class _Cells:
    """Ground cells of one prediction: lattice keys, positions (m) and features."""

    keys: NDArray[np.int64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    ahead: NDArray[np.float64]
    lateral: NDArray[np.float64]
    distance: NDArray[np.float64]
    features: NDArray[np.float64]

    def row(self, k: int) -> NDArray[np.float64]:
        """x, y, ahead, lateral, distance and the features of cell ``k`` as one array."""
        head = [self.x[k], self.y[k], self.ahead[k], self.lateral[k], self.distance[k]]
        return np.concatenate([head, self.features[k]])

    @classmethod
    def empty(cls, n_features: int) -> _Cells:
        z = np.zeros(0)
        return cls(np.zeros((0, 2), dtype=np.int64), z, z, z, z, z, np.zeros((0, n_features)))

    @classmethod
    def concat(cls, a: _Cells, b: _Cells) -> _Cells:
        return cls(
            *(np.concatenate([getattr(a, f), getattr(b, f)]) for f in cls.__dataclass_fields__)
        )


@dataclass
class Looks:
    """Appearance modes ("looks") of the classes: running Gaussians with diagonal covariance.

    Attributes
    ----------
    cls : ndarray of int, shape (L,)
        Class index of each look.
    n : ndarray, shape (L,)
        Tiles learnt (weighted by the label probability).
    mean : ndarray, shape (L, F)
        Mean features.
    m2 : ndarray, shape (L, F)
        Sums of squared deviations from the mean (``var = m2 / n``).
    support : ndarray, shape (L,)
        Updates that fed the look, weighted by the label probability.
    """

    cls: NDArray[np.intp]
    n: NDArray[np.float64]
    mean: NDArray[np.float64]
    m2: NDArray[np.float64]
    support: NDArray[np.float64]

    @classmethod
    def empty(cls, n_features: int) -> Looks:
        """No look yet."""
        return cls(
            np.zeros(0, dtype=np.intp),
            np.zeros(0),
            np.zeros((0, n_features)),
            np.zeros((0, n_features)),
            np.zeros(0),
        )

    @property
    def var(self) -> NDArray[np.float64]:
        """Variances, shape (L, F)."""
        return self.m2 / self.n[:, None]

    def add(
        self, c: int, n: float, mean: NDArray[np.float64], m2: NDArray[np.float64], w: float
    ) -> None:
        """Append a look of class ``c`` from a batch (``n`` tiles, ``mean``, ``m2``)."""
        self.cls = np.append(self.cls, c)
        self.n = np.append(self.n, n)
        self.mean = np.vstack([self.mean, mean])
        self.m2 = np.vstack([self.m2, m2])
        self.support = np.append(self.support, w)

    def merge(
        self, i: int, n: float, mean: NDArray[np.float64], m2: NDArray[np.float64], w: float
    ) -> None:
        """Merge a batch into look ``i`` (Chan et al.'s parallel update of mean and m2)."""
        total = self.n[i] + n
        delta = mean - self.mean[i]
        self.mean[i] = self.mean[i] + delta * (n / total)
        self.m2[i] = self.m2[i] + m2 + delta**2 * (self.n[i] * n / total)
        self.n[i] = total
        self.support[i] += w

    def drop(self, i: int) -> None:
        """Forget look ``i``."""
        keep = np.arange(len(self.cls)) != i
        self.cls, self.n, self.support = self.cls[keep], self.n[keep], self.support[keep]
        self.mean, self.m2 = self.mean[keep], self.m2[keep]


def _main_look(x: NDArray[np.float64], min_var: NDArray[np.float64]) -> NDArray[np.float64]:
    """The tiles of the main look of a near-field batch.

    A patch across a class boundary holds two looks, and its label is the class of (at
    most) one of them. A two-component Gaussian mixture (diagonal covariances) is fitted;
    if the Bayesian information criterion prefers it to one Gaussian and the two means are
    told apart (squared distance above the chi-square 0.999 quantile with the variances
    floored at ``min_var``), only the tiles of the larger component are kept.
    """
    from scipy.stats import chi2
    from sklearn.mixture import GaussianMixture

    if len(x) < 20:
        return x
    var1 = np.maximum(x.var(axis=0), 1e-12)
    # BIC of one diagonal Gaussian, in closed form: -2 log L + p log n with p = 2 F.
    bic1 = len(x) * np.sum(np.log(2.0 * np.pi * var1) + 1.0) + 2 * x.shape[1] * np.log(len(x))
    gmm = GaussianMixture(
        2, covariance_type="diag", init_params="k-means++", random_state=0, reg_covar=1e-6
    )
    gmm.fit(x)
    if gmm.bic(x) >= bic1:
        return x
    var = np.maximum(gmm.covariances_.max(axis=0), min_var[0])
    d2 = float((np.diff(gmm.means_, axis=0) ** 2 / var).sum())
    if d2 <= chi2.isf(1e-3, df=x.shape[1]):
        return x
    labels = gmm.predict(x)
    main = int(np.argmax(np.bincount(labels, minlength=2)))
    log.debug(
        "near-to-far: near field holds two looks; keeping %d of %d tiles",
        int((labels == main).sum()),
        len(x),
    )
    return x[labels == main]


def _inliers(features: NDArray[np.float64], k: float) -> NDArray[np.bool_]:
    """Rows within ``k`` robust standard deviations of the column medians in every column."""
    if not np.isfinite(k) or len(features) < 10:
        return np.ones(len(features), dtype=bool)
    median = np.median(features, axis=0)
    mad = 1.4826 * np.median(np.abs(features - median), axis=0)
    mad = np.maximum(mad, 1e-6)
    return np.all(np.abs(features - median) <= k * mad, axis=1)


# --------------------------------------------------------------------------------------------
# Traverses and evaluation
# --------------------------------------------------------------------------------------------


def _read_bgr(path: Any) -> NDArray[np.uint8]:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileFormatError(path, "missing or not an image OpenCV can decode")
    return image


def run_traverse(
    traverse: Traverse,
    near_labels: Sequence[str | int | None] | ArrayLike,
    *,
    every: int = 1,
    model: NearToFar | None = None,
    classes: Sequence[str] | None = None,
    progress: bool = False,
    **kwargs: Any,
) -> list[FarPrediction]:
    """Run near-to-far along a traverse, learning frame by frame.

    Each frame with a left image (every ``every``-th of them) is first *predicted* with the
    model learnt from the earlier frames only, then *learnt* with its near label. Frames before
    the first update give no prediction.

    Parameters
    ----------
    traverse : Traverse
        With a calibration and left images (colour).
    near_labels : sequence or ndarray
        One geometric near-field label per frame of the traverse (all frames, imaged or not):
        class names or indices (None or "" where unknown: the frame is not learnt), or an
        array (n_frames, K) of class probabilities (rows of NaN where unknown).
    every : int
        Use every ``every``-th imaged frame.
    model : NearToFar, optional
        A model to continue; by default a new one with ``classes`` and ``kwargs``.
    classes : sequence of str, optional
        Class names of a new model; by default the named surfaces of
        :data:`rough_map.terrain.SURFACES` (the simulator's classes).
    progress : bool
        Show a progress bar on stderr.
    **kwargs
        Passed to :class:`NearToFar`.

    Returns
    -------
    list of FarPrediction
        One per predicted frame, in time order, with ``frame`` and ``t`` set.

    Raises
    ------
    InputError
        No calibration, labels of the wrong length, an unknown label, ``every < 1``.
    """
    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    calib = traverse.spec.calibration
    if calib is None:
        raise InputError(f"{traverse.source} has no stereo calibration")
    if isinstance(near_labels, np.ndarray) and near_labels.ndim == 2:
        labels: list[Any] = [None if np.any(np.isnan(r)) else r for r in near_labels]
    else:
        labels = [None if isinstance(x, str) and not x else x for x in near_labels]
    if len(labels) != len(traverse):
        raise InputError(
            f"near_labels has {len(labels)} entries but the traverse has {len(traverse)} frames"
        )
    if model is None:
        if classes is None:
            from rough_map.terrain import SURFACES

            classes = tuple(SURFACES)
        model = NearToFar(classes, **kwargs)
    from tqdm import tqdm

    imaged = [i for i, f in enumerate(traverse.frames) if f.left is not None][::every]
    out: list[FarPrediction] = []
    start = time.perf_counter()
    for i in tqdm(imaged, desc="near-to-far", unit="frame", disable=not progress):
        frame = traverse.frames[i]
        path = traverse.resolve(frame.left)  # type: ignore[arg-type]
        image = _check_image(_read_bgr(path), calib)
        tiles = tile_features(image, model.tile_px)  # once for predict and update
        if hasattr(model, "looks_"):
            transform = pose_matrix(frame.pose)
            out.append(model._predict_features(tiles, calib, transform, t=frame.t, frame=i))
        if labels[i] is not None:
            model._update_features(tiles, calib, model._target(labels[i]))
    log.info(
        "near-to-far: %d frames, %d predictions in %.1f s",
        len(imaged),
        len(out),
        time.perf_counter() - start,
    )
    return out


def _world_class(world: HeightField, x: NDArray, y: NDArray) -> NDArray[np.int64]:
    """Class index of the world's nearest cell at (x, y) m; -1 outside or unclassified."""
    if world.classes is None:
        raise InputError("the world has no class map")
    ny, nx = world.classes.shape
    col = np.rint((np.asarray(x) - world.origin[0]) / world.spacing).astype(np.int64)
    row = np.rint((np.asarray(y) - world.origin[1]) / world.spacing).astype(np.int64)
    ok = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    out = np.full(col.shape, -1, dtype=np.int64)
    out[ok] = world.classes[row[ok], col[ok]]
    if ok.any():
        out[ok] = np.where(np.isfinite(world.heights[row[ok], col[ok]]), out[ok], -1)
    return out


def _class_map(classes: Sequence[str], world: HeightField) -> NDArray[np.int64]:
    """Index of each world class name in ``classes`` (-1 if absent), for remapping."""
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
    """

    edges: NDArray[np.float64]
    n: NDArray[np.int64]
    n_confident: NDArray[np.int64]
    accuracy: NDArray[np.float64]
    accuracy_all: NDArray[np.float64]
    threshold: float

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

        return {
            "threshold": float(self.threshold),
            "overall": number(self.overall()),
            "bins": [
                {
                    "from_m": float(self.edges[k]),
                    "to_m": float(self.edges[k + 1]),
                    "cells": int(self.n[k]),
                    "confident": int(self.n_confident[k]),
                    "accuracy": number(self.accuracy[k]),
                    "accuracy_all": number(self.accuracy_all[k]),
                }
                for k in range(len(self.n))
            ],
        }

    def to_text(self) -> str:
        """The table as aligned text (a Markdown table)."""
        lines = [
            f"| distance (m) | cells | confident (p >= {self.threshold:g}) | accuracy "
            "(confident) | accuracy (all) |",
            "|---|---:|---:|---:|---:|",
        ]
        for k in range(len(self.n)):
            lines.append(
                f"| {self.edges[k]:g}-{self.edges[k + 1]:g} | {self.n[k]} | "
                f"{self.n_confident[k]} | {self.accuracy[k]:.3f} | {self.accuracy_all[k]:.3f} |"
            )
        return "\n".join(lines)


def far_field_accuracy(
    predictions: Sequence[FarPrediction],
    world: HeightField,
    bins: Sequence[float] = DEFAULT_BINS,
    *,
    threshold: float = 0.0,
) -> AccuracyTable:
    """Compare far-field predictions with the world's class map, by distance.

    Parameters
    ----------
    predictions : sequence of FarPrediction
        E.g. from :func:`run_traverse`.
    world : HeightField
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
    for pred in predictions:
        if not len(pred):
            continue
        remap = _class_map(pred.classes, world)
        truth = _world_class(world, pred.x, pred.y)
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
    return AccuracyTable(edges, n, n_conf, accuracy, accuracy_all, float(threshold))


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
    world: HeightField,
    *,
    near: tuple[float, float] = (0.55, 1.45),
    near_half_width: float | None = None,
    cell: float = 0.1,
    threshold: float = 0.0,
) -> Coverage:
    """Ground area covered by the near-field patches, and with the far-field cells added.

    Parameters
    ----------
    predictions : sequence of FarPrediction
        Far-field predictions, e.g. from :func:`run_traverse`.
    poses : array_like, shape (F, 6)
        Poses of every frame whose near-field patch geometry classified, ``(x, y, z, roll,
        pitch, yaw)`` in m and rad (:meth:`Traverse.poses`).
    world : HeightField
        The true world: only cells inside it with a class count (the simulated world is a
        strip; what lies beyond cannot be checked), and it gives the truth for ``accuracy``.
    near : (float, float)
        The patch, m ahead (as :class:`NearToFar`).
    near_half_width : float, optional
        Half width of the patch, m; half of ``near[1] - near[0]`` by default.
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
    half = 0.5 * (near[1] - near[0]) if near_half_width is None else near_half_width
    # Near field: sample each patch at a quarter cell and mark the cells hit.
    step = cell / 4.0
    ax = np.arange(near[0] + step / 2, near[1], step)
    ay = np.arange(-half + step / 2, half, step)
    gx, gy = np.meshgrid(ax, ay)
    patch = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    near_keys: set[tuple[int, int]] = set()
    for pose in poses:
        pw = patch @ pose_matrix(pose)[:3, :3].T + pose[:3]
        ok = _world_class(world, pw[:, 0], pw[:, 1]) >= 0
        near_keys.update(_keys(pw[ok, 0], pw[ok, 1], cell))
    # Far field: confident predictions; fuse per cell by the mean probability.
    sums: dict[tuple[int, int], NDArray[np.float64]] = {}
    classes: tuple[str, ...] = ()
    for pred in predictions:
        if not len(pred):
            continue
        classes = pred.classes
        ok = (pred.confidence >= threshold) & (_world_class(world, pred.x, pred.y) >= 0)
        for key, p in zip(_keys(pred.x[ok], pred.y[ok], cell), pred.proba[ok], strict=True):
            if key in sums:
                sums[key] = sums[key] + p
            else:
                sums[key] = p.copy()
    far_keys = [k for k in sums if k not in near_keys]
    accuracy = float("nan")
    if far_keys:
        xs = (np.array([k[0] for k in far_keys]) + 0.5) * cell
        ys = (np.array([k[1] for k in far_keys]) + 0.5) * cell
        truth = _world_class(world, xs, ys)
        remap = _class_map(classes, world)
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


def _keys(x: NDArray, y: NDArray, cell: float) -> list[tuple[int, int]]:
    i = np.floor(np.asarray(x) / cell).astype(np.int64)
    j = np.floor(np.asarray(y) / cell).astype(np.int64)
    return list(zip(i.tolist(), j.tolist(), strict=True))
