"""Time of `rough-map features` after loading, on a 1.2 M-point cloud, against a baseline.

Run: ``python benchmarks/bench_features.py [--points 1200000]``

The figure is the time from a loaded N x 3 array to (R, w): tilt-free gridding of the
patch (cell means, centroid correction, noise estimate) and the PSD fit. The baseline, in
the same process, is the straightforward version: crop with a boolean mask,
``scipy.stats.binned_statistic_2d`` for the cell means, then the per-profile welch +
polyfit loop of ``bench_psd.py``. Both are also timed through the CLI entry point.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).parent))
from bench_psd import baseline as baseline_psd

from rough_map import terrain
from rough_map.patch import PatchSpec, grid_points
from rough_map.psd import patch_roughness
from rough_map.types import HeightField


def make_cloud(n: int, seed: int = 0) -> np.ndarray:
    h = terrain.generate("gravel", (300, 400), 0.004, seed=seed)
    hf = HeightField(h, 0.004, origin=(0.3, -0.6))
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.52, 1.48, n)
    y = rng.uniform(-0.48, 0.48, n)
    return np.column_stack([x, y, hf.sample(x, y) + rng.normal(0, 0.0005, n)])


def ours(points: np.ndarray) -> tuple[float, float]:
    g = grid_points(points)
    r = patch_roughness(
        g.heights, 0.008, gridding=g.gridding, noise_psd=g.noise_psd, subtract_noise=True
    )
    return r.R, r.w


def baseline(points: np.ndarray) -> tuple[float, float]:
    spec = PatchSpec()
    x0, y0, n, b = spec.x0, spec.y0, spec.n, spec.spacing
    inside = (
        (points[:, 0] >= x0)
        & (points[:, 0] < x0 + n * b)
        & (points[:, 1] >= y0)
        & (points[:, 1] < y0 + n * b)
    )
    p = points[inside]
    mean, _, _, _ = stats.binned_statistic_2d(
        p[:, 1],
        p[:, 0],
        p[:, 2],
        "mean",
        bins=[np.linspace(y0, y0 + n * b, n + 1), np.linspace(x0, x0 + n * b, n + 1)],
    )
    return baseline_psd(np.nan_to_num(mean, nan=np.nanmean(mean)))


def best(fn, arg, repeats):
    t_best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn(arg)
        t_best = min(t_best, time.perf_counter() - t)
    return t_best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_200_000)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    cloud = make_cloud(args.points)
    ours(cloud)
    t_ours = best(ours, cloud, args.repeats)
    t_base = best(baseline, cloud, max(2, args.repeats // 3))
    print(f"points: {len(cloud):,}")
    print(f"rough_map grid + PSD:                      {1e3 * t_ours:8.1f} ms")
    print(f"baseline (mask + binned_statistic + loop): {1e3 * t_base:8.1f} ms")
    print(f"ratio baseline / rough_map:                {t_base / t_ours:8.1f} x")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cloud.npy"
        np.save(path, cloud)
        runs = []
        for _ in range(3):
            out = subprocess.run(
                [sys.executable, "-m", "rough_map", "features", str(path), "--json"],
                capture_output=True,
                text=True,
                check=True,
            )
            runs.append(json.loads(out.stdout)["timing_ms"])
        proc = min(r["process"] for r in runs)
        load = min(r["load"] for r in runs)
        print(
            f"`rough-map features --json` (best of 3): {proc:8.1f} ms after loading "
            f"({load:.1f} ms to load)"
        )


if __name__ == "__main__":
    main()
