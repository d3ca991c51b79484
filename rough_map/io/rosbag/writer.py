"""Writing bags: the inverse of the readers, for examples and tests.

Messages are built with the classes of a rosbags typestore (:func:`ros_typestore`) and
written with the rosbags writers (:func:`write_bag`) as ROS 2 MCAP, ROS 2 sqlite3 or ROS 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from rough_map._files import PathLike
from rough_map.errors import InputError
from rough_map.io.rosbag.messages import IMU, ODOMETRY, POINTCLOUD2, TF_MESSAGE

Message = tuple[str, str, int, Any]
"""A message to write: topic, type (``pkg/msg/Type``), receive time in ns since the epoch,
and the message built with a typestore's classes."""

#: Storage formats :func:`write_bag` writes: ROS 2 MCAP, ROS 2 sqlite3, ROS 1 ``.bag``.
BAG_STORAGES = ("mcap", "sqlite3", "ros1")


def ros_typestore(ros1: bool = False) -> Any:
    """The message types of ROS 2 Humble, or of ROS 1 Noetic with ``tf2_msgs/TFMessage``.

    Messages are built with the typestore's classes (``store.types["nav_msgs/msg/Odometry"]``)
    and serialised with it: ``serialize_cdr`` (ROS 2) or ``serialize_ros1``.
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if TF_MESSAGE not in store.types:  # not in the bundled ROS 1 store
        store.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE)
        )
    return store


@dataclass(frozen=True)
class PointCloud2Layout:
    """How :func:`pointcloud2_message` lays x, y, z out in ``PointCloud2`` bytes.

    Attributes
    ----------
    code : str
        numpy type of x, y and z ("f4" or "f8").
    datatype : int
        Their ``sensor_msgs/PointField`` datatype (7 FLOAT32, 8 FLOAT64).
    bigendian : bool
        Byte order of the data.
    point_step : int
        Bytes per point.
    offsets : tuple of int
        Byte offsets of x, y and z in a point.
    extra : tuple of (name, offset, numpy code, datatype)
        Other fields (intensity, ring, time...), filled with ``k % 7`` for point k.
    height : int
        Rows of an organised cloud (1: unorganised); the points fill the rows in order.
    row_pad : int
        Bytes of padding after each row (``row_step = width * point_step + row_pad``).
    """

    code: str = "f4"
    datatype: int = 7
    bigendian: bool = False
    point_step: int = 12
    offsets: tuple[int, int, int] = (0, 4, 8)
    extra: tuple[tuple[str, int, str, int], ...] = ()
    height: int = 1
    row_pad: int = 0


def header_message(store: Any, ns: int, frame_id: str) -> Any:
    """A ``std_msgs/Header`` stamped ``ns`` (ns since the epoch) in ``frame_id``."""
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    header_type = types["std_msgs/msg/Header"]
    if "seq" in header_type.__dataclass_fields__:  # ROS 1
        return header_type(seq=0, stamp=stamp, frame_id=frame_id)
    return header_type(stamp=stamp, frame_id=frame_id)


def pointcloud2_message(
    store: Any,
    xyz: np.ndarray,
    ns: int,
    frame_id: str,
    layout: PointCloud2Layout = PointCloud2Layout(),
) -> Any:
    """A ``sensor_msgs/PointCloud2`` holding the points ``xyz`` (N, 3) in m (NaN allowed).

    The inverse of :func:`pointcloud2_to_xyz` (which drops the non-finite points).

    Raises
    ------
    InputError
        ``xyz`` is not (N, 3), or N is not a multiple of ``layout.height``.
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"xyz must be (N, 3), got shape {xyz.shape}")
    n = len(xyz)
    if n % layout.height:
        raise InputError(f"{n} points do not fill {layout.height} rows")
    types = store.types
    order = ">" if layout.bigendian else "<"
    names = ["x", "y", "z"] + [e[0] for e in layout.extra]
    formats = [order + layout.code] * 3 + [order + e[2] for e in layout.extra]
    offsets = list(layout.offsets) + [e[1] for e in layout.extra]
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": layout.point_step}
    )
    width = n // layout.height
    points = np.zeros(n, dtype=dtype)
    for i, c in enumerate("xyz"):
        points[c] = xyz[:, i]
    for name, *_ in layout.extra:
        points[name] = np.arange(n) % 7
    rows = points.tobytes()
    row_bytes = width * layout.point_step
    data = b"".join(
        rows[r * row_bytes : (r + 1) * row_bytes] + b"\xab" * layout.row_pad
        for r in range(layout.height)
    )
    field_type = types["sensor_msgs/msg/PointField"]
    datatypes = [layout.datatype] * 3 + [e[3] for e in layout.extra]
    fields = [
        field_type(name=nm, offset=off, datatype=dt, count=1)
        for nm, off, dt in zip(names, offsets, datatypes, strict=True)
    ]
    return types[POINTCLOUD2](
        header=header_message(store, ns, frame_id),
        height=layout.height,
        width=width,
        fields=fields,
        is_bigendian=layout.bigendian,
        point_step=layout.point_step,
        row_step=row_bytes + layout.row_pad,
        data=np.frombuffer(data, dtype=np.uint8),
        is_dense=not np.isnan(xyz).any(),
    )


def _vector3(store: Any, v: Any) -> Any:
    """A ``geometry_msgs/Vector3`` of the three numbers ``v``."""
    return store.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quaternion_message(store: Any, rpy: Any) -> Any:
    """A ``geometry_msgs/Quaternion`` of roll, pitch, yaw ``rpy`` (rad)."""
    x, y, z, w = (float(c) for c in Rotation.from_euler("xyz", rpy).as_quat())
    return store.types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def odometry_message(
    store: Any,
    ns: int,
    xyz: Any,
    rpy: Any,
    frame_id: str = "odom",
    child_frame_id: str = "base_link",
) -> Any:
    """A ``nav_msgs/Odometry``: ``child_frame_id`` at ``xyz`` (m) with roll, pitch, yaw
    ``rpy`` (rad) in ``frame_id``; zero twist and covariances."""
    t = store.types
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
        orientation=_quaternion_message(store, rpy),
    )
    twist = t["geometry_msgs/msg/Twist"](
        linear=_vector3(store, [0, 0, 0]), angular=_vector3(store, [0, 0, 0])
    )
    return t[ODOMETRY](
        header=header_message(store, ns, frame_id),
        child_frame_id=child_frame_id,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def imu_message(
    store: Any, ns: int, rpy: Any, *, known: bool = True, frame_id: str = "imu_link"
) -> Any:
    """A ``sensor_msgs/Imu`` with orientation ``rpy`` (rad), or with an orientation marked
    unknown (covariance[0] = -1) when not ``known``; gravity along +z (m/s²)."""
    covariance = np.zeros(9)
    if not known:
        covariance[0] = -1.0
    return store.types[IMU](
        header=header_message(store, ns, frame_id),
        orientation=_quaternion_message(store, rpy),
        orientation_covariance=covariance,
        angular_velocity=_vector3(store, [0, 0, 0]),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vector3(store, [0, 0, 9.81]),
        linear_acceleration_covariance=np.zeros(9),
    )


def tf_message(store: Any, ns: int, parent: str, child: str, xyz: Any, rpy: Any) -> Any:
    """A ``tf2_msgs/TFMessage`` with one transform: ``child`` at ``xyz`` (m) with roll,
    pitch, yaw ``rpy`` (rad) in ``parent``."""
    t = store.types
    transform = t["geometry_msgs/msg/TransformStamped"](
        header=header_message(store, ns, parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=_vector3(store, xyz), rotation=_quaternion_message(store, rpy)
        ),
    )
    return t[TF_MESSAGE](transforms=[transform])


def write_bag(
    path: PathLike,
    messages: list[Message],
    storage: str = "mcap",
    store: Any = None,
) -> Path:
    """Write ``(topic, msgtype, ns, message)`` tuples to a bag with the rosbags writers.

    Parameters
    ----------
    path : str or PathLike
        A new ROS 2 bag folder; for ``storage="ros1"`` the ``.bag`` file (the suffix is
        set to ``.bag``).
    messages : list of (str, str, int, message)
        Topic, message type (``pkg/msg/Type``), receive time in ns since the epoch, and the
        message built with ``store``'s classes; written in the order given.
    storage : {"mcap", "sqlite3", "ros1"}
        Format of the bag.
    store : Typestore, optional
        The typestore of the messages (default :func:`ros_typestore` for ``storage``).

    Returns
    -------
    Path
        The bag written.

    Raises
    ------
    InputError
        Unknown storage, or the bag exists already.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    if storage not in BAG_STORAGES:
        raise InputError(f"storage must be one of {', '.join(BAG_STORAGES)}, got {storage!r}")
    ros1 = storage == "ros1"
    store = store or ros_typestore(ros1)
    path = Path(path)
    if ros1:
        path = path.with_suffix(".bag")
    if path.exists():
        raise InputError(f"{path} exists; write the bag to a new path")
    if ros1:
        writer: Any = Writer1(path)
    else:
        plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, ns, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            raw = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            writer.write(connections[topic], ns, raw)
    return path
