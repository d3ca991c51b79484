"""Stereo -> cloud throughput: the patch path against the full-frame path, same run.

Run ``python benchmarks/bench_stereo.py [--reps 20]``. It renders one 1280x960 pair of rough
compact soil with the XB3-like rig (and times the renderer), then times, per frame,

* full frame: SGM over the whole image (0-255 px disparities), points, outlier filter,
  vehicle frame (``stereo_to_cloud(..., restrict_to_patch=False)``), the baseline;
* patch path (the default, ``stereo_to_cloud(...)``): a coarse pass on the pair binned 4x4
  finds the ground plane under the patch and its relief, then SGM at full resolution on the
  rows and columns that see the patch, on the residual to that plane's disparity over the
  relief only, points of every second column, outlier filter; with its breakdown;
* "patch, one pass": the patch path as it was before the coarse pass (one SGM pass over
  +-0.15 m around the vehicle's ``z = 0``, every column, 8 px margins);
* "patch fast": the default with ``row_step=2`` and ``blockSize=3`` (vertical binning; see
  ``configs/stereo.yaml`` for what it costs in PSD fidelity).

Times are the median and the best of the repetitions, wall clock, and the median CPU time
per frame (``time.process_time``: user + system time of all the process's threads, which
barely grows when other processes compete for the cores, unlike the wall time). OpenCV runs
with its default thread count (``cv2.getNumThreads()``, all cores); SGBM_3WAY, the only SGBM
mode it parallelises, is about 2/3 of the patch path's CPU time, the rest is one thread. The
load average is printed because other processes on the machine slow the wall times down.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import cv2
import numpy as np

from rough_map.patch import PatchSpec
from rough_map.simulate.render import render_stereo
from rough_map.stereo import (
    SGBMConfig,
    StereoCalibration,
    StereoConfig,
    fit_ground,
    patch_window,
    stereo_to_cloud,
)
from rough_map.stereo.matching import sgbm_raw
from rough_map.stereo.outliers import window_outlier_mask
from rough_map.stereo.triangulation import window_cloud
from rough_map.types import HeightField


def rough_world(spacing: float = 0.004, rms: float = 0.005, seed: int = 0) -> HeightField:
    """4 m x 5 m of FFT-filtered white noise (3 cm correlation), compact soil."""
    shape = (1250, 1000)
    rng = np.random.default_rng(seed)
    ky = np.fft.fftfreq(shape[0], spacing)[:, None]
    kx = np.fft.rfftfreq(shape[1], spacing)[None, :]
    gain = np.exp(-((np.pi * 0.03 * np.hypot(kx, ky)) ** 2) / 2)
    h = np.fft.irfft2(np.fft.rfft2(rng.standard_normal(shape)) * gain, shape)
    return HeightField(
        h * rms / h.std(),
        spacing,
        origin=(-0.5, -2.5),
        classes=np.zeros(shape, int),
        class_names=("compact_soil",),
    )


def timed(fn, reps: int) -> tuple[float, float, float]:
    """Median and best wall time and median CPU time (all threads) of ``fn()`` in s."""
    fn()
    walls, cpus = [], []
    for _ in range(reps):
        c = time.process_time()
        t = time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), min(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=20, help="repetitions per path")
    args = parser.parse_args()

    calib = StereoCalibration.xb3_default()
    patch = PatchSpec()
    config = StereoConfig()
    one_pass = config.model_copy(
        update={"fit_ground": False, "height_tolerance": 0.15, "col_step": 1, "margin_px": 8}
    )
    binned = config.model_copy(
        update={"row_step": 2, "sgbm": SGBMConfig(blockSize=3, P1=72, P2=288)}
    )
    world = rough_world()
    print(
        f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f} (other processes slow the wall times)"
    )

    rows = patch_window(calib, patch).rows
    left, right, _ = render_stereo(world, (0, 0, 0, 0, 0, 0), calib)  # warm-up (imports)
    t_full, t_full_best, _ = timed(lambda: render_stereo(world, (0, 0, 0, 0, 0, 0), calib), 3)
    t_rows, t_rows_best, _ = timed(
        lambda: render_stereo(world, (0, 0, 0, 0, 0, 0), calib, rows=rows), 3
    )
    print(
        f"render 1280x960 gray pair (median / best of 3): full frame {t_full:.2f} / "
        f"{t_full_best:.2f} s, patch rows {rows} {t_rows:.2f} / {t_rows_best:.2f} s"
    )

    paths = {
        "full frame": lambda: stereo_to_cloud(left, right, calib, config, restrict_to_patch=False),
        "patch, one pass": lambda: stereo_to_cloud(left, right, calib, one_pass),
        "patch": lambda: stereo_to_cloud(left, right, calib, config),
        "patch fast": lambda: stereo_to_cloud(left, right, calib, binned),
    }
    results = {name: (timed(fn, args.reps), len(fn())) for name, fn in paths.items()}

    print(
        f"\n{'path':<17}{'median ms':>10}{'best ms':>9}{'frames/s':>10}{'cpu ms':>8}{'points':>9}"
    )
    for name, ((med, best, cpu), n) in results.items():
        print(
            f"{name:<17}{med * 1e3:>10.1f}{best * 1e3:>9.1f}{1 / med:>10.1f}{cpu * 1e3:>8.0f}{n:>9}"
        )
    t_frame, t_patch = results["full frame"][0], results["patch"][0]
    print(
        f"patch / full-frame speed-up: {t_frame[0] / t_patch[0]:.1f}x (median wall), "
        f"{t_frame[2] / t_patch[2]:.1f}x (CPU); target >= 10 frames/s for the patch path, i.e. "
        f"<= ~120 ms of CPU per frame on 2 idle cores: {t_patch[2] * 1e3:.0f} ms here"
    )

    # Breakdown of the patch path (the calls stereo_to_cloud makes).
    fit = fit_ground(left, right, calib, config, patch=patch)
    assert fit is not None
    window = patch_window(
        calib,
        patch,
        height_tolerance=fit[1],
        plane=fit[0],
        clip=True,
        crop_margin=config.crop_margin,
        margin_px=config.margin_px,
    )
    coarse = timed(lambda: fit_ground(left, right, calib, config, patch=patch), args.reps)

    def fine_sgm():
        return sgbm_raw(
            left, right, config.sgbm, window.rows, window.cols, window.residual, 1, window.prior
        )

    sgm = timed(fine_sgm, args.reps)
    raw = fine_sgm()
    half = patch.size / 2 + config.crop_margin

    def points():
        return window_cloud(
            raw, calib, window, patch, margin=config.crop_margin, col_step=config.col_step
        )

    pts = timed(points, args.reps)
    x, y, z, dz = points()
    f = config.outlier_filter
    filt = timed(
        lambda: window_outlier_mask(
            x,
            y,
            dz,
            (patch.ahead - half, patch.lateral - half),
            f.cell,
            f.k,
            f.min_tolerance,
            f.min_count,
        ),
        args.reps,
    )
    print(
        f"\npatch path breakdown, median CPU / wall ms: coarse pass (ground plane "
        f"z = {fit[0][0]:.4f} x + {fit[0][1]:.4f} y + {fit[0][2]:.4f} m, relief "
        f"{fit[1][0]:+.3f}..{fit[1][1]:+.3f} m) {coarse[2] * 1e3:.1f} / {coarse[0] * 1e3:.1f}; "
        f"fine SGM ({window.rows[1] - window.rows[0]} rows x "
        f"{window.cols[1] - window.cols[0]} columns, {window.residual[1]} residual "
        f"disparities) {sgm[2] * 1e3:.1f} / {sgm[0] * 1e3:.1f}; points (every "
        f"{config.col_step} columns) {pts[2] * 1e3:.1f} / {pts[0] * 1e3:.1f}; outlier filter "
        f"({len(z)} points) {filt[2] * 1e3:.1f} / {filt[0] * 1e3:.1f}"
    )
    one = one_pass
    win1 = patch_window(calib, patch, height_tolerance=one.height_tolerance)
    print(
        f"one-pass patch path searched {win1.rows[1] - win1.rows[0]} rows x "
        f"{win1.cols[1] - win1.cols[0]} columns, {win1.residual[1]} residual disparities"
    )

    # The filter against open3d's statistical outlier removal on the same cloud (baseline).
    try:
        import open3d as o3d
    except ImportError:
        o3d = None
    if o3d is not None:
        unfiltered = one.model_copy(update={"outlier_filter": None})
        cloud = stereo_to_cloud(left, right, calib, unfiltered, patch=patch)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        o3d_time = timed(lambda: pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0), 1)
        print(
            f"open3d remove_statistical_outlier on the one-pass cloud ({len(cloud)} points): "
            f"{o3d_time[0] * 1e3:.0f} ms"
        )
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
