"""Does the start-up tuning of `rough-map map` still pay? The command against the library.

Run: ``python benchmarks/bench_startup.py [--length 6] [--runs 5] [-j 2]``

`rough-map map` starts its worker processes and the frame pass while it imports
scikit-learn and loads the model, and keeps imports it does not use out of the process
(:mod:`rough_map.cli.map`, :func:`rough_map.cli._common.start_up`). The baseline, run in turn
with it on the same traverse, is the plain library path in a fresh interpreter: load the
model, :func:`rough_map.workflow.analyse`, :func:`rough_map.workflow.write_outputs`. Both
write the same map. Each figure is a median of ``--runs`` alternating pairs, with the ratio
of the command to the baseline: below 1 the tuning pays.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_LIBRARY = """
import sys
from pathlib import Path
from rough_map.classify import load_terrain_model
from rough_map.io.traverse import load_traverse
from rough_map.workflow import analyse, write_outputs
traverse = load_traverse(sys.argv[1])
result = analyse(traverse, load_terrain_model("default"), n_jobs=int(sys.argv[3]))
write_outputs(result, Path(sys.argv[2]), png=False)
"""


def _wall(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--length", type=float, default=6.0, help="course length in m")
    ap.add_argument("--runs", type=int, default=5, help="alternating pairs timed")
    ap.add_argument("-j", "--jobs", type=int, default=2, help="worker processes")
    args = ap.parse_args()
    cli = str(Path(sys.executable).with_name("rough-map"))
    with tempfile.TemporaryDirectory(prefix="bench_startup_") as tmp:
        work = Path(tmp)
        sim = [cli, "simulate", "--out", str(work / "t"), "--course", "mixed", "--no-images"]
        sim += ["--length", str(args.length), "--seed", "1", "-q"]
        subprocess.run(sim, check=True, capture_output=True)
        jobs = str(args.jobs)
        command = [cli, "map", str(work / "t"), "--out", str(work / "a"), "-j", jobs]
        command += ["--no-png", "-q"]
        library = [sys.executable, "-c", _LIBRARY, str(work / "t"), str(work / "b"), jobs]
        _wall(command), _wall(library)  # warm the file cache and the tables
        a, b = [], []
        for _ in range(args.runs):
            for out, cmd, times in (("a", command, a), ("b", library, b)):
                shutil.rmtree(work / out, ignore_errors=True)
                times.append(_wall(cmd))
        ratios = [x / y for x, y in zip(a, b, strict=True)]
    print(f"traverse: mixed, {args.length:g} m, -j {args.jobs}, {args.runs} alternating pairs")
    print(f"rough-map map (start-up tuned)  {statistics.median(a):6.2f} s wall (median)")
    print(f"library analyse (baseline)      {statistics.median(b):6.2f} s wall (median)")
    print(
        f"ratio command / baseline        {statistics.median(ratios):6.2f} "
        f"(pairs {min(ratios):.2f}-{max(ratios):.2f}; below 1: the tuning pays)"
    )


if __name__ == "__main__":
    main()
