"""The coarse pass of the patch path: the ground plane under the patch and its relief.

:func:`fit_ground` matches the pair binned 4x4 (16x cheaper, a quarter of the disparities)
over the patch and a generous band of heights, fits a plane to the points, refines it by
aligning the binned images on it (:func:`align_plane`), and returns it with the band of
heights its relief spans: the full-resolution pass of
:func:`rough_map.stereo.stereo_to_cloud` then searches only that band around that plane.

Why the plane is aligned on the images
--------------------------------------
Pixel locking is worst where all residuals are nearly the same: a surface that *is* the
prior's plane, give or take a fraction of a pixel, comes back locked onto the prior, with
its offset lost. The plane SGM finds in the coarse pass is off by a few tenths of a pixel
(1-2 mm), so the fine pass would inherit that error on smooth ground. Aligning the binned
images directly on a plane (Gauss-Newton on three disparity parameters over thousands of
pixels, no integer search) finds it to about 0.01 px; on a rendered tilted plane the
points then lie within 0.15 mm (median) of the truth, against 0.8-0.9 mm for a prior at
``z = 0``.
"""

from __future__ import annotations

import logging

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.patch import PatchSpec
from rough_map.stereo.ground import Plane, fit_plane, ground_disparity, plane_from_disparity
from rough_map.stereo.matching import check_pair, sgbm_raw
from rough_map.stereo.settings import StereoConfig
from rough_map.stereo.triangulation import window_xyz
from rough_map.stereo.window import PatchWindow, patch_window

__all__ = ["align_plane", "fit_ground", "scaled_calibration"]

log = logging.getLogger(__name__)


def fit_ground(
    left: np.ndarray,
    right: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    patch: PatchSpec,
    plane: Plane | None = None,
) -> tuple[Plane, tuple[float, float]] | None:
    """The coarse pass of the patch path: the ground plane under the patch and its relief.

    SGM on the pair binned ``config.coarse_scale`` times each way, over the patch and
    ``config.height_tolerance`` m above and below ``plane`` (default ``z = 0``, or e.g.
    :func:`~rough_map.stereo.ground.level_plane` of the IMU's tilt), on the residual to that
    plane's disparity. A plane is fitted to the points over the patch footprint (least
    squares, trimmed at 3 robust sigma), then refined by aligning the binned images on it
    directly (see the module notes: SGM alone leaves it a few tenths of a pixel off). The
    heights of the points above it, 0.2th to 99.8th percentile, widened by
    ``config.band_margin`` and to at least ``+-config.min_band``, give the band the fine
    pass searches. The binned images are 16x cheaper to match and need a quarter of the
    disparities: 9-10 ms of CPU (one thread) in all.

    Parameters
    ----------
    left, right : ndarray of uint8
        Rectified pair, gray or BGR.
    calib : StereoCalibration
        The rig.
    config : StereoConfig, optional
        Settings; defaults to ``StereoConfig()``.
    patch : PatchSpec
        The patch of interest: centre ``ahead`` of the vehicle origin and ``lateral`` to its
        left, side ``size`` (m).
    plane : (float, float, float), optional
        Expected ground ``z = a x + b y + c`` in the vehicle frame, m.

    Returns
    -------
    ((float, float, float), (float, float)) or None
        The plane ``(a, b, c)`` and the height band ``(lo, hi)`` in m around it; None when
        fewer than 10 % of the patch's coarse pixels matched (no texture, occlusion).
    """
    import cv2  # heavy: only when matching

    config = config or StereoConfig()
    left_g, right_g = check_pair(left, right, calib)
    scale = config.coarse_scale
    small = scaled_calibration(calib, scale)
    size_px = (small.width, small.height)
    crop = (small.height * scale, small.width * scale)
    left_s = cv2.resize(left_g[: crop[0], : crop[1]], size_px, interpolation=cv2.INTER_AREA)
    right_s = cv2.resize(right_g[: crop[0], : crop[1]], size_px, interpolation=cv2.INTER_AREA)
    tol = config.height_tolerance
    window = patch_window(
        small,
        patch,
        height_tolerance=tol,
        crop_margin=config.crop_margin,
        margin_px=2,
        plane=plane,
        clip=True,
    )
    raw = sgbm_raw(
        left_s, right_s, config.sgbm, window.rows, window.cols, window.residual, 1, window.prior
    )
    x, y, z, _, keep = window_xyz(raw, small, window, patch, margin=config.crop_margin)
    expected = (window.rows[1] - window.rows[0]) * (window.cols[1] - window.cols[0])
    n = int(np.count_nonzero(keep))
    if n < max(100, 0.1 * expected):
        log.debug("coarse ground fit: only %d points, no fit", n)
        return None
    points = np.column_stack([x[keep], y[keep], z[keep]])
    fitted, heights, inliers = fit_plane(points, (patch.ahead, patch.lateral))
    # SGM's plane is off by a few tenths of a pixel where the ground is nearly planar: refine
    # it on the images themselves, over the plane's inliers.
    mask = np.zeros_like(keep)
    mask[keep] = inliers
    fitted, heights = _refine(left_s, right_s, small, window, mask, fitted, heights, points)
    lo, hi = np.quantile(heights, [0.002, 0.998])
    lo = max(-tol, min(float(lo) - config.band_margin, -config.min_band))
    hi = min(tol, max(float(hi) + config.band_margin, config.min_band))
    log.debug(
        "coarse ground fit: %d points, plane z = %.4f x + %.4f y + %.4f, band %.3f..%.3f m",
        n,
        *fitted,
        lo,
        hi,
    )
    return fitted, (lo, hi)


def _refine(
    left_s: np.ndarray,
    right_s: np.ndarray,
    small: StereoCalibration,
    window: PatchWindow,
    mask: np.ndarray,
    fitted: Plane,
    heights: np.ndarray,
    points: np.ndarray,
) -> tuple[Plane, np.ndarray]:
    """SGM's plane ``fitted`` (m) refined by :func:`align_plane` over the ``mask`` pixels of
    the binned pair, and the heights (m) of ``points`` above it; ``fitted`` and ``heights``
    unchanged when the alignment fails or moves more than 1 binned px over the window."""
    sgm = ground_disparity(small, plane=fitted)
    aligned = align_plane(left_s, right_s, window.rows, window.cols, sgm, mask)
    if aligned is None:
        return fitted, heights
    (r0, r1), (c0, c1) = window.rows, window.cols
    shift = max(
        abs((aligned[0] - sgm[0]) * u + (aligned[1] - sgm[1]) * v + (aligned[2] - sgm[2]))
        for u in (c0, c1)
        for v in (r0, r1)
    )
    try:
        if shift > 1.0:
            raise InputError(f"it moved {shift:.2f} px from SGM's plane")
        fitted = plane_from_disparity(small, aligned)
    except InputError as exc:
        log.debug("aligned plane rejected: %s", exc)
        return fitted, heights
    heights = points[:, 2] - (fitted[0] * points[:, 0] + fitted[1] * points[:, 1] + fitted[2])
    return fitted, heights


def align_plane(
    left: np.ndarray,
    right: np.ndarray,
    rows: tuple[int, int],
    cols: tuple[int, int],
    prior: tuple[float, float, float],
    mask: np.ndarray,
    iterations: int = 5,
) -> tuple[float, float, float] | None:
    """Refine a plane's disparity ``d = a u + b v + c`` by aligning the images directly.

    Gauss-Newton on ``left(u, v) = right(u - d(u, v), v) + o`` (a brightness offset ``o``)
    over the ``mask`` pixels of ``rows x cols``. Three parameters from thousands of pixels:
    no pixel locking, so the plane is found to a few hundredths of a pixel, which SGM around
    it cannot do for a surface that is itself nearly that plane (its residual disparities
    then all lock onto the same integer).

    Parameters
    ----------
    left, right : ndarray of uint8
        Gray rectified pair.
    rows, cols : (int, int)
        The band ``r0 <= v < r1``, ``c0 <= u < c1`` of the left image ``mask`` covers, px.
    prior : (float, float, float)
        The plane's disparity to start from, ``(a, b, c)``: px per px of u, px per px of v,
        px.
    mask : ndarray of bool, shape (r1 - r0, c1 - c0)
        The pixels of the plane.
    iterations : int
        Most Gauss-Newton steps.

    Returns
    -------
    (float, float, float) or None
        The refined ``(a, b, c)``; None if it does not converge.
    """
    if np.count_nonzero(mask) < 100:
        return None
    # Only the bounding box of the mask (the patch) is needed.
    in_rows = np.flatnonzero(mask.any(axis=1))
    in_cols = np.flatnonzero(mask.any(axis=0))
    mask = mask[in_rows[0] : in_rows[-1] + 1, in_cols[0] : in_cols[-1] + 1]
    r0, r1 = rows[0] + int(in_rows[0]), rows[0] + int(in_rows[-1]) + 1
    c0, c1 = cols[0] + int(in_cols[0]), cols[0] + int(in_cols[-1]) + 1
    ref = left[r0:r1, c0:c1].astype(np.float32)
    weight = mask.astype(np.float32)
    v, u = np.mgrid[r0:r1, c0:c1].astype(np.float32)
    u -= np.float32(0.5 * (c0 + c1))  # centred: a better conditioned system
    v -= np.float32(0.5 * (r0 + r1))
    uc, vc = 0.5 * (c0 + c1), 0.5 * (r0 + r1)
    a, b, c = prior
    c += a * uc + b * vc  # d = a (u - uc) + b (v - vc) + c
    step = None
    for k in range(iterations):
        # right_w(j, i) = right(u - d(u, v), v) for u = c0 + j, v = r0 + i.
        offset = (1.0 - a) * c0 - b * r0 - (c - a * uc - b * vc)
        step = _gauss_newton_step(right, ref, weight, (u, v), (r0, r1, c0, c1), (a, b, offset))
        if step is None:
            return None
        a, b, c = a + step[0], b + step[1], c + step[2]
        # The image noise leaves steps of ~0.01 px: converged below that, or close to it.
        change = abs(step[2]) + abs(step[0]) * (c1 - c0) / 2 + abs(step[1]) * (r1 - r0) / 2
        if change < 0.01 or (k == iterations - 1 and change < 0.05):
            return (float(a), float(b), float(c - a * uc - b * vc))
    log.debug("plane alignment did not converge (last step %s)", step)
    return None


def _gauss_newton_step(
    right: np.ndarray,
    ref: np.ndarray,
    weight: np.ndarray,
    centred: tuple[np.ndarray, np.ndarray],
    box: tuple[int, int, int, int],
    warp_abc: tuple[float, float, float],
) -> np.ndarray | None:
    """One step of :func:`align_plane`: the change of ``(a, b, c, o)`` (px per px, px per px,
    px, gray levels) that best explains ``ref - right_w``, ``right_w`` the right image warped
    by the affine map ``x = (1 - a) j - b i + offset``, ``y = r0 + i`` (``warp_abc = (a, b,
    offset)``, ``box = (r0, r1, c0, c1)``, ``centred = (u, v)`` the pixels' coordinates about
    the box's centre). None for a singular system."""
    import cv2  # heavy: only when matching

    u, v = centred
    r0, r1, c0, c1 = box
    a, b, offset = warp_abc
    warp = np.array([[1.0 - a, -b, offset], [0.0, 1.0, float(r0)]])
    warped = cv2.warpAffine(
        right,
        warp,
        (c1 - c0, r1 - r0),
        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float32)
    # d right / d x at the sampled points (the warp stretches x by 1 - a).
    gx = cv2.Sobel(warped, cv2.CV_32F, 1, 0, ksize=3, scale=0.125 / (1.0 - a))
    error = ref - warped
    gw = gx * weight
    # Residual e = J . delta with J = -gx (u, v, 1) for (a, b, c) and 1 for the offset.
    cols_j = (gw * u, gw * v, gw, weight)
    signs = (-1.0, -1.0, -1.0, 1.0)
    jtj = np.empty((4, 4))
    jte = np.empty(4)
    full = (gx * u, gx * v, gx)  # and 1 for the offset: its products are cols_j itself
    for i in range(4):
        jte[i] = signs[i] * float((cols_j[i] * error).sum())
        for j in range(i, 4):
            product = cols_j[i] if j == 3 else cols_j[i] * full[j]
            jtj[i, j] = jtj[j, i] = signs[i] * signs[j] * float(product.sum())
    try:
        return np.asarray(np.linalg.solve(jtj, jte))
    except np.linalg.LinAlgError:
        return None


def scaled_calibration(calib: StereoCalibration, scale: int) -> StereoCalibration:
    """The rig seen through images binned ``scale`` x ``scale`` (pixel centres kept).

    ``fx, fy, cx, cy, cx_right`` and the image size (px) are divided by ``scale``; the
    baseline (m) and the extrinsics are the rig's (of the rectified pair: no
    ``rectification``).
    """
    return calib.model_copy(
        update={
            "fx": calib.fx / scale,
            "fy": calib.fy / scale,
            "cx": (calib.cx + 0.5) / scale - 0.5,
            "cy": (calib.cy + 0.5) / scale - 0.5,
            "cx_right": None if calib.cx_right is None else (calib.cx_right + 0.5) / scale - 0.5,
            "width": calib.width // scale,
            "height": calib.height // scale,
            "rectification": None,
        }
    )
