"""A rectified stereo pair -> the point cloud of the patch of interest, vehicle frame.

:func:`stereo_to_cloud` has four paths, picked by its ``restrict_to_patch`` and the
:class:`~rough_map.stereo.settings.StereoConfig`:

* the *patch path* (the default): a coarse pass (:func:`~rough_map.stereo.coarse.fit_ground`)
  finds the ground plane under the patch and its relief, then SGM matches, at full
  resolution, the residual to that plane's disparity over the relief only, on the image
  rows and columns that see the patch; the raw output goes straight to the vehicle frame
  (:func:`~rough_map.stereo.triangulation.window_cloud`);
* the same in *one pass* (``fit_ground`` off, or a failed fit): the residual to the
  expected ground's disparity (the vehicle's ``z = 0``, or the level ground of an IMU tilt)
  over ``height_tolerance``;
* the patch path *without the prior* (``ground_prior`` off): the disparity itself over the
  window, optionally equalised (slower, kept for comparison);
* the *full frame* (``restrict_to_patch=False``): every pixel of
  :func:`~rough_map.stereo.frame.stereo_frame`, over the disparities of ``min_depth`` to
  ``max_depth`` (or the config's), any scene.

Each ends with an outlier filter (:mod:`rough_map.stereo.outliers`): the patch paths run the
statistical moving-window filter on the heights above the ground plane searched, in windows
aligned on the patch's corner; the full frame, which need not be ground, tests each pixel
against its neighbours in the image (:func:`~rough_map.stereo.outliers.image_outlier_mask`).
A calibration with a ``rectification`` rectifies the pair first.
"""

from __future__ import annotations

import logging

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.patch import PatchSpec
from rough_map.stereo.coarse import fit_ground
from rough_map.stereo.frame import stereo_frame
from rough_map.stereo.ground import level_plane
from rough_map.stereo.matching import compute_disparity, sgbm_raw
from rough_map.stereo.outliers import image_support, window_outlier_mask
from rough_map.stereo.rectify import rectify_pair
from rough_map.stereo.settings import StereoConfig
from rough_map.stereo.triangulation import disparity_to_points, to_vehicle, window_xyz
from rough_map.stereo.window import PatchWindow, patch_window

__all__ = ["stereo_to_cloud"]

log = logging.getLogger(__name__)

#: float32 columns ``x, y, z`` (vehicle frame) and ``dz`` (above the ground plane), m.
_Columns = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def stereo_to_cloud(
    left: np.ndarray,
    right: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    patch: PatchSpec | None = None,
    restrict_to_patch: bool = True,
    roll: float | None = None,
    pitch: float | None = None,
    min_depth: float | None = None,
    max_depth: float | None = None,
) -> np.ndarray:
    """Point cloud in the vehicle frame from a stereo pair (paper section 3.2).

    Parameters
    ----------
    left, right : ndarray of uint8
        Rectified images (raw ones if the calibration has a ``rectification``), gray
        ``(H, W)`` or BGR ``(H, W, 3)``, of the calibration's size.
    calib : StereoCalibration
        The rig.
    config : StereoConfig, optional
        Matcher, filter and window settings; defaults to ``StereoConfig()``.
    patch : PatchSpec, optional
        The patch of interest: centre ``ahead`` of the vehicle origin and ``lateral`` to its
        left, side ``size`` (m); default ``PatchSpec()``, the paper's.
    restrict_to_patch : bool
        If True (the patch path), match only what can see the patch: with
        ``config.fit_ground``, a coarse pass (:func:`~rough_map.stereo.coarse.fit_ground`)
        finds the ground plane under the patch and its relief, then SGM runs on the rows and
        columns that see the patch (:func:`~rough_map.stereo.window.patch_window`) and on the
        residual to that plane's disparity over the relief only; the points over the patch
        footprint plus ``config.crop_margin`` and inside the relief band are returned, those
        of every ``config.col_step``-th image column. If False, match the full frame
        (:func:`~rough_map.stereo.frame.stereo_frame`) and return every valid point.
    roll, pitch : float, optional
        Vehicle tilt in rad (e.g. the IMU's; conventions of
        :func:`~rough_map.stereo.ground.level_plane`). The patch path then expects level
        ground rather than the vehicle's ``z = 0`` plane. It only centres the coarse search
        (or, without ``config.fit_ground``, the search itself); the cloud stays in the
        vehicle frame.
    min_depth, max_depth : float, optional
        Full frame: the depths searched, m (see
        :func:`~rough_map.stereo.frame.disparity_range`); default the config's disparities.

    Returns
    -------
    ndarray of float64, shape (N, 3)
        Points ``(x, y, z)`` in m in the vehicle frame (x forward, y left, z up), after the
        statistical moving-window filter if ``config.outlier_filter`` is set.

    Raises
    ------
    InputError
        Images of different sizes, not 8-bit, or not matching the calibration; a patch
        outside the images.
    """
    config = config or StereoConfig()
    patch = PatchSpec() if patch is None else patch
    if restrict_to_patch:
        left_g, right_g = rectify_pair(left, right, calib)
        points = _patch_path(left_g, right_g, calib, config, patch, roll, pitch)
    else:
        frame = stereo_frame(left, right, calib, config, min_depth=min_depth, max_depth=max_depth)
        points = frame.vehicle_points()
    log.debug("stereo cloud: %d points", len(points))
    return points


def _patch_path(
    left_g: np.ndarray,
    right_g: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig,
    patch: PatchSpec,
    roll: float | None,
    pitch: float | None,
) -> np.ndarray:
    """The patch paths: the points over the patch, filtered; (N, 3) float64, m."""
    window = _search_window(left_g, right_g, calib, config, patch, roll, pitch)
    f = config.outlier_filter
    rescue = None
    if config.ground_prior:
        # Ground outside the searched volume (e.g. beyond the patch in the band's top rows)
        # can only match wrongly; such matches pile up at the ends of the search range
        # (trimmed) or reconstruct outside the volume (cropped).
        raw = sgbm_raw(
            left_g,
            right_g,
            config.sgbm,
            window.rows,
            window.cols,
            window.residual,
            config.row_step,
            window.prior,
        )
        xs, ys, zs, dzs, inside = window_xyz(
            raw,
            calib,
            window,
            patch,
            margin=config.crop_margin,
            row_step=config.row_step,
            col_step=config.col_step,
        )
        x, y, z, dz = xs[inside], ys[inside], zs[inside], dzs[inside]
        if f is not None:
            rescue = (raw[:, :: config.col_step], inside)
    else:
        x, y, z, dz = _disparity_cloud(left_g, right_g, calib, config, patch, window)
    if f is not None and len(z):
        # Heights above the ground plane (not z): a sloping plane adds no spread to the
        # windows, which are aligned on the footprint's corner.
        half = patch.size / 2.0 + config.crop_margin
        corner = (patch.ahead - half, patch.lateral - half)
        keep = window_outlier_mask(x, y, dz, corner, f.cell, f.k, f.min_tolerance, f.min_count)
        if rescue is not None:
            _rescue_supported(keep, *rescue, f.radius, f.disparity_tolerance, f.support)
        x, y, z = x[keep], y[keep], z[keep]
    points = np.empty((len(z), 3))
    points[:, 0] = x
    points[:, 1] = y
    points[:, 2] = z
    return points


def _rescue_supported(
    keep: np.ndarray,
    raw: np.ndarray,
    inside: np.ndarray,
    radius: int,
    tolerance: float,
    min_support: int,
) -> None:
    """Keep (in place) the points the ground windows rejected that their neighbours in the
    image support (:func:`~rough_map.stereo.outliers.image_support`): relief steeper than a
    window (a stone's flank, the floor beside an object, ploughed ridges) is not noise.
    ``raw`` is the matcher's output (1/16 px) whose pixels ``inside`` gave the points."""
    rejected = np.flatnonzero(~keep)
    if not len(rejected):
        return
    disp = raw.astype(np.float32) * np.float32(1.0 / 16.0)
    disp[~inside] = np.nan
    pixels = np.flatnonzero(inside)[rejected]
    supported = image_support(disp, pixels, radius, tolerance) >= min_support
    keep[rejected[supported]] = True
    log.debug(
        "outliers: %d of %d rejected points supported in the image", supported.sum(), len(rejected)
    )


def _search_window(
    left_g: np.ndarray,
    right_g: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig,
    patch: PatchSpec,
    roll: float | None,
    pitch: float | None,
) -> PatchWindow:
    """What the patch path matches at full resolution: around the ground the coarse pass
    fits (``config.fit_ground`` with ``ground_prior``), else, or if that fails, over
    ``config.height_tolerance`` (m) around the expected ground (level under ``roll`` and
    ``pitch``, rad, if given; else the vehicle's ``z = 0``)."""
    nominal = None if roll is None and pitch is None else level_plane(roll or 0.0, pitch or 0.0)
    # The search volume around the expected ground; this also checks the patch is in view.
    window = patch_window(
        calib,
        patch,
        height_tolerance=config.height_tolerance,
        crop_margin=config.crop_margin,
        margin_px=config.margin_px,
        plane=nominal,
        clip=True,
    )
    if not (config.fit_ground and config.ground_prior):
        return window
    fit = fit_ground(left_g, right_g, calib, config, patch=patch, plane=nominal)
    if fit is None:
        return window
    try:
        return patch_window(
            calib,
            patch,
            height_tolerance=fit[1],
            crop_margin=config.crop_margin,
            margin_px=config.margin_px,
            plane=fit[0],
            clip=True,
        )
    except InputError as exc:  # a wild fit: keep the whole search volume
        log.debug("fitted ground rejected: %s", exc)
        return window


def _disparity_cloud(
    left_g: np.ndarray,
    right_g: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig,
    patch: PatchSpec,
    window: PatchWindow,
) -> _Columns:
    """The patch path without the prior: the disparity itself over ``window``, optionally
    equalised (slower, kept for comparison); the points over the patch and inside the
    window's band."""
    disp = compute_disparity(
        left_g,
        right_g,
        config.sgbm,
        window.rows,
        cols=window.cols,
        disparities=window.disparities,
        row_step=config.row_step,
        equalize=config.equalize_subpixel,
        trim=1,
    )
    if config.col_step > 1:
        disp[:, np.arange(disp.shape[1]) % config.col_step != 0] = np.nan
    pts = to_vehicle(disparity_to_points(disp, calib, window.rows[0], config.row_step), calib)
    pa, pb, pc = window.plane
    dz = pts[:, 2] - (pa * pts[:, 0] + pb * pts[:, 1] + pc)
    lo, hi = window.band
    half = patch.size / 2.0 + config.crop_margin
    inside = (
        (np.abs(pts[:, 0] - patch.ahead) <= half)
        & (np.abs(pts[:, 1] - patch.lateral) <= half)
        & (dz >= lo)
        & (dz <= hi)
    )
    x, y, z = (np.ascontiguousarray(c, dtype=np.float32) for c in pts[inside].T)
    return x, y, z, dz[inside].astype(np.float32)
