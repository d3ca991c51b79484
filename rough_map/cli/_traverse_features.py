"""``rough-map features TRAVERSE_DIR --out FILE``: one row per frame."""

from __future__ import annotations

import argparse
import math

import numpy as np

from rough_map.cli._common import emit_json, patch_spec, status, table


def run_traverse(args: argparse.Namespace) -> int:
    from rough_map.errors import InputError
    from rough_map.features import features_metadata_path, traverse_features, write_features

    if args.out is None:
        raise InputError("a traverse needs --out FILE (.csv, or .parquet with pyarrow)")
    parquet = args.out.suffix.lower() == ".parquet"
    if not parquet and args.out.suffix.lower() != ".csv":  # say so before the long run
        raise InputError(f"--out must be a .csv or .parquet file, not {args.out.name!r}")
    if args.roll is not None or args.pitch is not None:
        raise InputError(
            "--roll/--pitch are for a single cloud; a traverse uses its IMU (or --no-tilt)"
        )
    feats = traverse_features(
        args.source,
        patch_spec(args),
        use_imu=not args.no_tilt,
        source=args.points_from,
        method=args.method,
        subtract_noise=not args.keep_noise,
        progress=args.progress,
    )
    write_features(feats, args.out)
    valid = feats.valid
    status(args, f"wrote {len(feats)} frames ({int((~valid).sum())} invalid) to {args.out}")
    if args.json:
        emit_json(
            {
                "file": str(args.out),
                "metadata": None if parquet else str(features_metadata_path(args.out)),
                "frames": len(feats),
                "invalid": int((~valid).sum()),
                "summary": _summary(feats),
            }
        )
        return 0
    rows = [
        [k, str(v["frames"]), f"{v['R']:.3e}", f"{v['w']:.2f}", v["iso"]]
        for k, v in _summary(feats).items()
    ]
    print(table(rows, ["label", "frames", "R m³/rad (geo. mean)", "w (mean)", "ISO"]))
    return 0


def _summary(feats) -> dict:
    from rough_map.iso8608 import iso_class

    out = {}
    labels = feats["label"]
    valid = feats.valid
    for lab in dict.fromkeys(labels):
        sel = valid & (labels == lab)
        if not sel.any():
            continue
        r = math.exp(float(np.mean(np.log(feats["R"][sel]))))
        out[lab or "(unlabelled)"] = {
            "frames": int(sel.sum()),
            "R": r,
            "w": float(np.mean(feats["w"][sel])),
            "iso": str(iso_class(r)),
        }
    return out
