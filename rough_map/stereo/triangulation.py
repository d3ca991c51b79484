"""Triangulation: disparities to 3-D points, and on to the vehicle frame.

``Z = fx B / d`` in the left camera frame (:func:`disparity_to_points`), then the rig's
extrinsics (:func:`to_vehicle`). The patch path folds both, and the prior its matcher used,
into one 4x4 reprojection of OpenCV's raw output (:func:`window_xyz`), and keeps the points
over the patch's footprint; :func:`crop_to_patch` does that cut on any cloud.
"""

from __future__ import annotations

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.patch import PatchSpec
from rough_map.stereo.window import PatchWindow

__all__ = [
    "crop_to_patch",
    "disparity_to_points",
    "reprojection",
    "to_vehicle",
    "window_cloud",
    "window_xyz",
]


def disparity_to_points(
    disp: np.ndarray, calib: StereoCalibration, rows_offset: int = 0, row_step: int = 1
) -> np.ndarray:
    """3-D points in the left camera frame from a disparity map.

    Parameters
    ----------
    disp : ndarray, shape (h, W)
        Disparity in px (NaN or ``<= -doffs`` where invalid), e.g. from
        :func:`compute_disparity`.
    calib : StereoCalibration
        The rig.
    rows_offset : int
        Image row of ``disp[0]``, px (``r0`` of a row band).
    row_step : int
        Rows binned per row of ``disp`` (see :func:`compute_disparity`): row ``i`` is image
        row ``rows_offset + row_step * i + (row_step - 1) / 2``.

    Returns
    -------
    ndarray of float64, shape (N, 3)
        ``(X, Y, Z)`` in m in the left camera frame (OpenCV), one per valid pixel, in row-major
        pixel order: ``Z = fx B / (d + doffs)``, ``X = (u - cx) Z / fx``, ``Y = (v - cy) Z / fy``.
    """
    disp = np.asarray(disp)
    if disp.ndim != 2:
        raise InputError(f"disp must be 2-D, got shape {disp.shape}")
    height, width = disp.shape
    doffs = calib.doffs
    with np.errstate(invalid="ignore"):
        valid = disp > -doffs  # False for NaN
    z = calib.focal_baseline / (disp[valid].astype(np.float64) + doffs)
    # Normalised image coordinates per column and per row, picked per valid pixel.
    x_norm = (np.arange(width) - calib.cx) / calib.fx
    rows = rows_offset + row_step * np.arange(height) + 0.5 * (row_step - 1)
    y_norm = (rows - calib.cy) / calib.fy
    points = np.empty((z.size, 3))
    points[:, 0] = np.broadcast_to(x_norm, disp.shape)[valid] * z
    points[:, 1] = np.broadcast_to(y_norm[:, None], disp.shape)[valid] * z
    points[:, 2] = z
    return points


def to_vehicle(points: np.ndarray, calib: StereoCalibration) -> np.ndarray:
    """Left-camera points (N, 3), m, to the vehicle frame (N, 3), m."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {points.shape}")
    transform = calib.T_vehicle_camera
    # Column by column rather than ``points @ R.T``: an (N, 3) x (3, 3) product goes through
    # BLAS, whose threads cost more than the arithmetic (and spin on a busy machine).
    x, y, z = (np.ascontiguousarray(c) for c in points.T)
    out = np.empty_like(points)
    for i in range(3):
        r = transform[i]
        out[:, i] = r[0] * x + r[1] * y + r[2] * z + r[3]
    return out


def reprojection(
    calib: StereoCalibration,
    origin: tuple[float, float],
    steps: tuple[float, float],
    prior: tuple[float, float, float] | None,
) -> np.ndarray:
    """4x4 ``Q`` for ``cv2.reprojectImageTo3D`` from raw SGBM output straight to the vehicle.

    Pixel ``(j, i)`` of the raw map is image pixel ``u = u0 + su j``, ``v = v0 + sv i``
    (``origin = (u0, v0)``, ``steps = (su, sv)``); its value is ``16 r``, ``r`` the matched
    disparity, or the residual to ``prior`` (then ``d = r + d0(u - r, v)``). Every step, from
    ``(j, i, 16 r)`` to ``(u, v, d)``, to the camera frame, to the vehicle frame, is linear in
    homogeneous coordinates, so one matrix does all: one pass, no float64 temporaries.
    """
    u0, v0 = origin
    su, sv = steps
    pa, pb, pc = prior if prior is not None else (0.0, 0.0, 0.0)
    to_image = np.array(
        [
            [su, 0.0, 0.0, u0],
            [0.0, sv, 0.0, v0],
            [pa * su, pb * sv, (1.0 - pa) / 16.0, pa * u0 + pb * v0 + pc],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    ratio = calib.fx / calib.fy
    to_camera = np.array(
        [
            [1.0, 0.0, 0.0, -calib.cx],
            [0.0, ratio, 0.0, -calib.cy * ratio],
            [0.0, 0.0, 0.0, calib.fx],
            [0.0, 0.0, 1.0 / calib.baseline, calib.doffs / calib.baseline],
        ]
    )
    return calib.T_vehicle_camera @ to_camera @ to_image


def window_xyz(
    raw: np.ndarray,
    calib: StereoCalibration,
    window: PatchWindow,
    patch: PatchSpec,
    *,
    margin: float,
    trim: int = 1,
    row_step: int = 1,
    col_step: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicle-frame coordinates of raw SGBM output (over the window's residual search).

    Parameters
    ----------
    raw : ndarray of int16
        :func:`rough_map.stereo.matching.sgbm_raw`'s output over ``window`` (its rows, its
        columns, its residual disparities and prior), 1/16 px.
    calib : StereoCalibration
        The rig (of the images matched: a binned pair has its own, scaled calibration).
    window : PatchWindow
        What was matched.
    patch : PatchSpec
        The patch of interest; its footprint, widened by ``margin`` (m), is kept.
    margin : float
        Margin around the patch footprint, m.
    trim : int
        Matches within ``trim`` px of the ends of the search range are dropped.
    row_step : int
        Image rows per row of ``raw`` (vertical binning), px.
    col_step : int
        Keep every ``col_step``-th column of ``raw`` only.

    Returns
    -------
    x, y, z, dz : ndarray of float32
        Images of the vehicle-frame coordinates and of the height above the window's plane,
        m.
    keep : ndarray of bool
        The pixels to keep: matched inside the search range less ``trim`` px at each end,
        over the footprint ``|x - ahead|, |y - lateral| <= size / 2 + margin`` and within
        the window's ``band``.
    """
    import cv2  # heavy: only when matching

    ahead, lateral = patch.ahead, patch.lateral
    half = patch.size / 2.0 + margin

    if col_step > 1:
        raw = raw[:, ::col_step]
    raw = np.ascontiguousarray(raw)
    min_d, num_d = window.residual
    q = reprojection(
        calib,
        (window.cols[0], window.rows[0] + 0.5 * (row_step - 1)),
        (col_step, row_step),
        window.prior,
    )
    x, y, z = cv2.split(cv2.reprojectImageTo3D(raw, q))
    keep = (raw >= 16 * (min_d + trim)) & (raw <= 16 * (min_d + num_d - 1 - trim))
    keep &= np.abs(x - np.float32(ahead)) <= np.float32(half)
    keep &= np.abs(y - np.float32(lateral)) <= np.float32(half)
    pa, pb, pc = (np.float32(v) for v in window.plane)
    lo, hi = window.band
    dz = z - pa * x - pb * y - pc
    keep &= (dz >= np.float32(lo)) & (dz <= np.float32(hi))
    return x, y, z, dz, keep


def window_cloud(
    raw: np.ndarray,
    calib: StereoCalibration,
    window: PatchWindow,
    patch: PatchSpec,
    *,
    margin: float,
    row_step: int = 1,
    col_step: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept pixels of :func:`window_xyz` (``trim`` 1 px) as float32 columns ``x, y, z,
    dz``, m."""
    x, y, z, dz, keep = window_xyz(
        raw, calib, window, patch, margin=margin, row_step=row_step, col_step=col_step
    )
    return x[keep], y[keep], z[keep], dz[keep]


def crop_to_patch(
    points: np.ndarray,
    patch: PatchSpec,
    margin: float = 0.05,
    height_tolerance: float | None = None,
    ground_z: float = 0.0,
) -> np.ndarray:
    """Points of the vehicle frame over the patch footprint.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in the vehicle frame, m.
    patch : PatchSpec
        The patch of interest: centre ``ahead`` of the vehicle origin and ``lateral`` to its
        left, side ``size`` (m).
    margin : float
        Margin added around the footprint, m.
    height_tolerance : float, optional
        If given, also drop points with ``|z - ground_z| > height_tolerance`` (m).
    ground_z : float
        Ground height in the vehicle frame, m.

    Returns
    -------
    ndarray, shape (M, 3)
        The points kept, in their original order.
    """
    half = patch.size / 2.0 + margin
    inside = (np.abs(points[:, 0] - patch.ahead) <= half) & (
        np.abs(points[:, 1] - patch.lateral) <= half
    )
    if height_tolerance is not None:
        inside &= np.abs(points[:, 2] - ground_z) <= height_tolerance
    return points[inside]
