"""``rough-map features TRAVERSE_DIR --out FILE``: one row per frame."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.cli._common import (
    chosen_vehicle,
    emit_json,
    open_traverses,
    patch_spec,
    status,
    table,
)
from rough_map.errors import InputError
from rough_map.features import (
    features_metadata_path,
    label_summary,
    traverse_features,
    write_features,
)
from rough_map.features.driving import speed_advice
from rough_map.features.table import FeatureTable
from rough_map.io.traverse import Traverse
from rough_map.patch import Extraction


def run_traverse(args: argparse.Namespace) -> int:
    if args.out is None:
        raise InputError("a traverse needs --out FILE (.csv, or .parquet with pyarrow)")
    parquet = args.out.suffix.lower() == ".parquet"
    if not parquet and args.out.suffix.lower() != ".csv":  # say so before the long run
        raise InputError(f"--out must be a .csv or .parquet file, not {args.out.name!r}")
    if args.roll is not None or args.pitch is not None:
        raise InputError(
            "--roll/--pitch are for a single cloud; a traverse uses its IMU (or --no-tilt)"
        )
    extraction = Extraction(
        patch=patch_spec(args),
        use_imu=not args.no_tilt,
        method=args.method,
        subtract_noise=not args.keep_noise,
        auto_spacing=args.spacing == "auto",
    )
    vehicle = chosen_vehicle(args)
    (traverse,) = open_traverses(args, args.source)
    feats = traverse_features(
        traverse, extraction, source=args.points_from, n_jobs=args.jobs, progress=args.progress
    )
    feats.require_valid()
    from rough_map.filter import smooth_table  # scikit-learn and filterpy: only here

    feats = smooth_table(feats)  # R_smooth, w_smooth and their sigmas along the path
    if vehicle is not None:
        feats = speed_advice(feats, vehicle, args.speed)
    write_features(feats, args.out)
    valid = feats.valid
    omega = np.asarray(feats.omega, dtype=float)
    step = math.pi / omega[-1] if omega.size else math.nan  # the band ends at pi / B
    band = f"{omega[0]:.1f} to {omega[-1]:.1f} rad/m" if omega.size else "none"
    wide = "" if feats.row_spacing is None else f" in rows {feats.row_spacing * 1e3:.1f} mm wide"
    status(
        args,
        f"wrote {len(feats)} frames ({int((~valid).sum())} invalid) to {args.out}; "
        f"{step * 1e3:.1f} mm grid{wide}{_chosen(traverse, extraction)}, "
        f"band {band}",
    )
    if vehicle is not None:
        v, v95 = feats["v_max"][valid], feats["v_max_95"][valid]
        status(
            args,
            f"{vehicle.name}: v_max median {np.median(v):.2f} m/s (lowest {v.min():.2f}), "
            f"{np.median(v95):.2f} m/s with 95 % confidence; top speed "
            f"{vehicle.limits.top_speed:g} m/s",
        )
    summary = {lab or "(unlabelled)": s for lab, s in label_summary(feats).items()}
    advice = None if vehicle is None else _advice(feats, vehicle)
    if args.json:
        emit_json(
            {
                "file": str(args.out),
                "metadata": None if parquet else str(features_metadata_path(args.out)),
                "frames": len(feats),
                "spacing_m": step,
                "row_spacing_m": feats.row_spacing,
                "band_rad_per_m": [float(omega[0]), float(omega[-1])] if omega.size else None,
                "invalid": int((~valid).sum()),
                "summary": summary,
                **({} if advice is None else {"speed_advice": advice}),
            }
        )
        return 0
    rows = [[k, str(s.frames), f"{s.R:.3e}", f"{s.w:.2f}", s.iso_class] for k, s in summary.items()]
    head = ["label", "frames", "R m³/rad (geo. mean)", "w (mean)", "ISO"]
    if advice is not None:
        by_label = advice["by_label"]
        for row in rows:
            v = by_label.get(row[0], {})
            row += [f"{v.get('v_max', math.nan):.2f}", f"{v.get('v_max_95', math.nan):.2f}"]
        head += ["v_max m/s (median)", "95 %"]
    print(table(rows, head))
    return 0


def _advice(feats: FeatureTable, vehicle: Any) -> dict[str, Any]:
    """The speed advice of a table for the summary: medians over the valid frames, overall
    and by label (m/s)."""
    valid = feats.valid
    labels = np.array([str(x) or "(unlabelled)" for x in feats["label"]], dtype=object)

    def medians(mask: np.ndarray) -> dict[str, float]:
        return {k: float(np.nanmedian(feats[k][mask])) for k in ("v_max", "v_max_95")}

    return {
        "vehicle": vehicle.name,
        "top_speed_m_s": vehicle.limits.top_speed,
        **medians(valid),
        "by_label": {
            str(lab): medians(valid & (labels == lab)) for lab in sorted(set(labels[valid]))
        },
    }


def _chosen(traverse: Traverse, extraction: Extraction) -> str:
    """How the grid step was chosen, for the status line."""
    if traverse.spec.surface is not None:
        return f" (the cells of {Path(traverse.spec.surface.path).name})"
    return " (auto)" if extraction.auto_spacing else ""
