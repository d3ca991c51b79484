"""The one home of poses, rotations and the pinhole camera projection.

Conventions (used everywhere in rough_map):

* vehicle frame: x forward, y left, z up, m;
* a pose ``(x, y, z, roll, pitch, yaw)`` (m, rad) takes vehicle coordinates to the world:
  ``p_world = Rz(yaw) @ Ry(pitch) @ Rx(roll) @ p_vehicle + (x, y, z)``; with ``yaw = 0``
  the rotation is the paper's Eq. 11 (``phi`` = pitch, ``theta`` = roll);
* camera frame: OpenCV's, x right, y down, z forward, m; a calibration's
  ``camera_to_vehicle`` 4x4 takes camera coordinates to the vehicle frame.

Rotations are extrinsic x-y-z Euler angles, composed as ``Rz @ Ry @ Rx`` (what
``scipy.spatial.transform.Rotation.from_euler("xyz", ...)`` gives, written out: importing
scipy.spatial takes 0.2-0.45 s, and the matrix is built once per frame).
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError

__all__ = [
    "CAMERA_AXES_IN_VEHICLE",
    "PinholeCamera",
    "check_angle",
    "compensate_tilt",
    "ground_to_pixel",
    "levelling_rotation",
    "pixel_to_ground",
    "pose_matrix",
    "rotation_matrix",
    "transform_columns",
    "transform_points",
]

#: Rotation from an OpenCV camera looking straight ahead to the vehicle frame (columns are the
#: camera axes x right, y down, z forward in vehicle coordinates).
CAMERA_AXES_IN_VEHICLE: NDArray[np.float64] = np.array(
    [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
)
CAMERA_AXES_IN_VEHICLE.setflags(write=False)


class PinholeCamera(Protocol):
    """What the projections need of a calibration (:class:`rough_map.config.StereoCalibration`)."""

    @property
    def fx(self) -> float: ...  # px
    @property
    def fy(self) -> float: ...  # px
    @property
    def cx(self) -> float: ...  # px
    @property
    def cy(self) -> float: ...  # px
    @property
    def camera_to_vehicle(self) -> Any: ...  # 4x4, camera (OpenCV, m) -> vehicle (m)


def rotation_matrix(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> NDArray[np.float64]:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``; angles in rad.

    With ``yaw = 0`` this is the paper's Eq. 11 (``phi`` = pitch, ``theta`` = roll).
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def transform_columns(
    points: ArrayLike, rotation: ArrayLike, offset: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The x, y and z columns of ``points @ rotation.T + offset``, as three arrays.

    Written as three multiply-adds per column instead of a matrix product: for an (N, 3)
    cloud a K = 3 product goes through BLAS, which is several times slower, and far slower
    still when BLAS spreads it over threads on a busy machine.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points, m.
    rotation : array_like, shape (3, 3)
        Rotation (or any linear map) applied to each point.
    offset : array_like, shape (3,), optional
        Translation added after the rotation, m.
    """
    q = np.asarray(points, dtype=float)
    rot = np.asarray(rotation, dtype=float)
    x, y, z = np.ascontiguousarray(q.T)  # strided columns are slow to combine
    t = np.zeros(3) if offset is None else np.asarray(offset, dtype=float)
    out = []
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # absurd -> inf, NaN
        for i in range(3):
            row = x * rot[i, 0]
            row += y * rot[i, 1]
            row += z * rot[i, 2]
            row += t[i]
            out.append(row)
    return out[0], out[1], out[2]


def transform_points(
    points: ArrayLike, rotation: ArrayLike, offset: ArrayLike | None = None
) -> NDArray[np.float64]:
    """``points @ rotation.T + offset`` as an (N, 3) array (:func:`transform_columns`)."""
    return np.column_stack(transform_columns(points, rotation, offset))


def pose_matrix(pose: Any) -> NDArray[np.float64]:
    """4x4 vehicle -> world transform of a pose.

    Parameters
    ----------
    pose : Pose, array_like of 6 float or array_like (4, 4)
        An object with ``x, y, z, roll, pitch, yaw`` attributes (m, rad; e.g.
        :class:`rough_map.config.Pose`), ``(x, y, z, roll, pitch, yaw)``, or the 4x4
        homogeneous matrix itself.

    Returns
    -------
    ndarray, shape (4, 4)
        Rotation and translation (m) taking vehicle coordinates to world coordinates.

    Raises
    ------
    InputError
        Not a pose of one of these forms, or not finite.
    """
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    if all(hasattr(pose, n) for n in names):
        values: Any = [getattr(pose, n) for n in names]
    else:
        values = pose
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise InputError(
            "pose must be a Pose, (x, y, z, roll, pitch, yaw) in m and rad, or a 4x4 matrix"
        ) from None
    if arr.shape not in ((4, 4), (6,)):
        raise InputError(
            "pose must be a Pose, (x, y, z, roll, pitch, yaw) in m and rad or a 4x4 matrix, "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError("pose has non-finite values")
    if arr.shape == (4, 4):
        return arr
    out = np.eye(4)
    out[:3, :3] = rotation_matrix(roll=arr[3], pitch=arr[4], yaw=arr[5])
    out[:3, 3] = arr[:3]
    return out


def _camera_to_vehicle(calib: PinholeCamera) -> NDArray[np.float64]:
    return np.asarray(calib.camera_to_vehicle, dtype=float)


def pixel_to_ground(
    calib: PinholeCamera, u: ArrayLike, v: ArrayLike, ground_z: float = 0.0
) -> NDArray[np.float64]:
    """Where the left-camera rays through pixels meet the plane ``z = ground_z``.

    Parameters
    ----------
    calib : StereoCalibration
        The rig (pinhole ``fx, fy, cx, cy`` in px and the left camera's pose in the vehicle
        frame).
    u, v : array_like
        Pixel column and row, px (broadcast together; integers are pixel centres).
    ground_z : float
        Height of the ground plane in the vehicle frame, m.

    Returns
    -------
    ndarray, shape (..., 3)
        Vehicle-frame points ``(x, y, z)`` in m; NaN for rays that do not go down to the
        plane (at or above the horizon, or a camera below the plane).
    """
    uu, vv = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
    transform = _camera_to_vehicle(calib)
    rays = np.stack([(uu - calib.cx) / calib.fx, (vv - calib.cy) / calib.fy, np.ones_like(uu)], -1)
    dirs = rays @ transform[:3, :3].T
    origin = transform[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (ground_z - origin[2]) / dirs[..., 2]
    s = np.where(s > 0, s, np.nan)
    return np.asarray(origin + s[..., None] * dirs, dtype=float)


def ground_to_pixel(
    calib: PinholeCamera, points: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Project vehicle-frame points into the left image.

    Parameters
    ----------
    calib : StereoCalibration
        The rig.
    points : array_like, shape (..., 3)
        Vehicle-frame ``(x, y, z)``, m.

    Returns
    -------
    u, v : ndarray, shape (...)
        Pixel column and row, px; NaN for points behind or within 1 cm of the camera plane.
        Points may project outside the image.
    """
    p = np.asarray(points, dtype=float)
    if p.shape[-1:] != (3,):
        raise InputError(f"points must have shape (..., 3) (x, y, z in m), got {p.shape}")
    transform = _camera_to_vehicle(calib)
    cam = (p - transform[:3, 3]) @ transform[:3, :3]  # R^T (p - t), row-wise
    z = np.where(cam[..., 2] > 0.01, cam[..., 2], np.nan)
    return calib.fx * cam[..., 0] / z + calib.cx, calib.fy * cam[..., 1] / z + calib.cy


def check_angle(name: str, value: float) -> float:
    """``value`` as a float, or :class:`InputError` unless it is an angle within +-pi/2 rad."""
    raw = value
    try:
        value = float(value) if not isinstance(value, str | bytes) else math.nan
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or abs(value) > math.pi / 2:
        raise InputError(f"{name} must be an angle in rad within +-pi/2, got {raw!r:.40}")
    return value


def levelling_rotation(normal: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns ``normal`` into +z (no yaw is introduced)."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    axis = np.cross(n, [0.0, 0.0, 1.0])
    s = np.linalg.norm(axis)
    c = float(n[2])
    if s < 1e-15:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def compensate_tilt(points: np.ndarray, roll: float, pitch: float) -> np.ndarray:
    """Rotate vehicle-frame points into the gravity-aligned frame (paper Eq. 11).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in the vehicle frame.
    roll, pitch : float
        Vehicle roll and pitch in rad (e.g. from the IMU).

    Returns
    -------
    ndarray, shape (N, 3)
        ``R_v^w @ p`` for every point.
    """
    rot = rotation_matrix(check_angle("roll", roll), check_angle("pitch", pitch))
    try:
        pts = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise InputError("points must be a numeric N x 3 array of x, y, z in m") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise InputError(f"points must have shape (N, 3) (x, y, z in m), got {pts.shape}")
    return np.column_stack(transform_columns(pts, rot))
