"""Where the vehicle was: its poses from whichever topic a bag has.

:func:`vehicle_trajectory` reads the topic given to ``rough-map import --pose-topic`` by its
message type:

``nav_msgs/Odometry``
    The pose of ``child_frame_id`` (the vehicle) in ``header.frame_id``.
``geometry_msgs/PoseStamped``, ``geometry_msgs/PoseWithCovarianceStamped``
    The pose of the vehicle (``vehicle_frame``, default ``base_link``) in
    ``header.frame_id``.
``tf2_msgs/TFMessage`` (``/tf``)
    The chain of transforms from the root of the tree down to ``vehicle_frame``, each
    dynamic link interpolated at the stamps of all of them (linear, slerp) and the static
    ones of ``/tf_static`` fixed, composed.
``sensor_msgs/NavSatFix``
    Latitude, longitude and altitude of each fix (status >= 0), projected to the CRS given
    (a projected EPSG code in metres), or to a local frame (x east, y north, m) with its
    geodetic origin at ``origin`` or, by default, at the first fix. A GNSS fix has no
    orientation: the heading is the direction of travel over 1 m of path (held while the
    vehicle stands still), roll and pitch zero (the IMU topic gives them).

The world frame of the poses is then the traverse's CRS: the one given (``--crs``,
``--origin``), the NavSatFix frame, or ``local``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from rough_map._bounded import short
from rough_map.config import Crs, GeodeticOrigin
from rough_map.errors import FileFormatError, InputError
from rough_map.io.rosbag.messages import (
    ODOMETRY,
    TF_MESSAGE,
    frame_name,
    quaternion_xyzw,
    stamp_ns,
    valid_quaternion,
)
from rough_map.io.rosbag.reader import topic_field, topic_messages
from rough_map.io.rosbag.tf import Transform, static_transforms, tf_transforms
from rough_map.io.rosbag.trajectory import Trajectory, read_trajectory, timed_samples

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)

__all__ = [
    "NAVSATFIX",
    "POSE_STAMPED",
    "POSE_TYPES",
    "POSE_WITH_COVARIANCE",
    "metric_crs",
    "vehicle_trajectory",
]

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
#: The message types a pose topic may carry.
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_WITH_COVARIANCE, TF_MESSAGE, NAVSATFIX)
#: Path over which a GNSS track's heading is taken, m.
HEADING_BASELINE_M = 1.0


def _topic_type(reader: AnyReader, path: Path, topic: str) -> str:
    types = sorted({c.msgtype for c in reader.connections if c.topic == topic})
    if len(types) == 1 and types[0] in POSE_TYPES:
        return types[0]
    if not types:
        return ODOMETRY  # topic_messages names the topics the bag has
    raise FileFormatError(
        path,
        f"not a pose topic: {short(topic, 30)} carries {', '.join(types)[:60]}, not one of "
        f"{', '.join(t.split('/')[-1] for t in POSE_TYPES)}",
        field=topic_field(topic),
    )


def vehicle_trajectory(
    reader: AnyReader,
    path: Path,
    topic: str,
    *,
    crs: Crs,
    vehicle_frame: str = "base_link",
) -> tuple[Trajectory, Crs]:
    """The vehicle's poses on ``topic`` (see the module docstring) and their CRS.

    Parameters
    ----------
    reader : AnyReader
        The open bag.
    path : Path
        The bag (for messages).
    topic : str
        The pose topic.
    crs : Crs
        The CRS of the poses' world frame (for NavSatFix: the CRS to project the fixes to;
        ``local`` without origin: a local frame at the first fix).
    vehicle_frame : str
        The vehicle's frame, for PoseStamped (as the trajectory's child frame) and /tf.

    Returns
    -------
    (Trajectory, Crs)
        The poses, and the CRS of their world frame.

    Raises
    ------
    FileFormatError
        Unknown topic, a type that is not a pose, no usable message, a /tf tree without
        ``vehicle_frame`` or whose links never overlap in time.
    InputError
        NavSatFix with a CRS that is not projected in metres.
    """
    msgtype = _topic_type(reader, path, topic)
    if msgtype == ODOMETRY:
        return read_trajectory(reader, path, topic, ODOMETRY), crs
    if msgtype in (POSE_STAMPED, POSE_WITH_COVARIANCE):
        return _pose_trajectory(reader, path, topic, msgtype, vehicle_frame), crs
    if msgtype == TF_MESSAGE:
        return _tf_trajectory(reader, path, topic, vehicle_frame), crs
    return _navsat_trajectory(reader, path, topic, crs, vehicle_frame)


def _pose_trajectory(
    reader: AnyReader, path: Path, topic: str, msgtype: str, vehicle_frame: str
) -> Trajectory:
    samples: list[tuple[int, list[float], np.ndarray]] = []
    frame_id, skipped = "", 0
    for receive_ns, msg in topic_messages(reader, path, topic, msgtype):
        pose = msg.pose.pose if msgtype == POSE_WITH_COVARIANCE else msg.pose
        position = [float(pose.position.x), float(pose.position.y), float(pose.position.z)]
        quaternion = quaternion_xyzw(pose.orientation)
        if not valid_quaternion(quaternion) or not np.isfinite(position).all():
            skipped += 1
            continue
        frame_id = msg.header.frame_id
        samples.append((stamp_ns(msg.header, receive_ns), position, quaternion))
    if skipped:
        log.warning("%s: %d poses on %s without a finite pose skipped", path, skipped, topic)
    none = f"no usable pose on {topic!r}"
    return timed_samples(
        samples, path, topic, none=none, repeated=f"poses on {topic}", frame_id=frame_id,
        child=vehicle_frame,
    )  # fmt: skip


def _links(reader: AnyReader, path: Path, topic: str) -> dict[tuple[str, str], list[Transform]]:
    """The transforms of a /tf topic by (parent, child), in time order."""
    links: dict[tuple[str, str], list[Transform]] = {}
    for _, msg in topic_messages(reader, path, topic, TF_MESSAGE):
        for tf in tf_transforms(msg):
            links.setdefault((tf.parent, tf.child), []).append(tf)
    for v in links.values():
        v.sort(key=lambda tf: tf.t)
    return links


def _chain(vehicle: str, parents: dict[str, str], path: Path, topic: str) -> list[tuple[str, str]]:
    """The links (parent, child) from the root of the tree down to ``vehicle``."""
    if vehicle not in parents:
        known = sorted(set(parents) | set(parents.values()))
        raise FileFormatError(
            path,
            f"no transform to the vehicle frame {vehicle!r} on {topic!r} or /tf_static; frames: "
            f"{', '.join(known)[:120]} (name it with --vehicle-frame)",
            field=topic_field(topic),
        )
    chain: list[tuple[str, str]] = []
    node = vehicle
    while node in parents and len(chain) < 64:
        chain.append((parents[node], node))
        node = parents[node]
    return chain[::-1]


def _tf_trajectory(reader: AnyReader, path: Path, topic: str, vehicle: str) -> Trajectory:
    vehicle = frame_name(vehicle)
    dynamic = _links(reader, path, topic)
    static = {(tf.parent, tf.child): tf for tf in static_transforms(reader, path)}
    parents = {child: parent for parent, child in [*static, *dynamic]}
    chain = _chain(vehicle, parents, path, topic)
    moving = [link for link in chain if link in dynamic]
    if not moving:
        raise FileFormatError(
            path, f"the chain to {vehicle!r} on {topic!r} never moves (all of it is static)",
            field=topic_field(topic),
        )  # fmt: skip
    stamps = {link: np.array([round(tf.t * 1e9) for tf in dynamic[link]]) for link in moving}
    lo = max(int(s[0]) for s in stamps.values())
    hi = min(int(s[-1]) for s in stamps.values())
    t_ns = np.unique(np.concatenate([s[(s >= lo) & (s <= hi)] for s in stamps.values()]))
    if lo > hi or len(t_ns) == 0:
        raise FileFormatError(
            path, f"the links of the chain to {vehicle!r} on {topic!r} never overlap in time",
            field=topic_field(topic),
        )  # fmt: skip
    rotation = Rotation.identity(len(t_ns))
    position = np.zeros((len(t_ns), 3))
    for link in chain:  # root first: p_root = R_total p + t_total
        r, t = _link_at(dynamic.get(link), static.get(link), stamps.get(link), t_ns)
        position = position + rotation.apply(t)
        rotation = rotation * r
    return Trajectory(
        t_ns=t_ns.astype(np.int64),
        position=position,
        quaternion=rotation.as_quat(),
        frame_id=chain[0][0],
        child_frame_id=vehicle,
    )


def _link_at(
    dynamic: list[Transform] | None,
    static: Transform | None,
    stamps: np.ndarray | None,
    t_ns: np.ndarray,
) -> tuple[Rotation, np.ndarray]:
    """One link's rotation and translation at the times ``t_ns`` (interpolated)."""
    if dynamic is None:
        assert static is not None
        n = len(t_ns)
        return Rotation.from_quat(np.tile(static.quaternion, (n, 1))), np.tile(
            static.translation, (n, 1)
        )
    assert stamps is not None
    knots = (stamps - stamps[0]) * 1e-9
    at = (t_ns - stamps[0]) * 1e-9
    xyz = np.array([tf.translation for tf in dynamic])
    quats = np.array([tf.quaternion for tf in dynamic])
    t = np.column_stack([np.interp(at, knots, c) for c in xyz.T])
    if len(knots) == 1:
        return Rotation.from_quat(np.tile(quats[0], (len(at), 1))), t
    keep = np.concatenate([[True], np.diff(knots) > 0])
    return Slerp(knots[keep], Rotation.from_quat(quats[keep]))(at), t


def _fixes(reader: AnyReader, path: Path, topic: str) -> Iterator[tuple[int, float, float, float]]:
    """(ns, latitude, longitude, altitude) of every valid fix."""
    skipped = 0
    for receive_ns, msg in topic_messages(reader, path, topic, NAVSATFIX):
        lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
        ok = int(msg.status.status) >= 0 and abs(lat) <= 90 and abs(lon) <= 180
        if not (ok and math.isfinite(lat) and math.isfinite(lon)):
            skipped += 1
            continue
        yield stamp_ns(msg.header, receive_ns), lat, lon, alt if math.isfinite(alt) else 0.0
    if skipped:
        log.warning("%s: %d NavSatFix messages on %s without a fix skipped", path, skipped, topic)


def _navsat_trajectory(
    reader: AnyReader, path: Path, topic: str, crs: Crs, vehicle_frame: str
) -> tuple[Trajectory, Crs]:
    from rasterio.warp import transform

    fixes = list(_fixes(reader, path, topic))
    if not fixes:
        raise FileFormatError(path, f"no valid NavSatFix on {topic!r}", field=topic_field(topic))
    if crs.epsg is None and crs.origin is None:
        _, lat0, lon0, alt0 = fixes[0]
        crs = Crs(code="local", origin=GeodeticOrigin(lat=lat0, lon=lon0, alt=alt0))
        log.info("%s: poses in a local frame with its origin at the first fix", path)
    target = metric_crs(crs)
    lats, lons = [f[1] for f in fixes], [f[2] for f in fixes]
    x, y = transform("EPSG:4326", target, lons, lats)
    z = np.array([f[3] for f in fixes]) - (crs.origin.alt if crs.origin is not None else 0.0)
    position = np.column_stack([x, y, z])
    yaw = _headings(position[:, :2])
    quaternion = Rotation.from_euler("z", yaw[:, None]).as_quat()
    samples = [(f[0], list(p), q) for f, p, q in zip(fixes, position, quaternion, strict=True)]
    none = f"no valid NavSatFix on {topic!r}"
    trajectory = timed_samples(
        samples, path, topic, none=none, repeated=f"fixes on {topic}", frame_id="gnss",
        child=vehicle_frame,
    )  # fmt: skip
    return trajectory, crs


def metric_crs(crs: Crs) -> Any:
    """The :class:`rasterio.crs.CRS` of ``crs``, checked to be projected in metres (a local
    frame with an origin is a transverse Mercator on it); None for a local frame without one.

    Raises
    ------
    InputError
        An EPSG code GDAL does not know, or a CRS that is not projected in metres.
    """
    from rasterio.errors import CRSError

    if crs.epsg is None and crs.origin is None:
        return None
    try:
        target = crs.rasterio()
    except CRSError:
        raise InputError(f"crs {crs.code} is not an EPSG code GDAL knows") from None
    if not target.is_projected or (target.linear_units or "").lower() not in ("metre", "meter"):
        raise InputError(f"crs {crs.code} is not a projected CRS in metres: poses are in metres")
    return target


def _headings(xy: np.ndarray) -> np.ndarray:
    """Direction of travel (rad, anticlockwise from +x) at each point, over
    :data:`HEADING_BASELINE_M` of path centred on it; held where the vehicle stands still."""
    step = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
    s = np.concatenate([[0.0], np.cumsum(step)])
    half = HEADING_BASELINE_M / 2
    ahead = np.clip(np.searchsorted(s, s + half), 0, len(s) - 1)
    behind = np.clip(np.searchsorted(s, s - half, side="right") - 1, 0, len(s) - 1)
    d = xy[ahead] - xy[behind]
    moving = np.hypot(d[:, 0], d[:, 1]) > 1e-3
    yaw = np.arctan2(d[:, 1], d[:, 0])
    if not moving.any():
        return np.zeros(len(xy))
    # hold the last heading (the first known one before any) where the vehicle stands still
    idx = np.where(moving, np.arange(len(xy)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.flatnonzero(moving)[0])
    return yaw[idx]
