"""The README tells the truth: its transcripts are what the commands print today.

``tools/readme_check.py`` reruns every ``$ command`` of the README's text blocks in a scratch
folder and compares the output (wall-clock figures masked). The slow measured tables are
checked by hand with ``--tables``.
"""

from __future__ import annotations

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
