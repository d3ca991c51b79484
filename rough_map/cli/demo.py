"""``rough-map demo``: the whole story on embedded default data.

1. The estimator on seeded synthetic patches of every ISO class and named surface.
2. A simulated rover traverse over the paper's mixed course (concrete with a manhole, dirt
   road, gravel): range clouds, stereo images of an XB3-like rig, IMU, true labels.
3. Stereo -> point clouds -> features, compared with the range-sensor features.
4. Features along the path, the default terrain model, the Bayesian path filter.
5. The grid map with near-to-far from the RGB images; GeoTIFF, PNGs, the paper's figures,
   the confusion matrix, and an index.html.
"""

from __future__ import annotations

import argparse
import math
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rough_map import iso8608, terrain
from rough_map.cli._common import (
    add_command,
    add_model_arg,
    chosen_model,
    non_negative_int,
    positive_float,
    positive_int,
    status,
    table,
)
from rough_map.errors import InputError
from rough_map.patch import DEFAULT_SPACING, Extraction

if TYPE_CHECKING:
    from rough_map.io.traverse import Traverse
    from rough_map.workflow import TraverseAnalysis


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "demo",
        "run the whole chain on built-in simulated data and say where the outputs are",
        __doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("rough_map_demo"),
        metavar="DIR",
        help="output folder (default ./rough_map_demo; replaced if it holds a previous demo)",
    )
    p.add_argument("--seed", type=non_negative_int(), default=0, help="random seed (default 0)")
    p.add_argument(
        "--length",
        type=positive_float("m"),
        default=24.0,
        metavar="M",
        help="length of the simulated mixed course in m (default 24: 8 m of each surface)",
    )
    p.add_argument(
        "--image-every",
        type=positive_int(),
        default=8,
        metavar="N",
        help="render the stereo pair of every N-th frame (default 8: every 2 m at 0.5 m/s)",
    )
    add_model_arg(p)
    p.add_argument(
        "--quick", action="store_true", help="only part 1: the estimator on synthetic patches"
    )
    p.set_defaults(func=run)


def _say(msg: str) -> None:
    print(msg, flush=True)


SYNTHETIC_HEAD = ["surface", "true R [m³/rad]", "true w", "R [m³/rad]", "w", "rms [mm]", "ISO"]
SYNTHETIC_CAPTION = (
    "The PSD estimator on seeded synthetic terrain: for every ISO 8608 class (w = -2) and "
    "every named surface, 10 patches of 0.896 m gridded at 8 mm. True R (m³/rad) and w next "
    "to the estimates (geometric mean of R, mean of w and of the rms height over the patches) "
    "and the ISO class of the estimated R."
)
STEREO_HEAD = [
    "frame", "label", "stereo points", "R range [m³/rad]", "R stereo [m³/rad]", "w range",
    "w stereo",
]  # fmt: skip
STEREO_CAPTION = (
    "Stereo against range: for each frame with a stereo pair, the features (R, w) of the "
    "patch from the stereo point cloud (SGBM on the XB3-like rig's images) next to those "
    "from the range sensor's cloud. Empty cells: no valid patch."
)


CLASS_HEAD = ["true class", "frames", "R [m³/rad]", "ISO", "w", "raw acc", "filtered acc"]
CLASS_CAPTION = (
    "Per true class of the simulated traverse: frames with a valid patch, geometric "
    "mean of R and its ISO 8608 class, mean w, and the share of frames the classifier "
    "(raw) and the path filter (filtered) label correctly."
)


def synthetic_rows(seed: int, patches: int = 10) -> list[list[str]]:
    """Part 1: R and w of synthetic patches next to the truth (rows of SYNTHETIC_HEAD)."""
    from rough_map.psd import patch_roughness_batch

    B = DEFAULT_SPACING  # the paper's name of the grid step, m
    n = 112
    rng = np.random.default_rng(seed)
    rows = []

    def estimate(make):
        est = patch_roughness_batch(np.stack([make(rng) for _ in range(patches)]), B)
        return (
            math.exp(np.mean([math.log(e.R) for e in est])),
            float(np.mean([e.w for e in est])),
            float(np.mean([e.rms for e in est])),
        )

    for cls in iso8608.CLASSES:
        R, w, rms = estimate(
            lambda g, c=cls: iso8608.synthesize_surface((4 * n, 4 * n), B, c, -2.0, seed=g)[:n, :n]
        )
        rows.append(
            [
                f"ISO {cls}",
                f"{iso8608.PHI0[cls]:.2e}",
                "-2.00",
                f"{R:.2e}",
                f"{w:.2f}",
                f"{rms * 1e3:.2f}",
                str(iso8608.iso_class(R)),
            ]
        )
    for name, spec in terrain.SURFACES.items():
        R, w, rms = estimate(lambda g, nm=name: terrain.generate(nm, (n, 4 * n), B, seed=g)[:, :n])
        rows.append(
            [
                name,
                f"{spec.R:.2e}",
                f"{spec.w:.2f}",
                f"{R:.2e}",
                f"{w:.2f}",
                f"{rms * 1e3:.2f}",
                str(iso8608.iso_class(R)),
            ]
        )
    return rows


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    _say(
        "== 1. The PSD estimator on synthetic terrain "
        "(10 patches of 0.896 m at 8 mm per surface) =="
    )
    synthetic = synthetic_rows(args.seed)
    _say(table(synthetic, SYNTHETIC_HEAD))
    if args.quick:
        return 0
    return _whole_story(args, t0, synthetic)


def _whole_story(args: argparse.Namespace, t0: float, synthetic: list[list[str]]) -> int:
    from rough_map.evaluation import evaluate_model
    from rough_map.export import export_map
    from rough_map.export.report import ReportTable, write_report
    from rough_map.workflow import AnalysisOptions, analyse_model_file, level_edges, write_tables

    out: Path = args.out
    if not _fresh_folder(out):
        _say(f"rough-map demo: {out} exists and is not a previous demo; use --out")
        return 2
    trav = _simulate(args, out / "traverse")

    _say(
        "\n== 3. Stereo (SGBM on the patch rows) -> point cloud -> R, w; against the range "
        "sensor =="
    )
    stereo_rows, stereo_note = _stereo_rows(trav)
    _say(table(stereo_rows, STEREO_HEAD) + f"\n{stereo_note}")

    _say("\n== 4. Features, terrain model and Bayesian path filter; 5. map, near-to-far ==")
    result = analyse_model_file(trav, chosen_model(args), AnalysisOptions(progress=args.progress))
    class_rows = _class_rows(result)
    _say(table(class_rows, CLASS_HEAD))
    evaluation = evaluate_model(result.model, [result.features])
    _say_scores(result, evaluation)

    _say("\n== 6. Outputs ==")
    paths = export_map(result.map, out, name="map", png=True)
    paths.update(write_tables(result, out))
    tables = [
        ReportTable("The PSD estimator on synthetic patches", SYNTHETIC_HEAD, synthetic,
                    SYNTHETIC_CAPTION),
        ReportTable("Stereo against the range sensor", STEREO_HEAD, stereo_rows, STEREO_CAPTION,
                    [stereo_note]),
        ReportTable("Features and classes by true class", CLASS_HEAD, class_rows, CLASS_CAPTION),
    ]  # fmt: skip
    paths.update(
        write_report(
            result, out, evaluation=evaluation, level_edges=level_edges(result), tables=tables
        )
    )
    rows = [[k, str(v)] for k, v in paths.items()]
    _say(table(rows, ["output", "path"]))
    _say(f"\nOpen {paths['index']} in a browser. Done in {time.perf_counter() - t0:.0f} s.")
    status(args, f"demo outputs in {out}")
    return 0


def _fresh_folder(out: Path) -> bool:
    """Make ``out`` an empty demo folder (a previous demo is replaced); False when it
    exists and is not a demo's."""
    if out.exists():
        if not (out / "DEMO").is_file():
            return False
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / "DEMO").write_text("written by rough-map demo; safe to delete\n")
    return True


def _simulate(args: argparse.Namespace, trav_dir: Path) -> Traverse:
    """Part 2: the mixed course, simulated into ``trav_dir``."""
    from rough_map.io.traverse import load_traverse
    from rough_map.simulate.course import simulate

    _say(
        f"\n== 2. Simulating the mixed course ({args.length:g} m: concrete with a manhole, "
        f"dirt road, gravel) =="
    )
    simulate(
        trav_dir,
        "mixed",
        length=args.length,
        seed=args.seed,
        images=True,
        image_every=args.image_every,
        width=6.0,
        progress=args.progress,
    )
    trav = load_traverse(trav_dir)
    n_img = sum(f.left is not None for f in trav.frames)
    _say(f"{len(trav)} frames at 2 Hz, 0.5 m/s; {n_img} stereo pairs (1280x960) -> {trav_dir}")
    return trav


def _class_rows(result: TraverseAnalysis) -> list[list[str]]:
    """Per true class: frames, R, ISO class, w, raw and filtered accuracy (CLASS_HEAD)."""
    from rough_map.features import label_summary

    f, pred = result.features, result.prediction
    assert pred is not None  # the demo always has a model
    rows = []
    for lab, s in label_summary(f).items():
        sel = f.valid & (f["label"] == lab)
        rows.append(
            [
                lab,
                str(s.frames),
                f"{s.R:.2e}",
                s.iso_class,
                f"{s.w:.2f}",
                f"{np.mean(pred.raw_class[sel] == lab):.2f}",
                f"{np.mean(pred.filtered_class[sel] == lab):.2f}",
            ]
        )
    return rows


def _say_scores(result: TraverseAnalysis, evaluation: dict[str, Any]) -> None:
    """Macro-F1 and accuracy, the defect, and the map's accuracy against the truth."""
    pred = result.prediction
    assert pred is not None  # the demo always has a model
    raw, filtered = evaluation["raw"], evaluation["filtered"]
    _say(
        f"macro-F1 (over the true classes {', '.join(evaluation['scored_classes'])}) raw "
        f"{raw['macro_f1']:.3f}, filtered {filtered['macro_f1']:.3f}; accuracy raw "
        f"{raw['accuracy']:.3f}, filtered {filtered['accuracy']:.3f}"
    )
    defect = pred.defect
    if defect is not None and defect.any():
        at = pred.distance[defect]
        _say(
            f"isolated defect: {int(defect.sum())} frames from {at.min():.1f} to "
            f"{at.max():.1f} m along the path (R spike: the manhole); the filter keeps the "
            "class of the ground around it"
        )
    truth = result.truth_accuracy()
    _say(
        f"map: {result.map.shape[1]} x {result.map.shape[0]} cells of 0.1 m; class accuracy "
        f"{truth['near_class_accuracy']:.3f} over the near-field cells"
    )
    if result.far_report:
        report = result.far_report
        far = truth.get("far_class_accuracy")
        acc = "" if far is None else f", far-field class accuracy {far:.3f}"
        _say(
            f"near-to-far: {report['near_area_m2']:.1f} m² seen by geometry, "
            f"{report['near_far_area_m2']:.1f} m² with appearance "
            f"(x{report['area_ratio']:.1f}){acc}"
        )


def _stereo_rows(trav: Traverse) -> tuple[list[list[str]], str]:
    """Features of the stereo clouds against those of the range clouds, per frame pair
    (rows of STEREO_HEAD; empty features when either patch is invalid), and the median
    stereo time."""
    from rough_map.features import frame_features
    from rough_map.stereo import read_image, stereo_to_cloud

    calib = trav.spec.calibration
    if calib is None:
        raise InputError(f"{trav.name}: the demo's traverse has no stereo calibration")
    extraction = Extraction()
    rows = []
    times = []
    for i, fr in enumerate(trav.frames):
        if fr.left is None or fr.right is None:
            continue
        left = read_image(trav.resolve(fr.left, f"frames[{i}].left"))
        right = read_image(trav.resolve(fr.right, f"frames[{i}].right"))
        t = time.perf_counter()
        cloud = stereo_to_cloud(left, right, calib, patch=extraction.patch)
        times.append(time.perf_counter() - t)
        roll, pitch = (fr.imu.roll, fr.imu.pitch) if fr.imu is not None else (None, None)
        st, _, _ = frame_features(cloud, extraction, roll=roll, pitch=pitch)
        rg, _, _ = frame_features(trav.load_cloud(i), extraction, roll=roll, pitch=pitch)
        row = [str(i), fr.label or "", f"{len(cloud):,}"]
        if st["valid"] and rg["valid"]:
            row += [f"{rg['R']:.2e}", f"{st['R']:.2e}", f"{rg['w']:.2f}", f"{st['w']:.2f}"]
        else:
            row += ["", "", "", ""]
        rows.append(row)
    ms = 1e3 * float(np.median(times)) if times else math.nan
    return rows, f"stereo: {ms:.0f} ms per pair (median)"
