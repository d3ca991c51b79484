"""Fuzzing the structured-text readers (issue 14): traverses, calibrations, configs, the
world truth, features tables, map states and map folders.

Each target mutates a small valid file (:func:`fuzzing.mutate`) and checks that the reader
returns or raises a one-line :class:`~rough_map.errors.RoughMapError`
(:func:`fuzzing.assert_bounded`). Structure-aware cases (deep nesting, huge numbers, YAML
aliases, wrong types) and the inputs that once broke a reader follow as plain tests.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from fuzzing import FUZZ, SEEDS, assert_bounded, deep_json, mutate, write_case
from hypothesis import given

from rough_map.classify.levels import load_roughness_levels
from rough_map.config import StereoCalibration, load_mapping
from rough_map.errors import FileFormatError, SchemaError
from rough_map.evaluation.score_files import read_map_dir
from rough_map.evaluation.truth import world_on_cells
from rough_map.features import read_features, write_features
from rough_map.filter.roughness import load_roughness_smoother
from rough_map.io.traverse import load_traverse
from rough_map.io.truth import TiledWorldWriter, load_world, open_world, save_world
from rough_map.io.truth_raster import read_class_names
from rough_map.map.state import iter_state_tiles, read_state_meta, write_state
from rough_map.near_far.settings import load_near_far_settings
from rough_map.resources import config_file
from rough_map.stereo import StereoConfig, load_calibration
from rough_map.types import HeightField

pytestmark = pytest.mark.fuzz

CALIBRATION = StereoCalibration.xb3_default().model_dump(exclude_none=True)

TRAVERSE: dict[str, Any] = {
    "schema_version": "1.0",
    "name": "fuzz",
    "crs": {"code": "local", "origin": {"lat": 45.0, "lon": 7.5}},
    "calibration": CALIBRATION,
    "height_field": "world.npz",
    "metadata": {"source": "test", "nested": {"a": [1, 2.5, None, True]}},
    "frames": [
        {"t": 0.0, "pose": {"x": 0.0, "y": 0.0, "yaw": 0.1}, "cloud": "clouds/0.npy",
         "label": "gravel", "imu": {"roll": 0.01, "pitch": -0.02}},
        {"t": 0.5, "pose": {"x": 0.5, "y": 0.0, "z": 0.1, "roll": 0.0, "pitch": 0.0},
         "left": "img/l1.png", "right": "img/r1.png"},
    ],
}  # fmt: skip

TRAVERSE_JSON = json.dumps(TRAVERSE, indent=1).encode()
TRAVERSE_YAML = yaml.safe_dump(TRAVERSE, sort_keys=False).encode()
CALIBRATION_YAML = yaml.safe_dump(CALIBRATION, sort_keys=False).encode()
LEVELS_YAML = b'levels: [low, medium, high]\nthresholds: ["C/D", 1.0e-4]\n'


def ros_camera(right: bool) -> bytes:
    """A ROS CameraInfo YAML file of a 640 x 480 camera (the right one 10 cm away)."""
    p = [500.0, 0, 320, -50.0 if right else 0.0, 0, 500, 240, 0, 0, 0, 1, 0]
    doc = {
        "image_width": 640,
        "image_height": 480,
        "camera_name": "right" if right else "left",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [500.0, 0, 320, 0, 500, 240, 0, 0, 1]},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.01, 0, 0, 0, 0]},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0, 0, 0, 1, 0, 0, 0, 1]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": p},
    }
    return yaml.safe_dump(doc, sort_keys=False).encode()


OPENCV_YAML = b"""%YAML:1.0
---
M1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 800., 0., 322., 0., 805., 238., 0., 0., 1. ]
D1: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.21, 0.06, 0.001, -0.0015, 0. ]
M2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 810., 0., 315., 0., 812., 245., 0., 0., 1. ]
D2: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.18, 0.04, -0.0008, 0.001, 0. ]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ -0.12, 0.003, 0.002 ]
image_width: 640
image_height: 480
"""


# ----------------------------------------------------------------------------- the bases


BASES: dict[str, bytes] = {}
"""The generated bases (filled once per module; not a fixture argument of the fuzz targets,
so that hypothesis does not print them with every failing case)."""


@pytest.fixture(scope="module", autouse=True)
def bases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """The binary and generated bases: world files, features table, state, GeoTIFF."""
    if BASES:
        return BASES
    folder = tmp_path_factory.mktemp("bases")
    out = BASES
    rng = np.random.default_rng(0)
    heights = rng.normal(0, 0.01, (6, 9))
    classes = np.repeat(np.array([0, 1, 0, 1, 1, 0, 0, 1, -1], dtype=np.int8)[None], 6, 0)
    world = HeightField(heights, 0.01, (0.0, -0.03), classes, ("gravel", "concrete"))
    save_world(world, folder / "world.npz")
    out["world.npz"] = (folder / "world.npz").read_bytes()
    with TiledWorldWriter(
        folder / "tiled.npz", (6, 9), 0.01, (0.0, -0.03), ("gravel", "concrete"), tile_columns=4
    ) as writer:
        writer.append(0, heights, classes)
    out["tiled.npz"] = (folder / "tiled.npz").read_bytes()
    for name in ("roughness_smoothing.yaml", "near_far.yaml", "stereo.yaml"):
        out[name] = config_file(name).read_bytes()
    out.update(_features_files(folder))
    tile = ((0, 1), (0, 2, 1, 4), {"sum_R": np.ones((2, 3)), "n": np.full((2, 3), 2.0)})
    write_state(folder / "state.npz", {"resolution": 0.1, "tile_cells": 4}, [tile])
    out["state.npz"] = (folder / "state.npz").read_bytes()
    out["map_class.tif"] = _class_tif(folder / "map_class.tif")
    return out


def _features_files(folder: Path) -> dict[str, bytes]:
    from rough_map.features.table import (
        BOOL_COLUMNS,
        COLUMNS,
        INT_COLUMNS,
        TEXT_COLUMNS,
        FeatureTable,
    )

    n, omega = 3, np.array([10.0, 20.0, 40.0])
    cols: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        if c in TEXT_COLUMNS:
            cols[c] = np.array(["gravel", "", "C"], dtype=object)
        elif c in BOOL_COLUMNS:
            cols[c] = np.array([True, False, True])
        elif c in INT_COLUMNS:
            cols[c] = np.arange(n, dtype=np.int64)
        else:
            cols[c] = np.arange(n, dtype=float) + 1.5
    table = FeatureTable(cols, omega, np.log(np.ones((n, 3)) * 1e-5), "fuzz")
    write_features(table, folder / "features.csv")
    sidecar = next(folder.glob("features.csv.*"))
    return {
        "features.csv": (folder / "features.csv").read_bytes(),
        "features.meta": sidecar.read_bytes(),
        "features.meta.name": sidecar.name.encode(),
    }


def _class_tif(path: Path) -> bytes:
    import rasterio
    from rasterio.transform import from_origin

    data = np.array([[0, 1, 1, 255], [0, 0, 1, 255], [1, 1, 0, 0]], dtype=np.uint8)
    profile = {"driver": "GTiff", "height": 3, "width": 4, "count": 1, "dtype": "uint8",
               "nodata": 255, "transform": from_origin(0.0, 0.3, 0.1, 0.1)}  # fmt: skip
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(data, 1)
        ds.update_tags(1, layer="class", CLASS_0="gravel", CLASS_1="concrete")
    return path.read_bytes()


# ------------------------------------------------------------------------------- targets


def _traverse(path: Path) -> object:
    traverse = load_traverse(path)
    for i in range(len(traverse)):  # every path through the containment check
        frame = traverse.frames[i]
        for key in ("cloud", "left", "right"):
            if getattr(frame, key) is not None:
                traverse.resolve(getattr(frame, key), f"frames[{i}].{key}")
    return traverse


@FUZZ
@given(seed=SEEDS)
def test_traverse_json(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    assert_bounded(
        _traverse, write_case(tmp_path_factory, "traverse.json", mutate(TRAVERSE_JSON, seed))
    )


@FUZZ
@given(seed=SEEDS)
def test_traverse_yaml(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    assert_bounded(
        _traverse, write_case(tmp_path_factory, "traverse.yaml", mutate(TRAVERSE_YAML, seed))
    )


@FUZZ
@given(seed=SEEDS)
def test_calibration_yaml(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    path = write_case(tmp_path_factory, "calib.yaml", mutate(CALIBRATION_YAML, seed))
    assert_bounded(load_calibration, path)


@FUZZ
@given(seed=SEEDS)
def test_ros_camera_info(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    right = write_case(tmp_path_factory, "right.yaml", mutate(ros_camera(True), seed))
    left = right.with_name("left.yaml")
    left.write_bytes(ros_camera(False))
    assert_bounded(load_calibration, [left, right])


@FUZZ
@given(seed=SEEDS)
def test_opencv_file_storage(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    path = write_case(tmp_path_factory, "stereo.yml", mutate(OPENCV_YAML, seed))
    assert_bounded(load_calibration, path)


@FUZZ
@given(seed=SEEDS)
def test_roughness_levels(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    path = write_case(tmp_path_factory, "levels.yaml", mutate(LEVELS_YAML, seed))
    assert_bounded(load_roughness_levels, path)


@FUZZ
@given(seed=SEEDS)
def test_configs(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    bases = BASES
    readers = [("near_far.yaml", load_near_far_settings),
               ("roughness_smoothing.yaml", load_roughness_smoother),
               ("stereo.yaml", StereoConfig.from_file)]  # fmt: skip
    name, reader = readers[seed % 3]
    assert_bounded(reader, write_case(tmp_path_factory, name, mutate(bases[name], seed)))


def _use_world(path: Path) -> object:
    world = open_world(path)
    x = np.linspace(-0.05, 0.15, 7)
    if getattr(world, "classes", 0) is not None:
        world_on_cells(world, x, np.zeros_like(x))
    return load_world(path)


@FUZZ
@given(seed=SEEDS)
def test_world_npz(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    bases = BASES
    name = ("world.npz", "tiled.npz")[seed % 2]
    path = write_case(tmp_path_factory, "world.npz", mutate(bases[name], seed))
    assert_bounded(_use_world, path, max_bytes=16 * 2**20)


@FUZZ
@given(seed=SEEDS)
def test_features_table(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    bases = BASES
    table, meta = bases["features.csv"], bases["features.meta"]
    if seed % 2:
        table = mutate(table, seed)
    else:
        meta = mutate(meta, seed)
    path = write_case(tmp_path_factory, "features.csv", table)
    path.with_name(bases["features.meta.name"].decode()).write_bytes(meta)
    assert_bounded(read_features, path)


@FUZZ
@given(seed=SEEDS)
def test_state_meta(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    bases = BASES
    path = write_case(tmp_path_factory, "state.npz", mutate(bases["state.npz"], seed))
    assert_bounded(read_state_meta, path)
    assert_bounded(lambda p: list(iter_state_tiles(p, 4)), path, max_bytes=4 * 2**20)


@pytest.mark.filterwarnings("ignore:Exception ignored in. 'rasterio._env.log_error'")
@FUZZ
@given(seed=SEEDS)
def test_map_dir(tmp_path_factory: pytest.TempPathFactory, seed: int) -> None:
    bases = BASES
    path = write_case(tmp_path_factory, "map_class.tif", bases["map_class.tif"])
    labels = b"t,x,y,raw_class\n0.0,0.05,0.05,gravel\n0.5,0.15,0.1,concrete\n"
    side = json.dumps({"0": "gravel", "1": "concrete"}).encode()
    kind = seed % 3
    if kind == 0:
        path.write_bytes(mutate(bases["map_class.tif"], seed))
    (path.parent / "labels.csv").write_bytes(mutate(labels, seed) if kind == 1 else labels)
    if kind == 2:
        path.with_name("map_class.classes.json").write_bytes(mutate(side, seed))
        assert_bounded(read_class_names, path)
    assert_bounded(read_map_dir, path.parent, max_bytes=16 * 2**20)


# --------------------------------------------------------------- structure-aware cases


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
@pytest.mark.parametrize("kind", ["list", "mapping"])
def test_deep_nesting_is_refused(tmp_path: Path, suffix: str, kind: str) -> None:
    if kind == "list":
        inner = deep_json(10_000)
    else:
        inner = deep_json(10_000, open_='{"a": ', close="}").replace('{"a": }', "{}")
        inner = '{"a": ' * 10_000 + "1" + "}" * 10_000
    text = '{"schema_version": "1.0", "name": "x", "metadata": ' + inner + ', "frames": []}'
    path = _write(tmp_path, "traverse" + suffix, text)
    with pytest.raises(FileFormatError, match="nested deeper than 64 levels"):
        load_traverse(path)
    levels = _write(tmp_path, "levels" + suffix, '{"levels": ' + inner + "}")
    with pytest.raises(FileFormatError, match="nested deeper than 64 levels"):
        load_roughness_levels(levels)


def test_deep_block_yaml_is_refused(tmp_path: Path) -> None:
    text = "".join("  " * i + "a:\n" for i in range(400))
    with pytest.raises(FileFormatError, match=r"nested deeper than 64 levels \(line 6\d\)"):
        load_mapping(_write(tmp_path, "calib.yaml", text))


def test_nesting_within_the_bound_is_read(tmp_path: Path) -> None:
    doc = {"name": "x", "metadata": json.loads(deep_json(60))}
    assert load_mapping(_write(tmp_path, "a.json", json.dumps(doc)))["name"] == "x"
    assert load_mapping(_write(tmp_path, "a.yaml", json.dumps(doc)))["name"] == "x"


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_huge_integers_are_refused(tmp_path: Path, suffix: str) -> None:
    doc = copy.deepcopy(TRAVERSE)
    text = json.dumps(doc).replace('"t": 0.5', '"t": ' + "7" * 5000)
    with pytest.raises(FileFormatError, match="an integer of 5000 digits"):
        load_traverse(_write(tmp_path, "traverse" + suffix, text))
    calib = json.dumps(CALIBRATION).replace('"width": 1280', '"width": ' + "9" * 31)
    with pytest.raises(FileFormatError, match="an integer of 31 digits"):
        load_calibration(_write(tmp_path, "calib" + suffix, calib))
    ok = json.dumps(CALIBRATION).replace('"width": 1280', '"width": ' + "9" * 30)
    with pytest.raises(SchemaError, match=r"width: Input should be less than or equal to 65536"):
        load_calibration(_write(tmp_path, "ok" + suffix, ok))


def test_non_finite_numbers_name_the_field(tmp_path: Path) -> None:
    calib = json.dumps(CALIBRATION).replace('"fx": 985.0', '"fx": 1e999')
    with pytest.raises(SchemaError, match=r"fx: Input should be a finite number"):
        load_calibration(_write(tmp_path, "calib.json", calib))
    near_far = _write(tmp_path, "nf.yaml", "tile_size_m: .inf\n")
    with pytest.raises(SchemaError, match=r"tile_size_m: Input should be a finite number"):
        load_near_far_settings(near_far)


def test_yaml_billion_laughs_is_refused(tmp_path: Path) -> None:
    lines = ["a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    for i in range(1, 10):
        prev, name = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 9) + "]")
    path = _write(tmp_path, "levels.yaml", "\n".join(lines) + "\n")
    with pytest.raises(FileFormatError, match="aliases expand to more than 100000 values"):
        load_roughness_levels(path)


def test_recursive_yaml_alias_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path, "traverse.yaml", "name: &a [x, *a]\n")
    with pytest.raises(FileFormatError, match="an alias refers to itself"):
        load_traverse(path)


def test_modest_aliases_are_read(tmp_path: Path) -> None:
    text = "base: &p {x: 0.0, y: 0.0}\nlevels: [low, high]\nthresholds: [C/D]\n"
    path = _write(tmp_path, "x.yaml", text)
    assert load_mapping(path)["base"] == {"x": 0.0, "y": 0.0}


def test_python_tags_stay_refused(tmp_path: Path) -> None:
    path = _write(tmp_path, "levels.yaml", "levels: !!python/object/apply:os.system [ls]\n")
    with pytest.raises(FileFormatError, match="could not determine a constructor"):
        load_roughness_levels(path)


def test_big_config_files_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "levels.yaml"
    with path.open("wb") as fh:
        fh.truncate(64 * 2**20 + 1)  # sparse: no disk used
    with pytest.raises(FileFormatError, match="larger than 64 MB"):
        load_roughness_levels(path)


def test_undecodable_and_control_characters(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_bytes(b"name: \xff\xfe\n")
    with pytest.raises(FileFormatError, match=r"not UTF-8 text \(byte 6\)"):
        load_mapping(tmp_path / "a.yaml")
    (tmp_path / "b.yaml").write_bytes(b"name: a\x00b\n")
    with pytest.raises(FileFormatError, match="invalid YAML: unacceptable character"):
        load_mapping(tmp_path / "b.yaml")


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every location in a JSON document."""
    out = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, (*prefix, i))
    return out


def _set(doc: Any, where: tuple[Any, ...], value: Any) -> Any:
    if not where:
        return value
    doc = copy.deepcopy(doc)
    node = doc
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    return doc


WRONG = [[1, 2], {"x": 1}, "text", None, True, -1, 10**29, 1.5e308, "x" * 5000]


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_wrong_types_at_every_level_of_a_traverse(tmp_path: Path, suffix: str) -> None:
    refused = 0
    for n, where in enumerate(_paths(TRAVERSE)):
        for k, wrong in enumerate(WRONG):
            doc = _set(TRAVERSE, where, wrong)
            text = json.dumps(doc) if suffix == ".json" else yaml.safe_dump(doc)
            path = _write(tmp_path, f"t{n}_{k}{suffix}", text)
            result = assert_bounded(load_traverse, path)
            refused += isinstance(result, SchemaError)
            if isinstance(result, SchemaError) and where and where[0] != "metadata":
                first = where[0] if isinstance(where[0], str) else ""
                assert first in str(result) or "top level" in str(result), (where, result)
    assert refused > len(_paths(TRAVERSE)) * 3


@pytest.mark.parametrize(
    ("reader", "base"),
    [(load_roughness_levels, {"levels": ["low", "high"], "thresholds": ["C/D"]}),
     (load_near_far_settings, {"tile_size_m": 0.05, "max_range_m": 8.0, "calibrate": True}),
     (load_calibration, CALIBRATION)],
)  # fmt: skip
def test_wrong_types_in_configs(tmp_path: Path, reader: Any, base: dict[str, Any]) -> None:
    for n, where in enumerate(_paths(base)):
        for k, wrong in enumerate(WRONG):
            path = _write(tmp_path, f"c{n}_{k}.yaml", yaml.safe_dump(_set(base, where, wrong)))
            assert_bounded(reader, path)
    with pytest.raises(SchemaError, match=r"expected a mapping at the top level, got list"):
        reader(_write(tmp_path, "list.yaml", "[1, 2]"))


# ------------------------------------------------------- inputs that once broke a reader


def test_world_file_regressions(tmp_path: Path, bases: dict[str, bytes]) -> None:
    path = tmp_path / "world.npz"
    path.write_bytes(bases["world.npz"][:200])  # truncated: BadZipFile before
    with pytest.raises(FileFormatError, match="not a rough_map world file"):
        open_world(path)
    np.save(tmp_path / "h.npy", np.zeros((3, 3)))  # a .npy as the height field: TypeError
    with pytest.raises(FileFormatError, match="not a rough_map world file"):
        load_world(tmp_path / "h.npy")
    # a class map with indices beyond its names: IndexError in map_accuracy before
    bad = HeightField(np.zeros((4, 4)), 0.01, (0.0, 0.0), np.full((4, 4), 7, np.int8), ("a",))
    save_world(bad, path)
    with pytest.raises(FileFormatError, match=r"\[classes\]: values 7\.\.7 are not -1 or an index"):
        load_world(path)
    np.savez(path, heights=np.zeros((0, 4)), classes=np.zeros(0, np.int8), spacing=0.01,
             origin=np.zeros(2), class_names=np.array(["a"]))  # fmt: skip
    with pytest.raises(FileFormatError, match=r"\[heights\]: expected at least one cell"):
        load_world(path)


def test_world_member_sizes_are_checked_before_reading(tmp_path: Path) -> None:
    import zipfile

    path = tmp_path / "world.npz"
    with zipfile.ZipFile(path, "w") as zf:  # a header declaring 10**12 float64 cells
        header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1)))
        header["shape"] = (10**6, 10**6)
        with zf.open("heights.npy", "w") as fh:
            np.lib.format.write_array_header_1_0(fh, header)
            fh.write(b"\0" * 64)
    with pytest.raises(
        FileFormatError, match=r"\[heights\]: shape \(1000000, 1000000\) does not fit"
    ):
        assert_bounded(load_world, path, max_bytes=2**20)
        load_world(path)
    with zipfile.ZipFile(path, "w") as zf:  # an object array: pickle
        with zf.open("heights.npy", "w") as fh:
            np.lib.format.write_array(fh, np.array([{}], dtype=object), allow_pickle=True)
    with pytest.raises(FileFormatError, match=r"\[heights\]: .*dtype object holds Python objects"):
        load_world(path)


def test_features_regressions(tmp_path: Path, bases: dict[str, bytes]) -> None:
    meta_name = bases["features.meta.name"].decode()
    text = bases["features.csv"].decode()
    header, first, *rest = text.splitlines(keepends=True)
    column = header.strip().split(",")[1]
    cells = first.split(",")
    cells[1] = "abc"
    (tmp_path / "f.csv").write_text(header + ",".join(cells) + "".join(rest))
    (tmp_path / meta_name.replace("features.csv", "f.csv")).write_bytes(bases["features.meta"])
    with pytest.raises(
        FileFormatError, match=rf"\[{column}\]: row 1: expected a (whole )?number, got 'abc'"
    ):
        read_features(tmp_path / "f.csv")
    (tmp_path / "g.csv").write_bytes(b"\xff\xfe" + bases["features.csv"])
    with pytest.raises(FileFormatError, match=r"not UTF-8 text \(byte 0\)"):
        read_features(tmp_path / "g.csv")
    old = tmp_path / "old.csv"  # rough_map 0.1: the wavenumbers in the first line
    old.write_text("# rough_map features of x; omega_rad_per_m=1.0,abc\n" + header)
    with pytest.raises(FileFormatError, match=r"\[omega_rad_per_m\]: expected numbers"):
        read_features(old)
    shutil.copy(tmp_path / "f.csv", tmp_path / "h.csv")
    deep = '{"format": ' + deep_json(5000) + "}"
    (tmp_path / meta_name.replace("features.csv", "h.csv")).write_text(deep)
    with pytest.raises(FileFormatError, match="nested deeper than 64 levels"):
        read_features(tmp_path / "h.csv")


def test_state_meta_regressions(tmp_path: Path, bases: dict[str, bytes]) -> None:
    path = tmp_path / "state.npz"
    path.write_bytes(bases["state.npz"][:-30])
    with pytest.raises(FileFormatError, match="not a readable map state"):
        read_state_meta(path)
    import zipfile

    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("meta.json", "[" * 3000 + "]" * 3000)
    with pytest.raises(FileFormatError, match="nested deeper than 64 levels"):
        read_state_meta(path)
    with zipfile.ZipFile(path, "w") as zf:  # a tile declaring more cells than a tile holds
        for name, array in (("_window", np.array([0, 2, 0, 2])), ("sum_R", np.ones((9, 9)))):
            with zf.open(f"tile_0_0/{name}.npy", "w") as fh:
                np.lib.format.write_array(fh, array)
    with pytest.raises(FileFormatError, match=r"\[tile_0_0/sum_R\]: shape \(9, 9\) does not fit"):
        list(iter_state_tiles(path, 4))


def test_class_name_regressions(tmp_path: Path, bases: dict[str, bytes]) -> None:
    path = tmp_path / "map_class.tif"
    path.write_bytes(bases["map_class.tif"])
    side = path.with_name("map_class.classes.json")
    side.write_text('{"' + "9" * 50 + '": "gravel"}')
    with pytest.raises(FileFormatError, match=r"\[keys\]: keys must be integer class values"):
        read_class_names(path)
    side.write_text('{"99999": "gravel", "1": "concrete"}')  # a value no uint8 layer holds
    assert read_map_dir(tmp_path)["layers"]["class"][1] == ("value_0", "concrete")
