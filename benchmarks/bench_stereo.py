"""Stereo -> features per frame, one thread, against baselines timed in the same run.

Run ``python benchmarks/bench_stereo.py [--traverse DIR] [--reps 5]``. Everything runs on one
thread (``cv2.setNumThreads(1)``, BLAS pinned to 1 thread with threadpoolctl), as in each
worker process of ``traverse_features``: the frame rate on ``n`` cores is about ``n`` times
``1000 / (CPU ms per frame)``. Times are CPU times (``time.process_time``), which barely grow
when other processes compete for the cores, unlike the wall times.

The frames are those of a simulated traverse with images (``--traverse``, e.g. made by
``rough-map simulate --out DIR --course mixed --length 6 --seed 3``), or else one pair of
rough compact soil rendered here and written as colour PNG files as the simulator writes
them. Per frame it times

* the pipeline, as ``traverse_features`` runs it on a frame: decode the pair
  (:func:`rough_map.stereo.read_image`), ``stereo_to_cloud`` (the patch path), and
  ``frame_features`` (gridding, PSD fit), with its breakdown by stage;
* baseline "decode": decoding the pair alone, the floor of any pipeline reading PNG files;
* baseline "plain SGBM": decoding the pair and OpenCV's ``StereoSGBM`` on the full image with
  the config's 256 disparities, nothing else;

and prints the pipeline's time as a ratio of each baseline. It then times the paths of
``stereo_to_cloud`` on the first pair (full frame, patch path in one pass, fast mode).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from rough_map.features import frame_features
from rough_map.io.traverse import load_traverse
from rough_map.patch import Extraction, PatchSpec
from rough_map.simulate.render import render_stereo
from rough_map.stereo import (
    SGBMConfig,
    StereoCalibration,
    StereoConfig,
    fit_ground,
    patch_window,
    read_image,
    stereo_to_cloud,
)
from rough_map.stereo.matching import sgbm_matcher, sgbm_raw
from rough_map.stereo.outliers import window_outlier_mask
from rough_map.stereo.triangulation import window_cloud
from rough_map.types import HeightField

#: (left PNG, right PNG, roll, pitch): one frame's files and IMU tilt (rad, or None).
Frame = tuple[Path, Path, float | None, float | None]


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


def cpu_ms(fn: Callable[[], object], reps: int) -> float:
    """Median CPU time of ``fn()`` over ``reps`` calls after one warm-up, ms."""
    fn()
    times = []
    for _ in range(reps):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    return 1e3 * statistics.median(times)


def rendered_frames(folder: Path, calib: StereoCalibration) -> list[Frame]:
    """One colour pair of rough compact soil, written as PNG files into ``folder``."""
    left, right, _ = render_stereo(rough_world(), (0, 0, 0, 0, 0, 0), calib, color=True)
    paths = folder / "left.png", folder / "right.png"
    for path, image in zip(paths, (left, right), strict=True):
        cv2.imwrite(str(path), image)
    return [(paths[0], paths[1], None, None)]


def traverse_frames(folder: str) -> tuple[list[Frame], StereoCalibration, str]:
    """The frames with a stereo pair of a traverse, its calibration and name."""
    trav = load_traverse(folder)
    if trav.spec.calibration is None:
        raise SystemExit(f"{folder}: the traverse has no calibration")
    frames = [
        (
            trav.resolve(f.left),
            trav.resolve(f.right),
            None if f.imu is None else f.imu.roll,
            None if f.imu is None else f.imu.pitch,
        )
        for f in trav.frames
        if f.left is not None and f.right is not None
    ]
    if not frames:
        raise SystemExit(f"{folder}: no frame has a stereo pair")
    return frames, trav.spec.calibration, trav.name


def stage_times(
    frame: Frame, calib: StereoCalibration, config: StereoConfig, ex: Extraction
) -> dict[str, float]:
    """CPU ms of each stage of one frame, run as ``stereo_to_cloud`` runs them."""
    patch = ex.patch
    left_path, right_path, roll, pitch = frame
    f = config.outlier_filter
    assert f is not None
    half = patch.size / 2 + config.crop_margin
    out: dict[str, float] = {}
    t = time.process_time()

    def lap(name: str) -> None:
        nonlocal t
        now = time.process_time()
        out[name] = 1e3 * (now - t)
        t = now

    left, right = read_image(left_path), read_image(right_path)
    lap("decode pair")
    window = patch_window(
        calib,
        patch,
        height_tolerance=config.height_tolerance,
        crop_margin=config.crop_margin,
        margin_px=config.margin_px,
        clip=True,
    )
    fit = fit_ground(left, right, calib, config, patch=patch)
    if fit is not None:
        window = patch_window(
            calib,
            patch,
            height_tolerance=fit[1],
            crop_margin=config.crop_margin,
            margin_px=config.margin_px,
            plane=fit[0],
            clip=True,
        )
    lap("coarse pass")
    raw = sgbm_raw(
        left, right, config.sgbm, window.rows, window.cols, window.residual, 1, window.prior
    )
    lap("fine SGM")
    x, y, z, dz = window_cloud(
        raw, calib, window, patch, margin=config.crop_margin, col_step=config.col_step
    )
    lap("points")
    corner = (patch.ahead - half, patch.lateral - half)
    keep = window_outlier_mask(x, y, dz, corner, f.cell, f.k, f.min_tolerance, f.min_count)
    points = np.column_stack([x[keep], y[keep], z[keep]]).astype(np.float64)
    lap("outlier filter")
    frame_features(points, ex, roll=roll, pitch=pitch)
    lap("features")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--traverse", help="a simulated traverse with images (default: render)")
    parser.add_argument("--reps", type=int, default=5, help="repetitions per timing")
    parser.add_argument("--frames", type=int, default=8, help="most frames of the traverse")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    threadpool_limits(limits=1)

    config = StereoConfig()
    with tempfile.TemporaryDirectory() as tmp:
        if args.traverse:
            frames, calib, name = traverse_frames(args.traverse)
            step = max(1, len(frames) // args.frames)
            frames = frames[::step][: args.frames]
        else:
            calib = StereoCalibration.xb3_default()
            frames, name = rendered_frames(Path(tmp), calib), "rendered rough compact soil"
        ex = Extraction(patch=PatchSpec())
        print(
            f"OpenCV {cv2.__version__}, 1 thread (BLAS pinned), {os.cpu_count()} CPUs, load "
            f"average {os.getloadavg()[0]:.1f}; {len(frames)} frame(s) of {name}, "
            f"median CPU ms of {args.reps} repetitions"
        )
        plain = sgbm_matcher(config.sgbm, config.sgbm.minDisparity, config.sgbm.numDisparities)
        rows: dict[str, list[float]] = {"pipeline": [], "decode": [], "plain SGBM": []}
        stages: dict[str, list[float]] = {}
        for frame in frames:

            def pipeline(frame: Frame = frame) -> object:
                left, right = read_image(frame[0]), read_image(frame[1])
                points = stereo_to_cloud(left, right, calib, config, patch=ex.patch)
                return frame_features(points, ex, roll=frame[2], pitch=frame[3])

            def decode(frame: Frame = frame) -> object:
                return read_image(frame[0]), read_image(frame[1])

            def plain_sgbm(frame: Frame = frame) -> object:
                return plain.compute(read_image(frame[0]), read_image(frame[1]))

            rows["pipeline"].append(cpu_ms(pipeline, args.reps))
            rows["decode"].append(cpu_ms(decode, args.reps))
            rows["plain SGBM"].append(cpu_ms(plain_sgbm, max(1, args.reps // 2)))
            runs = [stage_times(frame, calib, config, ex) for _ in range(args.reps)]
            for stage in runs[0]:
                stages.setdefault(stage, []).append(statistics.median(r[stage] for r in runs))

        pipe = statistics.mean(rows["pipeline"])
        header = f"{'per frame, one thread':<44}{'CPU ms':>8}{'frames/s':>10}"
        print(f"\n{header}{'pipeline / this':>16}")
        labels = {
            "pipeline": "decode + stereo_to_cloud + frame_features",
            "decode": "baseline: decode the pair (PNG)",
            "plain SGBM": "baseline: decode + plain SGBM, full image",
        }
        for key, values in rows.items():
            ms = statistics.mean(values)
            ratio = pipe / ms
            print(f"{labels[key]:<44}{ms:>8.1f}{1e3 / ms:>10.1f}{ratio:>16.2f}")
        print(
            f"pipeline / decode {pipe / statistics.mean(rows['decode']):.2f}, pipeline / plain "
            f"SGBM {pipe / statistics.mean(rows['plain SGBM']):.2f}; on 2 worker processes "
            f"about {2e3 / pipe:.0f} frames/s (target >= 16, per frame <= ~100 ms)"
        )
        print("\nbreakdown (mean over frames of the median per frame), CPU ms:")
        total = sum(statistics.mean(v) for v in stages.values())
        for stage, values in stages.items():
            ms = statistics.mean(values)
            print(f"  {stage:<16}{ms:>7.1f}  {100 * ms / total:>4.0f} %")
        print(f"  {'sum':<16}{total:>7.1f}")

        # The paths of stereo_to_cloud on the first pair, decoded once.
        left, right = read_image(frames[0][0]), read_image(frames[0][1])
        one_pass = config.model_copy(
            update={"fit_ground": False, "height_tolerance": 0.15, "col_step": 1, "margin_px": 8}
        )
        fast = config.model_copy(
            update={"row_step": 2, "sgbm": SGBMConfig(blockSize=3, P1=72, P2=288)}
        )
        paths: dict[str, Callable[[], np.ndarray]] = {
            "patch (default)": lambda: stereo_to_cloud(left, right, calib, config),
            "patch, one pass": lambda: stereo_to_cloud(left, right, calib, one_pass),
            "patch fast": lambda: stereo_to_cloud(left, right, calib, fast),
            "full frame": lambda: stereo_to_cloud(
                left, right, calib, config, restrict_to_patch=False
            ),
        }
        print(f"\n{'stereo_to_cloud, first pair':<28}{'CPU ms':>8}{'points':>9}")
        for label, fn in paths.items():
            reps = 1 if label == "full frame" else args.reps
            print(f"{label:<28}{cpu_ms(fn, reps):>8.1f}{len(fn()):>9}")
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
