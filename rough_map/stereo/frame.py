"""A whole stereo frame of any scene: the disparity map and the camera-frame points.

:func:`stereo_frame` rectifies a raw pair if the calibration says so
(:func:`~rough_map.stereo.rectify.rectify_pair`), matches every pixel over the disparities
of the depths that matter (:func:`disparity_range`), undoes SGM's pixel locking and drops
the pixels its neighbours in the image do not support
(:func:`~rough_map.stereo.outliers.image_outlier_mask`): a test that does not assume the
scene is a height field, so floor points next to objects stay. The full-frame path of
:func:`~rough_map.stereo.stereo_to_cloud` and ``rough-map stereo --disparity /
--camera-points`` use it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.patch import PatchSpec
from rough_map.stereo.matching import compute_disparity
from rough_map.stereo.outliers import image_outlier_mask
from rough_map.stereo.rectify import rectify_pair
from rough_map.stereo.settings import StereoConfig
from rough_map.stereo.triangulation import disparity_to_points, to_vehicle
from rough_map.stereo.window import patch_window

__all__ = ["StereoFrame", "disparity_range", "stereo_frame"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StereoFrame:
    """The disparity map of a rectified pair and what follows from it.

    Attributes
    ----------
    disparity : ndarray of float32, shape (H / row_step, W)
        ``u_left - u_right`` in px of the rectified left image, NaN where invalid.
    calib : StereoCalibration
        The rig (its rectified cameras).
    row_step : int
        Image rows binned per row of ``disparity`` (1: one row per image row).
    disparities : (int, int)
        ``(minDisparity, numDisparities)`` searched, px.
    """

    disparity: np.ndarray
    calib: StereoCalibration
    row_step: int = 1
    disparities: tuple[int, int] = (0, 16)

    def depth(self) -> np.ndarray:
        """Depth ``Z = fx B / (d + doffs)`` per pixel, m (float32, NaN where invalid)."""
        d = self.disparity.astype(np.float64) + self.calib.doffs
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(d > 0, self.calib.focal_baseline / d, np.nan)
        return z.astype(np.float32)

    def camera_points(self) -> np.ndarray:
        """``(N, 3)`` float64 points in the rectified left camera frame (OpenCV: x right, y
        down, z forward), m, one per valid pixel in row-major order."""
        return disparity_to_points(self.disparity, self.calib, 0, self.row_step)

    def vehicle_points(self) -> np.ndarray:
        """The :meth:`camera_points` in the vehicle frame (x forward, y left, z up), m."""
        return to_vehicle(self.camera_points(), self.calib)


def disparity_range(
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    min_depth: float | None = None,
    max_depth: float | None = None,
    patch: PatchSpec | None = None,
) -> tuple[int, int]:
    """``(minDisparity, numDisparities)`` (px) for the depths that matter.

    In order of precedence:

    * ``min_depth`` and/or ``max_depth`` (m): disparities ``fx B / Z - doffs`` from the
      farthest to the nearest depth, +-1 px; without ``max_depth`` from infinity
      (``-doffs``), without ``min_depth`` ``config.sgbm.numDisparities`` wide;
    * ``patch``: the nearest and farthest the patch of interest can be, on the ground of
      the calibration's ``camera_to_vehicle`` widened by ``config.height_tolerance`` (m)
      (:func:`~rough_map.stereo.window.patch_window`);
    * neither: ``config.sgbm.numDisparities`` wide from ``config.sgbm.minDisparity`` px
      beyond the disparity at infinity (``-doffs``; 0 for a rig without ``cx_right``).

    ``numDisparities`` is a multiple of 16; ``minDisparity`` may be negative (a rig with
    ``doffs``).

    Raises
    ------
    InputError
        Depths not positive or in the wrong order; a patch outside the images.
    """
    config = config or StereoConfig()
    infinity = math.floor(-calib.doffs)
    if min_depth is not None or max_depth is not None:
        for name, value in (("min_depth", min_depth), ("max_depth", max_depth)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number of m, got {value}")
        if min_depth is not None and max_depth is not None and not min_depth < max_depth:
            raise InputError(f"min_depth ({min_depth} m) must be below max_depth ({max_depth} m)")
        lo = infinity if max_depth is None else _disparity(calib, max_depth, math.floor) - 1
        if min_depth is None:
            return lo, config.sgbm.numDisparities
        hi = _disparity(calib, min_depth, math.ceil) + 1
        return lo, 16 * max(1, math.ceil((hi - lo + 1) / 16))
    if patch is not None:
        window = patch_window(
            calib, patch, height_tolerance=config.height_tolerance, crop_margin=config.crop_margin
        )
        return window.disparities
    return infinity + config.sgbm.minDisparity, config.sgbm.numDisparities


def _disparity(calib: StereoCalibration, depth: float, rounding: object) -> int:
    return int(rounding(calib.focal_baseline / depth - calib.doffs))  # type: ignore[operator]


def stereo_frame(
    left: np.ndarray,
    right: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    disparities: tuple[int, int] | None = None,
    min_depth: float | None = None,
    max_depth: float | None = None,
    patch: PatchSpec | None = None,
) -> StereoFrame:
    """Disparity of every pixel of a stereo pair (raw pairs are rectified first).

    Parameters
    ----------
    left, right : ndarray of uint8
        The pair, gray or BGR, of the calibration's size: rectified, or raw if the
        calibration has a ``rectification``.
    calib : StereoCalibration
        The rig.
    config : StereoConfig, optional
        Matcher (``sgbm``, ``row_step``, ``equalize_subpixel``) and filter
        (``outlier_filter``: its image test) settings; defaults to ``StereoConfig()``.
    disparities : (int, int), optional
        ``(minDisparity, numDisparities)`` px; default from ``min_depth``, ``max_depth``
        (m) or ``patch`` by :func:`disparity_range`.
    min_depth, max_depth : float, optional
        The nearest and farthest depths searched, m.
    patch : PatchSpec, optional
        Search the depths at which the patch of interest can be.

    Returns
    -------
    StereoFrame
    """
    config = config or StereoConfig()
    left_g, right_g = rectify_pair(left, right, calib)
    if disparities is None:
        disparities = disparity_range(
            calib, config, min_depth=min_depth, max_depth=max_depth, patch=patch
        )
    disp = compute_disparity(
        left_g,
        right_g,
        config.sgbm,
        disparities=disparities,
        row_step=config.row_step,
        equalize=config.equalize_subpixel,
    )
    f = config.outlier_filter
    if f is not None:
        keep = image_outlier_mask(disp, f.radius, f.disparity_tolerance, f.support)
        log.debug(
            "image outlier test: %d of %d pixels rejected",
            (~keep & np.isfinite(disp)).sum(),
            np.isfinite(disp).sum(),
        )
        disp[~keep] = np.nan
    return StereoFrame(disp, calib, config.row_step, (int(disparities[0]), int(disparities[1])))
