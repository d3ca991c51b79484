"""ROS messages decoded into numbers: PointCloud2 points, Odometry poses, IMU attitude.

Message type names (``pkg/msg/Type``) and the small conversions shared by the readers and
writers of :mod:`rough_map.io.rosbag`. Angles follow :mod:`rough_map.types`:
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; quaternions are scalar last (x, y, z, w) as in ROS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from rough_map.errors import InputError

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"

# sensor_msgs/PointField datatypes -> numpy type codes (byte order added per message).
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def stamp_ns(header: Any, fallback_ns: int = 0) -> int:
    """Header stamp in ns since the epoch; ``fallback_ns`` where the stamp is zero."""
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns else fallback_ns


def pointcloud2_to_xyz(msg: Any) -> np.ndarray:
    """x, y, z of a ``sensor_msgs/PointCloud2``, with any layout.

    Field offsets and types come from ``msg.fields`` (any of the PointField types; extra
    fields and padding are skipped), byte order from ``is_bigendian``; organised clouds
    (``height > 1``) and rows padded beyond ``width * point_step`` are handled. Points with
    a NaN or infinite coordinate (organised clouds mark missing returns so) are dropped.

    Parameters
    ----------
    msg : sensor_msgs/PointCloud2
        A deserialized message (rosbags), or any object with the same attributes.

    Returns
    -------
    ndarray, shape (N, 3), float64
        x, y, z in m in the frame ``msg.header.frame_id``; N may be 0.

    Raises
    ------
    InputError
        No x, y or z field, an unknown datatype, or a layout inconsistent with the data size.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        names = sorted(str(name) for name in fields)
        has = repr(names[:6])[:-1] + (", ...]" if len(names) > 6 else "]")
        raise InputError(f"PointCloud2 without field(s) {missing}; has {has[:80]}")
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for c in "xyz":
        code = _POINTFIELD_TYPES.get(int(fields[c].datatype))
        if code is None:
            raise InputError(f"PointCloud2 field {c!r} has unknown datatype {fields[c].datatype}")
        formats.append(order + code)
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height * width == 0:
        return np.empty((0, 3))
    offsets = [int(fields[c].offset) for c in "xyz"]
    for c, offset, fmt in zip("xyz", offsets, formats, strict=True):
        if offset + np.dtype(fmt).itemsize > point_step:
            raise InputError(f"PointCloud2 field {c!r} at offset {offset} overruns point_step")
    if row_step < width * point_step:
        raise InputError(f"PointCloud2 row_step {row_step} < width {width} * point_step")
    raw = msg.data
    if isinstance(raw, bytes | bytearray | memoryview):
        data = np.frombuffer(raw, dtype=np.uint8)
    else:  # rosbags gives a uint8 array
        data = np.ascontiguousarray(raw, dtype=np.uint8)
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        raise InputError(
            f"PointCloud2 data has {data.size} B, its layout ({height} x {width} points, "
            f"row_step {row_step}) needs {needed} B"
        )
    dtype = np.dtype(
        {"names": list("xyz"), "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    # A strided view over the raw bytes: rows row_step apart, points point_step apart.
    points = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    xyz = np.stack([points[c].astype(np.float64).ravel() for c in "xyz"], axis=1)
    return xyz[np.isfinite(xyz).all(axis=1)]


def imu_rpy(msg: Any) -> tuple[float, float, float] | None:
    """Roll, pitch, yaw (rad) of a ``sensor_msgs/Imu``; None if it has no orientation.

    A message has no orientation when ``orientation_covariance[0] == -1`` (the ROS
    convention) or its quaternion is zero or not finite.
    """
    quaternion = quaternion_xyzw(msg.orientation)
    if float(msg.orientation_covariance[0]) == -1.0 or not valid_quaternion(quaternion):
        return None
    roll, pitch, yaw = rotations(quaternion[None]).as_euler("xyz")[0]
    return float(roll), float(pitch), float(yaw)


@dataclass(frozen=True)
class OdometryPose:
    """Pose of a ``nav_msgs/Odometry``: ``child_frame_id`` in ``frame_id``.

    Attributes
    ----------
    t : float
        Header stamp, s since the Unix epoch.
    x, y, z : float
        m.
    roll, pitch, yaw : float
        rad.
    frame_id, child_frame_id : str
        World and vehicle frame ids.
    """

    t: float
    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float
    frame_id: str
    child_frame_id: str


def odometry_pose(msg: Any) -> OdometryPose:
    """The pose of a ``nav_msgs/Odometry`` message, with Euler angles in rad.

    Raises
    ------
    InputError
        The orientation quaternion is zero or not finite.
    """
    p = msg.pose.pose.position
    orientation = quaternion_xyzw(msg.pose.pose.orientation)
    if not valid_quaternion(orientation):
        raise InputError(f"Odometry orientation {orientation.tolist()} is not a rotation")
    roll, pitch, yaw = rotations(orientation[None]).as_euler("xyz")[0]
    return OdometryPose(
        t=stamp_ns(msg.header) * 1e-9,
        x=float(p.x),
        y=float(p.y),
        z=float(p.z),
        roll=float(roll),
        pitch=float(pitch),
        yaw=float(yaw),
        frame_id=frame_name(msg.header.frame_id),
        child_frame_id=frame_name(msg.child_frame_id),
    )


def quaternion_xyzw(q: Any) -> np.ndarray:
    """The (x, y, z, w) of a ``geometry_msgs/Quaternion`` as a float array."""
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def valid_quaternion(q: np.ndarray) -> bool:
    """Whether the (x, y, z, w) ``q`` is a rotation: finite, of a norm neither 0 nor
    overflowing (scipy normalises it)."""
    with np.errstate(over="ignore", invalid="ignore"):
        norm = float(np.linalg.norm(q))
    return bool(np.isfinite(q).all()) and np.isfinite(norm) and norm > 1e-9


def rotations(quaternions: np.ndarray) -> Rotation:
    """Rotations of quaternions (N, 4), scalar last like ROS."""
    return Rotation.from_quat(quaternions)


def frame_name(name: str) -> str:
    """A tf frame id without its leading "/" (ROS 1 style ``/base_link`` = ``base_link``)."""
    return str(name).lstrip("/")
