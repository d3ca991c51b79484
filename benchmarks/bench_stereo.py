"""Stereo -> cloud throughput: the patch path against the full-frame path, same run.

Run ``python benchmarks/bench_stereo.py [--reps 20]``. It renders one 1280x960 pair of rough
compact soil with the XB3-like rig (and times the renderer), then times, per frame,

* full frame: SGM over the whole image (0-255 px disparities), points, outlier filter,
  vehicle frame (``stereo_to_cloud(..., restrict_to_patch=False)``), the baseline;
* patch path: SGM over the rows and columns that can see the patch only, on the residual to
  the flat ground's disparity (+-0.15 m of height), the same steps, and the crop to the
  patch (``stereo_to_cloud(...)``), with its breakdown;
* "patch fast": the same with ``row_step=2`` and ``blockSize=3`` (vertical binning; see
  ``configs/stereo.yaml`` for what it costs in PSD fidelity).

OpenCV runs with its default thread count (``cv2.getNumThreads()``, all cores); SGBM_3WAY is
the only SGBM mode it parallelises. Times are wall clock, the median and the best of the
repetitions; the load average is printed because other processes on the machine slow SGM
down.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import cv2
import numpy as np

from rough_map.io.stereo import (
    SGBMConfig,
    StereoCalibration,
    StereoConfig,
    compute_disparity,
    crop_to_patch,
    disparity_to_points,
    patch_window,
    statistical_outlier_filter,
    stereo_to_cloud,
    to_vehicle,
)
from rough_map.simulate.render import render_stereo
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
    """Median and best wall time and mean CPU time (all threads) of ``fn()`` in s.

    CPU time is the process's user + system time: unlike wall time it barely grows when
    other processes compete for the cores.
    """
    fn()
    times = []
    cpu = time.process_time()
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times), (time.process_time() - cpu) / reps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=20, help="repetitions per path")
    args = parser.parse_args()

    calib = StereoCalibration.xb3_default()
    config = StereoConfig()
    window = patch_window(calib)
    world = rough_world()
    print(
        f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f} (other processes slow the wall times)"
    )

    left, right, _ = render_stereo(world, (0, 0, 0, 0, 0, 0), calib)  # warm-up (imports)
    t_full, t_full_best, _ = timed(lambda: render_stereo(world, (0, 0, 0, 0, 0, 0), calib), 3)
    t_rows, t_rows_best, _ = timed(
        lambda: render_stereo(world, (0, 0, 0, 0, 0, 0), calib, rows=window.rows), 3
    )
    print(
        f"render 1280x960 gray pair (median / best of 3): full frame {t_full:.2f} / "
        f"{t_full_best:.2f} s, patch rows {window.rows} {t_rows:.2f} / {t_rows_best:.2f} s"
    )

    full = timed(
        lambda: stereo_to_cloud(left, right, calib, config, restrict_to_patch=False), args.reps
    )
    fast = timed(lambda: stereo_to_cloud(left, right, calib, config), args.reps)
    binned = config.model_copy(
        update={"row_step": 2, "sgbm": SGBMConfig(blockSize=3, P1=72, P2=288)}
    )
    fast2 = timed(lambda: stereo_to_cloud(left, right, calib, binned), args.reps)
    n_full = len(stereo_to_cloud(left, right, calib, config, restrict_to_patch=False))
    n_fast = len(stereo_to_cloud(left, right, calib, config))
    n_fast2 = len(stereo_to_cloud(left, right, calib, binned))

    print(
        f"\n{'path':<16}{'median ms':>10}{'best ms':>9}{'frames/s':>10}{'cpu ms':>8}{'points':>9}"
    )
    for name, (med, best, cpu), n in (
        ("full frame", full, n_full),
        ("patch", fast, n_fast),
        ("patch fast", fast2, n_fast2),
    ):
        print(
            f"{name:<16}{med * 1e3:>10.1f}{best * 1e3:>9.1f}{1 / med:>10.1f}{cpu * 1e3:>8.0f}{n:>9}"
        )
    print(
        f"patch / full-frame speed-up: {full[0] / fast[0]:.1f}x (median), "
        f"{full[1] / fast[1]:.1f}x (best); target >= 10 frames/s for the patch path"
    )

    # Breakdown of the patch path (the calls stereo_to_cloud makes).
    rs = config.row_step
    sgm_kwargs = {
        "cols": window.cols,
        "disparities": window.residual,
        "row_step": rs,
        "prior": window.prior,
        "trim": 1,
    }
    sgbm = timed(
        lambda: compute_disparity(left, right, config.sgbm, window.rows, **sgm_kwargs), args.reps
    )
    disp = compute_disparity(left, right, config.sgbm, window.rows, **sgm_kwargs)

    def to_cloud():
        pts = to_vehicle(disparity_to_points(disp, calib, window.rows[0], rs), calib)
        return crop_to_patch(pts, height_tolerance=config.height_tolerance)

    points = timed(to_cloud, args.reps)
    cloud = to_cloud()
    filt = timed(lambda: statistical_outlier_filter(cloud), args.reps)
    print(
        f"\npatch path breakdown (median ms): SGM {sgbm[0] * 1e3:.1f} "
        f"({window.rows[1] - window.rows[0]} rows / {rs}, {window.residual[1]} residual "
        f"disparities), points + vehicle frame + crop {points[0] * 1e3:.1f}, outlier filter "
        f"{filt[0] * 1e3:.1f} ({len(cloud)} points)"
    )

    # The filter against open3d's statistical outlier removal on the same cloud (baseline).
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    o3d_time = timed(lambda: pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0), 1)
    print(f"open3d remove_statistical_outlier on the same cloud: {o3d_time[0] * 1e3:.0f} ms")
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
