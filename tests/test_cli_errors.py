"""Every failure of a ``rough-map`` command is one line on stderr, ``rough-map CMD: error:
MESSAGE``, printable, at most about 200 characters, with exit status 2 (issue 14).

Broken inputs per command (a missing file, an empty file, a truncated cloud, a folder where
a file is expected, a damaged model, bag, calibration, truth raster...) go through
``main([...])``; the exceptions the CLI meets that are not rough_map's own (an OSError, a
MemoryError, a worker process killed, a bug) go through :func:`failure_line`.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import pickle
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from rough_map._bounded import shorten
from rough_map.cli._common import MAX_ERROR_MESSAGE, error_line, printable
from rough_map.cli.main import failure_line, main
from rough_map.errors import FileFormatError, SchemaError

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
LIMIT = 240  # what tests/fuzzing.py accepts (the CLI's message is at most 200 characters)


def one_line_error(capsys: pytest.CaptureFixture[str], argv: list[object], command: str) -> str:
    """Run ``rough-map argv``; assert exit 2 and one printable error line; return it."""
    code = main([str(a) for a in argv])
    _, err = capsys.readouterr()
    lines = err.splitlines()
    assert code == 2, (code, err[-500:])
    assert len(lines) == 1, err[:2000]
    line = lines[0]
    assert len(line) <= LIMIT and line.isprintable(), repr(line)
    assert line.startswith(f"rough-map {command}: error: "), line
    return line


# --------------------------------------------------------------------------- the helpers


def test_printable_escapes_control_characters_and_joins_lines() -> None:
    assert printable("a\nb\r\n  c") == "a b c"
    assert printable("bad \x00\x1b[31m byte") == "bad \\x00\\x1b[31m byte"
    assert printable("name \udcff.ply") == "name \\udcff.ply"
    assert printable("tab\there") == "tab here"
    assert printable("plain é") == "plain é"


def test_shorten_keeps_the_start_and_the_end() -> None:
    text = "/data/file.ply: " + "x" * 300 + " END"
    short = shorten(text, 100)
    assert len(short) == 100
    assert short.startswith("/data/file.ply: ") and short.endswith(" END") and "…" in short
    assert shorten("short", 100) == "short"


def test_error_line_is_bounded() -> None:
    line = error_line("rough-map map", "/p/traverse.json: " + "\x00" * 5000)
    assert len(line) == len("rough-map map: error: ") + MAX_ERROR_MESSAGE and line.isprintable()
    assert line.startswith("rough-map map: error: /p/traverse.json: \\x00")


def test_oserror_names_its_file() -> None:
    exc = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/out/map.tif")
    assert failure_line("map", exc) == "rough-map map: error: /out/map.tif: No space left on device"
    exc = PermissionError(errno.EACCES, "Permission denied", "/a", None, "/b")
    assert failure_line("map", exc) == "rough-map map: error: /a -> /b: Permission denied"
    assert failure_line("map", OSError("plain")) == "rough-map map: error: plain"


def test_memory_error_says_out_of_memory() -> None:
    line = failure_line("map", MemoryError())
    assert line.startswith("rough-map map: error: out of memory while running map")


def test_other_exceptions_are_one_line_internal_errors(caplog) -> None:
    spec: dict[str, list[int]] = {}
    try:
        spec["frames"]
    except KeyError as exc:
        err = exc
    line = failure_line("features", err)
    assert line == (
        "rough-map features: internal error: KeyError: 'frames' "
        "(please report; rerun with -vv for the traceback)"
    )
    long = failure_line("features", ValueError("v" * 1000 + "\nsecond line"))
    assert len(long) <= LIMIT and "\n" not in long
    assert long.endswith("(please report; rerun with -vv for the traceback)")
    # The traceback is logged only at debug level (-vv).
    logger = logging.getLogger("rough_map")
    saved = logger.level
    try:
        logger.setLevel(logging.DEBUG)
        with caplog.at_level(logging.DEBUG, logger="rough_map"):
            failure_line("features", err)
        assert any(r.exc_info and r.exc_info[0] is KeyError for r in caplog.records)
    finally:
        logger.setLevel(saved)


def test_rough_map_errors_survive_pickling() -> None:
    """A worker's FileFormatError reaches the parent as itself (joblib pickles it)."""
    for exc in (
        FileFormatError("/a.ply", "bad header", field="vertex"),
        SchemaError("/t.json", "x"),
    ):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc)
        assert back.path == exc.path and back.field == exc.field


def _raise_in_worker(kind: str) -> None:
    if kind == "format":
        raise FileFormatError("/data/c.ply", "truncated", field="vertex")
    os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        ("format", "rough-map features: error: /data/c.ply [vertex]: truncated"),
        ("killed", "rough-map features: error: a worker process died (exit codes {SIGKILL(-9)})"),
    ],
)
def test_errors_of_joblib_workers_are_one_line(kind: str, expected: str) -> None:
    from joblib.externals.loky import get_reusable_executor

    executor = get_reusable_executor(max_workers=1)
    try:
        with pytest.raises(Exception) as info:
            executor.submit(_raise_in_worker, kind).result()
    finally:
        executor.shutdown(wait=True)
    line = failure_line("features", info.value)
    assert line.startswith(expected) and "\n" not in line and len(line) <= LIMIT


# --------------------------------------------------------------------------- argparse


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["nope"],
        ["features"],
        ["features", "a\nb", "extra\x00arg"],
        ["map", "--resolution", "x" * 500, "T", "--out", "D"],
    ],
)
def test_bad_arguments_are_one_line(capsys, argv) -> None:
    code = main(argv)
    _, err = capsys.readouterr()
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1 and len(lines[0]) <= LIMIT and lines[0].isprintable(), err


# --------------------------------------------------------------------------- broken inputs


@pytest.fixture(scope="module")
def broken(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One broken input of each kind."""
    d = tmp_path_factory.mktemp("broken")
    cases: dict[str, Path] = {}
    pts = np.random.default_rng(0).uniform(0, 1, (3000, 3))
    np.save(d / "good.npy", pts)
    (d / "truncated.npy").write_bytes((d / "good.npy").read_bytes()[:2000])
    (d / "empty.ply").write_bytes(b"")
    (d / "garbage.pcd").write_bytes(bytes(range(256)) * 40)
    (d / "folder.ply").mkdir()
    (d / "empty_traverse").mkdir()
    (d / "bad_json").mkdir()
    (d / "bad_json" / "traverse.json").write_bytes(b'{"frames": [\x00\x01\xff' + b"\n" * 50)
    (d / "deep").mkdir()
    (d / "deep" / "traverse.json").write_text("[" * 100_000 + "]" * 100_000)
    (d / "empty.bag").write_bytes(b"")
    (d / "garbage.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 30)
    (d / "garbage.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\xff" * 4000)
    (d / "bad.tif").write_bytes(b"II*\x00" + b"\xff" * 100)
    (d / "calib.yaml").write_text("fx: [1, 2\nfy: \x07\n")
    (d / "calib_empty.yaml").write_text("")
    (d / "left.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 50)
    # A model whose .skops is 30 KB of raw bytes, with a card whose sha256 matches them,
    # so that the reader gets as far as parsing it.
    model = d / "model"
    model.mkdir()
    raw = bytes(range(256)) * 120
    (model / "default.skops").write_bytes(raw)
    card = json.loads((MODELS / "default.card.json").read_text())
    card["sha256"] = hashlib.sha256(raw).hexdigest()
    card["size_bytes"] = len(raw)
    (model / "default.card.json").write_text(json.dumps(card))
    tampered = d / "tampered"
    shutil.copytree(MODELS, tampered)
    with open(tampered / "default.skops", "ab") as f:
        f.write(b"\x00")
    cases.update({p.name: p for p in d.iterdir()})
    return cases


FEATURES_INPUTS = ["truncated.npy", "empty.ply", "garbage.pcd", "folder.ply", "empty_traverse",
                   "bad_json", "deep"]  # fmt: skip


@pytest.mark.parametrize("name", FEATURES_INPUTS)
def test_features_on_broken_inputs(capsys, broken, tmp_path, name) -> None:
    argv = ["features", broken[name]]
    if broken[name].is_dir():
        argv += ["--out", tmp_path / "f.csv"]
    one_line_error(capsys, argv, "features")


def test_features_names_the_missing_file(capsys, tmp_path) -> None:
    line = one_line_error(capsys, ["features", tmp_path / "missing.ply"], "features")
    assert "missing.ply" in line


@pytest.mark.parametrize("name", ["empty_traverse", "bad_json", "deep", "empty.ply"])
def test_map_on_broken_traverses(capsys, broken, tmp_path, name) -> None:
    one_line_error(capsys, ["map", broken[name], "--out", tmp_path / "map"], "map")


@pytest.mark.parametrize("name", ["model", "tampered"])
def test_classify_with_a_broken_model(capsys, broken, small_traverse, tmp_path, name) -> None:
    line = one_line_error(
        capsys,
        [
            "classify",
            small_traverse,
            "--model",
            broken[name] / "default",
            "--out",
            tmp_path / "l.csv",
        ],
        "classify",
    )
    assert "default" in line


@pytest.mark.parametrize("name", ["empty.bag", "garbage.bag", "garbage.mcap", "folder.ply"])
def test_inspect_and_import_broken_bags(capsys, broken, tmp_path, name) -> None:
    one_line_error(capsys, ["inspect", broken[name]], "inspect")
    argv = ["import", broken[name], "--points-topic", "/points", "--odom-topic", "/odom"]
    one_line_error(capsys, [*argv, "--out", tmp_path / "t"], "import")


def test_score_with_a_broken_truth(capsys, broken, tmp_path) -> None:
    (tmp_path / "map").mkdir()
    one_line_error(capsys, ["score", tmp_path / "map", "--truth", broken["bad.tif"]], "score")


@pytest.mark.parametrize("calib", ["calib.yaml", "calib_empty.yaml", "garbage.pcd"])
def test_stereo_with_a_broken_calibration(capsys, broken, tmp_path, calib) -> None:
    argv = ["stereo", broken["left.png"], broken["left.png"], "--calib", broken[calib]]
    line = one_line_error(capsys, [*argv, "--out", tmp_path / "p.ply"], "stereo")
    assert "required" not in line


def test_stereo_with_broken_images(capsys, broken, tmp_path) -> None:
    calib = ROOT / "configs" / "stereo_calibration.yaml"
    argv = ["stereo", broken["left.png"], broken["empty.ply"], "--calib", calib]
    line = one_line_error(capsys, [*argv, "--out", tmp_path / "p.ply"], "stereo")
    assert "required" not in line


@pytest.mark.parametrize("name", ["empty_traverse", "bad_json", "garbage.pcd"])
def test_train_and_evaluate_on_broken_tables(capsys, broken, tmp_path, name) -> None:
    one_line_error(capsys, ["train", broken[name], "--out", tmp_path / "m"], "train")
    one_line_error(capsys, ["evaluate", broken[name], "--model", "default"], "evaluate")


def test_batch_on_a_broken_traverse(capsys, broken, tmp_path) -> None:
    one_line_error(capsys, ["batch", broken["bad_json"], "--out", tmp_path / "b"], "batch")


def test_a_broken_process_pool_is_one_line() -> None:
    from concurrent.futures.process import BrokenProcessPool

    exc = BrokenProcessPool("A result has failed to un-serialize.\nDetails follow")
    assert failure_line("map", exc) == (
        "rough-map map: error: a worker process failed (A result has failed to un-serialize.); "
        "rerun with -j 1 to see the error"
    )
