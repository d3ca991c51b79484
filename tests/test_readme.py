"""The README tells the truth: its transcripts are what the commands print today.

``tools/readme_check.py`` reruns every ``$ command`` of the README's text blocks in a scratch
folder and compares the output (wall-clock figures masked). The slow measured tables are
checked by hand with ``--tables``.
"""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

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


@pytest.mark.slow
def test_readme_transcripts_match_their_commands(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "readme_check.py"), "--keep", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]


def _limit_value(text: str) -> int:
    """``65,536 B`` -> 65536, ``4 GiB`` -> 4 * 2**30, ``100,000,000 px`` -> 100000000."""
    match = re.fullmatch(r"([\d,]+)\s*(KiB|MiB|GiB|B|px)?", text.strip())
    assert match, f"not a limit: {text!r}"
    scale = {"KiB": 2**10, "MiB": 2**20, "GiB": 2**30}.get(match.group(2) or "", 1)
    return int(match.group(1).replace(",", "")) * scale


def test_limits_table_shows_the_values_in_the_code() -> None:
    """Each row of the README's limits table names the constant it shows; they agree."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Limits", 1)[1].split("\n## ", 1)[0]
    rows = [r for r in section.splitlines() if r.startswith("| ") and "`rough_map." in r]
    assert len(rows) >= 15
    for row in rows:
        _, _what, shown, where, _ = row.split("|")
        module, _, name = where.strip().strip("`").rpartition(".")
        value = getattr(importlib.import_module(module), name)
        assert _limit_value(shown) == value, f"{where.strip()} is {value}, README shows {shown}"


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
