"""ROS bags: PointCloud2 decoding, inspection and import, over ROS 1, ROS 2 sqlite3 and MCAP.

The bags are written in ``tmp_path`` by rough_map's own bag writers (``write_bag``,
``pointcloud2_message``..., over the rosbags writers), which also make the README's example
bag (``write_example_bag``); no binary is committed.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

from rough_map.cli.main import main
from rough_map.errors import FileFormatError, InputError
from rough_map.io.rosbag import (
    EXAMPLE_LIDAR_MOUNT,
    IMU,
    ODOMETRY,
    POINTCLOUD2,
    TF_MESSAGE,
    PointCloud2Layout,
    Transform,
    import_bag,
    imu_message,
    imu_rpy,
    inspect_bag,
    odometry_message,
    odometry_pose,
    open_bag,
    pointcloud2_message,
    pointcloud2_to_xyz,
    read_imu,
    read_odometry,
    read_transforms,
    ros_typestore,
    static_transform,
    tf_message,
    tf_transforms,
    write_example_bag,
)
from rough_map.io.rosbag import write_bag as rosbag_write
from rough_map.io.traverse import load_traverse

KINDS = ["ros1", "sqlite3", "mcap"]
T0 = 1_700_000_000 * 10**9  # ns since the epoch of the first odometry message


@pytest.fixture
def cli_logging() -> Iterator[None]:
    """Undo the logging set-up of ``main()``: later tests read logs through caplog."""
    logger = logging.getLogger("rough_map")
    saved = logger.handlers[:], logger.level, logger.propagate
    yield
    logger.handlers[:], logger.level, logger.propagate = saved


STORES = {"ros1": ros_typestore(ros1=True), "ros2": ros_typestore()}


def store_of(kind: str) -> Typestore:
    return STORES["ros1" if kind == "ros1" else "ros2"]


# --------------------------------------------------------------------------------------------
# Message builders: rough_map.io.rosbag's writers, with the store of the bag's kind

Layout = PointCloud2Layout
LAYOUTS = {
    "xyz_f32_le": Layout(),
    "xyzi_padded_step32": Layout(
        point_step=32, offsets=(0, 4, 8), extra=(("intensity", 16, "f4", 7), ("ring", 20, "u2", 4))
    ),
    "xyz_f64_be": Layout(code="f8", datatype=8, bigendian=True, point_step=24, offsets=(0, 8, 16)),
    "organised_2rows_nan": Layout(
        point_step=16, offsets=(4, 8, 12), extra=(("t", 0, "u4", 6),), height=2, row_pad=8
    ),
}


def pointcloud2(ts: Typestore, xyz: np.ndarray, layout: Layout, ns: int, frame_id: str) -> Any:
    return pointcloud2_message(ts, xyz, ns, frame_id, layout)


def odometry(ts: Typestore, ns: int, xyz: Any, rpy: Any) -> Any:
    return odometry_message(ts, ns, xyz, rpy)


def imu(ts: Typestore, ns: int, rpy: Any, known: bool = True) -> Any:
    return imu_message(ts, ns, rpy, known=known)


def write_bag(path: Path, kind: str, messages: list[tuple[str, str, int, Any]]) -> Path:
    """Write ``(topic, msgtype, ns, message)`` tuples with the real rosbags writers."""
    return rosbag_write(path, messages, "ros1" if kind == "ros1" else kind, store_of(kind))


# --------------------------------------------------------------------------------------------
# A small drive: 2 s of odometry at 10 Hz, IMU at 50 Hz, four clouds, a lidar mount in tf


SPEED = np.array([1.0, 0.5, 0.0])  # m/s
YAW_RATE = 0.2  # rad/s
IMU_ROLL, IMU_PITCH = 0.05, -0.03  # rad
MOUNT_XYZ, MOUNT_RPY = (0.5, 0.0, 1.2), (0.0, 0.1, np.pi / 2)  # lidar in base_link
CLOUD_TIMES = [0.25, 0.75, 1.25, 2.5]  # s; the last one is after the odometry
CLOUD_LAYOUTS = list(LAYOUTS)


def cloud_points(k: int, layout: Layout) -> np.ndarray:
    rng = np.random.default_rng(k)
    xyz = rng.uniform(-5, 5, size=(12, 3))
    if layout.height > 1:
        xyz[[1, 7]] = np.nan  # missing returns of an organised cloud
    return xyz.astype(layout.code).astype(float)


def drive_messages(kind: str, tf_static: bool = True, imu_topic: bool = True) -> list:
    ts = store_of(kind)
    msgs: list[tuple[str, str, int, Any]] = []
    if tf_static:
        msgs.append(
            (
                "/tf_static",
                TF_MESSAGE,
                T0,
                tf_message(ts, T0, "base_link", "velodyne", MOUNT_XYZ, MOUNT_RPY),
            )
        )
    for i in range(21):
        t = i * 0.1
        ns = T0 + i * 10**8
        msgs.append(("/odom", ODOMETRY, ns, odometry(ts, ns, SPEED * t, [0.0, 0.0, YAW_RATE * t])))
    if imu_topic:
        for i in range(5, 96):
            ns = T0 + i * 2 * 10**7
            msgs.append(("/imu", IMU, ns, imu(ts, ns, [IMU_ROLL, IMU_PITCH, 1.0])))
    for k, (t, name) in enumerate(zip(CLOUD_TIMES, CLOUD_LAYOUTS, strict=True)):
        ns = T0 + round(t * 1e9)
        layout = LAYOUTS[name]
        msgs.append(
            (
                "/points",
                POINTCLOUD2,
                ns,
                pointcloud2(ts, cloud_points(k, layout), layout, ns, "velodyne"),
            )
        )
    msgs.sort(key=lambda m: m[2])
    return msgs


@pytest.fixture(scope="module", params=KINDS)
def drive_bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The drive in each bag format; written once, only read by the tests."""
    folder = tmp_path_factory.mktemp("bags")
    return write_bag(
        folder / f"drive_{request.param}", request.param, drive_messages(request.param)
    )


# --------------------------------------------------------------------------------------------
# PointCloud2 decoding


@pytest.mark.parametrize("name", LAYOUTS)
@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_pointcloud2_layouts_decode(name: str, kind: str) -> None:
    layout = LAYOUTS[name]
    xyz = cloud_points(3, layout)
    msg = pointcloud2(STORES[kind], xyz, layout, T0, "velodyne")
    got = pointcloud2_to_xyz(msg)
    expected = xyz[np.isfinite(xyz).all(axis=1)]
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, expected)


def test_pointcloud2_drops_inf_and_handles_empty() -> None:
    ts = STORES["ros2"]
    xyz = np.array([[1.0, 2.0, 3.0], [np.inf, 0.0, 0.0], [4.0, 5.0, 6.0]])
    got = pointcloud2_to_xyz(pointcloud2(ts, xyz, Layout(), T0, "l"))
    np.testing.assert_array_equal(got, xyz[[0, 2]])
    as_bytes = pointcloud2(ts, xyz, Layout(), T0, "l")
    as_bytes = type(as_bytes)(**{**as_bytes.__dict__, "data": as_bytes.data.tobytes()})
    np.testing.assert_array_equal(pointcloud2_to_xyz(as_bytes), xyz[[0, 2]])
    empty = pointcloud2(ts, np.empty((0, 3)), Layout(), T0, "l")
    assert pointcloud2_to_xyz(empty).shape == (0, 3)


def test_pointcloud2_bad_layouts() -> None:
    ts = STORES["ros2"]
    msg = pointcloud2(ts, np.zeros((4, 3)), Layout(), T0, "l")
    with pytest.raises(InputError, match="without field"):
        pointcloud2_to_xyz(type(msg)(**{**msg.__dict__, "fields": msg.fields[:2]}))
    with pytest.raises(InputError, match=r"needs 48 B"):
        pointcloud2_to_xyz(type(msg)(**{**msg.__dict__, "data": msg.data[:40]}))
    with pytest.raises(InputError, match="overruns point_step"):
        pointcloud2_to_xyz(type(msg)(**{**msg.__dict__, "point_step": 10, "row_step": 40}))
    bad_type = [type(f)(name=f.name, offset=f.offset, datatype=42, count=1) for f in msg.fields]
    with pytest.raises(InputError, match="unknown datatype 42"):
        pointcloud2_to_xyz(type(msg)(**{**msg.__dict__, "fields": bad_type}))


# --------------------------------------------------------------------------------------------
# Other messages


def test_odometry_imu_tf_messages() -> None:
    ts = STORES["ros2"]
    pose = odometry_pose(odometry(ts, T0 + 5, [1.0, 2.0, 3.0], [0.1, -0.2, 0.3]))
    assert (pose.x, pose.y, pose.z) == (1.0, 2.0, 3.0)
    np.testing.assert_allclose([pose.roll, pose.pitch, pose.yaw], [0.1, -0.2, 0.3], atol=1e-12)
    assert (pose.frame_id, pose.child_frame_id) == ("odom", "base_link")
    assert pose.t == pytest.approx(1_700_000_000.000000005, abs=1e-6)

    np.testing.assert_allclose(imu_rpy(imu(ts, T0, [0.05, -0.03, 1.0])), [0.05, -0.03, 1.0])
    assert imu_rpy(imu(ts, T0, [0.0, 0.0, 0.0], known=False)) is None

    (tf,) = tf_transforms(tf_message(ts, T0, "/base_link", "velodyne", MOUNT_XYZ, MOUNT_RPY))
    assert (tf.parent, tf.child, tf.translation) == ("base_link", "velodyne", MOUNT_XYZ)
    p_child = np.array([1.0, 0.0, 0.0, 1.0])
    expected = Rotation.from_euler("xyz", MOUNT_RPY).apply(p_child[:3]) + MOUNT_XYZ
    np.testing.assert_allclose((tf.matrix() @ p_child)[:3], expected)


def test_static_transform_chains_and_inverts() -> None:
    def tf(parent: str, child: str, xyz: tuple, yaw: float) -> Transform:
        q = Rotation.from_euler("z", yaw).as_quat()
        return Transform(0.0, parent, child, xyz, tuple(q))

    tfs = [
        tf("base_link", "mount", (1.0, 0.0, 0.0), np.pi / 2),
        tf("mount", "lidar", (0.0, 2.0, 0.0), 0.0),
    ]
    lidar_to_base = static_transform(tfs, "lidar", "base_link")
    # lidar origin: (0, 2, 0) in mount, rotated 90 deg about z: (-2, 0, 0), plus (1, 0, 0).
    np.testing.assert_allclose(lidar_to_base @ [0, 0, 0, 1], [-1.0, 0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(
        static_transform(tfs, "base_link", "lidar") @ lidar_to_base, np.eye(4), atol=1e-12
    )
    assert static_transform(tfs, "lidar", "camera") is None
    np.testing.assert_array_equal(static_transform(tfs, "/lidar", "lidar"), np.eye(4))


# --------------------------------------------------------------------------------------------
# Bags: inspect, round trip, topic readers


def test_inspect_bag(drive_bag: Path) -> None:
    info = inspect_bag(drive_bag)
    counts = {t.name: (t.msgtype, t.count) for t in info.topics}
    assert counts == {
        "/imu": (IMU, 91),
        "/odom": (ODOMETRY, 21),
        "/points": (POINTCLOUD2, 4),
        "/tf_static": (TF_MESSAGE, 1),
    }
    assert info.message_count == 117
    assert info.start == pytest.approx(T0 * 1e-9)
    assert info.duration == pytest.approx(2.5, abs=1e-6)


def test_points_round_trip_through_bag(drive_bag: Path) -> None:
    with open_bag(drive_bag) as reader:
        connections = [c for c in reader.connections if c.topic == "/points"]
        clouds = [
            pointcloud2_to_xyz(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages(connections)
        ]
    assert len(clouds) == len(CLOUD_LAYOUTS)
    for k, (got, name) in enumerate(zip(clouds, CLOUD_LAYOUTS, strict=True)):
        xyz = cloud_points(k, LAYOUTS[name])
        np.testing.assert_array_equal(got, xyz[np.isfinite(xyz).all(axis=1)], err_msg=name)


def test_topic_readers(drive_bag: Path) -> None:
    odom = read_odometry(drive_bag, "/odom")
    assert (odom.frame_id, odom.child_frame_id) == ("odom", "base_link")
    assert len(odom.t) == 21 and odom.t[0] == pytest.approx(T0 * 1e-9)
    np.testing.assert_allclose(odom.position[-1], SPEED * 2.0)
    np.testing.assert_allclose(odom.rpy()[-1], [0.0, 0.0, YAW_RATE * 2.0], atol=1e-12)
    att = read_imu(drive_bag, "/imu").rpy()
    np.testing.assert_allclose(att[:, :2], np.tile([IMU_ROLL, IMU_PITCH], (91, 1)), atol=1e-12)
    (tf,) = read_transforms(drive_bag)
    assert (tf.parent, tf.child) == ("base_link", "velodyne")


def test_imu_without_orientation_and_repeated_stamps(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ts = store_of("mcap")
    msgs = [("/imu", IMU, T0 + i, imu(ts, T0 + i, [0.1, 0.0, 0.0], known=i != 1)) for i in range(3)]
    msgs.append(("/imu", IMU, T0 + 3, imu(ts, T0 + 2, [0.2, 0.0, 0.0])))  # stamp of the last
    bag = write_bag(tmp_path / "imu", "mcap", msgs)
    att = read_imu(bag, "/imu")
    np.testing.assert_array_equal(att.t_ns, [T0, T0 + 2])
    np.testing.assert_allclose(att.rpy()[:, 0], [0.1, 0.1])
    assert "1 messages on /imu without orientation skipped" in caplog.text
    assert "1 messages on /imu with a repeated stamp ignored" in caplog.text
    unknown = [("/imu", IMU, T0, imu(ts, T0, [0.0, 0.0, 0.0], known=False))]
    with pytest.raises(FileFormatError, match=r"no usable sensor_msgs/msg/Imu message on '/imu'"):
        read_imu(write_bag(tmp_path / "unknown", "mcap", unknown), "/imu")


# --------------------------------------------------------------------------------------------
# Import


def test_import_bag(drive_bag: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "traverse"
    traverse = import_bag(drive_bag, out, "/points", "/odom", imu_topic="/imu")
    assert "1 clouds outside the odometry time span" in caplog.text

    reloaded = load_traverse(out)  # the file on disk validates
    reloaded.validate_files()
    assert reloaded.spec == traverse.spec
    assert len(reloaded) == 3
    np.testing.assert_allclose(reloaded.times(), [0.0, 0.5, 1.0], atol=1e-12)
    assert reloaded.spec.crs.code == "local"
    source = reloaded.spec.metadata["source"]
    assert source["t0_ns"] == T0 + 250_000_000
    assert (source["world_frame"], source["vehicle_frame"]) == ("odom", "base_link")

    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler("xyz", MOUNT_RPY).as_matrix()
    mount[:3, 3] = MOUNT_XYZ
    for i, (t, frame) in enumerate(zip(CLOUD_TIMES[:3], reloaded.frames, strict=False)):
        pose = frame.pose
        # Odometry samples at 10 Hz of a linear motion and a steady yaw: interpolation is exact.
        np.testing.assert_allclose([pose.x, pose.y, pose.z], SPEED * t, atol=1e-9)
        np.testing.assert_allclose(
            [pose.roll, pose.pitch, pose.yaw], [0, 0, YAW_RATE * t], atol=1e-9
        )
        assert frame.imu is not None
        np.testing.assert_allclose(
            [frame.imu.roll, frame.imu.pitch], [IMU_ROLL, IMU_PITCH], atol=1e-9
        )
        assert frame.cloud == f"clouds/{i:06d}.npy"
        xyz = cloud_points(i, LAYOUTS[CLOUD_LAYOUTS[i]])
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        expected = xyz @ mount[:3, :3].T + mount[:3, 3]  # velodyne -> base_link by /tf_static
        np.testing.assert_allclose(reloaded.load_cloud(i), expected, atol=1e-12)
        world = reloaded.load_cloud(i, frame="world")
        np.testing.assert_allclose(world, expected @ pose.matrix()[:3, :3].T + pose.matrix()[:3, 3])


@pytest.mark.parametrize("kind", ["sqlite3"])
def test_import_without_tf_keeps_points_and_every(
    kind: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bag = write_bag(tmp_path / "bag", kind, drive_messages(kind, tf_static=False, imu_topic=False))
    traverse = import_bag(bag, tmp_path / "out", "/points", "/odom", every=2)
    assert "no /tf_static transform from 'velodyne'" in caplog.text
    assert [f.cloud for f in traverse.frames] == ["clouds/000000.npy", "clouds/000002.npy"]
    assert all(f.imu is None for f in traverse.frames)
    xyz = cloud_points(2, LAYOUTS[CLOUD_LAYOUTS[2]])
    np.testing.assert_array_equal(traverse.load_cloud(1), xyz[np.isfinite(xyz).all(axis=1)])


def test_import_refuses_existing_traverse(drive_bag: Path, tmp_path: Path) -> None:
    import_bag(drive_bag, tmp_path / "out", "/points", "/odom")
    with pytest.raises(InputError, match="exists; import into a new folder"):
        import_bag(drive_bag, tmp_path / "out", "/points", "/odom")
    with pytest.raises(InputError, match="every must be >= 1"):
        import_bag(drive_bag, tmp_path / "other", "/points", "/odom", every=0)


# --------------------------------------------------------------------------------------------
# Errors


def test_unknown_topic_lists_available(drive_bag: Path, tmp_path: Path) -> None:
    with pytest.raises(
        FileFormatError,
        match=r"no topic '/lidar'.*available topics: /imu, /odom, /points, /tf_static",
    ) as info:
        import_bag(drive_bag, tmp_path / "out", "/lidar", "/odom")
    assert info.value.field == "/lidar"
    assert str(drive_bag) in str(info.value)
    assert not (tmp_path / "out" / "traverse.json").exists()


def test_wrong_message_type(drive_bag: Path, tmp_path: Path) -> None:
    with pytest.raises(
        FileFormatError,
        match=r"not a pose topic: '/imu' carries sensor_msgs/msg/Imu, not one of Odometry",
    ):
        import_bag(drive_bag, tmp_path / "out", "/points", "/imu")


def test_no_cloud_in_odometry_span(tmp_path: Path) -> None:
    msgs = [m for m in drive_messages("mcap") if m[0] != "/points" or m[2] > T0 + 2 * 10**9]
    bag = write_bag(tmp_path / "late", "mcap", msgs)
    with pytest.raises(
        FileFormatError, match=r"no point cloud imported.*1 outside the time span of the poses"
    ):
        import_bag(bag, tmp_path / "out", "/points", "/odom")


def storage_file(bag: Path, kind: str) -> Path:
    """The file holding the messages: the .bag itself, or the .db3/.mcap in a ROS 2 folder."""
    if kind == "ros1":
        return bag
    (data_file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    return data_file


@pytest.mark.parametrize("fraction", [0.5, 0.9])
@pytest.mark.parametrize("kind", KINDS)
def test_truncated_bag(kind: str, fraction: float, tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", kind, drive_messages(kind))
    data_file = storage_file(bag, kind)
    data = data_file.read_bytes()
    data_file.write_bytes(data[: int(len(data) * fraction)])
    # Damage found on opening (index, footer) or only while reading messages (sqlite pages).
    with pytest.raises(FileFormatError, match=r"truncated or corrupt\?") as info:
        import_bag(bag, tmp_path / "out", "/points", "/odom")
    assert str(bag) in str(info.value)
    assert not (tmp_path / "out" / "traverse.json").exists()


@pytest.mark.parametrize("kind", KINDS)
def test_corrupt_bytes_inside_bag(kind: str, tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", kind, drive_messages(kind))
    data_file = storage_file(bag, kind)
    data = bytearray(data_file.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 2000] = b"\xff" * 2000
    data_file.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match=r"(damaged bag|cannot read the bag)"):
        import_bag(bag, tmp_path / "out", "/points", "/odom")


def test_empty_missing_and_foreign_bags(tmp_path: Path) -> None:
    empty = tmp_path / "empty.bag"
    empty.touch()
    with pytest.raises(FileFormatError, match=r"empty\.bag: the bag is empty"):
        inspect_bag(empty)
    with pytest.raises(FileFormatError, match="no such bag"):
        inspect_bag(tmp_path / "missing.bag")
    with pytest.raises(FileFormatError, match="not a bag"):
        inspect_bag(tmp_path)  # a folder without metadata.yaml
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file" * 8)
    with pytest.raises(FileFormatError, match="cannot read the bag"):
        inspect_bag(garbage)


def test_bag_without_messages(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "none", "ros1", [])
    info = inspect_bag(bag)
    assert (info.topics, info.message_count, info.duration) == ((), 0, 0.0)
    with pytest.raises(
        FileFormatError, match="no topic '/points' in the bag; available topics: none"
    ):
        import_bag(bag, tmp_path / "out", "/points", "/odom")


# --------------------------------------------------------------------------------------------
# CLI


def test_cli_inspect(
    drive_bag: Path, capsys: pytest.CaptureFixture[str], cli_logging: None
) -> None:
    assert main(["inspect", str(drive_bag)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].split() == ["topic", "type", "count"]
    assert lines[3].split() == ["/points", POINTCLOUD2, "4"]
    assert "117 messages" in out

    assert main(["inspect", "--json", str(drive_bag)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["topics"][1] == {"name": "/odom", "msgtype": ODOMETRY, "count": 21}
    assert data["duration"] == pytest.approx(2.5)


def test_cli_import(
    drive_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], cli_logging: None
) -> None:
    out = tmp_path / "run"
    argv = [
        "import",
        str(drive_bag),
        "--points-topic",
        "/points",
        "--odom-topic",
        "/odom",
        "--imu-topic",
        "/imu",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    assert capsys.readouterr().out.strip() == str(out / "traverse.json")
    assert len(load_traverse(out)) == 3

    assert main([*argv[:3], "/nope", *argv[4:-1], str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error:" in err and "no topic '/nope'" in err


# --------------------------------------------------------------------------------------------
# The example bag: a simulated traverse recorded as a rover's logger would


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_example_bag_round_trip(small_traverse: Path, tmp_path: Path, storage: str) -> None:
    """write_example_bag -> import_bag gives the traverse back: poses, IMU, clouds."""
    original = load_traverse(small_traverse)
    bag = write_example_bag(original, tmp_path / "drive_bag", storage=storage)
    info = inspect_bag(bag)
    n = len(original)
    assert {t.name: (t.msgtype, t.count) for t in info.topics} == {
        "/imu": (IMU, n),
        "/odom": (ODOMETRY, n),
        "/points": (POINTCLOUD2, n),
        "/tf_static": (TF_MESSAGE, 1),
    }
    (tf,) = read_transforms(bag)
    assert (tf.parent, tf.child, tf.translation) == ("base_link", "lidar", EXAMPLE_LIDAR_MOUNT[0])

    back = import_bag(bag, tmp_path / "run", "/points", "/odom", imu_topic="/imu")
    assert len(back) == n
    np.testing.assert_allclose(back.times(), original.times() - original.times()[0], atol=1e-9)
    np.testing.assert_allclose(back.poses(), original.poses(), atol=1e-9)
    for a, b in zip(back.frames, original.frames, strict=True):
        assert a.imu is not None and b.imu is not None
        np.testing.assert_allclose([a.imu.roll, a.imu.pitch], [b.imu.roll, b.imu.pitch], atol=1e-9)
    for i in (0, n - 1):
        # float32 in the lidar frame, 1.2 m away: a few um after the mount is undone
        np.testing.assert_allclose(back.load_cloud(i), original.load_cloud(i), atol=1e-5)


def test_example_bag_refuses_bad_arguments(small_traverse: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="every must be >= 1, got 0"):
        write_example_bag(small_traverse, tmp_path / "a", every=0)
    with pytest.raises(InputError, match="storage must be one of mcap, sqlite3, ros1"):
        write_example_bag(small_traverse, tmp_path / "a", storage="zip")
    (tmp_path / "taken").mkdir()
    with pytest.raises(InputError, match="taken exists; write the bag to a new path"):
        write_example_bag(small_traverse, tmp_path / "taken", every=100)


def test_readme_bag_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The README's ROS bag section as written: simulate --bag, inspect, import."""
    bag = tmp_path / "drive_bag"
    sim = ["simulate", "--out", str(tmp_path / "sim"), "--course", "mixed", "--length", "2",
           "--no-images", "--seed", "1", "--points-per-cell", "4", "--bag", str(bag)]  # fmt: skip
    assert main(sim) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / "sim" / "traverse.json"), str(bag)]
    sim[2] = str(tmp_path / "sim2")
    assert main(sim) == 2
    assert "exists; write the bag to a new path" in capsys.readouterr().err

    assert main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out[1:5]] == ["/imu", "/odom", "/points", "/tf_static"]
    argv = ["import", str(bag), "--points-topic", "/points", "--odom-topic", "/odom",
            "--imu-topic", "/imu", "--out", str(tmp_path / "run1")]  # fmt: skip
    assert main(argv) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "run1" / "traverse.json")
    assert main(["-q", "features", str(tmp_path / "run1"), "--out", str(tmp_path / "f.csv")]) == 0
    assert capsys.readouterr().err == ""


def test_cli_bag_paths_that_do_not_exist(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    for argv in (
        ["inspect", str(tmp_path / "drive_bga")],
        ["import", str(tmp_path / "drive_bga"), "--points-topic", "/p", "--odom-topic", "/o",
         "--out", str(tmp_path / "out")],
    ):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert f"error: argument bag: no such file or folder: '{tmp_path / 'drive_bga'}'" in err
    assert main(["import", str(tmp_path), "--points-topic", "/p", "--odom-topic", "/o",
                 "--out", str(tmp_path / "out"), "--every", "0"]) == 2  # fmt: skip
    assert "argument --every: expected a positive whole number, got '0'" in capsys.readouterr().err
