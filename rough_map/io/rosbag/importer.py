"""A traverse folder from a bag: one frame per ``sensor_msgs/PointCloud2`` message."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import ValidationError

from rough_map._files import PathLike
from rough_map.config import SCHEMA_VERSION, Crs, FrameSpec, ImuAttitude, Pose, TraverseSpec
from rough_map.errors import FileFormatError, InputError
from rough_map.io.pointcloud import write_cloud
from rough_map.io.rosbag.messages import (
    IMU,
    POINTCLOUD2,
    TF_STATIC_TOPIC,
    frame_name,
    pointcloud2_to_xyz,
    stamp_ns,
)
from rough_map.io.rosbag.poses import metric_crs, vehicle_trajectory
from rough_map.io.rosbag.reader import deserialize, open_bag, raw_messages, topic_connections
from rough_map.io.rosbag.tf import Transform, static_transform, static_transforms
from rough_map.io.rosbag.trajectory import Trajectory, read_trajectory
from rough_map.io.traverse import TRAVERSE_FILES, Traverse, save_traverse

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)


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
    pose_topic: str,
    imu_topic: str | None = None,
    every: int = 1,
    progress: bool = False,
    *,
    crs: Crs | str | dict[str, Any] | None = None,
    vehicle_frame: str = "base_link",
) -> Traverse:
    """Turn a bag into a traverse folder: one frame per point cloud.

    For each ``PointCloud2`` message (every ``every``-th one), the vehicle pose is
    interpolated at the cloud's stamp (linear in position, slerp in orientation); clouds
    outside the span of the poses are dropped, with a warning giving their number. The
    poses come from ``pose_topic``: odometry, a (covariance) pose, the /tf tree or GNSS
    fixes (:func:`rough_map.io.rosbag.poses.vehicle_trajectory`). The points are written to
    ``clouds/<message index>.npy`` in the vehicle frame (the odometry ``child_frame_id``,
    else ``vehicle_frame``): if ``/tf_static`` links the cloud's ``frame_id`` to it, the
    points are transformed, otherwise the cloud is taken to be in the vehicle frame already. With
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
    pose_topic : str
        The vehicle's poses in the world: a ``nav_msgs/Odometry``,
        ``geometry_msgs/PoseStamped`` or ``PoseWithCovarianceStamped``, ``tf2_msgs/TFMessage``
        (``/tf``) or ``sensor_msgs/NavSatFix`` topic.
    imu_topic : str, optional
        ``sensor_msgs/Imu`` topic.
    every : int
        Keep one cloud in ``every`` (>= 1).
    progress : bool
        Show a tqdm progress bar on stderr.
    crs : Crs, str or dict, optional
        The CRS of the poses' world frame: ``"EPSG:<code>"`` (projected, metres), or
        ``{"code": "local", "origin": {"lat": .., "lon": .., "alt": ..}}`` for a local frame
        with a known geodetic origin (default ``local``; for GNSS fixes, a local frame at
        the first fix).
    vehicle_frame : str
        The vehicle's frame, for poses that do not name it (PoseStamped, NavSatFix) and the
        frame whose pose /tf gives.

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
    if every < 1:
        raise InputError(f"every must be >= 1, got {every}")
    world = Crs.from_any(crs or "local")
    metric_crs(world)
    bag, out_dir = Path(bag), Path(out_dir)
    if existing := [n for n in TRAVERSE_FILES if (out_dir / n).exists()]:
        raise InputError(f"{out_dir / existing[0]} exists; import into a new folder")

    with open_bag(bag) as reader:
        cloud_connections = topic_connections(reader, bag, points_topic, POINTCLOUD2)
        odometry, world_crs = vehicle_trajectory(
            reader, bag, pose_topic, crs=world, vehicle_frame=vehicle_frame
        )
        imu = read_trajectory(reader, bag, imu_topic, IMU) if imu_topic else None
        clouds = _CloudImport(bag, out_dir, points_topic, odometry, static_transforms(reader, bag))
        (out_dir / "clouds").mkdir(parents=True, exist_ok=True)
        _import_clouds(reader, clouds, cloud_connections, every, progress)

    counts = clouds.counts
    if not clouds.rows:
        raise FileFormatError(
            bag,
            f"no point cloud imported from {points_topic!r}: {counts.outside} outside the "
            f"time span of the poses on {pose_topic!r}, {counts.empty} without a finite point",
            field=points_topic,
        )
    try:
        spec = _traverse_spec(
            bag, clouds.rows, odometry, imu, counts, points_topic, pose_topic, imu_topic, every
        )
        spec = spec.model_copy(update={"crs": world_crs})
    except ValidationError as err:  # e.g. stamps ns apart but 1e18 ns from the first cloud
        first = err.errors()[0]
        raise FileFormatError(
            bag,
            f"the clouds do not make a valid traverse: {str(first['msg'])[:80]}",
            field=points_topic,
        ) from None
    _log_counts(bag, counts, len(clouds.rows), odometry)
    save_traverse(spec, out_dir)
    return Traverse.from_spec(spec, out_dir)


@dataclass
class _CloudImport:
    """An import under way: where the clouds go, how they reach the vehicle frame, what is
    written (``rows``: stamp in ns and relative path of each cloud) and what was left out."""

    bag: Path
    out_dir: Path
    points_topic: str
    odometry: Trajectory
    transforms: list[Transform]
    counts: _ImportCounts = field(default_factory=_ImportCounts)
    to_vehicle: dict[str, np.ndarray | None] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)
    last_ns: int = -(2**63)  # stamps before 1970 are int64 too

    def add(self, index: int, msg: Any, t_ns: int) -> None:
        """Write the cloud of ``PointCloud2`` message ``index`` (receive time ``t_ns``), in
        the vehicle frame, unless it is outside the odometry, out of order or empty."""
        ns = stamp_ns(msg.header, t_ns)
        if not self.odometry.covers(ns):
            self.counts.outside += 1
            return
        if ns <= self.last_ns:
            self.counts.unordered += 1
            return
        try:
            xyz = pointcloud2_to_xyz(msg)
        except InputError as err:
            raise FileFormatError(self.bag, f"message {index}: {err}", self.points_topic) from err
        if len(xyz) == 0:
            self.counts.empty += 1
            return
        cloud_frame = frame_name(msg.header.frame_id)
        if cloud_frame not in self.to_vehicle:
            self.to_vehicle[cloud_frame] = _sensor_to_vehicle(
                self.transforms, cloud_frame, self.odometry.child_frame_id
            )
        transform = self.to_vehicle[cloud_frame]
        if transform is not None:
            xyz = xyz @ transform[:3, :3].T + transform[:3, 3]
        self.counts.frames[cloud_frame] = self.counts.frames.get(cloud_frame, 0) + 1
        relative = f"clouds/{index:06d}.npy"
        write_cloud(self.out_dir / relative, xyz)
        self.rows.append({"ns": ns, "cloud": relative})
        self.last_ns = ns


def _import_clouds(
    reader: AnyReader, clouds: _CloudImport, connections: list[Any], every: int, progress: bool
) -> None:
    """Feed every ``every``-th message of the cloud connections to ``clouds``."""
    from tqdm import tqdm

    total = sum(c.msgcount for c in connections)
    with tqdm(total=total, disable=not progress, unit="cloud", desc="import") as bar:
        for index, (connection, t_ns, raw) in enumerate(
            raw_messages(reader, clouds.bag, connections)
        ):
            bar.update()
            if index % every:
                continue
            clouds.add(index, deserialize(reader, clouds.bag, connection, raw), t_ns)


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
    pose_topic: str,
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
        "pose_topic": pose_topic,
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
