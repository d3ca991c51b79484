"""The example bag: a traverse recorded as a rover's logger would record it."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import PathLike
from rough_map.errors import InputError
from rough_map.geometry import rotation_matrix
from rough_map.io.rosbag.messages import (
    IMU,
    ODOMETRY,
    POINTCLOUD2,
    TF_MESSAGE,
    TF_STATIC_TOPIC,
)
from rough_map.io.rosbag.writer import (
    BAG_STORAGES,
    Message,
    imu_message,
    odometry_message,
    pointcloud2_message,
    ros_typestore,
    tf_message,
    write_bag,
)
from rough_map.io.traverse import Traverse, load_traverse

log = logging.getLogger(__name__)

#: Stamp of the first message of :func:`write_example_bag`, ns since the Unix epoch.
EXAMPLE_T0_NS = 1_700_000_000 * 10**9

#: Mount of the lidar of :func:`write_example_bag` on ``base_link``: x, y, z in m, then
#: roll, pitch, yaw in rad (looking forward and 0.5 rad down, 1.1 m above the ground).
EXAMPLE_LIDAR_MOUNT = ((0.2, 0.0, 1.1), (0.0, 0.5, 0.0))


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
    ``points_topic="/points"``, ``pose_topic="/odom"``, ``imu_topic="/imu"`` gives the
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
    from tqdm import tqdm

    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    if storage not in BAG_STORAGES:  # before reading every cloud
        raise InputError(f"storage must be one of {', '.join(BAG_STORAGES)}, got {storage!r}")
    store = ros_typestore(storage == "ros1")
    mount_xyz, mount_rpy = EXAMPLE_LIDAR_MOUNT
    messages: list[Message] = [
        (
            TF_STATIC_TOPIC,
            TF_MESSAGE,
            EXAMPLE_T0_NS,
            tf_message(store, EXAMPLE_T0_NS, "base_link", "lidar", mount_xyz, mount_rpy),
        )
    ]
    indices = range(0, len(traverse), every)
    for i in tqdm(indices, desc="bag", unit="frame", disable=not progress):
        messages += _frame_messages(store, traverse, i)
    bag = write_bag(out, messages, storage, store)
    log.info("%s: %d frames of %s", bag, len(indices), traverse.name)
    return bag


def _frame_messages(store: Any, traverse: Traverse, i: int) -> list[Message]:
    """Odometry, IMU (if the frame has one) and lidar cloud of frame ``i``."""
    mount_xyz, mount_rpy = EXAMPLE_LIDAR_MOUNT
    to_lidar = rotation_matrix(*mount_rpy)  # lidar -> base_link
    frame = traverse.frames[i]
    ns = EXAMPLE_T0_NS + round(frame.t * 1e9)
    p = frame.pose
    odometry = odometry_message(store, ns, (p.x, p.y, p.z), (p.roll, p.pitch, p.yaw))
    messages: list[Message] = [("/odom", ODOMETRY, ns, odometry)]
    if frame.imu is not None:
        rpy = (frame.imu.roll, frame.imu.pitch, p.yaw)
        messages.append(("/imu", IMU, ns, imu_message(store, ns, rpy)))
    points = traverse.load_cloud(i)  # vehicle frame
    in_lidar = (points - np.asarray(mount_xyz)) @ to_lidar  # = to_lidar.T @ (p - t)
    messages.append(("/points", POINTCLOUD2, ns, pointcloud2_message(store, in_lidar, ns, "lidar")))
    return messages
