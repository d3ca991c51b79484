"""The README tells the truth: its transcripts are what the commands print today.

``tools/readme_check.py`` reruns every ``$ command`` of the README's text blocks in a scratch
folder and compares the output (wall-clock figures masked). The slow measured tables are
checked by hand with ``--tables``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rough_map import _bounded, limits
from rough_map.errors import FileFormatError

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import readme_check  # noqa: E402


def test_matcher_folds_spaces_masks_timing_and_ellipsis() -> None:
    exp = ["a  b", "...", "time 3.0 ms"]
    assert readme_check.matches(exp, ["a b", "x", "y", "time 12.5 ms"])
    assert readme_check.matches(exp, ["a b", "time 1 ms"])
    assert not readme_check.matches(exp, ["a c", "time 1 ms"])
    assert not readme_check.matches(["a"], ["a", "b"])


def test_transcripts_are_parsed_per_command() -> None:
    lines = ["x", "```text", "$ one", "out1", "$ two", "```", "```text", "no command", "```"]
    (block,) = readme_check.transcripts(lines)
    assert [s.command for s in block.steps] == ["one", "two"]
    assert block.steps[0].expected == ["out1"]


def test_a_block_can_carry_its_own_tolerance() -> None:
    lines = ["<!-- readme_check rtol=0.01 -->", "```text", "$ one", "R 2.306e-04", "```"]
    lines += ["```text", "$ two", "```"]
    first, second = readme_check.transcripts(lines)
    assert (first.rtol, second.rtol) == (0.01, 0.0)
    assert readme_check.matches(first.steps[0].expected, ["R 2.308e-04"], first.rtol)
    assert not readme_check.matches(first.steps[0].expected, ["R 2.308e-04"], second.rtol)


@pytest.mark.slow
def test_stereo_block_tolerance_covers_the_cpu_dispatch(tmp_path: Path) -> None:
    """The README's stereo block is compared within 1 % because OpenCV's sub-pixel
    disparities depend on the instruction set it dispatches to: the README's pair read with
    OpenCV's AVX code turned off moves the cloud, and its R stays well within that."""
    run = [sys.executable, "-m", "rough_map"]
    sim = ["simulate", "--out", "sim", "--course", "mixed", "--length", "3"]
    sim += ["--image-every", "3", "--seed", "1", "-q"]
    subprocess.run(run + sim, cwd=tmp_path, check=True, capture_output=True, timeout=600)
    readings = []
    for name, off in (("a", None), ("b", "AVX512_SKX,AVX2,FMA3,AVX")):
        env = dict(os.environ, **({"OPENCV_CPU_DISABLE": off} if off else {}))
        pair = ["sim/left/000003.png", "sim/right/000003.png"]
        calib = str(ROOT / "configs" / "stereo_calibration.yaml")
        cmd = run + ["stereo", *pair, "--calib", calib, "--out", f"{name}.npy"]
        subprocess.run(cmd, cwd=tmp_path, env=env, check=True, capture_output=True, timeout=600)
        out = subprocess.run(
            run + ["features", f"{name}.npy", "--json"],
            cwd=tmp_path,
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        )
        readings.append(json.loads(out.stdout))
    a, b = readings
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    blocks = readme_check.transcripts(lines)
    (block,) = [k for k in blocks if any(" stereo " in s.command for s in k.steps)]
    assert block.rtol == 0.01
    assert abs(a["R"] / b["R"] - 1) < block.rtol / 2
    assert abs(a["noise_psd"] / b["noise_psd"] - 1) < block.rtol / 2


@pytest.mark.slow
def test_readme_transcripts_match_their_commands(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "readme_check.py"), "--keep", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]


def test_limits_table_is_the_table_of_data() -> None:
    """The README's limits table is ``rough_map.limits.markdown_table()``, row for row."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Limits", 1)[1].split("\n## ", 1)[0]
    table = limits.markdown_table()
    assert table in section, "README's limits table differs from rough_map.limits"
    assert len(table.splitlines()) == 2 + len(dataclasses.fields(limits.Limits))


def test_limits_are_shown_in_their_units() -> None:
    assert limits.shown(65_536, "B") == "64 KiB"
    assert limits.shown(4 * 2**30, "B") == "4 GiB"
    assert limits.shown(10_000, "B") == "10,000 B"
    assert limits.shown(1100, "x") == "1,100x"
    assert limits.shown(64, "") == "64"
    assert limits.shown(2**24, "cells") == "16,777,216 cells"


def test_readers_take_their_limits_from_the_table(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reader enforces the table's value, not one of its own: with the nesting limit
    lowered to 3 in the table, a document nested 4 deep is refused; and no module of the
    package defines a ``MAX_`` constant of the table's any more."""
    doc = tmp_path / "deep.json"
    doc.write_text('{"a": [[[1]]]}', encoding="utf-8")
    assert _bounded.parse_document(doc) == {"a": [[[1]]]}
    monkeypatch.setattr(_bounded, "LIMITS", dataclasses.replace(limits.LIMITS, document_depth=3))
    with pytest.raises(FileFormatError, match=r"deep\.json.*nested deeper than 3 levels"):
        _bounded.parse_document(doc)
    old = re.compile(r"^_?(MAX_(POINTS|HEADER|PIXELS|DOCUMENT_BYTES|YAML_BYTES|DEPTH|NODES|CARD|"
                     r"INT_DIGITS|FILE|MEMBERS|CHUNK|SAMPLES|CELLS|PROFILE|SCHEMA|RATIO)|"
                     r"LAZ_MAX_RATIO|DEFLATE_RATIO) = ", re.M)  # fmt: skip
    for path in (ROOT / "rough_map").rglob("*.py"):
        assert not old.search(path.read_text(encoding="utf-8")), path


def test_matcher_with_a_tolerance_lets_only_the_numbers_move() -> None:
    assert readme_check.same_line("R 2.308e-04 (sigma 0.300)", "R 2.306e-04 (sigma 0.301)", 0.05)
    assert not readme_check.same_line("R 2.308e-04", "R 2.306e-04")
    assert not readme_check.same_line("R 2.308e-04", "R 2.508e-04", 0.05)
    assert not readme_check.same_line("R 2.308e-04 ISO E", "R 2.308e-04 ISO F", 0.05)


def test_the_lock_pins_every_dependency_within_pyproject_ranges() -> None:
    """``constraints.txt`` (what .ci/setup.sh installs) pins each of the library's
    dependencies, at a version its pyproject range admits."""
    import tomllib

    from packaging.requirements import Requirement

    pins = {}
    for line in (ROOT / "constraints.txt").read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not pinned with =="
            pins[name.strip().lower().replace("_", "-")] = version.strip()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    for spec in project["dependencies"]:
        req = Requirement(spec)
        name = req.name.lower().replace("_", "-")
        assert name in pins, f"constraints.txt does not pin {name}"
        assert req.specifier.contains(pins[name]), f"{name}=={pins[name]} is outside {spec}"
    setup = (ROOT / ".ci" / "setup.sh").read_text(encoding="utf-8")
    assert "-c constraints.txt" in setup
