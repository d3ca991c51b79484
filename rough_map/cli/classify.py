"""``rough-map classify TRAVERSE --model M --out labels.csv``: terrain class of every frame.

The CSV is the ``labels.csv`` that ``map`` writes (:data:`rough_map.export.labels.LABEL_COLUMNS`):
one row per frame, ``frame``, ``t`` (s), ``x``, ``y`` (m), ``distance`` (m) along the path,
``valid``, the true ``label`` if the traverse has one, the raw (per-frame classifier) class
and its probability ``raw_p``, the filtered class (path filter, mode as the model's unless
``--mode``) and ``filtered_p``, the roughness ``level``, the isolated ``defect`` flag and R
and w smoothed along the path. A frame without a valid patch has an empty raw and filtered
class and probability: the classifier has nothing to go on, and the filter only carries its
belief forward over it."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np

from rough_map.cli._common import (
    add_jobs_arg,
    add_mode_arg,
    add_model_arg,
    add_traverses_arg,
    add_vehicle_args,
    chosen_model,
    chosen_vehicle,
    emit_json,
    open_traverses,
    status,
    table,
)
from rough_map.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "classify",
        help="raw and filtered terrain class and roughness level of every frame",
        description=(
            "Classify the patch ahead in every frame of a traverse with a model from "
            "`rough-map train`, filter the classes along the path, and write one CSV row per "
            "frame: raw class and probability, filtered class and probability, roughness "
            "level. Frames without a valid patch get no raw class. Frames that see an "
            "isolated defect (a short spike of R, such as a manhole) are marked defect=true; "
            "in the smooth and viterbi modes the filter does not take their class."
        ),
    )
    add_traverses_arg(p)
    add_model_arg(p)
    p.add_argument(
        "--out", type=Path, required=True, metavar="labels.csv", help="the per-frame CSV to write"
    )
    add_mode_arg(p)
    add_vehicle_args(p)
    add_jobs_arg(p)
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # rough_map.classify imports scikit-learn and skops: only when classifying
    from rough_map.classify import load_terrain_model
    from rough_map.features import feature_tables

    if args.out.suffix.lower() != ".csv":
        raise InputError(f"--out must be a .csv file, not {args.out.name!r}")
    vehicle = chosen_vehicle(args)
    model = load_terrain_model(chosen_model(args))
    (tab,) = feature_tables(
        open_traverses(args, args.traverse),
        model.reading(),
        n_jobs=args.jobs,
        progress=args.progress,
    )
    pred = model.predict(tab.require_valid(), mode=args.mode)
    from rough_map.export.labels import write_labels  # the labels.csv that map writes too
    from rough_map.filter import smooth_table

    # R and w smoothed along the path, as map's labels.csv has them (the frames the
    # filter leaves out as isolated defects stay out of the smoothing, as in map)
    defect = None if pred.mode == "forward" else pred.defect
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tab = smooth_table(tab, defect=defect)
    if vehicle is not None:
        from rough_map.features.driving import speed_advice

        tab = speed_advice(tab, vehicle, args.speed)
    write_labels(tab, pred, args.out)
    n_invalid = int((~pred.valid).sum())
    status(args, f"wrote {len(tab)} frames ({n_invalid} without a valid patch) to {args.out}")
    counts = Counter(str(c) for c in pred.filtered_class if c)
    levels = Counter(str(c) for c in pred.level if c)
    if args.json:
        emit_json(
            {
                "file": str(args.out),
                "frames": len(tab),
                "invalid": n_invalid,
                "mode": pred.mode,
                "filtered_class_frames": dict(counts),
                "level_frames": dict(levels),
                "defect_frames": int(pred.defect.sum()),
                "novel_frames": int(pred.novel.sum()),
            }
        )
        return 0
    rows = [[c, str(counts.get(str(c), 0))] for c in pred.classes]
    print(table(rows, ["filtered class", "frames"]))
    if np.isfinite(pred.novelty).any():
        print(
            f"{int(pred.novel.sum())} of {int(np.isfinite(pred.novelty).sum())} frames look "
            "unlike every class the model was trained on (novelty above 1 in the table)"
        )
    if levels:
        print()
        print(
            table([[lv, str(levels.get(lv, 0))] for lv in model.level_names_], ["level", "frames"])
        )
    return 0
