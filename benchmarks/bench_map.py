"""`rough-map map` on a long drive: time per frame by stage and end to end, against a floor.

Run: ``python benchmarks/bench_map.py [--frames 7200] [--points-per-cell 1.3] [-j 2]``

The traverse is an hour of driving at 2 Hz (7,200 frames by default): the clouds of a short
simulated course (``rough-map simulate --no-images``; 1.3 points per 8 mm cell gives light
clouds of about 20 k points, the simulator's default 12 gives its heavy ones of about
190 k), copied to one file per frame along a straight path 0.25 m apart. It is made once
in ``--work`` and reused.

The floor, measured in the same run and on the same files, is the least any tool must do:
load each cloud (``np.load``), crop it to the patch, grid it (mean height per 8 mm cell with
``np.bincount``) and take one 2-D FFT, on one core. Every figure is printed next to it as a
ratio, since the machines here are shared and noisy: the per-frame stages in this process
(one core, BLAS pinned to one thread) and `rough-map map TRAVERSE --out DIR -j N` end to
end, with the peak of the summed RSS of all its processes (sampled every 50 ms).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
from threadpoolctl import threadpool_limits

from rough_map.classify import load_terrain_model
from rough_map.features import FramePass, frame_jobs
from rough_map.features.frames import CHUNK, height_sample, process_frames, process_points
from rough_map.io.pointcloud import read_cloud
from rough_map.io.traverse import load_traverse, save_traverse
from rough_map.online import OnlineMapper
from rough_map.patch import Extraction, PatchSpec


def make_traverse(work: Path, frames: int, ppc: float, seed: int = 5) -> Path:
    """A straight drive of ``frames`` clouds at 2 Hz, 0.25 m apart (made once, reused)."""
    out = work / f"drive_{frames}_{ppc:g}"
    if (out / "traverse.json").is_file():
        return out
    base = work / f"base_{ppc:g}"
    if not (base / "traverse.json").is_file():
        shutil.rmtree(base, ignore_errors=True)
        subprocess.run(
            [
                sys.executable,
                "-m",
                "rough_map.cli.main",
                "simulate",
                "--out",
                str(base),
                "--length",
                "50",
                "--no-images",
                "--points-per-cell",
                str(ppc),
                "--seed",
                str(seed),
                "-q",
            ],
            check=True,
        )
    src = load_traverse(base)
    clouds = [src.resolve(f.cloud) for f in src.frames if f.cloud]
    tmp = out.with_name(out.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "clouds").mkdir(parents=True)
    spec = src.spec.model_dump(mode="json", exclude_none=True)
    spec.pop("height_field", None)
    spec["name"] = f"drive-{frames}"
    spec["frames"] = []
    for i in range(frames):
        name = f"clouds/{i:06d}.npy"
        shutil.copyfile(clouds[i % len(clouds)], tmp / name)
        spec["frames"].append(
            {"t": i * 0.5, "pose": {"x": i * 0.25, "y": 0.0, "yaw": 0.0}, "cloud": name}
        )
    from rough_map.config import TraverseSpec

    save_traverse(TraverseSpec.model_validate(spec), tmp)
    tmp.rename(out)
    return out


def floor(paths: list[Path]) -> float:
    """Seconds per frame: load, crop, grid (cell means) and one FFT, one core."""
    spec = PatchSpec()
    n, inv = spec.n, 1.0 / spec.spacing
    t0 = time.perf_counter()
    for p in paths:
        pts = np.load(p)
        u = ((pts[:, 0] - spec.x0) * inv).astype(np.intp)
        v = ((pts[:, 1] - spec.y0) * inv).astype(np.intp)
        ok = (u >= 0) & (u < n) & (v >= 0) & (v < n)
        cell = v[ok] * n + u[ok]
        cnt = np.bincount(cell, minlength=n * n)
        sz = np.bincount(cell, pts[ok, 2], minlength=n * n)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.nan_to_num(sz / cnt).reshape(n, n)
        np.fft.rfft2(z - z.mean())
    return (time.perf_counter() - t0) / len(paths)


def stages(folder: Path, sample: int) -> dict[str, float]:
    """Seconds per frame of each stage, in this process, on the first ``sample`` frames."""
    trav = load_traverse(folder)
    jobs = frame_jobs(trav)[:sample]
    model = load_terrain_model("default")
    settings = FramePass(Extraction.from_dict(model.extraction_), height_resolution=0.1)
    out: dict[str, float] = {}
    t0 = time.perf_counter()
    clouds = [read_cloud(j.cloud) for j in jobs if j.cloud]
    out["read"] = (time.perf_counter() - t0) / len(jobs)
    t0 = time.perf_counter()
    results = [
        o for k in range(0, len(jobs), CHUNK) for o in process_frames(jobs[k : k + CHUNK], settings)
    ]
    out["read + features + heights (chunks)"] = (time.perf_counter() - t0) / len(jobs)
    t0 = time.perf_counter()
    for c, j in zip(clouds, jobs, strict=True):
        process_points(c, j, settings)
    out["  features + heights, frame by frame"] = (time.perf_counter() - t0) / len(jobs)
    t0 = time.perf_counter()
    for c, j in zip(clouds, jobs, strict=True):
        height_sample(c, j, 0.1, settings.height_points)
    out["  of which heights"] = (time.perf_counter() - t0) / len(jobs)
    mapper = OnlineMapper(model, resolution=0.1, extraction=settings.extraction)
    t0 = time.perf_counter()
    for r, j in zip(results, jobs, strict=True):
        mapper.add(r, j.pose, classes=True)
    out["classify + filter + fuse (online)"] = (time.perf_counter() - t0) / len(jobs)
    mapper.finish()
    return out


def run_with_peak_rss(cmd: list[str], what: str) -> tuple[float, float]:
    """Wall time (s) of the command ``cmd`` and the peak of the summed RSS (MiB) of its
    processes, polled every 50 ms; SystemExit naming ``what`` if it fails."""
    t0 = time.perf_counter()
    proc = psutil.Popen(cmd, stdout=subprocess.DEVNULL)
    peak = 0.0
    done = threading.Event()

    def watch() -> None:
        nonlocal peak
        while not done.is_set():
            try:
                procs = [proc, *proc.children(recursive=True)]
                total = 0
                for p in procs:
                    try:
                        total += p.memory_info().rss
                    except psutil.Error:
                        pass
                peak = max(peak, total / 2**20)
            except psutil.Error:
                pass
            time.sleep(0.05)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    code = proc.wait()
    wall = time.perf_counter() - t0
    done.set()
    th.join()
    if code != 0:
        raise SystemExit(f"{what} failed with exit code {code}")
    return wall, peak


def run_map(folder: Path, out: Path, jobs: int) -> tuple[float, float]:
    """Wall time (s) of `rough-map map` and the peak of the summed RSS of its processes."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [
        sys.executable,
        "-m",
        "rough_map.cli.main",
        "map",
        str(folder),
        "--out",
        str(out),
        "-j",
        str(jobs),
        "-q",
    ]
    return run_with_peak_rss(cmd, "rough-map map")


def make_stereo_traverse(work: Path, source: Path, frames: int) -> Path:
    """``frames`` stereo frames (no clouds), the pairs of ``source`` copied one per frame."""
    out = work / f"stereo_{frames}"
    if (out / "traverse.json").is_file():
        return out
    src = load_traverse(source)
    pairs = [(f, src.resolve(f.left), src.resolve(f.right)) for f in src.frames if f.left]
    if not pairs:
        raise SystemExit(f"{source} has no stereo pairs")
    tmp = out.with_name(out.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "left").mkdir(parents=True)
    (tmp / "right").mkdir()
    spec = src.spec.model_dump(mode="json", exclude_none=True)
    spec.pop("height_field", None)
    spec["frames"] = []
    for i in range(frames):
        frame, left, right = pairs[i % len(pairs)]
        shutil.copyfile(left, tmp / f"left/{i:06d}.png")
        shutil.copyfile(right, tmp / f"right/{i:06d}.png")
        row = frame.model_dump(mode="json", exclude_none=True)
        row.pop("cloud", None)
        row.update(t=i * 0.5, left=f"left/{i:06d}.png", right=f"right/{i:06d}.png")
        row["pose"]["x"] = i * 0.25
        spec["frames"].append(row)
    from rough_map.config import TraverseSpec

    save_traverse(TraverseSpec.model_validate(spec), tmp)
    tmp.rename(out)
    return out


def stereo(folder: Path, jobs: int) -> None:
    """`rough-map features --points-from stereo -j N` end to end, against decoding alone."""
    from rough_map.io.images import read_image

    trav = load_traverse(folder)
    t0 = time.perf_counter()
    for f in trav.frames[:40]:
        read_image(trav.resolve(f.left))
        read_image(trav.resolve(f.right))
    decode = (time.perf_counter() - t0) / 40
    cmd = [sys.executable, "-m", "rough_map.cli.main", "features", str(folder),
           "--points-from", "stereo", "--out", str(folder.parent / "stereo.csv"),
           "-j", str(jobs), "-q"]  # fmt: skip
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    n = len(trav)
    print(
        f"stereo: {n} pairs; decoding a pair on one core {decode * 1e3:.0f} ms "
        f"({1 / decode:.1f} pairs/s)"
    )
    print(
        f"rough-map features --points-from stereo -j {jobs}: {wall:.1f} s wall, "
        f"{n / wall:.1f} frames/s end to end (start-up included), x{n / wall / 16:.2f} the "
        f"camera's 16 frames/s, x{n / wall * decode:.2f} the one-core decoding rate"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=7200)
    ap.add_argument("--points-per-cell", type=float, default=1.3)
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--sample", type=int, default=300, help="frames timed per stage")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rough_map_bench"))
    ap.add_argument("--json", action="store_true")
    ap.add_argument(
        "--stereo",
        type=Path,
        metavar="TRAVERSE",
        help="instead: a stereo traverse of --frames pairs copied from TRAVERSE's, end to end",
    )
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.stereo:
        stereo(make_stereo_traverse(args.work, args.stereo, args.frames), args.jobs)
        return
    folder = make_traverse(args.work, args.frames, args.points_per_cell)
    paths = sorted((folder / "clouds").glob("*.npy"))
    n_points = len(np.load(paths[0]))
    with threadpool_limits(1, "blas"):
        for p in paths:  # the floor is computing, not reading the disk: warm the page cache
            np.load(p)
        fl = floor(paths)
        st = stages(folder, min(args.sample, len(paths)))
    wall, peak = run_map(folder, args.work / "map_out", args.jobs)
    with threadpool_limits(1, "blas"):  # the load moves: the lower of two floors, around the run
        fl = min(fl, floor(paths))
    result = {
        "frames": len(paths),
        "points_per_cloud": n_points,
        "floor_ms_per_frame": fl * 1e3,
        "stages_ms_per_frame": {k: v * 1e3 for k, v in st.items()},
        "map_wall_s": wall,
        "map_jobs": args.jobs,
        "floor_total_s": fl * len(paths),
        "map_over_floor": wall / (fl * len(paths)),
        "peak_rss_mb": peak,
        "cpus": psutil.cpu_count(),
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(
        f"{len(paths)} frames of {n_points} points; floor (load, crop, grid, FFT; 1 core): "
        f"{fl * 1e3:.2f} ms/frame, {fl * len(paths):.1f} s in all"
    )
    for k, v in st.items():
        print(f"  {k:<36} {v * 1e3:7.2f} ms/frame  x{v / fl:5.1f} floor")
    print(
        f"rough-map map -j {args.jobs}: {wall:.1f} s wall, x{wall / (fl * len(paths)):.2f} "
        f"the single-core floor; peak RSS of all its processes {peak:.0f} MB"
    )


if __name__ == "__main__":
    main()
