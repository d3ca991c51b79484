#!/usr/bin/env python3
"""An independent, seeded fuzzer of every rough_map reader and entry point, and of the CLI.

    .venv/bin/python tools/fuzz_all.py                       # 4,000 cases + 80 CLI runs
    .venv/bin/python tools/fuzz_all.py --cases 400 --cli 0 --targets bag   # a quick look
    .venv/bin/python tools/fuzz_all.py --seed 7 --jobs 2 --out /tmp/fuzz.json
    .venv/bin/python tools/fuzz_all.py --replay load_traverse:123456   # one case, traceback

The 4,000 cases take about 10-15 minutes on 2 cores (the bases are built on the first run,
about 40 s, and kept in ``--work``; delete that folder to rebuild them).

What it measures is the hardening issue's figure: over at least 4,000 mutated inputs, 0
exceptions outside ``RoughMapError``, 0 hangs, 0 crashes and 0 allocations beyond the
input's real size; and that the CLI exits with 0 or 2 and, on failure, one line on stderr.

How it works:

1. Bases. One valid input of every kind is built once into ``--work``/bases (about 40 s:
   a simulated 2 m traverse, its bag in ROS 1, ROS 2 sqlite3 and MCAP storage, a cloud in
   every format, images, calibrations, configs, a features table, a map folder with its
   state and grid_map bag, the shipped model); see ``fuzz_all_bases.py``. The targets
   (``fuzz_all_targets.py``) say which files of a base each entry point reads.
2. Cases. Case ``k`` goes to target ``k mod T`` with its own 32-bit seed; the seed picks the
   file of the base to break and the mutation (``fuzz_all_mutators.py``: truncations,
   flipped bytes, hostile words and numbers, deep nesting, wrong types, missing keys, huge
   counts, PLY/PCD header lines, LAS header fields, NPY headers, ZIP members and bombs,
   PNG sizes, YAML alias bombs and tags, a missing file or a folder in its place, a path
   out of a traverse), or, for ``lib_*`` targets, hostile arguments
   (NaN/inf/empty/ragged/object arrays, zero or huge spacing, bad windows...).
3. Runs. This process imports rough_map once, then forks one child per case (up to
   ``--jobs`` at a time). A child that uses more than ``--timeout`` s of CPU (RLIMIT_CPU,
   so that a loaded machine does not make hangs), or gets nowhere for 6 times that in wall
   time, is killed (**hang**); one that dies by a signal is a **crash**; one whose peak
   resident memory grows by more than max(200 MB, 50 x the case's bytes), or that meets a
   ``MemoryError`` (its address space is capped at 2 GB above the start), is **memory**.
   Otherwise the outcome is **ok** (a result), **clean** (a ``RoughMapError`` of one
   printable line of at most 240 characters), **bad_message** (a ``RoughMapError`` that is
   not), **exception** (any other type, recorded with its first line; also a YAML tag that
   ran code), or **escape** (a traverse made to name a valid cloud outside its folder, by a
   symbolic link, an absolute or a ``../`` path, was read).
4. CLI sample. ``--cli`` cases run ``python -m rough_map CMD ...`` as a subprocess on a
   mutated input (features on a cloud and a traverse, map, inspect, import, classify with a
   damaged model, score with a damaged truth, stereo with a damaged calibration): the exit
   status must be 0 or 2, and stderr on failure one line.

The report (``--out``, JSON) has the counts per target and outcome and every non-clean case
with its target and seed; ``--replay TARGET:SEED`` runs that case in this process and shows
the traceback. Exit status: 0 when every case was ok or clean, 1 otherwise, 2 usage error.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import random  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from collections import Counter, defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz_all_bases  # noqa: E402
import fuzz_all_mutators as mut  # noqa: E402
import fuzz_all_targets as tg  # noqa: E402

OUTCOMES = ("ok", "clean", "bad_message", "exception", "hang", "crash", "memory", "escape")
ESCAPE_MARKER = "ESCAPE"
MAX_MESSAGE = 240
MB = 1 << 20
#: Imported once here, before the children fork, so that each case does not pay for it.
PRELOAD = """rough_map.io.pointcloud rough_map.io.las rough_map.io.images rough_map.io.traverse
rough_map.io.truth rough_map.io.truth_raster rough_map.io.rosbag.reader
rough_map.io.rosbag.importer rough_map.export.gridmap_msg rough_map.features rough_map.config
rough_map.stereo.rectify rough_map.stereo.settings rough_map.classify.persistence
rough_map.classify.levels rough_map.filter.roughness rough_map.near_far.settings
rough_map.near_far.tiles rough_map.map.state rough_map.evaluation.score_files rough_map.psd
rough_map.patch laspy open3d cv2 rasterio skops.io sklearn.ensemble rosbags.highlevel yaml
pandas pyarrow.parquet""".split()


# --------------------------------------------------------------------------- one case


def _case_seed(seed: int, k: int) -> int:
    return random.Random(f"{seed}:{k}").getrandbits(32)


def prepare(target: tg.Target, seed: int, bases: Path, case_dir: Path) -> Path | None:
    """Copy the target's base into ``case_dir`` and break one file; returns the path the
    call reads (None for library targets)."""
    rng = random.Random(seed)
    if target.src is None:
        return None
    src = bases / target.src
    root = case_dir / src.name
    if src.is_dir():
        shutil.copytree(src, root)
    else:
        shutil.copy(src, root)
    if not target.mutable:
        return root
    rel = rng.choice(target.mutable)
    victim = root if rel == "." else root / rel
    roll = rng.random()
    if roll < 0.03:
        victim.unlink()  # a missing file
    elif roll < 0.05:
        victim.unlink()
        victim.mkdir()  # a folder where a file is expected
    elif roll < 0.09 and target.src.startswith("trav"):
        _escape(root, bases, rng)
        (case_dir / ESCAPE_MARKER).write_text("a path of the traverse points outside it\n")
    else:
        data = victim.read_bytes()
        others = [
            p.read_bytes() for p in (bases / "image.png", bases / "poses.txt", bases / "world.npz")
        ]
        victim.write_bytes(mut.mutate_file(data, target.kinds.get(rel, "bytes"), rng, others))
    return root


def _escape(root: Path, bases: Path, rng: random.Random) -> None:
    """Make the traverse at ``root`` name a valid cloud outside its folder: through a
    symbolic link, an absolute path or a ``../`` path in its traverse file."""
    outside = (bases / "clouds" / "cloud.npy").resolve()
    kind = rng.randrange(3)
    if kind == 0:
        link = root / "clouds" / "000000.npy"
        link.unlink()
        link.symlink_to(outside)
        return
    (spec_file,) = [p for p in root.iterdir() if p.stem == "traverse"]
    import yaml

    spec = yaml.safe_load(spec_file.read_text())
    spec["frames"][0]["cloud"] = (
        str(outside) if kind == 1 else os.path.relpath(outside, root.resolve())
    )
    text = json.dumps(spec) if spec_file.suffix == ".json" else yaml.safe_dump(spec)
    spec_file.write_text(text)


def _size(path: Path | None) -> int:
    if path is None:
        return 1 << 16
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _status(key: str) -> int:
    """VmRSS/VmHWM/VmSize of this process in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    return 0


def _has_memory_error(exc: BaseException | None) -> bool:
    seen = 0
    while exc is not None and seen < 20:
        if isinstance(exc, MemoryError):
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


def classify(exc: BaseException | None) -> tuple[str, str, str]:
    """(outcome, exception type, first line of the message) of a call's exception."""
    from rough_map.errors import RoughMapError

    if exc is None:
        return "ok", "", ""
    text = str(exc)
    first = text.splitlines()[0][:300] if text else ""
    name = type(exc).__name__
    if _has_memory_error(exc):
        return "memory", name, first
    if isinstance(exc, RoughMapError):
        bad = "\n" in text or len(text) > MAX_MESSAGE or not text.isprintable()
        return ("bad_message" if bad else "clean"), name, repr(text[:300]) if bad else first
    return "exception", name, first


def run_case(target: tg.Target, seed: int, bases: Path, case_dir: Path) -> dict[str, Any]:
    """Prepare and run one case in this process; the outcome record."""
    root = prepare(target, seed, bases, case_dir)
    size = _size(root)
    try:
        Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS
    except OSError:
        pass
    rss0 = _status("VmRSS")
    os.chdir(case_dir)
    exc: BaseException | None = None
    try:
        target.call(root, random.Random(seed ^ 0x5EED))
    except Exception as err:  # every outcome is recorded; classify() judges it
        exc = err
    except RecursionError as err:
        exc = err
    outcome, name, message = classify(exc)
    grew = max(0, _status("VmHWM") - rss0)
    if outcome not in ("memory",) and grew > max(200 * MB, 50 * size):
        outcome, message = "memory", f"peak RSS grew by {grew // MB} MB for {size} bytes; {message}"
    if outcome == "ok" and (case_dir / ESCAPE_MARKER).exists():
        outcome, name, message = "escape", "PathEscape", "read a cloud outside the traverse"
    if (case_dir / mut.CODE_MARKER).exists():
        outcome, name, message = "exception", "CodeExecution", "a YAML tag ran code"
    return {
        "outcome": outcome,
        "type": name,
        "message": message,
        "bytes": size,
        "rss_mb": round(grew / MB, 1),
    }


def run_cli_case(
    case: tuple[str, str, list[str], str],
    seed: int,
    bases: Path,
    case_dir: Path,
    timeout: float,
    base: bool = False,
) -> dict[str, Any]:
    name, src, argv, rel = case
    target = tg.Target(name, src, [] if base else [rel], lambda *a: None, {rel: _kind(rel)})
    root = prepare(target, seed, bases, case_dir)
    out = case_dir / "out"
    args = [a.replace("{case}", str(root)).replace("{out}", str(out)) for a in argv]
    if "{out}/" in " ".join(argv):
        out.mkdir()
    proc = subprocess.run(
        [*tg.RM, *args],
        capture_output=True,
        timeout=timeout,
        cwd=case_dir,
        stdin=subprocess.DEVNULL,
    )
    err = proc.stderr.decode("utf-8", "backslashreplace")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    rec = {
        "outcome": "ok" if proc.returncode == 0 else "clean",
        "type": "",
        "message": "",
        "bytes": _size(root),
        "rss_mb": 0.0,
        "argv": " ".join(args)[:300],
    }
    if proc.returncode == 0 and (case_dir / ESCAPE_MARKER).exists():
        rec.update(outcome="escape", type="PathEscape", message="read a cloud outside the traverse")
    if proc.returncode < 0:
        rec.update(outcome="crash", type=f"signal {-proc.returncode}")
    elif proc.returncode not in (0, 2):
        rec.update(outcome="exception", type=f"exit {proc.returncode}", message=err[-300:])
    elif proc.returncode == 2:
        last = lines[-1] if lines else ""
        if len(lines) != 1 or len(last) > MAX_MESSAGE or not last.isprintable():
            rec.update(outcome="bad_message", type=f"{len(lines)} lines", message=err[:300])
        elif "internal error" in last:
            rec.update(outcome="exception", type="internal error", message=last)
        else:
            rec["message"] = last
    return rec


def _kind(rel: str) -> str:
    return {
        ".json": "json",
        ".yaml": "yaml",
        ".npy": "npy",
        ".skops": "zip",
        ".ply": "text",
        ".png": "png",
    }.get(Path(rel).suffix, "bytes")


# --------------------------------------------------------------------------- the pool


def _child(job: dict[str, Any], wfd: int, bases: Path, timeout: float) -> None:
    """Body of a forked child: run the case, write its record to ``wfd``, exit."""
    os.setpgid(0, 0)
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)
    os.dup2(null, 1)
    os.dup2(null, 2)
    vm = _status("VmSize")
    try:
        resource.setrlimit(resource.RLIMIT_AS, (vm + 2048 * MB, resource.RLIM_INFINITY))
        cpu = int(timeout) + int(resource.getrusage(resource.RUSAGE_SELF).ru_utime)
        resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
    except (ValueError, OSError):
        pass
    try:
        case_dir = Path(job["dir"])
        if job["cli"] is not None:
            rec = run_cli_case(
                job["cli"], job["seed"], bases, case_dir, timeout, job.get("base", False)
            )
        else:
            rec = run_case(job["target"], job["seed"], bases, case_dir)
    except subprocess.TimeoutExpired:
        rec = {"outcome": "hang", "type": "", "message": "CLI subprocess timed out"}
    except BaseException as err:  # a failure of the fuzzer's own preparation
        rec = {
            "outcome": "exception",
            "type": "fuzzer:" + type(err).__name__,
            "message": str(err)[:300],
        }
    os.write(wfd, json.dumps(rec).encode())
    os.close(wfd)
    os._exit(0)


def run_jobs(
    jobs: list[dict[str, Any]], bases: Path, work: Path, n_jobs: int, timeout: float, progress: bool
) -> list[dict[str, Any]]:
    """Run every job in forked children, ``n_jobs`` at a time; the records in job order."""
    pending = list(enumerate(jobs))
    running: dict[int, tuple[int, int, float, Path, float]] = {}
    records: list[dict[str, Any] | None] = [None] * len(jobs)
    done = 0
    while pending or running:
        while pending and len(running) < n_jobs:
            k, job = pending.pop(0)
            case_dir = work / f"case{k}"
            shutil.rmtree(case_dir, ignore_errors=True)
            case_dir.mkdir(parents=True)
            job["dir"] = str(case_dir)
            r, w = os.pipe()
            limit = job.get("timeout", timeout)
            pid = os.fork()
            if pid == 0:
                os.close(r)
                _child(job, w, bases, limit)
            os.close(w)
            os.set_blocking(r, False)
            running[pid] = (k, r, time.monotonic(), case_dir, limit)
        time.sleep(0.002)
        for pid, (k, r, start, case_dir, limit) in list(running.items()):
            buf = _drain(r, running, pid)
            got, status = os.waitpid(pid, os.WNOHANG)
            elapsed = time.monotonic() - start
            if got == 0 and elapsed > 6 * limit:
                for kill in (os.killpg, os.kill):  # its group (a CLI subprocess too), itself
                    try:
                        kill(pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                os.waitpid(pid, 0)
                rec: dict[str, Any] = {
                    "outcome": "hang",
                    "type": "",
                    "message": f"no end after {6 * limit:.0f} s wall time",
                }
            elif got == 0:
                continue
            else:
                buf += _drain(r, running, pid, final=True)
                if os.WIFSIGNALED(status):
                    sig = os.WTERMSIG(status)
                    if sig == signal.SIGXCPU:
                        rec = {"outcome": "hang", "type": "", "message": f"over {limit:.0f} s CPU"}
                    else:
                        rec = {"outcome": "crash", "type": signal.Signals(sig).name, "message": ""}
                else:
                    try:
                        rec = json.loads(buf.decode())
                    except ValueError:
                        rec = {
                            "outcome": "crash",
                            "type": f"exit {os.WEXITSTATUS(status)}",
                            "message": "no record",
                        }
            os.close(r)
            _, _, start, _, _ = running.pop(pid)
            rec["seconds"] = round(time.monotonic() - start, 2)
            records[k] = rec
            shutil.rmtree(case_dir, ignore_errors=True)
            done += 1
            if progress and done % 100 == 0:
                print(f"  {done}/{len(jobs)} cases", file=sys.stderr, flush=True)
    return [r or {} for r in records]


_BUFFERS: dict[int, bytes] = {}


def _drain(fd: int, running: dict, pid: int, final: bool = False) -> bytes:
    chunks = []
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            break
        if not chunk:
            break
        chunks.append(chunk)
    data = _BUFFERS.pop(pid, b"") + b"".join(chunks)
    if not final:
        _BUFFERS[pid] = data
        return b""
    return data


# --------------------------------------------------------------------------- main


def _bases(work: Path) -> Path:
    bases = work / "bases"
    if not (bases / "DONE").exists():
        shutil.rmtree(bases, ignore_errors=True)
        print(f"building the bases in {bases} ...", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, __file__, "--build-bases", str(bases)], check=True)
    return bases


def _preload() -> None:
    import importlib

    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except Exception:  # an optional backend that is not installed
            pass


def summary(records: list[dict[str, Any]]) -> str:
    counts: dict[str, Counter] = defaultdict(Counter)
    for r in records:
        counts[r["target"]][r["outcome"]] += 1
    rows = [["target", *OUTCOMES, "total"]]
    for name in sorted(counts):
        c = counts[name]
        rows.append([name, *(str(c[o]) for o in OUTCOMES), str(sum(c.values()))])
    total = Counter(r["outcome"] for r in records)
    rows.append(["TOTAL", *(str(total[o]) for o in OUTCOMES), str(len(records))])
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(
            c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--seed", type=int, default=0, help="seed of the run (default 0)")
    p.add_argument("--cases", type=int, default=4000, help="library cases (default 4000)")
    p.add_argument("--cli", type=int, default=80, help="CLI cases (default 80)")
    p.add_argument("--targets", default="", help="only targets whose name holds this text")
    p.add_argument("--jobs", type=int, default=2, help="cases run at a time (default 2)")
    p.add_argument("--timeout", type=float, default=10.0, help="s before a case is a hang")
    p.add_argument("--cli-timeout", type=float, default=120.0, help="s for a CLI case")
    p.add_argument("--work", type=Path, default=Path("/tmp/fuzz_all_work"), help="work folder")
    p.add_argument("--out", type=Path, default=None, help="write the JSON report here")
    p.add_argument("--replay", default=None, metavar="TARGET:SEED", help="run one case here")
    p.add_argument("--build-bases", type=Path, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.build_bases is not None:
        fuzz_all_bases.build_bases(args.build_bases)
        return 0
    bases = _bases(args.work)
    _preload()
    targets = [t for t in tg.targets(bases) if args.targets in t.name]
    cli = [c for c in tg.cli_cases(bases) if args.targets in c[0]]
    if args.replay:
        return _replay(args.replay, targets, cli, bases, args.work)
    if not targets and not cli:
        print(f"no target matches {args.targets!r}", file=sys.stderr)
        return 2
    jobs: list[dict[str, Any]] = []
    # The bases themselves first (seed -1 breaks nothing: a record of what a valid input gives).
    for t in (t for t in targets if t.src is not None):
        jobs.append(
            {
                "target": tg.Target(t.name, t.src, [], t.call),
                "name": t.name,
                "seed": 1,
                "cli": None,
                "base": True,
            }
        )
    for k in range(args.cases if targets else 0):
        t = targets[k % len(targets)]
        jobs.append({"target": t, "name": t.name, "seed": _case_seed(args.seed, k), "cli": None})
    for c in cli if args.cli else []:
        jobs.append(
            {
                "target": None,
                "name": c[0],
                "seed": 1,
                "cli": c,
                "base": True,
                "timeout": args.cli_timeout,
            }
        )
    for k in range(args.cli if cli else 0):
        c = cli[k % len(cli)]
        jobs.append(
            {
                "target": None,
                "name": c[0],
                "seed": _case_seed(args.seed + 1, k),
                "cli": c,
                "timeout": args.cli_timeout,
            }
        )
    started = time.monotonic()
    records = run_jobs(jobs, bases, args.work / "cases", args.jobs, args.timeout, True)
    for job, rec in zip(jobs, records, strict=True):
        rec["target"], rec["seed"] = job["name"], job["seed"]
        rec["base"] = job.get("base", False)
    base = [r for r in records if r["base"]]
    fuzz = [r for r in records if not r["base"]]
    bad = [r for r in fuzz if r["outcome"] not in ("ok", "clean")]
    print(summary(fuzz))
    print(f"\n{len(fuzz)} cases in {time.monotonic() - started:.0f} s; {len(bad)} not clean")
    for r in base:
        if r["outcome"] != "ok":
            print(f"base of {r['target']} fails: {r['outcome']} {r['type']}: {r['message'][:150]}")
    shown: Counter = Counter()
    for r in bad:
        key = (r["target"], r["outcome"], r["type"])
        shown[key] += 1
        if shown[key] <= 2:
            print(f"  {r['target']}:{r['seed']}  {r['outcome']}  {r['type']}: {r['message'][:160]}")
    if args.out:
        report = {
            "seed": args.seed,
            "cases": len(fuzz),
            "jobs": args.jobs,
            "seconds": round(time.monotonic() - started),
            "summary": _counts(fuzz),
            "bases": base,
            "failures": bad,
        }
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 1 if bad else 0


def _counts(records: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    out: dict[str, Counter] = defaultdict(Counter)
    for r in records:
        out[r["target"]][r["outcome"]] += 1
    return {k: dict(v) for k, v in sorted(out.items())}


def _replay(spec: str, targets: list, cli: list, bases: Path, work: Path) -> int:
    name, _, seed_text = spec.rpartition(":")
    seed = int(seed_text)
    case_dir = work / "replay"
    shutil.rmtree(case_dir, ignore_errors=True)
    case_dir.mkdir(parents=True)
    for c in cli:
        if c[0] == name:
            rec = run_cli_case(c, seed, bases, case_dir, 120)
            print(json.dumps(rec, indent=1))
            return 0
    (t,) = [t for t in targets if t.name == name]
    root = prepare(t, seed, bases, case_dir)
    print(f"case files in {case_dir}", file=sys.stderr)
    try:
        t.call(root, random.Random(seed ^ 0x5EED))
    except Exception:
        traceback.print_exc()
        return 1
    print("ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())
