"""Conventions every ``rough-map`` command keeps (issue: a CLI that keeps its conventions).

-q/-v before or after the command, one-line errors for bad numbers and misspelt paths, help
text with defaults on every option, status lines that -q silences, JSON written whole, and
the files other tools read: a plain features CSV with its metadata beside it, a stereo
calibration example that ``rough-map stereo`` loads.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from rough_map.classify import load_terrain_model
from rough_map.cli._common import emit_json, mentions_default
from rough_map.cli.main import build_parser, main
from rough_map.errors import FileFormatError, InputError
from rough_map.features import (
    features_metadata_path,
    read_features,
    traverse_features,
    write_features,
)
from rough_map.io.traverse import load_traverse

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "configs" / "stereo_calibration.yaml"


def run(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def small(small_traverse: Path) -> Path:
    """The shared 3 m mixed course, clouds only (conftest.small_traverse)."""
    return small_traverse


@pytest.fixture(scope="module")
def small_features(small: Path):
    return traverse_features(small)


@pytest.fixture(scope="module")
def imaged(imaged_traverse: Path) -> Path:
    """The shared 6 m mixed course with images (conftest.imaged_traverse)."""
    return imaged_traverse


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


COMMANDS = sorted(_subparsers())


# --------------------------------------------------------------------------- parser


@pytest.mark.parametrize(
    ("argv", "quiet", "verbose"),
    [
        (["-q", "map", "T", "--out", "D"], True, 0),
        (["map", "T", "--out", "D", "-q"], True, 0),
        (["map", "-q", "T", "--out", "D"], True, 0),
        (["-v", "features", "C"], False, 1),
        (["features", "C", "-vv"], False, 2),
        (["--quiet", "features", "C", "--verbose"], True, 1),
        (["features", "C"], False, 0),
    ],
)
def test_quiet_and_verbose_before_or_after_the_command(
    argv: list[str], quiet: bool, verbose: int, tmp_path: Path
) -> None:
    (tmp_path / "T").mkdir()
    (tmp_path / "C").touch()
    args = build_parser().parse_args([str(tmp_path / a) if a in "TC" else a for a in argv])
    assert (args.quiet, args.verbose) == (quiet, verbose)


@pytest.mark.parametrize(
    "command",
    COMMANDS,
)
def test_every_option_has_help_showing_its_default(command: str) -> None:
    parser = _subparsers()[command]
    formatter = parser._get_formatter()
    problems = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or not action.option_strings:
            continue
        text = formatter._expand_help(action) if action.help else ""
        if not text.strip():
            problems.append(f"{action.option_strings[0]}: no help")
        elif not (
            action.default is None or action.default is False or action.default == argparse.SUPPRESS
        ) and not mentions_default(text, action.default):  # 0 is a default to show
            problems.append(f"{action.option_strings[0]}: help does not show {action.default!r}")
    assert problems == []
    assert str(0.1) in _subparsers()["map"].format_help()  # --resolution's default, shown


@pytest.mark.parametrize(
    "command",
    COMMANDS,
)
def test_numeric_options_are_checked(command: str) -> None:
    plain = [
        a.option_strings[0]
        for a in _subparsers()[command]._actions
        if a.type in (float, int) and a.option_strings
    ]
    assert plain == []


BAD_NUMBERS = [
    (["map", "{t}", "--out", "{d}", "--resolution", "0"],
     "argument --resolution: expected a positive number of metres, got '0'"),
    (["map", "{t}", "--out", "{d}", "--resolution", "nan"],
     "argument --resolution: expected a finite number, got 'nan'"),
    (["features", "{t}", "--out", "{d}/f.csv", "--spacing", "-0.008"],
     "argument --spacing: expected a positive number of metres, got '-0.008'"),
    (["features", "{t}", "--out", "{d}/f.csv", "--size", "0"],
     "argument --size: expected a positive number of metres, got '0'"),
    (["features", "{t}", "--ahead", "inf"], "argument --ahead: expected a finite number"),
    (["features", "{t}", "--roll", "ten"], "argument --roll: expected a number, got 'ten'"),
    (["simulate", "--out", "{d}", "--length", "0"],
     "argument --length: expected a positive number of metres, got '0'"),
    (["simulate", "--out", "{d}", "--rate", "0"],
     "argument --rate: expected a positive number of hertz, got '0'"),
    (["simulate", "--out", "{d}", "--speed", "-0.5"],
     "argument --speed: expected a positive number of metres per second, got '-0.5'"),
    (["simulate", "--out", "{d}", "--image-every", "0"],
     "argument --image-every: expected a positive whole number, got '0'"),
    (["simulate", "--out", "{d}", "--image-every", "1.5"],
     "argument --image-every: expected a whole number, got '1.5'"),
    (["simulate", "--out", "{d}", "--seed", "-1"],
     "argument --seed: expected a non-negative whole number, got '-1'"),
    (["simulate", "--out", "{d}", "--noise=-1e-3"],
     "argument --noise: expected a non-negative number of metres, got '-1e-3'"),
    (["simulate", "--out", "{d}", "--width", "0"],
     "argument --width: expected a positive number of metres, got '0'"),
    (["train", "{t}", "--out", "{d}/m", "--cv", "1"],
     "argument --cv: expected a whole number >= 2, got '1'"),
    (["import", "{t}", "--points-topic", "/p", "--odom-topic", "/o", "--out", "{d}",
      "--every", "0"], "argument --every: expected a positive whole number, got '0'"),
    (["stereo", "{t}/traverse.json", "{t}/traverse.json", "--calib", "{t}/traverse.json",
      "--out", "{d}/c.npy", "--size", "0"],
     "argument --size: expected a positive number of metres, got '0'"),
]  # fmt: skip


@pytest.mark.parametrize(("argv", "message"), BAD_NUMBERS)
def test_bad_numbers_are_one_line_errors(
    argv: list[str], message: str, small: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "out"
    code, stdout, err = run(capsys, *(a.format(t=small, d=out) for a in argv))
    assert code == 2
    assert stdout == ""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"rough-map {argv[0]}: error: {message}"), err
    assert not out.exists()  # refused before doing anything


def test_a_patch_that_cannot_be_cut_is_one_line(small: Path, tmp_path, capsys) -> None:
    cloud = small / "clouds" / "000000.npy"
    code, _, err = run(capsys, "features", cloud, "--size", "0.02")
    assert code == 2 and err.count("\n") == 1
    assert "rough-map features: error: size / spacing gives 2 samples per profile" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["features", "{x}"],
        ["features", "{x}", "--out", "{d}/f.csv"],
        ["map", "{x}", "--out", "{d}"],
        ["classify", "{x}", "--model", "default", "--out", "{d}/l.csv"],
        ["train", "{t}", "{x}", "--out", "{d}/m"],
        ["evaluate", "{x}", "--model", "default"],
        ["report", "{x}", "--out", "{d}"],
        ["inspect", "{x}"],
        ["import", "{x}", "--points-topic", "/p", "--odom-topic", "/o", "--out", "{d}"],
        ["stereo", "{x}", "{t}/traverse.json", "--calib", "{t}/traverse.json", "--out", "{d}/c"],
        ["stereo", "{t}/traverse.json", "{t}/traverse.json", "--calib", "{x}", "--out", "{d}/c"],
        ["train", "{t}", "--out", "{d}/m", "--levels", "{x}"],
    ],
)
def test_misspelt_paths_are_no_such_file_or_folder(
    argv: list[str], small: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    missing = small.parent / "smal"  # a typo of the traverse folder
    out = tmp_path / "out"
    code, _, err = run(capsys, *(a.format(x=missing, t=small, d=out) for a in argv))
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"no such file or folder: '{missing}'" in err
    assert "suffix" not in err
    assert not out.exists()


def test_help_and_version_return_zero(capsys) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("rough-map ")
    assert main(["map", "--help"]) == 0
    assert "--resolution M" in capsys.readouterr().out
    assert main(["nosuchcommand"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "rough-map: error: argument COMMAND: invalid choice" in err


# --------------------------------------------------------------------------- -q and status


def test_quiet_leaves_stderr_empty(small: Path, tmp_path: Path, capsys) -> None:
    runs = [
        ["-q", "features", small, "--out", tmp_path / "f.csv"],
        ["features", small, "--out", tmp_path / "f2.csv", "-q"],
        ["features", small / "clouds" / "000001.npy", "-q"],
        ["-q", "map", small, "--out", tmp_path / "map", "--no-png"],
        ["classify", small, "--model", "default", "--out", tmp_path / "l.csv", "-q"],
        ["-q", "simulate", "--out", tmp_path / "sim", "--length", "2", "--no-images"],
        ["schema", "--out", tmp_path / "schema", "-q"],
    ]
    for argv in runs:
        code, out, err = run(capsys, *argv)
        assert code == 0, (argv, err)
        assert err == "", (argv, err)
        assert out


def test_status_lines_show_without_quiet_and_errors_with_it(small, tmp_path, capsys) -> None:
    code, _, err = run(capsys, "features", small, "--out", tmp_path / "f.csv")
    n = len(load_traverse(small))
    assert code == 0 and f"wrote {n} frames (0 invalid) to {tmp_path / 'f.csv'}" in err
    code, _, err = run(capsys, "-q", "features", small)  # a traverse needs --out
    assert code == 2 and err.startswith("rough-map features: error: a traverse needs --out")


def test_units_in_text_output(small: Path, tmp_path: Path, capsys) -> None:
    code, out, _ = run(capsys, "features", small / "clouds" / "000001.npy")
    assert code == 0 and "m³/rad" in out and "m^3" not in out
    code, out, _ = run(capsys, "features", small, "--out", tmp_path / "f.csv")
    assert code == 0 and "R m³/rad (geo. mean)" in out
    for module in (ROOT / "rough_map" / "cli").glob("*.py"):
        if module.stem not in ("demo", "report", "evaluate"):  # another owner's
            text = module.read_text()
            assert "m^3" not in text and "m^2" not in text, module.name


# --------------------------------------------------------------------------- JSON


def test_emit_json_writes_whole_documents_or_nothing(capsys) -> None:
    emit_json({"a": np.float32(1.5), "b": [np.nan, np.inf], "c": Path("x/y"), "d": np.arange(2)})
    assert json.loads(capsys.readouterr().out) == {"a": 1.5, "b": [None, None], "c": "x/y",
                                                   "d": [0, 1]}  # fmt: skip
    with pytest.raises(TypeError, match="cannot write a object as JSON"):
        emit_json({"ok": 1, "bad": object()})
    assert capsys.readouterr().out == ""


def test_accuracy_table_to_dict() -> None:
    from rough_map.evaluation.near_far import AccuracyTable

    table = AccuracyTable(
        edges=np.array([0.0, 1.5, 2.0]),
        n=np.array([4, 0]),
        n_confident=np.array([2, 0]),
        accuracy=np.array([0.5, np.nan]),
        accuracy_all=np.array([0.75, np.nan]),
        threshold=0.6,
    )
    assert table.to_dict() == {
        "threshold": 0.6,
        "overall": 0.5,
        "abstained_fraction": 0.0,
        "bins": [
            {"from_m": 0.0, "to_m": 1.5, "cells": 4, "confident": 2, "accuracy": 0.5,
             "accuracy_all": 0.75, "abstained": 0, "abstained_fraction": 0.0},
            {"from_m": 1.5, "to_m": 2.0, "cells": 0, "confident": 0, "accuracy": None,
             "accuracy_all": None, "abstained": 0, "abstained_fraction": None},
        ],
    }  # fmt: skip
    json.dumps(table.to_dict(), allow_nan=False)


@pytest.mark.slow
def test_map_json_on_a_traverse_with_images(imaged: Path, tmp_path: Path, capsys) -> None:
    """near-to-far runs (stereo images), and its accuracy table is in the JSON."""
    # every label, uncalibrated: settled and calibrated, near-to-far abstains on this short
    # course (7 images, the class changing every 2 m)
    config = tmp_path / "near_far.yaml"
    config.write_text("calibrate: false\nsettle_frames: 0\n", encoding="utf-8")
    code, out, err = run(
        capsys, "-q", "map", imaged, "--out", tmp_path / "map", "--json",
        "--near-far-config", config,
    )  # fmt: skip
    assert code == 0, err
    assert err == ""
    summary = json.loads(out)  # one whole document
    assert summary["frames"] == len(load_traverse(imaged))
    assert summary["area_ratio"] > 1.0
    bins = summary["far_accuracy_by_distance"]["bins"]
    assert bins[0]["from_m"] == 0.0 and sum(b["cells"] for b in bins) > 0
    outputs = summary["outputs"]
    assert Path(outputs["features_metadata"]) == tmp_path / "map" / "features.csv.json"
    assert Path(outputs["png_far_class"]).is_file()
    assert read_features(outputs["features"]).valid.all()


# --------------------------------------------------------------------------- features files


def test_features_csv_is_plain_with_metadata_beside_it(small_features, tmp_path: Path) -> None:
    path = write_features(small_features, tmp_path / "features.csv")
    sidecar = tmp_path / "features.csv.json"
    assert features_metadata_path(path) == sidecar
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))  # no options: the first line is the header
    assert len(rows) == len(small_features)
    assert rows[0]["frame"] == "0" and float(rows[0]["R"]) == pytest.approx(small_features["R"][0])
    assert rows[0]["valid"] == "true"
    meta = json.loads(sidecar.read_text())
    assert meta["format"] == "rough_map features" and meta["name"] == small_features.name
    np.testing.assert_allclose(meta["omega_rad_per_m"], small_features.omega, rtol=1e-15)
    assert meta["units"]["R"] == "m³/rad" and meta["units"]["psd_01"] == "log10(m³/rad)"
    assert meta["spectrum_columns"][0] == "psd_01" and "psd_01" in rows[0]

    back = read_features(path)
    assert back.name == small_features.name
    np.testing.assert_array_equal(back.omega, small_features.omega)
    np.testing.assert_allclose(back["R"], small_features["R"], rtol=1e-8)
    np.testing.assert_allclose(back.log_psd, small_features.log_psd, rtol=1e-8)
    assert list(back["label"]) == list(small_features["label"])


def test_features_csv_reads_with_pandas(small_features, tmp_path: Path) -> None:
    pd = pytest.importorskip("pandas")
    frame = pd.read_csv(write_features(small_features, tmp_path / "features.csv"))
    assert list(frame.columns[:3]) == ["frame", "t", "x"]
    np.testing.assert_allclose(frame["R"], small_features["R"], rtol=1e-8)


def test_features_csv_without_its_metadata(small_features, tmp_path: Path, capsys) -> None:
    path = write_features(small_features, tmp_path / "features.csv")
    moved = shutil.copy(path, tmp_path / "copy.csv")  # the CSV alone
    with pytest.raises(FileFormatError, match=r"copy\.csv: its metadata file copy\.csv\.json is "
                       r"missing \(it holds the wavenumbers of the psd_NN columns\)"):  # fmt: skip
        read_features(moved)
    code, _, err = run(capsys, "classify", moved, "--model", "default", "--out",
                       tmp_path / "l.csv")  # fmt: skip
    assert code == 2 and err.count("\n") == 1 and "copy.csv.json is missing" in err

    sidecar = features_metadata_path(path)
    meta = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**meta, "omega_rad_per_m": meta["omega_rad_per_m"][:-1]}))
    with pytest.raises(FileFormatError, match=r"55 wavenumbers for 56 psd_NN columns"):
        read_features(path)
    sidecar.write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(FileFormatError, match="format_version 99; this rough_map reads up to 1"):
        read_features(path)
    sidecar.write_text(json.dumps({**meta, "row_spacing_m": -0.032}))
    with pytest.raises(FileFormatError, match=r"features\.csv\.json \[row_spacing_m\]: must be a "
                       r"positive width in m"):  # fmt: skip
        read_features(path)
    sidecar.write_text(json.dumps({**meta, "row_spacing_m": 0.032}))
    assert read_features(path).row_spacing == 0.032
    sidecar.write_text("{not json")
    with pytest.raises(FileFormatError, match="invalid JSON at line 1"):
        read_features(path)


def test_features_csv_of_rough_map_0_1_still_reads(small_features, tmp_path: Path) -> None:
    """The old form: the wavenumbers in a '# rough_map features' first line."""
    path = write_features(small_features, tmp_path / "new.csv")
    omega = ",".join(f"{o:.12g}" for o in small_features.omega)
    old = tmp_path / "old.csv"
    old.write_text(f"# rough_map features of {small_features.name}; omega_rad_per_m={omega}\n"
                   + path.read_text())  # fmt: skip
    back = read_features(old)
    assert back.name == small_features.name
    np.testing.assert_allclose(back.omega, small_features.omega, rtol=1e-11)
    np.testing.assert_allclose(back["R"], small_features["R"], rtol=1e-8)


def test_features_csv_without_the_newer_columns_reads_them_as_nan(
    small_features, tmp_path: Path
) -> None:
    """A table written before the lateral scale and omega_noise columns (or the standard
    errors, or the smoothed roughness) were added reads with those columns NaN."""
    import csv

    path = write_features(small_features, tmp_path / "f.csv")
    assert np.isfinite(small_features["lateral_scale"][small_features.valid]).all()
    newer = ("lateral_scale", "omega_noise", "se_lnR", "se_w", "R_smooth")
    rows = list(csv.DictReader(path.open(newline="", encoding="utf-8")))
    keep = [k for k in rows[0] if k not in newer]
    with path.open("w", newline="", encoding="utf-8") as fh:
        out = csv.DictWriter(fh, keep, extrasaction="ignore")
        out.writeheader()
        out.writerows(rows)
    back = read_features(path)
    for name in newer:
        assert np.isnan(back[name]).all(), name
    np.testing.assert_allclose(back["R"], small_features["R"], rtol=1e-8)


def test_features_parquet_keeps_the_metadata_inside(small_features, tmp_path: Path) -> None:
    pq = pytest.importorskip("pyarrow.parquet")
    path = write_features(small_features, tmp_path / "features.parquet")
    assert not features_metadata_path(path).exists()
    meta = json.loads(pq.read_schema(path).metadata[b"rough_map"])
    assert meta["name"] == small_features.name
    back = read_features(path)
    np.testing.assert_array_equal(back.omega, small_features.omega)
    np.testing.assert_allclose(back.log_psd, small_features.log_psd, rtol=1e-12)


def test_features_command_reports_the_metadata_file(small: Path, tmp_path, capsys) -> None:
    out = tmp_path / "f.csv"
    code, stdout, _ = run(capsys, "features", small, "--out", out, "--json")
    assert code == 0
    assert json.loads(stdout)["metadata"] == str(tmp_path / "f.csv.json")
    assert read_features(out).valid.all()


# --------------------------------------------------------------------------- stereo


def test_stereo_calibration_example_is_the_simulators_rig() -> None:
    from rough_map.config import StereoCalibration

    assert StereoCalibration.from_file(CALIBRATION) == StereoCalibration.xb3_default()


@pytest.mark.slow
def test_stereo_command_loads_the_calibration_example(imaged: Path, tmp_path, capsys) -> None:
    out = tmp_path / "cloud.npy"
    code, stdout, err = run(capsys, "stereo", imaged / "left" / "000000.png",
                            imaged / "right" / "000000.png", "--calib", CALIBRATION,
                            "--out", out)  # fmt: skip
    assert code == 0, err
    points = np.load(out)
    assert stdout.strip() == f"{out}: {len(points)} points" and len(points) > 50_000
    # over the 0.896 m patch 1 m ahead (plus its 5 cm crop margin), on the ground
    lo, hi = np.percentile(points, [1, 99], axis=0)
    assert lo[0] == pytest.approx(0.552, abs=0.06) and hi[0] == pytest.approx(1.448, abs=0.06)
    assert lo[1] == pytest.approx(-0.448, abs=0.06) and hi[1] == pytest.approx(0.448, abs=0.06)
    assert np.abs(np.median(points[:, 2])) < 0.05


@pytest.mark.slow
def test_points_from_stereo_marks_frames_without_a_pair(imaged: Path, tmp_path, capsys) -> None:
    out = tmp_path / "f.csv"
    code, _, err = run(capsys, "features", imaged, "--points-from", "stereo", "--out", out)
    assert code == 0, err
    feats = read_features(out)
    paired = np.array([f.left is not None for f in load_traverse(imaged).frames])
    assert paired.sum() == 7 and (~paired).sum() == 12  # --image-every 3 over 19 frames
    assert list(feats["reason"][~paired]) == ["no stereo pair"] * 12
    assert not feats.valid[~paired].any()
    assert feats.valid[paired].all()


def test_stereo_without_pairs_or_calibration(small: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="stereo needs a 'calibration' in the traverse"):
        traverse_features(small, source="stereo")
    from rough_map.config import StereoCalibration

    doc = json.loads((small / "traverse.json").read_text())
    doc["calibration"] = StereoCalibration.xb3_default().model_dump()
    (tmp_path / "traverse.json").write_text(json.dumps(doc))
    (tmp_path / "clouds").symlink_to(small / "clouds")
    linked = load_traverse(tmp_path, allow_outside=[small])  # clouds/ links there
    feats = traverse_features(linked, source="stereo")  # no frame has a pair: none stops
    assert not feats.valid.any() and set(feats["reason"]) == {"no stereo pair"}
    assert traverse_features(linked, source="auto").valid.all()  # auto: the clouds


def test_every_command_that_classifies_defaults_to_the_shipped_model(
    small: Path, tmp_path: Path, capsys
) -> None:
    """One ``--model`` option: optional everywhere, the shipped default when left out, and
    the same help in every command."""
    code, _, err = run(capsys, "-q", "classify", small, "--out", tmp_path / "l.csv")
    assert code == 0, err
    again = tmp_path / "l2.csv"
    assert run(capsys, "-q", "classify", small, "--model", "default", "--out", again)[0] == 0
    assert (tmp_path / "l.csv").read_bytes() == again.read_bytes()
    code, out, err = run(capsys, "-q", "evaluate", small, "--json")
    assert code == 0 and json.loads(out)["model"] == "default", err
    helps = set()
    for command in ("classify", "evaluate", "map", "report", "batch", "demo"):
        code, out, _ = run(capsys, command, "--help")
        line = " ".join(out.split())
        assert code == 0 and "--model M model name or file" in line, command
        helps.add(line[line.index("--model M model") :].split(" --", 1)[0])
    assert len(helps) == 1, helps


def test_help_shows_the_defaults_that_come_from_the_config_and_zero(capsys) -> None:
    """The --far-* options default to the near-far config: their help says its values; a
    default of 0 (simulate's --seed) is shown like any other."""
    import yaml

    shipped = yaml.safe_load((ROOT / "configs" / "near_far.yaml").read_text(encoding="utf-8"))
    _, out, _ = run(capsys, "map", "--help")
    text = " ".join(out.split())
    for key in ("tile_size_m", "max_range_m", "weight", "min_confidence"):
        assert f"the config's {key}, {shipped[key]} in the shipped one" in text, key
    _, out, _ = run(capsys, "simulate", "--help")
    assert "seed of the world and the drive (default: 0)" in " ".join(out.split())


def test_a_map_too_fine_for_the_memory_is_refused_up_front(
    small: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    """``map --resolution`` far below what the machine can hold is one line, before any
    frame is read and with nothing written (it took 11-17 GB before); the API refuses it
    too, and a budget that fits lets the same map through."""
    import time

    from rough_map.map import grid_geometry
    from rough_map.workflow import analyse

    started = time.monotonic()
    code, _, err = run(capsys, "map", small, "--out", tmp_path / "m", "--resolution", "0.0002")
    assert code == 2 and time.monotonic() - started < 30
    assert len(err.splitlines()) == 1 and "resolution 0.0002 m: the map over this traverse" in err
    assert "use a resolution of at least" in err and not (tmp_path / "m").exists()
    monkeypatch.setattr(grid_geometry, "memory_budget", lambda: 2**10)  # 1 kB
    with pytest.raises(InputError, match=r"beyond the 0\.0 GB a map may take here"):
        analyse(load_traverse(small), load_terrain_model("default"), resolution=0.1, near_far=False)


def test_classify_and_map_write_one_labels_schema(small: Path, tmp_path: Path, capsys) -> None:
    """``classify --out labels.csv`` and map's ``labels.csv``: the same columns, and the
    same rows for the same traverse and model (issue 30: they had two schemas)."""
    from rough_map.export.labels import LABEL_COLUMNS

    assert run(capsys, "-q", "classify", small, "--out", tmp_path / "labels.csv")[0] == 0
    assert run(capsys, "-q", "map", small, "--out", tmp_path / "map", "--no-png")[0] == 0
    with open(tmp_path / "labels.csv", newline="") as f:
        mine = list(csv.reader(f))
    with open(tmp_path / "map" / "labels.csv", newline="") as f:
        mapped = list(csv.reader(f))
    assert tuple(mine[0]) == tuple(mapped[0]) == LABEL_COLUMNS
    assert mine == mapped


def test_map_and_report_take_what_their_help_offers(small: Path, tmp_path: Path, capsys) -> None:
    """map and report read the traverse's clouds: their help offers a traverse, and a
    features table is one line saying so; classify and evaluate take the table."""
    table_file = tmp_path / "f.csv"
    assert run(capsys, "-q", "features", small, "--out", table_file)[0] == 0
    for command in ("map", "report"):
        _, out, _ = run(capsys, command, "--help")
        assert "features table" not in " ".join(out.split()), command
        code, _, err = run(capsys, command, table_file, "--out", tmp_path / command)
        assert code == 2 and len(err.splitlines()) == 1 and "is a features table" in err
    code, _, err = run(capsys, "-q", "classify", table_file, "--out", tmp_path / "l.csv")
    assert code == 0, err
    assert run(capsys, "-q", "evaluate", table_file)[0] == 0


def test_a_ctrl_c_as_the_workers_start_is_not_lost() -> None:
    """The workers start with SIGINT ignored; a Ctrl-C meanwhile is kept and taken when the
    block ends (it was lost: it could land on a BLAS thread, where it was ignored, and a
    report ran on to its end). Run as rough-map does: rough_map.cli blocks SIGINT while
    the libraries start their threads, main() unblocks it in the main thread. In a process
    of its own (signals reach only a main thread, and a test may run in another), 20 times
    while other processes keep the cores busy."""
    import subprocess
    import sys

    script = """
import sys, os, signal, time
sys.argv[0] = "rough-map"
import rough_map.cli.main
from rough_map.features.frames import children_ignore_sigint
signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # as main() does
reached = []
try:
    with children_ignore_sigint():
        os.kill(os.getpid(), signal.SIGINT)
        reached.append("inside")
    deadline = time.monotonic() + 2  # the run goes on; the interrupt comes within it
    while time.monotonic() < deadline:
        time.sleep(0.01)
    reached.append("after")
except KeyboardInterrupt:
    reached.append("interrupted")
assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
print(",".join(reached))
"""
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        for _ in range(20):
            res = subprocess.run([sys.executable, "-c", script], capture_output=True,
                                 text=True, timeout=120)  # fmt: skip
            assert res.returncode == 0, res.stderr
            assert res.stdout.strip() == "inside,interrupted"
    finally:
        for p in burners:
            p.kill()
            p.wait()


def test_a_ctrl_c_in_a_deferred_block_is_taken_when_it_ends() -> None:
    """loky's shut-down of its workers runs to its end under a Ctrl-C (interrupted half-way
    it left semaphores that its resource tracker warned of, and tracebacks, in a CI run):
    the KeyboardInterrupt comes after the block, the handler is put back."""
    import subprocess
    import sys

    script = """
import os, signal
from rough_map.features.frames import sigint_deferred
reached = []
try:
    with sigint_deferred():
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10**5):
            pass
        reached.append("inside")
    reached.append("after")
except KeyboardInterrupt:
    reached.append("interrupted")
assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
with sigint_deferred():
    reached.append("quiet")
print(",".join(reached))
"""
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "inside,interrupted,quiet"


def test_a_ctrl_c_inside_an_extensions_import_is_an_interrupt(
    monkeypatch, capsys, tmp_path: Path
) -> None:
    """A pybind11 extension (open3d, cv2, scipy's pocketfft) that a Ctrl-C interrupts while
    it is imported raises ``ImportError('initialization failed')`` from the
    KeyboardInterrupt: exit 130 and one line, as any Ctrl-C (it was an internal error, 2,
    once in a fresh-clone CI run of the test below)."""
    import rough_map.cli.features as features_cli

    def interrupted_import(args) -> int:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    monkeypatch.setattr(features_cli, "run", interrupted_import)
    assert main(["features", str(tmp_path), "--out", str(tmp_path / "f.csv")]) == 130
    assert capsys.readouterr().err == "rough-map: interrupted\n"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["map", "features", "report", "batch", "train"])
def test_ctrl_c_during_a_two_process_run_is_one_line(command: str, tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while the
    workers are busy: exit 130, one line, no worker traceback, no leaked semaphore."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from rough_map.simulate.course import simulate

    trav = tmp_path / "t"
    simulate(trav, "mixed", length=12.0, seed=3, images=False)
    exe = Path(sys.executable).with_name("rough-map")
    target = {"features": "f.csv", "train": "model"}.get(command, "m")
    out = ["--out", str(tmp_path / target), *(["--force"] if command == "train" else [])]
    interrupted = 0
    for delay in (0.4, 0.6, 0.9, 1.5, 2.5):  # start-up, the workers importing, the frames
        proc = subprocess.Popen(
            [str(exe), command, str(trav), *out, "-j", "2"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        time.sleep(delay)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        if proc.returncode == 0 or (proc.returncode == -signal.SIGINT and "wrote" in err):
            continue  # it finished first (or the signal came as it was exiting)
        assert proc.returncode == 130, err
        lines = err.strip().splitlines()  # a status line may come first, if it was that late
        assert lines[-1] == "rough-map: interrupted" and len(lines) <= 2, err
        assert "Traceback" not in err and "leaked" not in err, err
        interrupted += 1
    assert interrupted, "every run finished before the interrupt"


def _features_json(capsys, *argv: object) -> dict:
    code, out, err = run(capsys, "features", *argv, "--json")
    assert code == 0, err
    return json.loads(out)


def test_a_cloud_in_other_units_columns_or_frame_reads_as_in_the_vehicle_frame(
    dense_cloud, tmp_path: Path, capsys
) -> None:
    """The same ground given in millimetres (--units mm), as a text file headed
    time,lon,lat,alt (--columns), or in a world frame moved and turned (--at X,Y,YAW) reads
    as it does in the vehicle frame in metres (issue 30, item 2)."""
    pts = dense_cloud(n_points=200_000)
    np.save(tmp_path / "m.npy", pts)
    ref = _features_json(capsys, tmp_path / "m.npy")
    np.save(tmp_path / "mm.npy", pts * 1000.0)
    mm = _features_json(capsys, tmp_path / "mm.npy", "--units", "mm")
    assert mm["R"] == pytest.approx(ref["R"], rel=1e-6) and mm["w"] == pytest.approx(ref["w"])
    code, _, err = run(capsys, "features", tmp_path / "mm.npy")
    assert code == 2 and "in millimetres? clouds are read in metres" in err
    text = tmp_path / "gnss.csv"
    rows = np.column_stack([np.arange(len(pts)), pts])
    np.savetxt(text, rows[:, [0, 1, 2, 3]], delimiter=",", header="time,lon,lat,alt", comments="")
    code, _, err = run(capsys, "features", text)
    assert code == 2 and "has no x, y, z: name them (--columns X,Y,Z)" in err
    cols = _features_json(capsys, text, "--columns", "lon,lat,alt")
    assert cols["R"] == pytest.approx(ref["R"], rel=1e-5)
    yaw = math.radians(30.0)
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.column_stack(
        [
            512_000.0 + c * pts[:, 0] - s * pts[:, 1],
            4_100_000.0 + s * pts[:, 0] + c * pts[:, 1],
            250.0 + pts[:, 2],
        ]
    )
    np.save(tmp_path / "world.npy", world)
    code, _, err = run(capsys, "features", tmp_path / "world.npy")
    assert code == 2 and "a world-frame cloud?" in err
    at = _features_json(capsys, tmp_path / "world.npy", "--at", "512000,4100000,30")
    assert at["R"] == pytest.approx(ref["R"], rel=0.02) and at["w"] == pytest.approx(
        ref["w"], abs=0.01
    )
    framed = _features_json(capsys, tmp_path / "world.npy", "--frame", "world", "--at",
                            "512000,4100000,30")  # fmt: skip
    assert framed["R"] == at["R"]
    code, _, err = run(capsys, "features", tmp_path / "world.npy", "--frame", "world")
    assert code == 2 and "--frame world" in err and "give --at X,Y[,YAW]" in err
    code, _, err = run(capsys, "features", tmp_path / "m.npy", "--frame", "vehicle", "--at", "1,2")
    assert code == 2 and "--frame vehicle says it is not one" in err
    code, _, err = run(capsys, "features", tmp_path / "m.npy", "--at", "1,2,x")
    assert code == 2 and "expected X,Y or X,Y,YAW" in err
