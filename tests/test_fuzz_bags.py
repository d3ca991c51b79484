"""Fuzzing of the ROS bag readers: every mutated bag gives a result or a one-line
FileFormatError, never another exception, a hang, or an allocation its size does not justify.

Bases are small bags written with rough_map's own writers (ROS 1 ``.bag``, ROS 2 sqlite3 and
MCAP folders, a grid_map bag, :mod:`bag_cases`); the fuzz targets mutate the storage file
bytes or the ``metadata.yaml`` text, or give hostile values to metadata fields and
PointCloud2 layouts. The inputs that once broke a reader are in :mod:`test_bag_hardening`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_cases import (
    KINDS,
    STORES,
    T0,
    case_of,
    check_case,
    limit,
    storage_file,
    write_bases,
    write_grid_base,
)
from fuzzing import FUZZ, N_EXAMPLES, SEEDS, assert_bounded, mutate, write_case
from hypothesis import given, settings
from hypothesis import strategies as st
from ruamel.yaml import YAML

from rough_map.errors import FileFormatError
from rough_map.export.gridmap_msg import (
    read_gridmap_bag,
)
from rough_map.io.rosbag import (
    import_bag,
    inspect_bag,
    pointcloud2_message,
    pointcloud2_to_xyz,
)

pytestmark = pytest.mark.fuzz


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return write_bases(tmp_path_factory)


@pytest.fixture(scope="module")
def grid_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_grid_base(tmp_path_factory)


# -- fuzz targets ----------------------------------------------------------------------------


@FUZZ
@given(seed=SEEDS)
def test_fuzz_ros1_bag(
    bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    base = bags["ros1"]
    check_case(case_of(tmp_path_factory, base, mutate(base.read_bytes(), seed)), seed)


@FUZZ
@given(seed=SEEDS)
def test_fuzz_mcap(
    bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    base = bags["mcap"]
    data = mutate(storage_file(base).read_bytes(), seed)
    check_case(case_of(tmp_path_factory, base, data), seed)


@FUZZ
@given(seed=SEEDS)
def test_fuzz_db3(
    bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    base = bags["sqlite3"]
    data = mutate(storage_file(base).read_bytes(), seed)
    check_case(case_of(tmp_path_factory, base, data), seed)


@FUZZ
@given(seed=SEEDS)
def test_fuzz_metadata_yaml(
    bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    base = bags["mcap"]
    data_file = write_case(
        tmp_path_factory, storage_file(base).name, storage_file(base).read_bytes()
    )
    meta = data_file.parent / "metadata.yaml"
    meta.write_bytes(mutate((base / "metadata.yaml").read_bytes(), seed))
    assert_bounded(inspect_bag, data_file.parent, max_bytes=limit(data_file, meta))


HOSTILE = [
    None,
    True,
    "x" * 5000,
    -1,
    2**70,
    1e308,
    float("nan"),
    [],
    {},
    [[[[1]]]],
    {"a": 1},
    ["../../etc/passwd"],
    ["/etc/passwd"],
    "nanoseconds",
]
FIELDS = [
    ("version",),
    ("storage_identifier",),
    ("relative_file_paths",),
    ("relative_file_paths", 0),
    ("duration",),
    ("duration", "nanoseconds"),
    ("starting_time", "nanoseconds_since_epoch"),
    ("message_count",),
    ("files",),
    ("compression_mode",),
    ("compression_format",),
    ("topics_with_message_count",),
    ("topics_with_message_count", 0),
    ("topics_with_message_count", 0, "message_count"),
    ("topics_with_message_count", 0, "topic_metadata"),
    ("topics_with_message_count", 0, "topic_metadata", "name"),
    ("topics_with_message_count", 0, "topic_metadata", "type"),
    ("topics_with_message_count", 0, "topic_metadata", "serialization_format"),
    ("topics_with_message_count", 0, "topic_metadata", "offered_qos_profiles"),
    ("topics_with_message_count", 0, "topic_metadata", "type_description_hash"),
]


@settings(FUZZ, max_examples=max(50, N_EXAMPLES // 4))
@given(field=st.sampled_from(FIELDS), value=st.sampled_from(HOSTILE), drop=st.booleans())
def test_fuzz_metadata_fields(
    bags: dict[str, Path],
    tmp_path_factory: pytest.TempPathFactory,
    field: tuple,
    value: Any,
    drop: bool,
) -> None:
    """metadata.yaml with one field of a wrong type or value, or missing."""
    base = bags["mcap"]
    yaml = YAML(typ="safe")
    document = yaml.load((base / "metadata.yaml").read_text())
    node = document["rosbag2_bagfile_information"]
    for key in field[:-1]:
        node = node[key]
    if drop:
        del node[field[-1]]
    else:
        node[field[-1]] = value
    data_file = write_case(
        tmp_path_factory, storage_file(base).name, storage_file(base).read_bytes()
    )
    with (data_file.parent / "metadata.yaml").open("w") as f:
        yaml.dump(document, f)
    assert_bounded(inspect_bag, data_file.parent, max_bytes=limit(data_file) + (4 << 20))


@settings(FUZZ, max_examples=max(50, N_EXAMPLES // 4))
@given(seed=SEEDS)
def test_fuzz_import_bag(
    bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    """The whole import (rough-map import-bag) over a damaged bag of any of the formats."""
    base = bags[f"{KINDS[seed % 3]}_full"]
    bag = case_of(tmp_path_factory, base, mutate(storage_file(base).read_bytes(), seed))
    out = tmp_path_factory.mktemp("out")
    result = assert_bounded(import_bag, bag, out, "/points", "/odom", imu_topic="/imu")
    if isinstance(result, FileFormatError):
        assert not (out / "traverse.json").exists()


@FUZZ
@given(seed=SEEDS)
def test_fuzz_gridmap_bag(
    grid_bag: Path, tmp_path_factory: pytest.TempPathFactory, seed: int
) -> None:
    bag = case_of(tmp_path_factory, grid_bag, mutate(storage_file(grid_bag).read_bytes(), seed))
    topic = "/grid" if seed % 2 else None
    assert_bounded(read_gridmap_bag, bag, topic, max_bytes=limit(storage_file(bag)))


CLOUD_FIELDS = st.fixed_dictionaries(
    {
        "height": st.sampled_from([0, 1, 2, 3, 2**31, 2**32 - 1]),
        "width": st.sampled_from([0, 1, 2, 4, 7, 2**31, 2**32 - 1]),
        "point_step": st.sampled_from([0, 1, 4, 12, 13, 16, 2**32 - 1]),
        "row_step": st.sampled_from([0, 12, 24, 48, 49, 2**32 - 1]),
        "offset": st.sampled_from([0, 1, 4, 8, 11, 2**32 - 4]),
        "datatype": st.sampled_from([0, 1, 4, 7, 8, 9, 255]),
        "size": st.sampled_from([0, 1, 11, 47, 48, 96, 200]),
        "nan": st.booleans(),
    }
)


@settings(FUZZ, max_examples=max(100, N_EXAMPLES // 2))
@given(spec=CLOUD_FIELDS)
def test_fuzz_pointcloud2_layout(spec: dict[str, Any]) -> None:
    """PointCloud2 messages with hostile sizes, offsets, datatypes and data lengths."""
    ts = STORES[False]
    msg = pointcloud2_message(ts, np.arange(12.0).reshape(4, 3), T0, "lidar")
    z = msg.fields[2]
    fields = [
        *msg.fields[:2],
        type(z)(name="z", offset=spec["offset"], datatype=spec["datatype"], count=1),
    ]
    data = np.full(spec["size"], 0x7F if spec["nan"] else 0x3F, dtype=np.uint8)
    hostile = type(msg)(
        **{
            **msg.__dict__,
            **{k: spec[k] for k in ("height", "width", "point_step", "row_step")},
            "fields": fields,
            "data": data,
        }
    )
    xyz = assert_bounded(pointcloud2_to_xyz, hostile, max_bytes=100 * spec["size"] + (1 << 20))
    if isinstance(xyz, np.ndarray):
        assert xyz.shape[1] == 3 and np.isfinite(xyz).all()
