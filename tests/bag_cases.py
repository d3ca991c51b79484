"""Small bags for the tests of the bag readers (:mod:`test_fuzz_bags`, :mod:`test_bag_hardening`):
written with rough_map's own writers in each format, copied and damaged per case."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fuzzing import assert_bounded, write_case

from rough_map.export.gridmap_msg import (
    GRID_MAP,
    grid_map_message,
    grid_map_typestore,
    read_gridmap_bag,
)
from rough_map.io.rosbag import (
    IMU,
    ODOMETRY,
    POINTCLOUD2,
    TF_MESSAGE,
    imu_message,
    inspect_bag,
    odometry_message,
    open_bag,
    pointcloud2_message,
    pointcloud2_to_xyz,
    ros_typestore,
    tf_message,
    write_bag,
)
from rough_map.io.rosbag.reader import topic_messages
from rough_map.io.rosbag.trajectory import read_trajectory
from rough_map.map.grid import GridMapData

T0 = 1_700_000_000 * 10**9
KINDS = ("ros1", "sqlite3", "mcap")
STORES = {True: ros_typestore(ros1=True), False: ros_typestore()}


def drive(ros1: bool, full: bool = False) -> list[tuple[str, str, int, Any]]:
    """Two clouds of four points and three odometry poses (with ``full``: IMU and
    /tf_static too), in receive order."""
    ts = STORES[ros1]
    msgs = []
    for i in range(3):
        ns = T0 + i * 10**8
        msgs.append(("/odom", ODOMETRY, ns, odometry_message(ts, ns, (0.1 * i, 0, 0), (0, 0, i))))
        if full:
            msgs.append(("/imu", IMU, ns, imu_message(ts, ns, (0.01, 0.02, 0.0))))
    for k in range(2):
        ns = T0 + 5 * 10**7 + k * 10**8
        xyz = np.arange(12.0).reshape(4, 3) + k
        msgs.append(("/points", POINTCLOUD2, ns, pointcloud2_message(ts, xyz, ns, "lidar")))
    if full:
        mount = tf_message(ts, T0, "base_link", "lidar", (0.2, 0, 1), (0, 0.3, 0))
        msgs.append(("/tf_static", TF_MESSAGE, T0, mount))
    return sorted(msgs, key=lambda m: m[2])


def storage_file(bag: Path) -> Path:
    """The file holding the messages: the .bag itself, or the .db3/.mcap of a folder."""
    if bag.is_file():
        return bag
    (data,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    return data


def read_bag(bag: Path) -> tuple[list[np.ndarray], Any]:
    """What an import reads: every cloud decoded, and the odometry."""
    with open_bag(bag) as reader:
        clouds = [
            pointcloud2_to_xyz(m) for _, m in topic_messages(reader, bag, "/points", POINTCLOUD2)
        ]
        return clouds, read_trajectory(reader, bag, "/odom", ODOMETRY)


def limit(*paths: Path) -> int:
    """The allocation bound of a case: a generous multiple of the input size."""
    size = sum(p.stat().st_size for p in paths if p.is_file())
    return 64 * size + (16 << 20)


def write_bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The small drive in each format (``<kind>``), and with IMU and tf (``<kind>_full``)."""
    folder = tmp_path_factory.mktemp("bases")
    out = {}
    for kind in KINDS:
        out[kind] = write_bag(folder / kind, drive(kind == "ros1"), kind)
        out[f"{kind}_full"] = write_bag(folder / f"{kind}_full", drive(kind == "ros1", True), kind)
        read_bag(out[kind])  # valid, and the lazy imports and caches are warm
    return out


def case_of(factory: pytest.TempPathFactory, base: Path, data: bytes) -> Path:
    """A copy of bag ``base`` whose storage file holds ``data``."""
    if base.is_file():
        return write_case(factory, base.name, data)
    data_file = write_case(factory, storage_file(base).name, data)
    shutil.copy(base / "metadata.yaml", data_file.parent / "metadata.yaml")
    return data_file.parent


def check_case(bag: Path, seed: int) -> None:
    """Inspect one case in four, read (open, decode every cloud, odometry) the others."""
    fn = inspect_bag if seed % 4 == 0 else read_bag
    assert_bounded(fn, bag, max_bytes=limit(bag, *(bag.iterdir() if bag.is_dir() else ())))


def grid_map_data(rows: int = 3, cols: int = 4) -> GridMapData:
    layers = {
        "R": np.arange(rows * cols, dtype=float).reshape(rows, cols),
        "w": np.ones((rows, cols)),
    }
    layers["R"][0, 1] = np.nan
    return GridMapData("map", 0.5, (10.0, -2.0), (rows * 0.5, cols * 0.5), layers, ("R",))


def write_grid_bag(path: Path, msgs: list[Any], topic: str = "/grid") -> Path:
    """GridMap messages in an MCAP bag, as :func:`write_gridmap_bag` writes them."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = grid_map_typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, GRID_MAP, typestore=store)
        for i, msg in enumerate(msgs):
            writer.write(conn, T0 + i, store.serialize_cdr(msg, GRID_MAP))
    return path


def write_grid_base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A grid_map bag of one small map (two layers, 3 x 4 cells), checked to read back."""
    msg = grid_map_message(grid_map_data(), grid_map_typestore(), stamp_ns=T0)
    bag = write_grid_bag(tmp_path_factory.mktemp("grid") / "grid", [msg])
    (back,) = read_gridmap_bag(bag)
    np.testing.assert_array_equal(back.layers["w"], np.ones((3, 4)))
    return bag


def case_of_path(tmp_path: Path, base: Path, data: bytes) -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    bag = tmp_path / base.name
    if base.is_file():
        bag.write_bytes(data)
        return bag
    shutil.copytree(base, bag)
    storage_file(bag).write_bytes(data)
    return bag


def metadata_case(tmp_path: Path, base: Path, text: str) -> Path:
    bag = case_of_path(tmp_path, base, storage_file(base).read_bytes())
    (bag / "metadata.yaml").write_text(text)
    return bag


def grid_message(**changes: Any) -> Any:
    msg = grid_map_message(grid_map_data(), grid_map_typestore(), stamp_ns=T0)
    info = {k: v for k, v in changes.items() if k in ("resolution", "length_x", "length_y")}
    if info:
        msg.info = type(msg.info)(**{**msg.info.__dict__, **info})
    for key in ("layers", "data", "outer_start_index"):
        if key in changes:
            setattr(msg, key, changes[key])
    return msg


def write_compressed(path: Path, compression: str) -> Path:
    """The small drive with compressed chunks: ROS 1 bz2 or lz4, or MCAP zstd."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    ros1 = compression != "zstd"
    writer: Any
    if ros1:
        path = path.with_suffix(".bag")
        writer = Writer1(path)
        writer.set_compression(Writer1.CompressionFormat[compression.upper()])
    else:
        writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    store = STORES[ros1]
    with writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, ns, msg in drive(ros1):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            raw = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            writer.write(connections[topic], ns, raw)
    return path
