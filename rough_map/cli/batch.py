"""``rough-map batch T1 T2 ... --out DIR``: many traverses mapped and fused into one map.

Map each traverse as `rough-map map` does into DIR/<name>/ (GeoTIFFs, PNGs, features.csv,
labels.csv, map_state.npz), then add all their fusion sums into one map in one CRS (the same
Bayesian fusion) written at DIR's top level: DIR/map.tif, DIR/map_class.tif,
DIR/map_<layer>.png and DIR/batch.json. Resumable: a traverse already mapped with the same
inputs and settings is not redone, and each traverse's folder appears only when complete.
With --vehicle, each traverse's outputs and the fused map get the speed advice (v_max,
v_max_95) and the costmap (DIR/map_costmap.pgm/.yaml), as `rough-map map --vehicle` does.
With --scheduler the traverses are mapped on the workers of a Dask cluster (pip install
'rough-map[cluster]'); workers must see the traverses at the paths given here. The outputs
are the same bytes for any -j and on a cluster.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    NEAR_FAR,
    add_allow_outside_arg,
    add_cluster_args,
    add_command,
    add_costmap_args,
    add_jobs_arg,
    add_map_args,
    add_model_arg,
    add_vehicle_args,
    chosen_vehicle,
    costmap_settings,
    emit_json,
    existing_path,
    status,
    table,
)
from rough_map.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "batch",
        "map many traverses (in parallel or on a Dask cluster) and fuse them into one map",
        __doc__,
    )
    p.add_argument(
        "traverses", nargs="+", type=existing_path, metavar="TRAVERSE", help="traverse folders"
    )
    p.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="output folder (created if needed)"
    )
    add_model_arg(p)
    add_map_args(p, settings=False)
    p.add_argument("--no-png", action="store_true", help="skip the PNGs")
    add_cluster_args(p)
    add_jobs_arg(p)
    add_allow_outside_arg(p)
    add_vehicle_args(p)
    add_costmap_args(p)
    p.add_argument("--json", action="store_true", help="what was done, as JSON on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map.batch import run_batch

    vehicle = chosen_vehicle(args)
    costmap = costmap_settings(args) if vehicle is not None else None
    model = "default" if args.model is None else str(args.model)
    if costmap is not None and costmap.lethal_classes:  # say so before the long run
        from rough_map.classify import load_terrain_model

        classes = [str(c) for c in load_terrain_model(model).classes_]
        unknown = [c for c in costmap.lethal_classes if c not in classes]
        if unknown:
            raise InputError(
                f"--lethal-class {unknown[0]!r} is not a class of the model ({', '.join(classes)})"
            )
    result = run_batch(
        args.traverses,
        args.out,
        model=model,
        resolution=args.resolution,
        near_far=NEAR_FAR[args.near_far],
        png=not args.no_png,
        n_jobs=args.jobs,
        scheduler=args.scheduler,
        tls=tuple(args.tls) if args.tls else None,
        progress=args.progress,
        allow_outside=args.allow_outside or (),
        vehicle=vehicle,
        speed=args.speed,
        costmap=costmap,
    )
    if args.json:
        emit_json(
            {
                "mapped": result.mapped,
                "skipped": result.skipped,
                "outputs": {k: str(v) for k, v in result.outputs.items()},
                "traverses": result.summaries,
            }
        )
        return 0
    rows = [
        [
            name,
            "mapped" if name in result.mapped else "done before",
            str(s["frames"]),
            str(s["valid"]),
        ]
        for name, s in result.summaries.items()
    ]
    print(table(rows, ["traverse", "this run", "frames", "valid"]))
    status(args, f"fused map of {len(rows)} traverses in {args.out}")
    return 0
