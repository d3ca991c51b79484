"""Kill ``rough-map map``, ``features`` and ``train`` at random moments and check what is left.

Run by hand (not in CI; a few minutes)::

    .venv/bin/python tools/kill_check.py --kills 30 --seed 1 --work /tmp/rough_map_kill_check

It simulates two small traverses under ``--work``, records the outputs of an uninterrupted
run of each command twice: the *old* set (other inputs or settings) and the *new* set (the
reference). Then, ``--kills`` times (spread over the three commands, seeded), it puts the
old set in place (with a file of the user's), starts the command, SIGKILLs it at a random
moment (or at a chosen one: when its staging folder appears, when its GeoTIFF is written,
when its features metadata is written) and checks:

- partial: every file under a final name reads back (GeoTIFF, PNG, CSV, JSON, zip);
- mixed: each output folder (and the features CSV + metadata pair) is entirely the old set
  or entirely the new one, byte for byte; the user's file is still there;
- card: a model without its card, or whose card's sha256 is not the model's;
- then it reruns the command without a kill: it must exit 0 and give the reference bytes,
  keep the user's file, and leave no temporary file (``.*.tmp.*``) behind.

Prints a table of counts; exit status 1 when any check failed.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import random
import re
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROUGH_MAP = [sys.executable, "-m", "rough_map"]
TEMP = re.compile(
    r"^\..+\.[0-9a-f]{12}\.tmp(\..*)?$|^\..+\.(tmp|old)\.[0-9a-f]{12}$|^\..+\.pending$"
)
USER_FILE = "notes_of_the_user.txt"


@dataclass
class Command:
    """One command under test: how to run it for the old and the new set, and its outputs."""

    name: str
    new: list[str]
    old: list[str]
    outputs: list[str]  # paths under the work dir: folders or files
    chosen: list[Callable[[Path], bool]] = field(default_factory=list)
    duration: float = 0.0


def run(args: list[str], cwd: Path) -> None:
    done = subprocess.run([*ROUGH_MAP, "-q", *args], cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"rough-map {' '.join(args)} failed:\n{done.stderr}")


def digest(path: Path) -> dict[str, str]:
    """sha256 of every file under ``path`` (or of ``path``), temporary names excluded."""
    if path.is_file():
        return {path.name: hashlib.sha256(path.read_bytes()).hexdigest()}
    if not path.is_dir():
        return {}
    return {
        p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(path.rglob("*"))
        if p.is_file() and not any(TEMP.match(part) for part in p.relative_to(path).parts)
    }


def pair(work: Path, out: str) -> dict[str, str]:
    """The set of an output: a folder's files; a features CSV with its metadata."""
    path = work / out
    if path.suffix == ".csv":
        return {**digest(path), **digest(path.with_name(path.name + ".json"))}
    found = digest(path)
    found.pop(USER_FILE, None)
    return found


def readable(path: Path) -> str | None:
    """Why ``path`` does not read back (None when it does)."""
    try:
        suffix = path.suffix.lower()
        if suffix == ".tif":
            import rasterio

            with rasterio.open(path) as ds:
                ds.read()
        elif suffix == ".png":
            from PIL import Image

            with Image.open(path) as img:
                img.load()
        elif suffix == ".csv":
            with open(path, newline="", encoding="utf-8") as fh:
                rows = list(csv.reader(fh))
            if not rows:
                return "empty csv"
        elif suffix == ".json":
            json.loads(path.read_text(encoding="utf-8"))
        elif suffix in (".skops", ".npz", ".zip"):
            with zipfile.ZipFile(path) as zf:
                bad = zf.testzip()
            if bad is not None:
                return f"bad zip member {bad}"
        elif path.stat().st_size == 0:
            return "empty"
    except Exception as exc:  # any failure to read back is the finding
        return f"{type(exc).__name__}: {exc}"
    return None


def temps(work: Path) -> list[Path]:
    return [p for p in work.rglob(".*") if TEMP.match(p.name) and "traverses" not in p.parts]


def card_problem(work: Path) -> str | None:
    model, card = work / "train" / "model.skops", work / "train" / "model.card.json"
    if not model.exists() and not card.exists():
        return None
    if model.exists() != card.exists():
        return "model without card" if model.exists() else "card without model"
    try:
        recorded = json.loads(card.read_text())["sha256"]
    except (OSError, ValueError, KeyError) as exc:
        return f"card unreadable: {exc}"
    if recorded != hashlib.sha256(model.read_bytes()).hexdigest():
        return "card sha256 is not the model's"
    return None


def put_old(work: Path, cmd: Command, old: Path) -> None:
    for out in cmd.outputs:
        target = work / out
        for p in (target, target.with_name(target.name + ".json")):
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
        for p in list(target.parent.glob(".*")):
            if TEMP.match(p.name):
                shutil.rmtree(p) if p.is_dir() else p.unlink()
    if old.exists():
        shutil.copytree(old, work, dirs_exist_ok=True)
    for out in cmd.outputs:
        if (work / out).is_dir():
            (work / out / USER_FILE).write_text("mine\n")


def snapshot(work: Path, cmd: Command, dest: Path) -> None:
    if dest.exists():
        shutil.rmtree(dest)
    for out in cmd.outputs:
        src = work / out
        for p in (src, src.with_name(src.name + ".json")):
            if p.is_dir():
                shutil.copytree(
                    p, dest / p.relative_to(work), ignore=shutil.ignore_patterns(USER_FILE)
                )
            elif p.is_file():
                (dest / p.relative_to(work)).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(p, dest / p.relative_to(work))


def staged(work: Path, pattern: str) -> bool:
    return any(work.rglob(pattern))


def kill_once(
    work: Path, cmd: Command, delay: float | None, moment: Callable[[Path], bool] | None
) -> bool:
    """Start the command and SIGKILL it after ``delay`` s or at ``moment``; True if killed."""
    proc = subprocess.Popen(
        [*ROUGH_MAP, "-q", *cmd.new], cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    start = time.monotonic()
    while proc.poll() is None:
        elapsed = time.monotonic() - start
        if (delay is not None and elapsed >= delay) or (moment is not None and moment(work)):
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return True
        if elapsed > 10 * cmd.duration + 30:
            proc.kill()
            sys.exit(f"{cmd.name} hung")
        time.sleep(0.003)
    return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rough_map_kill_check"))
    ap.add_argument("--length", type=float, default=3.0, help="traverse length, m")
    opts = ap.parse_args()
    rng = random.Random(opts.seed)
    work = opts.work.resolve()
    if work.exists():
        shutil.rmtree(work)
    (work / "traverses").mkdir(parents=True)
    for seed in (1, 2):
        run(["simulate", "--out", f"traverses/t{seed}", "--length", str(opts.length),
             "--no-images", "--seed", str(seed)], work)  # fmt: skip
    t1, t2 = "traverses/t1", "traverses/t2"
    commands = [
        Command(
            "map",
            ["map", t1, "--out", "map_out"],
            ["map", t2, "--out", "map_out"],
            ["map_out"],
            [
                lambda w: staged(w, ".map_out.tmp.*"),
                lambda w: staged(w, ".map_out.tmp.*/map_class.tif"),
                lambda w: staged(w, ".map_out.tmp.*/labels.csv"),
            ],
        ),
        Command(
            "features",
            ["features", t1, "--out", "feat/features.csv"],
            ["features", t2, "--out", "feat/features.csv"],
            ["feat/features.csv"],
            [lambda w: staged(w, "feat/.features.csv.pending/complete")],
        ),
        Command(
            "train",
            ["train", t1, t2, "--out", "train/model", "--save-features", "train/feats",
             "--cv", "2", "--force"],
            ["train", t2, t1, "--out", "train/model", "--save-features", "train/feats", "--cv", "2",
             "--no-tilt", "--force"],
            ["train/feats"],
            [lambda w: staged(w, ".feats.tmp.*"),
             lambda w: staged(w, "train/.model.skops.pending/complete")],
        ),
    ]  # fmt: skip
    (work / "feat").mkdir()
    refs: dict[str, tuple[dict[str, dict[str, str]], dict[str, dict[str, str]]]] = {}
    for cmd in commands:
        run(cmd.old, work)
        snapshot(work, cmd, work / "old" / cmd.name)
        old = {o: pair(work, o) for o in cmd.outputs}
        t0 = time.monotonic()
        run(cmd.new, work)
        cmd.duration = time.monotonic() - t0
        new = {o: pair(work, o) for o in cmd.outputs}
        refs[cmd.name] = (old, new)
        print(f"{cmd.name}: uninterrupted run {cmd.duration:.1f} s", file=sys.stderr)

    counts: dict[str, Counter[str]] = {c.name: Counter() for c in commands}
    problems: list[str] = []
    plan = [commands[k % 3] for k in range(opts.kills)]
    rng.shuffle(plan)
    chosen_left = {c.name: list(c.chosen) for c in commands}
    for k, cmd in enumerate(plan):
        c = counts[cmd.name]
        c["runs"] += 1
        put_old(work, cmd, work / "old" / cmd.name)
        moment = chosen_left[cmd.name].pop(0) if chosen_left[cmd.name] else None
        delay = None if moment is not None else rng.uniform(0.0, cmd.duration)
        c["chosen moment" if moment else "random moment"] += 1
        if not kill_once(work, cmd, delay, moment):
            c["finished before the kill"] += 1
        old, new = refs[cmd.name]
        for out in cmd.outputs:
            target = work / out
            for p in [target] if target.is_file() else sorted(target.rglob("*")):
                if p.is_file() and not TEMP.match(p.name) and (why := readable(p)):
                    c["partial file"] += 1
                    problems.append(f"kill {k} {cmd.name}: {p}: {why}")
            got = pair(work, out)
            state = "old" if got == old[out] else "new" if got == new[out] else "MIXED"
            c[f"left {state}"] += 1
            if state == "MIXED":
                c["mixed folder"] += 1
                problems.append(f"kill {k} {cmd.name}: {out} is neither the old nor the new set")
            if target.is_dir() and not (target / USER_FILE).is_file():
                c["user file lost"] += 1
                problems.append(f"kill {k} {cmd.name}: the user's file in {out} is gone")
        if cmd.name == "train" and (why := card_problem(work)):
            c["model/card disagree"] += 1
            problems.append(f"kill {k} train: {why}")
        if temps(work):
            c["temp left by the kill"] += 1
        t0 = time.monotonic()
        done = subprocess.run(
            [*ROUGH_MAP, "-q", *cmd.new], cwd=work, capture_output=True, text=True
        )
        cmd.duration = min(cmd.duration, time.monotonic() - t0)  # kill within a run's time
        if done.returncode != 0:
            c["rerun failed"] += 1
            problems.append(
                f"kill {k} {cmd.name}: rerun exit {done.returncode}: {done.stderr[-300:]}"
            )
            continue
        for out in cmd.outputs:
            if pair(work, out) != new[out]:
                c["rerun differs"] += 1
                problems.append(f"kill {k} {cmd.name}: rerun of {out} differs from the reference")
        if left := temps(work):
            c["temp after rerun"] += 1
            problems.append(f"kill {k} {cmd.name}: left after the rerun: {[str(p) for p in left]}")
        if cmd.name == "train" and (why := card_problem(work)):
            c["model/card disagree after rerun"] += 1
            problems.append(f"kill {k} train (rerun): {why}")

    keys = [
        "runs", "random moment", "chosen moment", "finished before the kill", "left old",
        "left new", "left MIXED", "partial file", "mixed folder", "user file lost",
        "model/card disagree", "temp left by the kill", "rerun failed", "rerun differs",
        "temp after rerun", "model/card disagree after rerun",
    ]  # fmt: skip
    width = max(len(k) for k in keys)
    print(f"{'':{width}}  " + "  ".join(f"{c.name:>8}" for c in commands) + "     total")
    for key in keys:
        vals = [counts[c.name][key] for c in commands]
        print(f"{key:{width}}  " + "  ".join(f"{v:>8}" for v in vals) + f"  {sum(vals):>8}")
    for p in problems:
        print(p)
    bad = ("partial file", "mixed folder", "user file lost", "rerun failed", "rerun differs",
           "temp after rerun", "model/card disagree after rerun")  # fmt: skip
    return 1 if any(counts[c.name][k] for c in commands for k in bad) else 0


if __name__ == "__main__":
    sys.exit(main())
