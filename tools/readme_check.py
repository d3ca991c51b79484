#!/usr/bin/env python3
"""Rerun the README's commands and compare what they print with what the README shows.

Every ```text block of README.md that holds ``$ command`` lines is a transcript: each command
runs, in order, in one scratch folder (so a block may use what an earlier block wrote), with
``rough-map`` taken from this Python's environment and ``configs/`` and ``models/`` of the
checkout linked into it (as a user runs them from the checkout), and its output must match the
lines under
it. Matching folds runs of white space, masks wall-clock figures (``12.3 ms``) and lets a line
``...`` stand for any number of lines. A command that fails is compared on its stderr (the
one-line error a user sees).

Tables between ``<!-- readme_check: NAME -->`` and ``<!-- /readme_check -->`` come from the
generators in :data:`TABLES`; they are slow (simulated courses), so they run only with
``--tables``.

    python tools/readme_check.py                  # every transcript (a few minutes)
    python tools/readme_check.py --only features  # the blocks whose commands contain 'features'
    python tools/readme_check.py --tables         # also regenerate the generated tables
    python tools/readme_check.py --update         # write what the commands print into README.md
    python tools/readme_check.py --rtol 0.05      # numbers within 5 % (after setup.sh --latest)

Exit status 0 when everything matches, 1 otherwise (the differences are printed).
"""

from __future__ import annotations

import argparse
import difflib
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TIMING = re.compile(r"\d+(?:\.\d+)?\s*ms\b")
TABLE_START = re.compile(r"<!-- readme_check: (\S+) -->")
TABLE_END = "<!-- /readme_check -->"
#: A block whose numbers depend on the CPU (OpenCV dispatches SSE, AVX2 or AVX-512 code,
#: whose sub-pixel disparities differ in their last bits) carries this line above its fence:
#: its numbers are compared within the relative tolerance given.
BLOCK_RTOL = re.compile(r"<!-- readme_check rtol=(\S+) -->")


@dataclass
class Step:
    command: str
    expected: list[str] = field(default_factory=list)


@dataclass
class Block:
    start: int  # line index of the first line inside the fence
    end: int  # line index of the closing fence
    steps: list[Step]
    rtol: float = 0.0  # the block's own tolerance (BLOCK_RTOL)


def transcripts(lines: list[str]) -> list[Block]:
    """The ```text blocks that hold ``$ `` commands."""
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        if lines[i].strip() == "```text":
            j = i + 1
            while j < len(lines) and lines[j].strip() != "```":
                j += 1
            body = lines[i + 1 : j]
            if any(b.startswith("$ ") for b in body):
                steps: list[Step] = []
                for b in body:
                    if b.startswith("$ "):
                        steps.append(Step(b[2:].strip()))
                    elif steps:
                        steps[-1].expected.append(b)
                m = BLOCK_RTOL.search(lines[i - 1]) if i else None
                blocks.append(Block(i + 1, j, steps, float(m.group(1)) if m else 0.0))
            i = j
        i += 1
    return blocks


def _norm(line: str) -> str:
    return " ".join(TIMING.sub("<ms>", line).split())


NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def same_line(expected: str, actual: str, rtol: float = 0.0) -> bool:
    """Two normalised lines are the same: to the letter, or with ``rtol`` > 0 the same text
    around numbers that agree within ``rtol`` of their size (a check on newer libraries,
    whose last digits may move)."""
    if expected == actual or rtol <= 0:
        return expected == actual
    if NUMBER.split(expected) != NUMBER.split(actual):
        return False
    for a, b in zip(NUMBER.findall(expected), NUMBER.findall(actual), strict=True):
        x, y = float(a), float(b)
        if abs(x - y) > rtol * max(abs(x), abs(y)):
            return False
    return True


def matches(expected: list[str], actual: list[str], rtol: float = 0.0) -> bool:
    """Line-by-line match; an expected ``...`` line matches any run of lines; numbers within
    ``rtol`` (relative) match when it is given (:func:`same_line`)."""
    exp = [_norm(e) for e in expected if e.strip() or False]
    act = [_norm(a) for a in actual if a.strip()]

    def go(i: int, j: int) -> bool:
        if i == len(exp):
            return j == len(act)
        if exp[i] == "...":
            return any(go(i + 1, k) for k in range(j, len(act) + 1))
        return j < len(act) and same_line(exp[i], act[j], rtol) and go(i + 1, j + 1)

    return go(0, 0)


def run_step(step: Step, cwd: Path, env: dict[str, str]) -> tuple[int, list[str]]:
    proc = subprocess.run(
        ["bash", "-c", step.command],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    out = proc.stdout if proc.returncode == 0 else proc.stderr
    return proc.returncode, out.rstrip("\n").splitlines()


def _environment() -> dict[str, str]:
    env = dict(os.environ)
    bindir = str(Path(sys.executable).parent)
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    env["COLUMNS"] = "100"
    env.pop("VIRTUAL_ENV", None)
    return env


def check_transcripts(
    lines: list[str],
    only: str | None,
    update: bool,
    scratch: Path,
    log: Callable[[str], None],
    rtol: float = 0.0,
) -> tuple[bool, list[str]]:
    env = _environment()
    ok = True
    new = list(lines)
    # Replace from the bottom so earlier line numbers stay valid.
    edits: list[tuple[int, int, list[str]]] = []
    for block in transcripts(lines):
        if only and not any(only in s.command for s in block.steps):
            continue
        body: list[str] = []
        for step in block.steps:
            log(f"$ {step.command}")
            code, out = run_step(step, scratch, env)
            body.append("$ " + step.command)
            if matches(step.expected, out, max(rtol, block.rtol)):
                body.extend(step.expected)
                continue
            ok = False
            body.extend(out)
            log(f"  differs (exit {code}):")
            for d in difflib.unified_diff(step.expected, out, "README", "now", lineterm="", n=1):
                log("  " + d)
        edits.append((block.start, block.end, body))
    if update:
        for start, end, body in reversed(edits):
            new[start:end] = body
    return ok, new


def check_tables(
    lines: list[str], update: bool, log: Callable[[str], None]
) -> tuple[bool, list[str]]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from readme_tables import TABLES

    ok = True
    new = list(lines)
    i = 0
    while i < len(new):
        m = TABLE_START.search(new[i])
        if not m:
            i += 1
            continue
        end = next(k for k in range(i + 1, len(new)) if new[k].strip() == TABLE_END)
        name = m.group(1)
        if name not in TABLES:
            log(f"unknown generated table {name!r}")
            ok = False
            i = end + 1
            continue
        log(f"table {name}: regenerating")
        body = TABLES[name](log).rstrip("\n").splitlines()
        if [_norm(x) for x in body] != [_norm(x) for x in new[i + 1 : end]]:
            ok = False
            for d in difflib.unified_diff(new[i + 1 : end], body, "README", "now", lineterm=""):
                log("  " + d)
        if update:
            new[i + 1 : end] = body
            end = i + 1 + len(body)
        i = end + 1
    return ok, new


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="only the blocks with a command containing this text")
    ap.add_argument("--tables", action="store_true", help="also regenerate the generated tables")
    ap.add_argument("--update", action="store_true", help="write the new outputs into README.md")
    ap.add_argument(
        "--rtol",
        type=float,
        default=0.0,
        help="let numbers differ by this relative amount (after 'setup.sh --latest': 0.05); "
        "default 0, every digit as printed on the tested versions",
    )
    ap.add_argument("--keep", type=Path, help="scratch folder to use and keep (default: temporary)")
    args = ap.parse_args(argv)

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    lines = README.read_text(encoding="utf-8").splitlines()
    with tempfile.TemporaryDirectory(prefix="readme_check_") as tmp:
        scratch = args.keep or Path(tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        for name in ("configs", "models", "tests"):
            if not (scratch / name).exists():
                (scratch / name).symlink_to(ROOT / name)
        ok, new = check_transcripts(lines, args.only, args.update, scratch, log, args.rtol)
    if args.tables:
        ok_t, new = check_tables(new, args.update, log)
        ok = ok and ok_t
    if args.update and new != lines:
        README.write_text("\n".join(new) + "\n", encoding="utf-8")
        log("README.md updated: review the diff")
    log("README matches its commands" if ok else "README differs from its commands")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
