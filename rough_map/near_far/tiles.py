"""Image tiles: their colour features, and where the ray through each tile centre meets the
ground.

The left image is cut into square tiles of ``tile_px`` px, laid from the top-left corner.
:func:`tile_features` gives six numbers per tile (:data:`FEATURE_NAMES`);
:func:`tile_geometry` intersects the ray through each tile centre with the vehicle's ground
plane ``z = 0`` (:func:`rough_map.geometry.pixel_to_ground`).
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.geometry import pixel_to_ground
from rough_map.io.images import read_image

__all__ = [
    "FEATURE_NAMES",
    "TileGeometry",
    "check_image",
    "read_bgr",
    "tile_features",
    "tile_geometry",
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


@dataclass(frozen=True)
class TileGeometry:
    """Tile layout of one calibration: tile grid and the ground point of each tile centre.

    Attributes
    ----------
    n_rows, n_cols : int
        Tiles down and across the image.
    ground : ndarray, shape (n_rows * n_cols, 3)
        Vehicle-frame point (m) where the ray through each tile centre (row-major over the
        tile grid) meets the plane ``z = 0``; NaN where the ray misses the ground.
    distance : ndarray, shape (n_rows * n_cols,)
        Horizontal distance of the ground point from the vehicle origin, m (NaN: none).
    """

    n_rows: int
    n_cols: int
    ground: NDArray[np.float64]
    distance: NDArray[np.float64]


def tile_geometry(calib: StereoCalibration, tile_px: int) -> TileGeometry:
    """The :class:`TileGeometry` of tiles of ``tile_px`` px in the left image of ``calib``."""
    n_rows, n_cols = calib.height // tile_px, calib.width // tile_px
    centre = 0.5 * (tile_px - 1)
    u = tile_px * np.arange(n_cols) + centre
    v = tile_px * np.arange(n_rows) + centre
    ground = pixel_to_ground(calib, u[None, :], v[:, None]).reshape(-1, 3)
    return TileGeometry(n_rows, n_cols, ground, np.hypot(ground[:, 0], ground[:, 1]))


def check_image(image: ArrayLike, calib: StereoCalibration) -> NDArray[np.uint8]:
    """``image`` as an 8-bit BGR array of the size of ``calib``'s images.

    Raises
    ------
    InputError
        Not 8-bit, not three channels, or not ``calib.width`` x ``calib.height`` px.
    """
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


def read_bgr(path: Any) -> NDArray[np.uint8]:
    """The colour image at ``path`` as 8-bit BGR (OpenCV), read with the size checks of
    :func:`rough_map.io.images.read_image`.

    Raises
    ------
    FileFormatError
        The file is missing, declares too many pixels, or OpenCV cannot decode it.
    """

    return np.asarray(read_image(path, color=True), dtype=np.uint8)


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
    if not (isinstance(tile_px, Integral) and tile_px >= 2):
        raise InputError(f"tile_px must be an integer >= 2 px, got {tile_px!r}")
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
