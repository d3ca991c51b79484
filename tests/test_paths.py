"""Paths in a traverse stay inside its folder unless the user allows more (issue 14).

Every file a traverse names (clouds, stereo images, the height field), symbolic links
followed, must resolve inside the traverse folder; ``allow_outside`` / ``--allow-outside
DIR`` names folders that are allowed too.
"""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from rough_map.cli.main import main
from rough_map.errors import SchemaError
from rough_map.features.frames import frame_jobs
from rough_map.io.traverse import load_traverse
from rough_map.io.truth import traverse_truth

OUTSIDE = r"resolves outside the traverse folder \(pass --allow-outside DIR to allow\)"


@pytest.fixture
def layout(small_traverse: Path, tmp_path: Path) -> tuple[Path, Path]:
    """``tmp/runs/trav`` (a copy of the small traverse) and ``tmp/outside`` (a cloud and a
    copy of the world truth)."""
    trav = tmp_path / "runs" / "trav"
    shutil.copytree(small_traverse, trav)
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copy(trav / "clouds" / "000000.npy", outside / "secret.npy")
    shutil.copy(trav / "world_truth.npz", outside / "world.npz")
    return trav, outside


def edit(trav: Path, **changes: object) -> None:
    """Change the traverse file: ``cloud0=...`` sets frames[0].cloud, others top-level keys."""
    doc = json.loads((trav / "traverse.json").read_text())
    for key, value in changes.items():
        if key == "cloud0":
            doc["frames"][0]["cloud"] = value
        elif key == "pair1":
            doc["frames"][1]["left"], doc["frames"][1]["right"] = value  # type: ignore[misc]
        else:
            doc[key] = value
    (trav / "traverse.json").write_text(json.dumps(doc))


def test_dotdot_cloud_is_refused_and_allowed_on_request(layout: tuple[Path, Path]) -> None:
    trav, outside = layout
    edit(trav, cloud0="../../outside/secret.npy")
    traverse = load_traverse(trav)  # the file itself is fine: paths are checked when used
    with pytest.raises(
        SchemaError, match=r"frames\[0\]\.cloud: '\.\./\.\./outside/secret\.npy' " + OUTSIDE
    ):
        traverse.load_cloud(0)
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: .*" + OUTSIDE):
        traverse.validate_files()
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud"):
        frame_jobs(traverse)
    allowed = load_traverse(trav, allow_outside=[outside])
    assert allowed.load_cloud(0).shape[1] == 3
    assert allowed.cloud_path(0) == (outside / "secret.npy").resolve()
    allowed.validate_files()
    # the allowance travels with the object to worker processes
    assert pickle.loads(pickle.dumps(allowed)).load_cloud(0).shape[1] == 3


def test_symlinked_cloud_file_is_refused(layout: tuple[Path, Path]) -> None:
    trav, outside = layout
    link = trav / "clouds" / "000000.npy"
    link.unlink()
    link.symlink_to(outside / "secret.npy")
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: 'clouds/000000\.npy' " + OUTSIDE):
        load_traverse(trav).load_cloud(0)
    assert load_traverse(trav, allow_outside=[outside]).load_cloud(0).shape[1] == 3


def test_symlinked_clouds_folder_is_refused(layout: tuple[Path, Path]) -> None:
    trav, outside = layout
    moved = outside / "clouds"
    shutil.move(trav / "clouds", moved)
    (trav / "clouds").symlink_to(moved)
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: .*" + OUTSIDE):
        load_traverse(trav).validate_files()
    load_traverse(trav, allow_outside=[moved]).validate_files()


def test_a_link_inside_the_folder_is_fine(layout: tuple[Path, Path]) -> None:
    trav, _ = layout
    (trav / "alias").symlink_to(trav / "clouds")
    edit(trav, cloud0="alias/000000.npy")
    assert load_traverse(trav).load_cloud(0).shape[1] == 3


def test_dotdot_height_field_is_refused(layout: tuple[Path, Path]) -> None:
    trav, outside = layout
    edit(trav, height_field="../../outside/world.npz")
    with pytest.raises(SchemaError, match=r"traverse\.json: height_field: .*" + OUTSIDE):
        traverse_truth(load_traverse(trav))
    with pytest.raises(SchemaError, match=r"height_field: .*" + OUTSIDE):
        load_traverse(trav).validate_files()
    world = traverse_truth(load_traverse(trav, allow_outside=[outside]))
    assert world is not None and world.shape[0] > 0


def test_image_paths_are_refused(layout: tuple[Path, Path]) -> None:
    trav, outside = layout
    (outside / "l.png").write_bytes(b"")
    edit(trav, pair1=["../../outside/l.png", "../../outside/l.png"])
    with pytest.raises(SchemaError, match=r"frames\[1\]\.left: .*" + OUTSIDE):
        frame_jobs(load_traverse(trav))
    with pytest.raises(SchemaError, match=r"frames\[1\]\.left: .*" + OUTSIDE):
        load_traverse(trav).validate_files()
    jobs = frame_jobs(load_traverse(trav, allow_outside=[outside]))
    assert jobs[1].left == (outside / "l.png").resolve()


@pytest.mark.parametrize("path", ["/etc/passwd", "C:\\data\\c.npy", "\\\\server\\share\\c.npy"])
def test_absolute_paths_are_refused_when_loading(layout: tuple[Path, Path], path: str) -> None:
    trav, _ = layout
    edit(trav, cloud0=path)
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: .* must be a path relative"):
        load_traverse(trav, allow_outside=["/"])


def test_unresolvable_paths_name_the_field(layout: tuple[Path, Path]) -> None:
    trav, _ = layout
    edit(trav, cloud0="x" * 300 + ".npy")  # a name too long for the file system
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: 'x+\.\.\. cannot be read"):
        load_traverse(trav).load_cloud(0)
    (trav / "loop").symlink_to(trav / "loop")
    edit(trav, cloud0="loop/c.npy")
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: 'loop/c\.npy'"):
        load_traverse(trav).validate_files()
    edit(trav, cloud0="a\x00b.npy")
    with pytest.raises(SchemaError, match=r"frames\[0\]\.cloud: .*NUL"):
        load_traverse(trav)


def test_cli_refuses_and_allows_outside(
    layout: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    trav, outside = layout
    edit(trav, cloud0="../../outside/secret.npy")
    out = trav.parent / "f.csv"
    assert main(["-q", "features", str(trav), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "frames[0].cloud" in err and "--allow-outside" in err and "\n" not in err.strip()
    assert not out.exists()
    args = ["-q", "features", str(trav), "--out", str(out), "--allow-outside", str(outside)]
    assert main(args) == 0
    assert out.is_file()
    maps = trav.parent / "map"
    assert main(["-q", "map", str(trav), "--out", str(maps), "--near-far", "off"]) == 2
    err = capsys.readouterr().err
    assert "frames[0].cloud" in err and "--allow-outside DIR" in err
    assert main(["-q", "map", str(trav), "--out", str(maps), "--near-far", "off",
                 "--allow-outside", "/nowhere", "--allow-outside", str(outside)]) == 0  # fmt: skip
    assert (maps / "map_state.npz").is_file() or any(maps.iterdir())


def test_every_traverse_command_takes_allow_outside(capsys: pytest.CaptureFixture[str]) -> None:
    for command in ("map", "report", "classify", "evaluate", "train", "features", "batch"):
        try:
            main([command, "--help"])
        except SystemExit:
            pass
        assert "--allow-outside DIR" in capsys.readouterr().out, command


def test_feature_tables_keep_the_allowance(layout: tuple[Path, Path]) -> None:
    from rough_map.features import feature_tables

    trav, outside = layout
    edit(trav, cloud0="../../outside/secret.npy")
    with pytest.raises(SchemaError, match=OUTSIDE):
        feature_tables([trav])
    (table,) = feature_tables([load_traverse(trav, allow_outside=[outside])])
    assert len(table) == len(load_traverse(trav)) and np.asarray(table.valid).any()
