"""ROS bags without ROS: inspect them and import a traverse from them.

Reads ROS 1 ``.bag`` files and ROS 2 bags (a folder with ``metadata.yaml``, or a single
``.db3``/``.mcap`` file) through :class:`rosbags.highlevel.AnyReader`. Messages used:

* ``sensor_msgs/PointCloud2``: any field layout and endianness, see :func:`pointcloud2_to_xyz`;
* ``nav_msgs/Odometry``: the pose of the vehicle (``child_frame_id``) in the world
  (``header.frame_id``);
* ``sensor_msgs/Imu``: attitude from the orientation quaternion;
* ``tf2_msgs/TFMessage`` on ``/tf_static``: the mounting of the sensor on the vehicle.

Times are the message header stamps (the bag's receive time where a stamp is zero).
Angles follow :mod:`rough_map.types`: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

The same messages can be written (:func:`write_bag`, :func:`pointcloud2_message`...), and
:func:`write_example_bag` records a traverse (a simulated one, say) as a rover's logger
would: the example bag of the README and the bags of the tests are made this way.
"""

from __future__ import annotations

import logging
import struct
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rough_map._files import PathLike
from rough_map.config import SCHEMA_VERSION, FrameSpec, ImuAttitude, Pose, TraverseSpec
from rough_map.errors import FileFormatError, InputError
from rough_map.io.pointcloud import write_cloud
from rough_map.io.traverse import TRAVERSE_FILES, Traverse, save_traverse

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader
    from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"

# sensor_msgs/PointField datatypes -> numpy type codes (byte order added per message).
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a bag: name, message type (``pkg/msg/Type``) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag.

    Attributes
    ----------
    path : Path
        The bag.
    topics : tuple of TopicInfo
        Sorted by name.
    start, end : float
        Receive time of the first and last message, s since the Unix epoch.
    message_count : int
        Messages on all topics.
    """

    path: Path
    topics: tuple[TopicInfo, ...]
    start: float
    end: float
    message_count: int

    @property
    def duration(self) -> float:
        """Time from the first to the last message, s."""
        return self.end - self.start


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timed orientations, and positions, of a frame moving in another one.

    Times are kept as integer ns: a float64 of seconds since the epoch only resolves
    0.24 us, which would blur interpolation.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        Times, ns since the Unix epoch, strictly increasing.
    position : ndarray, shape (N, 3)
        Origin of ``child_frame_id`` in ``frame_id``, m (zeros for an IMU).
    quaternion : ndarray, shape (N, 4)
        Orientation of ``child_frame_id`` in ``frame_id``, scalar last (x, y, z, w) as in ROS.
    frame_id, child_frame_id : str
        The reference frame and the moving frame (for an IMU: its frame and "").
    """

    t_ns: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray
    frame_id: str
    child_frame_id: str

    @property
    def t(self) -> np.ndarray:
        """Times, s since the Unix epoch (float64, about 0.24 us resolution)."""
        return self.t_ns * 1e-9

    def rpy(self) -> np.ndarray:
        """Roll, pitch, yaw of each sample, shape (N, 3), rad."""
        return _rotations(self.quaternion).as_euler("xyz")

    def covers(self, t_ns: np.ndarray | int) -> np.ndarray:
        """Whether each time (ns since the epoch) lies within the span of the samples."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        return (t_ns >= self.t_ns[0]) & (t_ns <= self.t_ns[-1])

    def interpolate(self, t_ns: np.ndarray | int) -> tuple[np.ndarray, Rotation]:
        """Position (linear) and orientation (slerp) at times within the span.

        Parameters
        ----------
        t_ns : int or array of int
            Times, ns since the Unix epoch.

        Returns
        -------
        position : ndarray, shape (M, 3)
            m.
        rotation : scipy.spatial.transform.Rotation
            M rotations.

        Raises
        ------
        InputError
            A time is outside the span of the samples.
        """
        from scipy.spatial.transform import Slerp

        times = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if not self.covers(times).all():
            raise InputError(
                f"times outside the trajectory span [{self.t_ns[0]}, {self.t_ns[-1]}] ns"
            )
        # Seconds from the first sample: exact differences of integers, then small floats.
        knots = (self.t_ns - self.t_ns[0]) * 1e-9
        at = (times - self.t_ns[0]) * 1e-9
        position = np.column_stack([np.interp(at, knots, c) for c in self.position.T])
        if len(knots) == 1:
            return position, _rotations(np.repeat(self.quaternion, len(at), axis=0))
        return position, Slerp(knots, _rotations(self.quaternion))(at)


@dataclass(frozen=True)
class Transform:
    """One transform of a ``tf2_msgs/TFMessage``: pose of ``child`` in ``parent``.

    ``p_parent = R(quaternion) @ p_child + translation``.

    Attributes
    ----------
    t : float
        Stamp, s since the Unix epoch.
    parent, child : str
        Frame ids (leading "/" removed).
    translation : tuple of float
        m.
    quaternion : tuple of float
        x, y, z, w.
    """

    t: float
    parent: str
    child: str
    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform child -> parent (m)."""
        transform = np.eye(4)
        transform[:3, :3] = _rotations(np.asarray([self.quaternion])).as_matrix()[0]
        transform[:3, 3] = self.translation
        return transform


# --------------------------------------------------------------------------------------------
# Opening bags


def _rosbags_errors() -> tuple[type[BaseException], ...]:
    """What rosbags and its storage backends raise on a damaged or foreign bag."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    errors: list[type[BaseException]] = [AnyReaderError, Reader1Error, Reader2Error, SerdeError]
    try:  # the sqlite3 storage of rosbags goes through apsw
        import apsw

        errors.append(apsw.Error)
    except ImportError:
        pass
    return tuple(errors)


# What garbage bytes make the parsers of rosbags raise (a size read from a damaged record,
# a seek past the end, ...). Caught only around calls into rosbags, never around our code.
_CORRUPT_DATA_ERRORS = (struct.error, EOFError, OverflowError, ValueError, IndexError, KeyError)


def _read_errors() -> tuple[type[BaseException], ...]:
    return (*_rosbags_errors(), *_CORRUPT_DATA_ERRORS)


@contextmanager
def open_bag(path: PathLike) -> Iterator[AnyReader]:
    """Open a ROS 1 or ROS 2 bag for reading.

    Errors of rosbags and its storage backends inside the ``with`` block (damaged chunks
    met while iterating, undecodable messages) are raised as :class:`FileFormatError`.

    Parameters
    ----------
    path : str or PathLike
        A ``.bag`` file, a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.

    Yields
    ------
    rosbags.highlevel.AnyReader
        The open reader.

    Raises
    ------
    FileFormatError
        The bag does not exist, is empty, truncated or corrupt.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise FileFormatError(path, "no such bag")
    if path.is_file() and path.stat().st_size == 0:
        raise FileFormatError(path, "the bag is empty (0 bytes)")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except FileNotFoundError as err:
        raise FileFormatError(path, f"not a bag: {err}") from err
    except _read_errors() as err:
        raise FileFormatError(path, f"cannot read the bag (truncated or corrupt?): {err}") from err
    try:
        yield reader
    except _rosbags_errors() as err:
        raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {err}") from err
    finally:
        reader.close()


def inspect_bag(path: PathLike) -> BagInfo:
    """List the topics of a bag with their message types and counts.

    Parameters
    ----------
    path : str or PathLike
        A ``.bag`` file, a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.

    Returns
    -------
    BagInfo
        Topics (name, type, count), time span in s and message count.

    Raises
    ------
    FileFormatError
        The bag cannot be read.
    """
    path = Path(path)
    with open_bag(path) as reader:
        topics = tuple(
            TopicInfo(name, info.msgtype or "(mixed types)", info.msgcount)
            for name, info in sorted(reader.topics.items())
        )
        count = reader.message_count
        start, end = (reader.start_time, reader.end_time) if count else (0, 0)
    if count:
        end = max(start, end - 1)  # rosbags' end_time is one ns past the last message
    return BagInfo(path, topics, start * 1e-9, end * 1e-9, count)


def _connections(reader: AnyReader, path: Path, topic: str, msgtype: str) -> list[Any]:
    """The connections of ``topic``, checked to carry ``msgtype``."""
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        available = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise FileFormatError(
            path, f"no topic {topic!r} in the bag; available topics: {available}", field=topic
        )
    wrong = sorted({c.msgtype for c in found if c.msgtype != msgtype})
    if wrong:
        raise FileFormatError(
            path, f"topic {topic!r} carries {', '.join(wrong)}, expected {msgtype}", field=topic
        )
    return found


def _raw_messages(
    reader: AnyReader, path: Path, connections: list[Any]
) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages(connections)``, with damaged-bag errors as FileFormatError."""
    messages = reader.messages(connections)
    errors = _read_errors()
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except errors as err:
            raise FileFormatError(path, f"damaged bag (truncated or corrupt?): {err!r}") from err
        yield item


def _deserialize(reader: AnyReader, path: Path, connection: Any, raw: bytes) -> Any:
    try:
        return reader.deserialize(raw, connection.msgtype)
    except _read_errors() as err:
        raise FileFormatError(
            path, f"undecodable {connection.msgtype} message: {err!r}", field=connection.topic
        ) from err


def _messages(reader: AnyReader, path: Path, topic: str, msgtype: str) -> Iterator[tuple[int, Any]]:
    """(receive time in ns, deserialized message) of one topic, in receive order."""
    connections = _connections(reader, path, topic, msgtype)
    for connection, t_ns, raw in _raw_messages(reader, path, connections):
        yield t_ns, _deserialize(reader, path, connection, raw)


# --------------------------------------------------------------------------------------------
# Messages


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
        raise InputError(f"PointCloud2 without field(s) {missing}; has {sorted(fields)}")
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
    convention) or its quaternion is zero.
    """
    quaternion = _quaternion(msg.orientation)
    if float(msg.orientation_covariance[0]) == -1.0 or not np.any(quaternion):
        return None
    roll, pitch, yaw = _rotations(quaternion[None]).as_euler("xyz")[0]
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
    """The pose of a ``nav_msgs/Odometry`` message, with Euler angles in rad."""
    p = msg.pose.pose.position
    roll, pitch, yaw = _rotations(_quaternion(msg.pose.pose.orientation)[None]).as_euler("xyz")[0]
    return OdometryPose(
        t=stamp_ns(msg.header) * 1e-9,
        x=float(p.x),
        y=float(p.y),
        z=float(p.z),
        roll=float(roll),
        pitch=float(pitch),
        yaw=float(yaw),
        frame_id=_frame_id(msg.header.frame_id),
        child_frame_id=_frame_id(msg.child_frame_id),
    )


def tf_transforms(msg: Any) -> list[Transform]:
    """The transforms of a ``tf2_msgs/TFMessage``."""
    out = []
    for tf in msg.transforms:
        tr, q = tf.transform.translation, tf.transform.rotation
        out.append(
            Transform(
                t=stamp_ns(tf.header) * 1e-9,
                parent=_frame_id(tf.header.frame_id),
                child=_frame_id(tf.child_frame_id),
                translation=(float(tr.x), float(tr.y), float(tr.z)),
                quaternion=(float(q.x), float(q.y), float(q.z), float(q.w)),
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Topics


def read_odometry(bag: PathLike, topic: str) -> Trajectory:
    """The ``nav_msgs/Odometry`` poses of a topic as a :class:`Trajectory`.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, no message, or an unreadable bag.
    """
    with open_bag(bag) as reader:
        return _read_trajectory(reader, Path(bag), topic, ODOMETRY)


def read_imu(bag: PathLike, topic: str) -> Trajectory:
    """The orientations of a ``sensor_msgs/Imu`` topic as a :class:`Trajectory`.

    Messages without orientation are skipped.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, no message with an orientation, or an unreadable
        bag.
    """
    with open_bag(bag) as reader:
        return _read_trajectory(reader, Path(bag), topic, IMU)


def read_transforms(bag: PathLike, topic: str = TF_STATIC_TOPIC) -> list[Transform]:
    """All transforms published on a ``tf2_msgs/TFMessage`` topic, in bag order.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, or an unreadable bag.
    """
    with open_bag(bag) as reader:
        return [
            tf
            for _, msg in _messages(reader, Path(bag), topic, TF_MESSAGE)
            for tf in tf_transforms(msg)
        ]


def static_transform(transforms: list[Transform], source: str, target: str) -> np.ndarray | None:
    """Compose transforms into the 4x4 transform ``source`` -> ``target`` frame (m).

    The transforms form a tree (tf); the path between the two frames may go up and down it.

    Returns
    -------
    ndarray, shape (4, 4), or None
        ``p_target = T @ p_source``; identity if the frames are equal; None if not connected.
    """
    source, target = _frame_id(source), _frame_id(target)
    if source == target:
        return np.eye(4)
    edges: dict[str, list[tuple[str, np.ndarray]]] = {}
    for tf in transforms:  # later transforms of the same pair win, like in tf
        m = tf.matrix()
        edges.setdefault(tf.child, []).append((tf.parent, m))
        edges.setdefault(tf.parent, []).append((tf.child, np.linalg.inv(m)))
    # Breadth-first from the source; each node keeps source -> node.
    found = {source: np.eye(4)}
    queue = deque([source])
    while queue:
        node = queue.popleft()
        for neighbour, node_to_neighbour in reversed(edges.get(node, [])):
            if neighbour not in found:
                found[neighbour] = node_to_neighbour @ found[node]
                if neighbour == target:
                    return found[neighbour]
                queue.append(neighbour)
    return None


def _read_trajectory(reader: AnyReader, path: Path, topic: str, msgtype: str) -> Trajectory:
    """Odometry poses, or IMU orientations (``msgtype`` IMU), of a topic, sorted by stamp."""
    samples: list[tuple[int, list[float], np.ndarray]] = []  # (ns, position, quaternion)
    frame_id = child_frame_id = ""
    skipped = 0
    for t_ns, msg in _messages(reader, path, topic, msgtype):
        if msgtype == ODOMETRY:
            pose = msg.pose.pose
            position = [pose.position.x, pose.position.y, pose.position.z]
            quaternion = _quaternion(pose.orientation)
            child_frame_id = msg.child_frame_id
        else:
            position = [0.0, 0.0, 0.0]
            unknown = float(msg.orientation_covariance[0]) == -1.0  # the ROS convention
            quaternion = np.zeros(4) if unknown else _quaternion(msg.orientation)
        frame_id = msg.header.frame_id
        if not np.any(quaternion):
            skipped += 1
            continue
        samples.append((stamp_ns(msg.header, t_ns), position, quaternion))
    if skipped:
        log.warning("%s: %d messages on %s without orientation skipped", path, skipped, topic)
    if not samples:
        raise FileFormatError(path, f"no usable {msgtype} message on {topic!r}", field=topic)
    samples.sort(key=lambda sample: sample[0])
    t_ns, keep = np.unique(np.array([s[0] for s in samples], dtype=np.int64), return_index=True)
    if len(t_ns) < len(samples):
        log.warning(
            "%s: %d messages on %s with a repeated stamp ignored",
            path,
            len(samples) - len(t_ns),
            topic,
        )
    return Trajectory(
        t_ns=t_ns,
        position=np.array([samples[i][1] for i in keep], dtype=float),
        quaternion=np.array([samples[i][2] for i in keep]),
        frame_id=_frame_id(frame_id),
        child_frame_id=_frame_id(child_frame_id),
    )


def _quaternion(q: Any) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def _rotations(quaternions: np.ndarray) -> Rotation:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(quaternions)  # scalar last, like ROS


def _frame_id(name: str) -> str:
    return str(name).lstrip("/")


# --------------------------------------------------------------------------------------------
# Import


@dataclass
class _ImportCounts:
    """Why clouds were left out of an import."""

    outside: int = 0
    empty: int = 0
    unordered: int = 0
    no_imu: int = 0
    frames: dict[str, int] = field(default_factory=dict)


def import_bag(
    bag: PathLike,
    out_dir: PathLike,
    points_topic: str,
    odom_topic: str,
    imu_topic: str | None = None,
    every: int = 1,
    progress: bool = False,
) -> Traverse:
    """Turn a bag into a traverse folder: one frame per point cloud.

    For each ``PointCloud2`` message (every ``every``-th one), the odometry pose is
    interpolated at the cloud's stamp (linear in position, slerp in orientation); clouds
    outside the span of the odometry are dropped, with a warning giving their number. The
    points are written to ``clouds/<message index>.npy`` in the vehicle frame (the odometry
    ``child_frame_id``): if ``/tf_static`` links the cloud's ``frame_id`` to it, the points
    are transformed, otherwise the cloud is taken to be in the vehicle frame already. With
    ``imu_topic``, the IMU roll and pitch at the stamp (slerp) are stored too. Frame times
    count from the first cloud; its absolute stamp is kept in ``metadata.source.t0_ns``.

    Every file is written atomically and ``traverse.json`` last, so an interrupted import
    leaves no traverse file.

    Parameters
    ----------
    bag : str or PathLike
        A ROS 1 ``.bag``, a ROS 2 bag folder, or a ``.db3``/``.mcap`` file.
    out_dir : str or PathLike
        Traverse folder to create or fill; must not hold a traverse file yet.
    points_topic : str
        ``sensor_msgs/PointCloud2`` topic.
    odom_topic : str
        ``nav_msgs/Odometry`` topic: vehicle pose in the world (``crs`` is ``"local"``).
    imu_topic : str, optional
        ``sensor_msgs/Imu`` topic.
    every : int
        Keep one cloud in ``every`` (>= 1).
    progress : bool
        Show a tqdm progress bar on stderr.

    Returns
    -------
    Traverse
        The saved traverse.

    Raises
    ------
    FileFormatError
        Unreadable bag, unknown topic (the message lists the available ones), wrong message
        type, bad PointCloud2 layout, or no cloud left to import.
    InputError
        ``every < 1``, or ``out_dir`` already holds a traverse.
    """
    from tqdm import tqdm

    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    bag, out_dir = Path(bag), Path(out_dir)
    if existing := [n for n in TRAVERSE_FILES if (out_dir / n).exists()]:
        raise InputError(f"{out_dir / existing[0]} exists; import into a new folder")

    rows: list[dict[str, Any]] = []
    counts = _ImportCounts()
    with open_bag(bag) as reader:
        cloud_connections = _connections(reader, bag, points_topic, POINTCLOUD2)
        odometry = _read_trajectory(reader, bag, odom_topic, ODOMETRY)
        imu = _read_trajectory(reader, bag, imu_topic, IMU) if imu_topic else None
        transforms = _static_transforms(reader, bag)
        to_vehicle: dict[str, np.ndarray | None] = {}

        clouds_dir = out_dir / "clouds"
        clouds_dir.mkdir(parents=True, exist_ok=True)
        total = sum(c.msgcount for c in cloud_connections)
        last_ns = -1
        with tqdm(total=total, disable=not progress, unit="cloud", desc="import") as bar:
            for index, (connection, t_ns, raw) in enumerate(
                _raw_messages(reader, bag, cloud_connections)
            ):
                bar.update()
                if index % every:
                    continue
                msg = _deserialize(reader, bag, connection, raw)
                ns = stamp_ns(msg.header, t_ns)
                if not odometry.covers(ns):
                    counts.outside += 1
                    continue
                if ns <= last_ns:
                    counts.unordered += 1
                    continue
                try:
                    xyz = pointcloud2_to_xyz(msg)
                except InputError as err:
                    raise FileFormatError(bag, f"message {index}: {err}", points_topic) from err
                if len(xyz) == 0:
                    counts.empty += 1
                    continue
                cloud_frame = _frame_id(msg.header.frame_id)
                if cloud_frame not in to_vehicle:
                    to_vehicle[cloud_frame] = _sensor_to_vehicle(
                        transforms, cloud_frame, odometry.child_frame_id
                    )
                transform = to_vehicle[cloud_frame]
                if transform is not None:
                    xyz = xyz @ transform[:3, :3].T + transform[:3, 3]
                counts.frames[cloud_frame] = counts.frames.get(cloud_frame, 0) + 1
                relative = f"clouds/{index:06d}.npy"
                write_cloud(out_dir / relative, xyz)
                rows.append({"ns": ns, "cloud": relative})
                last_ns = ns

    if not rows:
        raise FileFormatError(
            bag,
            f"no point cloud imported from {points_topic!r}: {counts.outside} outside the "
            f"odometry time span, {counts.empty} without a finite point",
            field=points_topic,
        )
    spec = _traverse_spec(
        bag, rows, odometry, imu, counts, points_topic, odom_topic, imu_topic, every
    )
    _log_counts(bag, counts, len(rows), odometry)
    save_traverse(spec, out_dir)
    return Traverse.from_spec(spec, out_dir)


def _static_transforms(reader: AnyReader, path: Path) -> list[Transform]:
    topics = {c.topic: c.msgtype for c in reader.connections}
    if topics.get(TF_STATIC_TOPIC) != TF_MESSAGE:
        return []
    return [
        tf
        for _, msg in _messages(reader, path, TF_STATIC_TOPIC, TF_MESSAGE)
        for tf in tf_transforms(msg)
    ]


def _sensor_to_vehicle(
    transforms: list[Transform], cloud_frame: str, vehicle_frame: str
) -> np.ndarray | None:
    if not cloud_frame or not vehicle_frame or cloud_frame == vehicle_frame:
        return None
    transform = static_transform(transforms, cloud_frame, vehicle_frame)
    if transform is None:
        log.warning(
            "no %s transform from %r to the vehicle frame %r: clouds taken as in the vehicle frame",
            TF_STATIC_TOPIC,
            cloud_frame,
            vehicle_frame,
        )
    else:
        log.info("clouds in %r moved to %r with %s", cloud_frame, vehicle_frame, TF_STATIC_TOPIC)
    return transform


def _traverse_spec(
    bag: Path,
    rows: list[dict[str, Any]],
    odometry: Trajectory,
    imu: Trajectory | None,
    counts: _ImportCounts,
    points_topic: str,
    odom_topic: str,
    imu_topic: str | None,
    every: int,
) -> TraverseSpec:
    ns = np.array([r["ns"] for r in rows], dtype=np.int64)
    position, rotation = odometry.interpolate(ns)
    rpy = rotation.as_euler("xyz")
    attitude: list[ImuAttitude | None] = [None] * len(rows)
    if imu is not None:
        inside = imu.covers(ns)
        counts.no_imu = int((~inside).sum())
        if inside.any():
            _, imu_rotation = imu.interpolate(ns[inside])
            imu_rpy_ = imu_rotation.as_euler("xyz")
            for k, i in enumerate(np.flatnonzero(inside)):
                attitude[i] = ImuAttitude(roll=imu_rpy_[k, 0], pitch=imu_rpy_[k, 1])
    frames = [
        FrameSpec(
            t=(int(ns[i]) - int(ns[0])) * 1e-9,
            pose=Pose(
                x=position[i, 0],
                y=position[i, 1],
                z=position[i, 2],
                roll=rpy[i, 0],
                pitch=rpy[i, 1],
                yaw=rpy[i, 2],
            ),
            cloud=row["cloud"],
            imu=attitude[i],
        )
        for i, row in enumerate(rows)
    ]
    source = {
        "bag": bag.name,
        "points_topic": points_topic,
        "odom_topic": odom_topic,
        "imu_topic": imu_topic,
        "every": every,
        "t0_ns": int(ns[0]),
        "world_frame": odometry.frame_id,
        "vehicle_frame": odometry.child_frame_id,
        "cloud_frames": sorted(counts.frames),
    }
    return TraverseSpec(
        schema_version=SCHEMA_VERSION,
        name=bag.stem if bag.is_file() else bag.name,
        crs="local",
        metadata={"source": source},
        frames=frames,
    )


def _log_counts(bag: Path, counts: _ImportCounts, kept: int, odometry: Trajectory) -> None:
    if counts.outside:
        log.warning(
            "%s: %d clouds outside the odometry time span [%.3f, %.3f] s dropped",
            bag,
            counts.outside,
            odometry.t[0],
            odometry.t[-1],
        )
    if counts.unordered:
        log.warning(
            "%s: %d clouds with a stamp not after the previous one dropped", bag, counts.unordered
        )
    if counts.empty:
        log.warning("%s: %d clouds without a finite point dropped", bag, counts.empty)
    if counts.no_imu:
        log.warning(
            "%s: %d frames outside the IMU time span have no imu attitude", bag, counts.no_imu
        )
    log.info("%s: imported %d frames", bag, kept)


# --------------------------------------------------------------------------------------------
# Writing bags: the inverse of the readers above, for examples and tests

#: Storage formats :func:`write_bag` writes: ROS 2 MCAP, ROS 2 sqlite3, ROS 1 ``.bag``.
BAG_STORAGES = ("mcap", "sqlite3", "ros1")

#: Stamp of the first message of :func:`write_example_bag`, ns since the Unix epoch.
EXAMPLE_T0_NS = 1_700_000_000 * 10**9

#: Mount of the lidar of :func:`write_example_bag` on ``base_link``: x, y, z in m, then
#: roll, pitch, yaw in rad (looking forward and 0.5 rad down, 1.1 m above the ground).
EXAMPLE_LIDAR_MOUNT = ((0.2, 0.0, 1.1), (0.0, 0.5, 0.0))


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
    return store.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quaternion_message(store: Any, rpy: Any) -> Any:
    from scipy.spatial.transform import Rotation

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
    messages: list[tuple[str, str, int, Any]],
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


def write_example_bag(
    traverse: Traverse | PathLike,
    out: PathLike,
    *,
    storage: str = "mcap",
    every: int = 1,
    progress: bool = False,
) -> Path:
    """A bag of a traverse as a rover's logger would record it, e.g. of a simulated one.

    Topics: ``/points`` (``sensor_msgs/PointCloud2``, float32 x, y, z in the ``lidar``
    frame), ``/odom`` (``nav_msgs/Odometry``, ``base_link`` in ``odom``), ``/imu``
    (``sensor_msgs/Imu``, roll and pitch of the frame's IMU, yaw of its pose; frames with an
    IMU only) and ``/tf_static`` (the lidar mount :data:`EXAMPLE_LIDAR_MOUNT`), one message
    of each per frame at ``EXAMPLE_T0_NS`` plus the frame time. :func:`import_bag` with
    ``points_topic="/points"``, ``odom_topic="/odom"``, ``imu_topic="/imu"`` gives the
    traverse back (clouds to float32 precision, no labels or images).

    Parameters
    ----------
    traverse : Traverse or path
        A traverse with a cloud in every frame used.
    out : str or PathLike
        A new bag folder (ROS 2), or ``.bag`` file (``storage="ros1"``).
    storage : {"mcap", "sqlite3", "ros1"}
        Format of the bag.
    every : int
        Write every ``every``-th frame (>= 1).
    progress : bool
        Show a tqdm progress bar on stderr.

    Returns
    -------
    Path
        The bag written.

    Raises
    ------
    InputError
        ``every < 1``, unknown storage, or ``out`` exists.
    SchemaError
        A frame has no cloud, or its file is missing.
    """
    from scipy.spatial.transform import Rotation
    from tqdm import tqdm

    from rough_map.io.traverse import load_traverse

    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    if storage not in BAG_STORAGES:  # before reading every cloud
        raise InputError(f"storage must be one of {', '.join(BAG_STORAGES)}, got {storage!r}")
    store = ros_typestore(storage == "ros1")
    mount_xyz, mount_rpy = EXAMPLE_LIDAR_MOUNT
    to_lidar = Rotation.from_euler("xyz", mount_rpy).as_matrix()  # lidar -> base_link
    messages: list[tuple[str, str, int, Any]] = [
        (
            TF_STATIC_TOPIC,
            TF_MESSAGE,
            EXAMPLE_T0_NS,
            tf_message(store, EXAMPLE_T0_NS, "base_link", "lidar", mount_xyz, mount_rpy),
        )
    ]
    indices = range(0, len(traverse), every)
    for i in tqdm(indices, desc="bag", unit="frame", disable=not progress):
        frame = traverse.frames[i]
        ns = EXAMPLE_T0_NS + round(frame.t * 1e9)
        p = frame.pose
        messages.append(
            (
                "/odom",
                ODOMETRY,
                ns,
                odometry_message(store, ns, (p.x, p.y, p.z), (p.roll, p.pitch, p.yaw)),
            )
        )
        if frame.imu is not None:
            rpy = (frame.imu.roll, frame.imu.pitch, p.yaw)
            messages.append(("/imu", IMU, ns, imu_message(store, ns, rpy)))
        points = traverse.load_cloud(i)  # vehicle frame
        in_lidar = (points - np.asarray(mount_xyz)) @ to_lidar  # = to_lidar.T @ (p - t)
        messages.append(
            ("/points", POINTCLOUD2, ns, pointcloud2_message(store, in_lidar, ns, "lidar"))
        )
    bag = write_bag(out, messages, storage, store)
    log.info("%s: %d frames of %s", bag, len(indices), traverse.name)
    return bag
