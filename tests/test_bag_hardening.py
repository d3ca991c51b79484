"""Damaged and hostile bags that once broke the bag readers, each now a one-line
FileFormatError: record lengths of 2**64 - 1 that made rosbags allocate them, a metadata.yaml
listing 20,000 files or nested 5,000 levels deep, grid maps whose layout does not fit their
data, PointCloud2 messages whose layout overruns their data, NaN quaternions, compressed
chunks lying about their size. Found by :mod:`test_fuzz_bags` and by hand.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from bag_cases import (
    KINDS,
    STORES,
    T0,
    case_of_path,
    drive,
    grid_map_data,
    grid_message,
    metadata_case,
    read_bag,
    storage_file,
    write_bases,
    write_compressed,
    write_grid_bag,
    write_grid_base,
)
from fuzzing import assert_bounded

from rough_map.errors import FileFormatError, InputError
from rough_map.export.gridmap_msg import (
    GRID_MAP,
    grid_map_message,
    grid_map_typestore,
    read_gridmap_bag,
)
from rough_map.io.rosbag import (
    ODOMETRY,
    POINTCLOUD2,
    import_bag,
    inspect_bag,
    odometry_message,
    pointcloud2_message,
    pointcloud2_to_xyz,
    read_odometry,
    read_transforms,
    write_bag,
)

# -- regression tests ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return write_bases(tmp_path_factory)


@pytest.fixture(scope="module")
def grid_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_grid_base(tmp_path_factory)


def test_mcap_record_length_of_2_64_is_refused(bags: dict[str, Path], tmp_path: Path) -> None:
    """The MCAP header record said 2**64 - 1 bytes: rosbags allocated them (MemoryError)."""
    data = bytearray(storage_file(bags["mcap"]).read_bytes())
    data[9:17] = struct.pack("<Q", 2**64 - 1)
    bag = case_of_path(tmp_path, bags["mcap"], bytes(data))
    with pytest.raises(
        FileFormatError, match=r"record at byte 8 declares 18446744073709551615 B past the end"
    ):
        inspect_bag(bag)
    with pytest.raises(FileFormatError, match="past the end"):
        inspect_bag(storage_file(bag))  # the .mcap alone


def test_mcap_chunk_index_pointing_elsewhere(bags: dict[str, Path], tmp_path: Path) -> None:
    """A chunk index whose chunk offset is 2**63: rosbags seeked there (OSError)."""
    data = bytearray(storage_file(bags["mcap"]).read_bytes())
    (at,) = struct.unpack_from("<Q", data, len(data) - 37 + 9)  # the summary section
    while data[at] != 0x08:  # to its first chunk index record
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    data[at + 9 + 16 : at + 9 + 24] = struct.pack("<Q", 2**63)
    bag = case_of_path(tmp_path, bags["mcap"], bytes(data))
    with pytest.raises(FileFormatError, match=r"chunk index at byte \d+ does not match a chunk"):
        read_bag(bag)


def test_ros1_record_lengths_are_checked(bags: dict[str, Path], tmp_path: Path) -> None:
    data = bytearray(bags["ros1"].read_bytes())
    data[13:17] = struct.pack("<I", 2**32 - 1)  # the bag header record's header length
    with pytest.raises(FileFormatError, match=r"record header at byte 13 runs past the end"):
        inspect_bag(case_of_path(tmp_path, bags["ros1"], bytes(data)))


def test_ros1_index_record_with_another_layout(bags: dict[str, Path], tmp_path: Path) -> None:
    """An index data record whose count disagrees with its size: rosbags asserted."""
    data = bytearray(bags["ros1"].read_bytes())
    at = data.index(b"count=", data.index(b"\x04\x00\x00\x00op=\x04")) + 6  # of an index record
    data[at : at + 4] = struct.pack("<I", 1000)
    with pytest.raises(FileFormatError, match=r"bad index record at byte \d+"):
        inspect_bag(case_of_path(tmp_path, bags["ros1"], bytes(data)))


def test_ros1_type_name_that_is_no_python_name(bags: dict[str, Path], tmp_path: Path) -> None:
    """A message definition naming "3ensor_msgs/PointField": rosbags' generated code raised
    SyntaxError."""
    data = bags["ros1"].read_bytes().replace(b"MSG: sensor_msgs/Po", b"MSG: 3ensor_msgs/Po")
    with pytest.raises(FileFormatError, match=r"cannot read the bag .*: SyntaxError: "):
        read_bag(case_of_path(tmp_path, bags["ros1"], data))


def test_sqlite_damage(bags: dict[str, Path], tmp_path: Path) -> None:
    data = bytearray(storage_file(bags["sqlite3"]).read_bytes())
    with pytest.raises(FileFormatError, match=r"not an SQLite file \(bad header\)"):
        inspect_bag(
            case_of_path(tmp_path / "a", bags["sqlite3"], b"SQLite format 2" + bytes(data[15:]))
        )
    data[4096 : 4096 * 3] = b"\xff" * 8192  # pages of the tables
    with pytest.raises(FileFormatError, match=r"(cannot read the bag|damaged bag)"):
        read_bag(case_of_path(tmp_path / "b", bags["sqlite3"], bytes(data)))


def test_metadata_listing_20000_files(bags: dict[str, Path], tmp_path: Path) -> None:
    """A metadata.yaml listing 20,000 storage files made rosbags hang (that file is now also
    over the size limit; 15,000 names fit in it)."""
    text = (bags["mcap"] / "metadata.yaml").read_text()
    name = storage_file(bags["mcap"]).name
    many = "\n".join(f"  - {name}" for _ in range(15_000))
    text = text.replace(f"relative_file_paths:\n  - {name}", f"relative_file_paths:\n{many}")
    with pytest.raises(FileFormatError, match=r"relative_file_paths\]: 15000 files listed"):
        inspect_bag(metadata_case(tmp_path, bags["mcap"], text))


@pytest.mark.parametrize(
    "nested",
    [
        "[" * 5000 + "]" * 5000,
        "{a: " * 3000 + "1" + "}" * 3000,
        "\n" + "".join(" " * i + "- \n" for i in range(0, 600, 2)),
    ],
    ids=["flow-list", "flow-map", "block"],
)
def test_deep_metadata_yaml(bags: dict[str, Path], tmp_path: Path, nested: str) -> None:
    """YAML nested thousands of levels deep made rosbags raise RecursionError."""
    text = f"rosbag2_bagfile_information:\n  custom_data: {nested}\n"
    with pytest.raises(FileFormatError, match=r"metadata\.yaml: nested deeper than 32 levels"):
        inspect_bag(metadata_case(tmp_path, bags["mcap"], text))


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            "version: 9",
            "version: nine",
            r"\[rosbag2_bagfile_information.version\]: expected int, got str",
        ),
        (
            "message_count: 3\n",
            "message_count: [3]\n",
            r"topics_with_message_count\[0\].message_count\]: expected int, got list",
        ),
        ("storage_identifier: mcap", "storage_identifier: zip", r"unsupported storage 'zip'"),
        ("version: 9", "version: " + "9" * 1000, r"unsupported version a 3322-bit number"),
        ("- b.mcap\n", "- b.mcap\n  - x/b.mcap\n", r"paths\[1\]\]: 'x/b.mcap' listed twice"),
        (
            "compression_mode: ''",
            "compression_mode: file",
            r"compressed bags \(mode 'file'\) are not supported",
        ),
        ("  - b", "  - ../b", r"relative_file_paths\[0\]\]: '../b.*' leaves the bag folder"),
        ("  - b", "  - /etc/b", r"'/etc/b.*' leaves the bag folder"),
        ("nanoseconds: 200000000", "nanoseconds: -5", r"duration.nanoseconds\]: -5 outside"),
        (
            "rosbag2_bagfile_information:",
            "rosbag2_bagfile_informations:",
            r"rosbag2_bagfile_information\]: missing",
        ),
        # a 500 kB list in files[0].path took rosbags' YAML parser 16 s of CPU
        (
            "    path: b.mcap",
            "    path: [" + "0.0, " * 99 + "0.0]",
            r"files\[0\]\.path\]: expected str",
        ),
        (
            "  files:\n",
            "  files: " + "[{}, " * 3 + "]]]\n  old_files:\n",
            r"files\[0\]\.path\]: missing",
        ),
    ],
)
def test_hostile_metadata_fields(
    bags: dict[str, Path], tmp_path: Path, old: str, new: str, match: str
) -> None:
    base = bags["mcap"]
    text = (base / "metadata.yaml").read_text().replace(storage_file(base).name, "b.mcap")
    assert old in text
    bag = metadata_case(tmp_path, base, text.replace(old, new, 1))
    shutil.move(storage_file(bag), bag / "b.mcap")
    with pytest.raises(FileFormatError, match=match) as info:
        inspect_bag(bag)
    assert "\n" not in str(info.value)


def test_metadata_file_symlinked_outside(bags: dict[str, Path], tmp_path: Path) -> None:
    base = bags["mcap"]
    bag = case_of_path(tmp_path / "bag", base, storage_file(base).read_bytes())
    outside = tmp_path / "outside.mcap"
    storage_file(bag).rename(outside)
    (bag / outside.name).symlink_to(outside)
    text = (bag / "metadata.yaml").read_text().replace(f"- {base.name}.mcap", "- outside.mcap")
    (bag / "metadata.yaml").write_text(
        text.replace(f"path: {base.name}.mcap", "path: outside.mcap")
    )
    with pytest.raises(FileFormatError, match=r"'outside\.mcap' is not a file of the bag folder"):
        inspect_bag(bag)


@pytest.mark.parametrize("kind", KINDS)
def test_missing_topic_lists_available_ones(
    bags: dict[str, Path], tmp_path: Path, kind: str
) -> None:
    with pytest.raises(
        FileFormatError, match=r"no topic '/nope' in the bag; available topics: /odom, /points$"
    ) as info:
        import_bag(bags[kind], tmp_path / "out", "/nope", "/odom")
    assert info.value.field == "/nope" and str(bags[kind]) in str(info.value)


def test_missing_topic_among_many_is_cut(tmp_path: Path) -> None:
    ts = STORES[False]
    msgs = [
        (
            f"/odom_{i:03d}_{'x' * 30}",
            ODOMETRY,
            T0 + i,
            odometry_message(ts, T0 + i, (0, 0, 0), (0, 0, 0)),
        )
        for i in range(50)
    ]
    bag = write_bag(tmp_path / "many", msgs, "mcap")
    with pytest.raises(
        FileFormatError, match=r"available topics: '/odom_000_x+\.\.\., \.\.\. \(49 more\)$"
    ) as info:
        read_odometry(bag, "/nope")
    assert len(str(info.value)) <= 240


def test_gridmap_unknown_topic(grid_bag: Path) -> None:
    with pytest.raises(
        FileFormatError, match=r"no grid_map_msgs/msg/GridMap on /nope; available topics: /grid$"
    ):
        read_gridmap_bag(grid_bag, "/nope")


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"length_x": 2.0}, r"layer 'R' has 12 values; expected 4 x 4"),
        ({"layers": ["R"]}, r"1 layer names for 2 data arrays"),
        ({"resolution": 0.0}, r"resolution 0.0 m is not a finite positive number"),
        ({"resolution": float("nan")}, r"resolution nan m is not a finite positive number"),
        ({"length_y": float("inf")}, r"lengths \(1.5, inf\) m are not finite"),
        ({"resolution": 1e-300}, r"give more than 2\*\*31 cells a side"),
        (
            {"layers": [], "data": [], "length_x": 1e6, "resolution": 1e-3},
            r"cells without any layer",
        ),
        ({"outer_start_index": 2}, r"start index != 0"),
    ],
)
def test_gridmap_inconsistent_messages(tmp_path: Path, changes: dict, match: str) -> None:
    """Grid maps whose layout does not fit their data: reshape errors, huge sizes before."""
    bag = write_grid_bag(tmp_path / "grid", [grid_message(**changes)])
    with pytest.raises(FileFormatError, match=r"\[/grid\]: message 0: .*" + match) as info:
        read_gridmap_bag(bag)
    assert "\n" not in str(info.value)


def test_gridmap_undecodable_message(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = grid_map_typestore()
    with Writer(tmp_path / "grid", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/grid", GRID_MAP, typestore=store)
        raw = store.serialize_cdr(grid_map_message(grid_map_data(), store), GRID_MAP)
        writer.write(conn, T0, raw)
        writer.write(conn, T0 + 1, raw[:60])
    with pytest.raises(FileFormatError, match=r"\[/grid\]: undecodable GridMap message 1: "):
        read_gridmap_bag(tmp_path / "grid")


def test_pointcloud2_layout_beyond_its_data(tmp_path: Path) -> None:
    """A cloud declaring 2**22 points of 12 B over 48 B of data, in a bag and alone."""
    ts = STORES[False]
    msgs = drive(False)
    at, msg = next((i, m) for i, m in enumerate(msgs) if m[0] == "/points")
    hostile = type(msg[3])(**{**msg[3].__dict__, "height": 2**20})
    msgs[at] = (*msg[:3], hostile)
    with pytest.raises(InputError, match=r"data has 48 B, its layout \(1048576 x 4 points"):
        pointcloud2_to_xyz(hostile)
    bag = write_bag(tmp_path / "bag", msgs, "mcap", ts)
    with pytest.raises(FileFormatError, match=r"\[/points\]: message 0: PointCloud2 data has 48 B"):
        import_bag(bag, tmp_path / "out", "/points", "/odom")
    assert not (tmp_path / "out" / "traverse.json").exists()


def test_nan_and_zero_quaternions_are_skipped(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ts = STORES[False]
    msgs = drive(False, full=True)
    bad = [m for m in msgs if m[0] == "/odom"][1][3]
    bad.pose.pose.orientation = type(bad.pose.pose.orientation)(x=np.nan, y=0.0, z=0.0, w=1.0)
    for m in msgs:
        if m[0] == "/tf_static":
            m[3].transforms[0].transform.rotation = type(bad.pose.pose.orientation)(
                x=0.0, y=0.0, z=0.0, w=0.0
            )
    bag = write_bag(tmp_path / "bag", msgs, "mcap", ts)
    with caplog.at_level(logging.WARNING):
        assert read_transforms(bag) == []
        odom = read_odometry(bag, "/odom")
        traverse = import_bag(bag, tmp_path / "out", "/points", "/odom", imu_topic="/imu")
    assert len(odom.t_ns) == 2
    assert "1 messages on /odom without orientation skipped" in caplog.text
    assert "1 transforms with a non-finite or zero pose skipped" in caplog.text
    assert len(traverse) == 2
    only_nan = [m for m in msgs if m[0] != "/odom" or m[3] is bad]
    with pytest.raises(
        FileFormatError, match=r"\[/odom\]: no usable nav_msgs/msg/Odometry message on '/odom'"
    ):
        read_odometry(write_bag(tmp_path / "nan", only_nan, "mcap", ts), "/odom")


def test_foreign_definition_of_a_standard_type(tmp_path: Path) -> None:
    """A bag defining nav_msgs/msg/Odometry with other fields: refused before decoding."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("string child_frame_id\nfloat64 pose", ODOMETRY))
    odd = store.types[ODOMETRY](child_frame_id="x", pose=1.0)
    bag = write_bag(tmp_path / "odd", [("/odom", ODOMETRY, T0, odd)], "mcap", store)
    with pytest.raises(
        FileFormatError, match=r"\[/odom\]: the bag defines nav_msgs/msg/Odometry with other fields"
    ):
        read_odometry(bag, "/odom")


@pytest.mark.parametrize("compression", ["bz2", "lz4", "zstd"])
def test_compressed_chunks(tmp_path: Path, compression: str) -> None:
    """Compressed chunks are read; one whose declared size is not what it decompresses to,
    or that would expand beyond 256 MiB, is refused before rosbags decompresses it."""
    bag = write_compressed(tmp_path / "bag", compression)
    clouds, odometry = read_bag(bag)
    assert len(clouds) == 2 and len(odometry.t_ns) == 3
    np.testing.assert_array_equal(clouds[1], np.arange(12.0).reshape(4, 3) + 1)

    data = bytearray(storage_file(bag).read_bytes())
    if compression == "zstd":
        at = 8  # after the magic, to the first chunk record
        while data[at] != 0x06:
            at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
        size_at, width = at + 9 + 16, 8
    else:
        size_at, width = data.index(b"size=") + 5, 4
    (size,) = struct.unpack_from("<Q" if width == 8 else "<I", data, size_at)
    for declared, match in [
        (size + 1, rf"decompresses to {size} B, not {size + 1}"),
        (2**28 + 1, f"declares {2**28 + 1} B"),
        (2**28, rf"decompresses to {size} B, not {2**28}"),
    ]:
        data[size_at : size_at + width] = declared.to_bytes(width, "little")
        case = case_of_path(tmp_path / str(declared), bag, bytes(data))
        err = assert_bounded(inspect_bag, case, max_bytes=1 << 24)  # no decompression bomb
        assert isinstance(err, FileFormatError) and re.search(match, str(err)), err


def test_stamps_too_far_apart_for_frame_times(tmp_path: Path) -> None:
    """Clouds 1 ns apart but 4e18 ns after the first: equal float times, refused cleanly."""
    ts = STORES[False]
    first, last = -(2**31) * 10**9, (2**31 - 2) * 10**9
    msgs = [
        ("/odom", ODOMETRY, T0 + i, odometry_message(ts, ns, (0, 0, 0), (0, 0, 0)))
        for i, ns in enumerate([first, last + 10])
    ]
    xyz = np.ones((4, 3))
    for i, ns in enumerate([first, last, last + 1]):
        msgs.append(("/points", POINTCLOUD2, T0 + 5 + i, pointcloud2_message(ts, xyz, ns, "lidar")))
    bag = write_bag(tmp_path / "bag", msgs, "mcap", ts)
    with pytest.raises(
        FileFormatError, match=r"\[/points\]: the clouds do not make a valid traverse: "
    ):
        import_bag(bag, tmp_path / "out", "/points", "/odom")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes here")
def test_named_pipe_is_no_bag(tmp_path: Path) -> None:
    """A FIFO named like a bag would block a reader forever."""
    os.mkfifo(tmp_path / "pipe.bag")
    with pytest.raises(FileFormatError, match=r"pipe\.bag: not a bag: neither a regular file"):
        inspect_bag(tmp_path / "pipe.bag")
