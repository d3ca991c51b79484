"""The ground under the patch: planes of the vehicle frame and their disparities.

A plane ``z = a x + b y + c`` of the vehicle frame (m) seen by the rectified rig has a
disparity affine in the pixel, ``d0(u, v) = a' u + b' v + c'`` (:func:`ground_disparity`,
and back, :func:`plane_from_disparity`). :func:`level_plane` is the level ground as a tilted
vehicle sees it (the IMU's roll and pitch); :func:`fit_plane` fits a plane to points, robust
to their outliers. These are the geometry of the patch path's prior and coarse pass
(:mod:`rough_map.stereo.window`, :mod:`rough_map.stereo.coarse`).
"""

from __future__ import annotations

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.geometry import rotation_matrix
from rough_map.stereo.outliers import MAD_TO_SIGMA

__all__ = ["Plane", "fit_plane", "ground_disparity", "level_plane", "plane_from_disparity"]

#: A plane ``z = a x + b y + c`` of the vehicle frame, m.
Plane = tuple[float, float, float]


def level_plane(roll: float = 0.0, pitch: float = 0.0, ground_z: float = 0.0) -> Plane:
    """The level ground seen from a tilted vehicle: ``z = a x + b y + c`` in the vehicle frame.

    The vehicle -> level rotation is ``Ry(pitch) Rx(roll)`` (as
    :func:`rough_map.geometry.rotation_matrix`, pitch positive nose down, roll positive left
    side up); the level ground is the plane ``ground_z`` m above the vehicle origin in the
    level frame. With no tilt it is ``z = ground_z``.

    Parameters
    ----------
    roll, pitch : float
        Vehicle tilt, rad.
    ground_z : float
        Height of the level ground above the vehicle origin in the level frame, m.

    Returns
    -------
    (float, float, float)
        ``(a, b, c)``: m per m of x, m per m of y, m.

    Raises
    ------
    InputError
        A tilt of more than about 84 degrees (``cos(roll) cos(pitch) <= 0.1``): the ground
        would be seen edge-on.
    """
    # Third row of Ry(pitch) Rx(roll): the level frame's z axis in vehicle coordinates.
    nx, ny, nz = (float(v) for v in rotation_matrix(roll, pitch)[2])
    if nz <= 0.1:
        raise InputError(f"roll {roll} rad and pitch {pitch} rad tilt the vehicle too far")
    return (-nx / nz, -ny / nz, ground_z / nz)


def ground_disparity(
    calib: StereoCalibration, ground_z: float = 0.0, *, plane: Plane | None = None
) -> tuple[float, float, float]:
    """Disparity of a ground plane of the vehicle frame, ``d0 = a u + b v + c``.

    The plane is ``z = ground_z``, or ``z = pa x + pb y + pc`` if ``plane = (pa, pb, pc)``,
    i.e. ``g . p = pc`` with ``g = (-pa, -pb, 1)``. A left-camera ray through pixel ``(u, v)``
    with unit depth has vehicle-frame direction ``m = R (xn, yn, 1)``, ``xn = (u - cx) / fx``,
    ``yn = (v - cy) / fy``, from the camera centre ``t``; it meets the plane at depth
    ``Z = (pc - g . t) / (g . m)``, so ``d0 = fx B / Z - doffs`` is affine in ``(u, v)``. Pixels
    looking above the horizon get ``d0 <= 0``.

    Returns
    -------
    (float, float, float)
        ``(a, b, c)``: px per px of u, px per px of v, px.
    """
    transform = calib.T_vehicle_camera
    pa, pb, pc = (0.0, 0.0, float(ground_z)) if plane is None else map(float, plane)
    g = np.array([-pa, -pb, 1.0])
    height = pc - float(g @ transform[:3, 3])
    if height >= 0:
        raise InputError(f"the camera must be above the ground (ground plane z = {pc} m)")
    k = calib.focal_baseline / height
    r20, r21, r22 = g @ transform[:3, :3]
    a = k * r20 / calib.fx
    b = k * r21 / calib.fy
    c = k * (r22 - r20 * calib.cx / calib.fx - r21 * calib.cy / calib.fy) - calib.doffs
    return (float(a), float(b), float(c))


def plane_from_disparity(calib: StereoCalibration, prior: tuple[float, float, float]) -> Plane:
    """The plane of the vehicle frame whose disparity is ``prior`` (inverse of
    :func:`ground_disparity`).

    Parameters
    ----------
    calib : StereoCalibration
        The rig.
    prior : (float, float, float)
        Disparity ``d0 = a' u + b' v + c'``: px per px of u, px per px of v, px.

    Returns
    -------
    (float, float, float)
        The plane ``z = a x + b y + c``: m per m of x, m per m of y, m.

    Raises
    ------
    InputError
        The disparity is of no plane under the camera.
    """
    al, be, ga = prior
    ga += calib.doffs
    m = np.array([al * calib.fx, be * calib.fy, ga + al * calib.cx + be * calib.cy])
    transform = calib.T_vehicle_camera
    w = transform[:3, :3] @ m  # = k g, g = (-a, -b, 1), k = fx B / (c - g . t)
    if not w[2] < 0:
        raise InputError("the ground plane's disparity puts the camera below the ground")
    g = w / w[2]
    return (float(-g[0]), float(-g[1]), float(calib.focal_baseline / w[2] + g @ transform[:3, 3]))


def fit_plane(
    points: np.ndarray, centre: tuple[float, float]
) -> tuple[Plane, np.ndarray, np.ndarray]:
    """Robust least-squares plane ``z = a x + b y + c`` through points.

    Least squares, then three times: points more than ``max(3 sigma, 5 mm)`` off the plane
    are dropped and the plane fitted again, ``sigma`` the robust standard deviation of the
    kept points' residuals (``1.4826`` times their median absolute deviation).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        ``(x, y, z)`` in m.
    centre : (float, float)
        ``(x, y)`` in m about which the fit is centred (better conditioned), e.g. the
        patch's centre.

    Returns
    -------
    plane : (float, float, float)
        ``(a, b, c)``: m per m of x, m per m of y, m.
    heights : ndarray, shape (N,)
        Height of every point above the plane, m.
    inliers : ndarray of bool, shape (N,)
        The points of the last fit.
    """
    x = points[:, 0].astype(np.float64) - centre[0]
    y = points[:, 1].astype(np.float64) - centre[1]
    z = points[:, 2].astype(np.float64)
    keep = np.ones(len(z), dtype=bool)
    coef = np.zeros(3)
    res = z
    for _ in range(3):
        xs, ys, zs = x[keep], y[keep], z[keep]
        # 3x3 normal equations from elementwise sums: dot products would go through BLAS,
        # whose threads cost more than the arithmetic (and spin on a busy machine).
        sxy = float((xs * ys).sum())
        sx, sy = float(xs.sum()), float(ys.sum())
        ata = np.array(
            [
                [float((xs * xs).sum()), sxy, sx],
                [sxy, float((ys * ys).sum()), sy],
                [sx, sy, float(len(zs))],
            ]
        )
        atb = np.array([float((xs * zs).sum()), float((ys * zs).sum()), float(zs.sum())])
        coef = np.linalg.solve(ata, atb)
        res = z - (coef[0] * x + coef[1] * y + coef[2])
        kept = res[keep]
        # The MAD (scipy.stats.median_abs_deviation's value) without scipy's per-call
        # overhead, which is as large as the medians themselves here.
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(kept - np.median(kept))))
        new = np.abs(res) <= max(3.0 * sigma, 0.005)
        if np.array_equal(new, keep):
            break
        keep = new
    a, b, c = (float(v) for v in coef)
    return (a, b, c - a * centre[0] - b * centre[1]), res, keep
