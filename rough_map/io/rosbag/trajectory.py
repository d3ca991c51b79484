"""Timed poses from a bag: ``nav_msgs/Odometry`` and ``sensor_msgs/Imu`` topics.

Interpolated at any time within their span: linear in position, slerp in orientation.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from rough_map._files import PathLike
from rough_map.errors import FileFormatError, InputError
from rough_map.io.rosbag.messages import (
    IMU,
    ODOMETRY,
    frame_name,
    quaternion_xyzw,
    rotations,
    stamp_ns,
    valid_quaternion,
)
from rough_map.io.rosbag.reader import open_bag, topic_field, topic_messages

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)


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
        return rotations(self.quaternion).as_euler("xyz")

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
            return position, rotations(np.repeat(self.quaternion, len(at), axis=0))
        return position, Slerp(knots, rotations(self.quaternion))(at)


def read_odometry(bag: PathLike, topic: str) -> Trajectory:
    """The ``nav_msgs/Odometry`` poses of a topic as a :class:`Trajectory`.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, no message, or an unreadable bag.
    """
    with open_bag(bag) as reader:
        return read_trajectory(reader, Path(bag), topic, ODOMETRY)


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
        return read_trajectory(reader, Path(bag), topic, IMU)


def read_trajectory(reader: AnyReader, path: Path, topic: str, msgtype: str) -> Trajectory:
    """Odometry poses, or IMU orientations (``msgtype`` IMU), of a topic, sorted by stamp.

    Messages without orientation (or with a zero or non-finite quaternion or position),
    and repeated stamps, are left out with a warning.

    Raises
    ------
    FileFormatError
        Unknown topic, wrong message type, or no usable message.
    """
    samples: list[tuple[int, list[float], np.ndarray]] = []  # (ns, position, quaternion)
    frame_id = child_frame_id = ""
    skipped = 0
    for receive_ns, msg in topic_messages(reader, path, topic, msgtype):
        if msgtype == ODOMETRY:
            pose = msg.pose.pose
            position = [float(pose.position.x), float(pose.position.y), float(pose.position.z)]
            quaternion = quaternion_xyzw(pose.orientation)
            child_frame_id = msg.child_frame_id
        else:
            position = [0.0, 0.0, 0.0]
            unknown = float(msg.orientation_covariance[0]) == -1.0  # the ROS convention
            quaternion = np.zeros(4) if unknown else quaternion_xyzw(msg.orientation)
        frame_id = msg.header.frame_id
        if not valid_quaternion(quaternion) or not np.isfinite(position).all():
            skipped += 1
            continue
        samples.append((stamp_ns(msg.header, receive_ns), position, quaternion))
    if skipped:
        # a zero, non-finite or overflowing quaternion is no orientation either
        log.warning("%s: %d messages on %s without orientation skipped", path, skipped, topic)
    return timed_samples(
        samples,
        path,
        topic,
        none=f"no usable {msgtype} message on {topic!r}",
        repeated=f"messages on {topic}",
        frame_id=frame_id,
        child=child_frame_id,
    )


def timed_samples(
    samples: list[tuple[int, list[float], np.ndarray]],
    path: Path,
    topic: str,
    *,
    none: str,
    repeated: str,
    frame_id: str,
    child: str,
) -> Trajectory:
    """Samples ``(ns, position, quaternion)`` of a topic, sorted by stamp with repeated
    stamps left out (``repeated`` names them in the warning), as a :class:`Trajectory`.

    Raises
    ------
    FileFormatError
        No sample (the message ``none``).
    """
    if not samples:
        raise FileFormatError(path, none, field=topic_field(topic))
    samples.sort(key=lambda sample: sample[0])
    t_ns, keep = np.unique(np.array([s[0] for s in samples], dtype=np.int64), return_index=True)
    if len(t_ns) < len(samples):
        log.warning(
            "%s: %d %s with a repeated stamp ignored", path, len(samples) - len(t_ns), repeated
        )
    return Trajectory(
        t_ns=t_ns,
        position=np.array([samples[i][1] for i in keep], dtype=float),
        quaternion=np.array([samples[i][2] for i in keep], dtype=float),
        frame_id=frame_name(frame_id),
        child_frame_id=frame_name(child),
    )
