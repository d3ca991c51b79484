"""The traverse format: pydantic models, the committed JSON Schema, loading and saving."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from rough_map.cli.main import main
from rough_map.config import (
    SCHEMA_VERSION,
    Crs,
    Pose,
    TraverseSpec,
    format_location,
    schema_texts,
    write_schemas,
)
from rough_map.errors import FileFormatError, SchemaError
from rough_map.io.pointcloud import write_cloud
from rough_map.io.traverse import Traverse, load_traverse, save_traverse

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cli_logging() -> Iterator[None]:
    """Undo the logging set-up of ``main()``: later tests read logs through caplog."""
    logger = logging.getLogger("rough_map")
    saved = logger.handlers[:], logger.level, logger.propagate
    yield
    logger.handlers[:], logger.level, logger.propagate = saved


CAMERA_TO_VEHICLE = [  # camera looking ahead, 1 m up: x_v = z_c, y_v = -x_c, z_v = -y_c
    [0.0, 0.0, 1.0, 0.0],
    [-1.0, 0.0, 0.0, 0.0],
    [0.0, -1.0, 0.0, 1.0],
    [0.0, 0.0, 0.0, 1.0],
]


def minimal() -> dict[str, Any]:
    return {
        "schema_version": "1.0",
        "name": "field_a",
        "frames": [
            {"t": 0.0, "pose": {"x": 0.0, "y": 0.0}, "cloud": "clouds/a.npy", "label": "gravel"},
            {"t": 0.5, "pose": {"x": 1.0, "y": 0.1}, "cloud": "clouds/b.npy", "label": "grass"},
        ],
    }


def full() -> dict[str, Any]:
    data = minimal()
    data.update(
        crs={"code": "local", "origin": {"lat": 47.4, "lon": 8.5, "alt": 420.0}},
        calibration={
            "fx": 985.0, "fy": 985.0, "cx": 639.5, "cy": 479.5, "width": 1280, "height": 960,
            "baseline": 0.24, "camera_to_vehicle": CAMERA_TO_VEHICLE,
        },
        height_field="truth/heights.npz",
        metadata={"simulator": {"seed": 3, "ground_truth": "truth/"}},
    )  # fmt: skip
    data["frames"][0].update(
        pose={"x": 0, "y": 0, "z": 0.2, "roll": 0.01, "pitch": -0.02, "yaw": 1.5},
        left="img/l0.png",
        right="img/r0.png",
        imu={"roll": 0.011, "pitch": -0.019},
    )
    return data


def write(folder: Path, data: dict[str, Any], name: str = "traverse.json") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data) if name.endswith(".json") else yaml.safe_dump(data)
    (folder / name).write_text(text)
    return folder / name


def load_error(folder: Path, data: dict[str, Any]) -> SchemaError:
    write(folder, data)
    with pytest.raises(SchemaError) as info:
        load_traverse(folder)
    return info.value


# --------------------------------------------------------------------------------------------
# The committed schema


def test_committed_schema_is_up_to_date() -> None:
    committed = ROOT / "data_schema" / "traverse.schema.json"
    assert committed.read_text(encoding="utf-8") == schema_texts()["traverse.schema.json"], (
        "data_schema/ is stale: run `rough-map schema --out data_schema`"
    )


def test_schema_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], cli_logging: None
) -> None:
    assert main(["schema", "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / "traverse.schema.json")]
    assert write_schemas(tmp_path / "again") == [tmp_path / "again" / "traverse.schema.json"]
    assert main(["schema", "--check", "--out", str(tmp_path)]) == 0
    (tmp_path / "traverse.schema.json").write_text("{}\n")
    assert main(["schema", "--check", "--out", str(tmp_path)]) == 1
    assert "out of date" in capsys.readouterr().err


def test_examples_against_json_schema() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(schema_texts()["traverse.schema.json"])
    validator = jsonschema.Draft202012Validator(schema)
    for data in (minimal(), full(), {**minimal(), "crs": "EPSG:32633"}, {**minimal(), "crs": 2056}):
        validator.validate(data)
    typo = minimal()
    typo["frames"][0]["lable"] = "gravel"
    assert not validator.is_valid(typo)


# --------------------------------------------------------------------------------------------
# Valid traverses


@pytest.mark.parametrize("name", ["traverse.json", "traverse.yaml", "traverse.yml"])
def test_minimal_traverse_loads(name: str, tmp_path: Path) -> None:
    write(tmp_path, minimal(), name)
    traverse = load_traverse(tmp_path)
    assert traverse.source == tmp_path / name and traverse.root == tmp_path
    assert traverse.name == "field_a" and len(traverse) == 2
    assert traverse.spec.crs == Crs(code="local")
    assert traverse.frames[1].pose == Pose(x=1.0, y=0.1, z=0.0, roll=0.0, pitch=0.0, yaw=0.0)
    assert traverse.labels() == ["gravel", "grass"]
    np.testing.assert_array_equal(traverse.times(), [0.0, 0.5])
    assert load_traverse(tmp_path / name).spec == traverse.spec  # the file itself


def test_full_traverse_loads(tmp_path: Path) -> None:
    write(tmp_path, full())
    spec = load_traverse(tmp_path).spec
    assert spec.crs.origin is not None and spec.crs.origin.lat == 47.4
    assert spec.calibration is not None and spec.calibration.baseline == 0.24
    assert spec.metadata["simulator"]["seed"] == 3
    assert spec.frames[0].imu is not None and spec.frames[0].imu.pitch == -0.019
    np.testing.assert_array_equal(spec.frames[0].pose.matrix()[3], [0, 0, 0, 1])


@pytest.mark.parametrize(
    ("crs", "code", "epsg"),
    [
        ("local", "local", None),
        ("LOCAL", "local", None),
        ("EPSG:32633", "EPSG:32633", 32633),
        ("epsg:2056", "EPSG:2056", 2056),
        (32633, "EPSG:32633", 32633),
        ({"code": "EPSG:4978"}, "EPSG:4978", 4978),
    ],
)
def test_crs_forms(crs: object, code: str, epsg: int | None) -> None:
    spec = TraverseSpec.model_validate({**minimal(), "crs": crs})
    assert (spec.crs.code, spec.crs.epsg) == (code, epsg)


def test_save_load_round_trip(tmp_path: Path) -> None:
    spec = TraverseSpec.model_validate(full())
    path = save_traverse(spec, tmp_path / "out")
    assert path == tmp_path / "out" / "traverse.json"
    assert load_traverse(tmp_path / "out").spec == spec
    text = path.read_text()
    frame_lines = [line.strip().rstrip(",") for line in text.splitlines() if '"t":' in line]
    assert [json.loads(line)["t"] for line in frame_lines] == [0.0, 0.5]  # a frame per line
    assert "null" not in text  # unset optional fields are left out
    again = TraverseSpec.model_validate({**minimal(), "crs": "EPSG:32633"})
    save_traverse(Traverse.from_spec(again, tmp_path / "out"), tmp_path / "out")
    assert json.loads(path.read_text())["crs"] == "EPSG:32633"
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["traverse.json"]


def test_save_refuses_beside_yaml(tmp_path: Path) -> None:
    write(tmp_path, minimal(), "traverse.yaml")
    with pytest.raises(FileFormatError, match=r"holds traverse\.yaml"):
        save_traverse(TraverseSpec.model_validate(minimal()), tmp_path)


def test_load_cloud_vehicle_and_world(tmp_path: Path) -> None:
    data = minimal()
    data["frames"][1]["pose"] = {"x": 10.0, "y": 20.0, "z": 1.0, "yaw": np.pi / 2}
    write(tmp_path, data)
    (tmp_path / "clouds").mkdir()
    write_cloud(tmp_path / "clouds" / "b.npy", np.array([[1.0, 0.0, 0.0], [0.0, 2.0, -1.0]]))
    traverse = load_traverse(tmp_path)
    np.testing.assert_array_equal(traverse.load_cloud(1), [[1.0, 0.0, 0.0], [0.0, 2.0, -1.0]])
    # Yaw +90 deg: vehicle x (forward) points to world +y.
    world = traverse.load_cloud(-1, frame="world")
    np.testing.assert_allclose(world, [[10.0, 21.0, 1.0], [8.0, 20.0, 0.0]], atol=1e-12)


# --------------------------------------------------------------------------------------------
# Errors name the file, the frame and the field


def test_error_names_file_frame_and_field(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    data = minimal()
    data["frames"] += [
        {"t": 1.0, "pose": {"x": 2.0, "y": 0.0}, "cloud": "c.npy"},
        {"t": 1.5, "pose": {"y": 0.0, "yaw": 0.1}, "cloud": "d.npy"},
    ]
    write(Path("runs/a"), data)
    with pytest.raises(SchemaError) as info:
        load_traverse("runs/a")
    assert str(info.value) == "runs/a/traverse.json: frames[3].pose.x: Field required"
    assert info.value.field == "frames[3].pose.x"
    assert info.value.path == Path("runs/a/traverse.json")


def test_unknown_keys_are_errors(tmp_path: Path) -> None:
    data = minimal()
    data["frames"][1]["lable"] = "grass"
    data["metdata"] = {}
    message = str(load_error(tmp_path, data))
    assert "frames[1].lable: unknown field (a typo?)" in message
    assert "metdata: unknown field (a typo?)" in message


def test_times_must_increase(tmp_path: Path) -> None:
    data = minimal()
    data["frames"].append({"t": 0.5, "pose": {"x": 2.0, "y": 0.0}, "cloud": "c.npy"})
    error = load_error(tmp_path, data)
    assert str(error).endswith(
        "traverse.json: frames[2].t: time 0.5 s is not after frames[1].t = 0.5 s"
    )
    assert error.field == "frames[2].t"


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"schema_version": "2.0"}, "schema_version: Input should be '1.0'"),
        ({"name": ""}, "name: String should have at least 1 character"),
        ({"frames": []}, "frames: List should have at least 1 item"),
        ({"crs": "UTM33"}, "crs: crs must be 'local', 'EPSG:<code>' or an EPSG integer"),
        ({"crs": {"code": "EPSG:2056", "origin": {"lat": 0, "lon": 0}}}, "crs: origin is only"),
        (
            {"crs": {"code": "local", "origin": {"lat": 91, "lon": 0}}},
            "crs.origin.lat: Input should be less than or equal to 90",
        ),
        ({"height_field": "/truth.npz"}, "height_field: '/truth.npz' must be a path relative"),
        ({"calibration": {"fx": 1}}, "calibration.fy: Field required"),
    ],
)
def test_top_level_errors(change: dict[str, Any], expected: str, tmp_path: Path) -> None:
    assert expected in str(load_error(tmp_path, {**minimal(), **change}))


def test_calibration_transform_checked(tmp_path: Path) -> None:
    calibration = full()["calibration"]
    calibration["camera_to_vehicle"] = [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    error = load_error(tmp_path, {**minimal(), "calibration": calibration})
    assert "calibration.camera_to_vehicle: camera_to_vehicle rotation block is not" in str(error)


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ({"cloud": None}, "frames[2]: a frame needs a cloud or a left/right image pair"),
        ({"left": "l.png"}, "frames[2]: left and right images come together"),
        ({"cloud": "C:\\c.npy"}, "frames[2].cloud: 'C:\\\\c.npy' must be a path relative"),
        ({"pose": {"x": 0, "y": "north"}}, "frames[2].pose.y: Input should be a valid number"),
        ({"imu": {"roll": 0}}, "frames[2].imu.pitch: Field required"),
        ({"label": ""}, "frames[2].label: String should have at least 1 character"),
    ],
)
def test_frame_errors(extra: dict[str, Any], expected: str, tmp_path: Path) -> None:
    data = minimal()
    data["frames"].append({"t": 1.0, "pose": {"x": 0, "y": 0}, "cloud": "c.npy", **extra})
    assert expected in str(load_error(tmp_path, data))


def test_many_errors_are_counted(tmp_path: Path) -> None:
    data = minimal()
    data["frames"] = [{"t": i, "pose": {}, "cloud": "c.npy"} for i in range(3)]
    message = str(load_error(tmp_path, data))
    assert message.count("Field required") == 3
    assert message.endswith("(and 3 more problems)")


def test_nan_is_refused(tmp_path: Path) -> None:
    (tmp_path / "traverse.json").write_text(json.dumps(minimal()).replace('"x": 1.0', '"x": NaN'))
    with pytest.raises(SchemaError, match=r"frames\[1\]\.pose\.x: Input should be a finite number"):
        load_traverse(tmp_path)


def test_missing_files_checked_lazily(tmp_path: Path) -> None:
    write(tmp_path, minimal())
    (tmp_path / "clouds").mkdir()
    write_cloud(tmp_path / "clouds" / "a.npy", np.zeros((3, 3)))
    traverse = load_traverse(tmp_path)  # loads although clouds/b.npy is missing
    assert traverse.load_cloud(0).shape == (3, 3)
    with pytest.raises(
        SchemaError, match=r"traverse\.json: frames\[1\]\.cloud: clouds/b\.npy does not exist"
    ):
        traverse.load_cloud(1)
    with pytest.raises(
        SchemaError, match=r"frames\[1\]\.cloud: clouds/b\.npy does not exist$"
    ) as info:
        traverse.validate_files()
    assert info.value.field == "frames[1].cloud"
    with pytest.raises(IndexError, match=r"frame 7 out of range: .* has 2 frames"):
        traverse.load_cloud(7)


# --------------------------------------------------------------------------------------------
# Files that are not traverses


def test_yaml_is_loaded_safely(tmp_path: Path) -> None:
    (tmp_path / "traverse.yaml").write_text("!!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(
        FileFormatError, match=r"traverse\.yaml: invalid YAML: could not determine a constructor"
    ):
        load_traverse(tmp_path)


def test_syntax_errors_and_wrong_top_level(tmp_path: Path) -> None:
    (tmp_path / "traverse.json").write_text('{"schema_version": "1.0",\n "name": }')
    with pytest.raises(
        FileFormatError, match=r"invalid JSON at line 2, column 10: Expecting value"
    ):
        load_traverse(tmp_path)
    (tmp_path / "traverse.json").write_text("[1, 2]")
    with pytest.raises(SchemaError, match="expected a mapping at the top level, got list"):
        load_traverse(tmp_path)
    (tmp_path / "bad.yaml").write_text("name: [unclosed\n")
    with pytest.raises(FileFormatError, match=r"bad\.yaml: invalid YAML: .*line 2"):
        load_traverse(tmp_path / "bad.yaml")


def test_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(FileFormatError, match=r"not a traverse folder: none of traverse\.json"):
        load_traverse(tmp_path)
    with pytest.raises(FileFormatError, match="no such file or folder"):
        load_traverse(tmp_path / "nope")
    write(tmp_path, minimal())
    write(tmp_path, minimal(), "traverse.yml")
    with pytest.raises(
        FileFormatError, match=r"ambiguous traverse folder: both traverse\.json, traverse\.yml"
    ):
        load_traverse(tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(
        FileFormatError, match=r"notes\.txt \[suffix\]: expected \.json, \.yaml or \.yml"
    ):
        load_traverse(tmp_path / "notes.txt")


def test_format_location() -> None:
    assert format_location(("frames", 3, "pose", "yaw")) == "frames[3].pose.yaw"
    assert format_location(()) == "(top level)"
    assert SCHEMA_VERSION == "1.0"


def test_world_frame_clouds_read_as_their_vehicle_frame_twins(small_traverse, tmp_path):
    """cloud_frame: world (registered scans): each cloud is moved into the vehicle frame
    with its pose, so the features are those of the same clouds stored in the vehicle
    frame (issue 30)."""
    import json
    import shutil

    from rough_map.features import traverse_features
    from rough_map.io.pointcloud import write_cloud
    from rough_map.io.traverse import load_traverse

    world = tmp_path / "world"
    shutil.copytree(small_traverse, world)
    trav = load_traverse(small_traverse)
    for i, frame in enumerate(trav.frames):
        write_cloud(world / frame.cloud, trav.load_cloud(i, frame="world"))
    spec = json.loads((world / "traverse.json").read_text())
    spec["cloud_frame"] = "world"
    (world / "traverse.json").write_text(json.dumps(spec))
    twin = load_traverse(world)
    np.testing.assert_allclose(twin.load_cloud(2), trav.load_cloud(2), atol=1e-5)
    np.testing.assert_allclose(twin.load_cloud(2, frame="world"),
                               trav.load_cloud(2, frame="world"), atol=1e-5)  # fmt: skip
    a, b = traverse_features(trav), traverse_features(twin)
    assert list(a.valid) == list(b.valid) and a.valid.any()
    np.testing.assert_allclose(b["R"][a.valid], a["R"][a.valid], rtol=1e-3)
    np.testing.assert_allclose(b["w"][a.valid], a["w"][a.valid], atol=1e-3)
