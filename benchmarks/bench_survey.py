"""`rough-map survey` on a large DEM: windows per second against the batched-PSD floor of
the same windows, and the peak of the summed RSS of its processes.

Run: ``python benchmarks/bench_survey.py [--size 10000] [--spacing 0.01] [-j 2]``

The DEM (``--size`` cells a side of ``--spacing`` m, a tiled float32 GeoTIFF of synthetic ISO
class D ground in UTM 33N) is built once in ``--work``. The command runs end to end in a
child process (reading, measuring, writing the GeoTIFFs and the CSV; no PNGs). The floor is
the estimator alone in this process on one core: a sample of the same windows already in
memory, measured in batches with :func:`rough_map.psd.patch_roughness_each`; its rate times
``-j`` is what N processes could reach if nothing but the estimator ran. The survey also
reads and decompresses the raster (on synthetic ground, which deflate hardly compresses,
about as long as the estimator) and writes its files. The figures that matter are the
ratios, since machines here are noisy.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from bench_map import run_with_peak_rss
from rasterio.windows import Window
from threadpoolctl import threadpool_limits

from rough_map.io.raster import open_height_raster
from rough_map.iso8608 import synthesize_surface
from rough_map.psd import patch_roughness_each
from rough_map.survey import SurveySpec, survey_geometry

TILE = 1000  # cells a side of each synthesised block of the DEM


def make_dem(path: Path, size: int, spacing: float) -> Path:
    """A ``size`` x ``size`` DEM of synthetic ground, synthesised a block at a time."""
    if path.exists():
        with rasterio.open(path) as ds:
            if ds.shape == (size, size) and math.isclose(ds.res[0], spacing):
                return path
    path.parent.mkdir(parents=True, exist_ok=True)
    profile = {
        "driver": "GTiff",
        "width": size,
        "height": size,
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:32633",
        "transform": Affine(spacing, 0.0, 500_000.0, 0.0, -spacing, 4_100_000.0),
        "nodata": float("nan"),
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
        "bigtiff": "if_safer",
    }
    rng = np.random.default_rng(0)
    with rasterio.open(path, "w", **profile) as ds:
        for r in range(0, size, TILE):
            for c in range(0, size, TILE):
                h, w = min(TILE, size - r), min(TILE, size - c)
                block = synthesize_surface((h, w), spacing, "D", -2.3, seed=rng)
                ds.write(block.astype(np.float32)[None], window=Window(c, r, w, h))
    return path


def floor_rate(dem: Path, spec: SurveySpec, sample: int, repeats: int) -> float:
    """Windows per second of the estimator alone on ``sample`` of the DEM's windows."""
    raster = open_height_raster(dem)
    size, step = spec.cells(raster.spacing)
    band = raster.rows(0, size)
    n = min(sample, (band.shape[1] - size) // step + 1)
    stack = np.stack([band[:, j * step : j * step + size] for j in range(n)])
    gridding = spec.gridding or raster.gridding
    best = math.inf
    with threadpool_limits(1):
        for _ in range(repeats):
            t = time.perf_counter()
            for k in range(0, n, 64):
                patch_roughness_each(stack[k : k + 64], raster.spacing, gridding=gridding)
            best = min(best, time.perf_counter() - t)
    return n / best


def run_survey(dem: Path, out: Path, jobs: int) -> tuple[float, float]:
    """Wall time (s) of `rough-map survey` and the peak of the summed RSS (MiB)."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "rough_map", "survey", str(dem), "--out", str(out)]
    cmd += ["--no-png", "-j", str(jobs), "-q"]
    return run_with_peak_rss(cmd, "rough-map survey")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2000, help="cells a side (default 2000)")
    ap.add_argument("--spacing", type=float, default=0.01, help="cell size in m (default 0.01)")
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--sample", type=int, default=256, help="windows the floor measures")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rough_map_bench_survey"))
    args = ap.parse_args()
    dem = make_dem(args.work / f"dem_{args.size}.tif", args.size, args.spacing)
    spec = SurveySpec()
    geo = survey_geometry(open_height_raster(dem), spec)
    windows = geo.shape[0] * geo.shape[1]
    floor = floor_rate(dem, spec, args.sample, args.repeats)
    wall, peak = run_survey(dem, args.work / "out", args.jobs)
    rate = windows / wall
    print(f"DEM {args.size} x {args.size} cells of {args.spacing:g} m: {windows} windows")
    print(f"survey -j {args.jobs}: {wall:.1f} s, {rate:.0f} windows/s, peak RSS {peak:.0f} MiB")
    jobs = args.jobs
    print(f"floor (estimator alone, 1 core): {floor:.0f} windows/s; x{jobs}: {floor * jobs:.0f}")
    print(
        f"ratio to the floor on 1 core: {rate / floor:.2f}; to the floor x{jobs}: "
        f"{rate / (floor * jobs):.2f}"
    )


if __name__ == "__main__":
    main()
