"""``rough-map map TRAVERSE --model M --out DIR``: the semantic map, exported.

Compute the features of every frame, classify them with the model, smooth the classes along
the path, fuse the patches into a grid map (R, w, sigma, level, class probabilities, count,
last seen, elevation) and, when the frames have stereo images, extend it beyond the patch
with near-to-far learning. Writes DIR/map.tif (float bands), DIR/map_class.tif (class with
colour table), one PNG per layer, DIR/labels.csv, DIR/features.csv (with its metadata in
DIR/features.csv.json) and, with --state, DIR/map_state.npz (the fusion sums, which
`rough-map batch` adds up across traverses). Each cloud is read once; -j N spreads the
frames over N processes with the same result. DIR is written as a set: staged beside it and
swapped in whole when complete, so it holds either the old outputs or the new ones; your own
files in DIR are kept.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    add_command,
    add_costmap_args,
    add_jobs_arg,
    add_map_args,
    add_model_arg,
    add_route_args,
    add_traverses_arg,
    add_vehicle_args,
    analysis_options,
    chosen_model,
    costmap_settings,
    emit_json,
    open_traverses,
    start_up,
    status,
    table,
    unused_optional_imports,
)
from rough_map.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "map",
        "fuse a traverse into a grid map; write GeoTIFF, PNGs and per-frame labels",
        __doc__,
    )
    add_traverses_arg(p, tables=False)
    add_model_arg(p)
    p.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="output folder (created if needed)"
    )
    add_map_args(p)
    add_route_args(p)
    add_vehicle_args(p)
    add_costmap_args(p)
    p.add_argument(
        "--roughness",
        choices=("raw", "smoothed"),
        default="raw",
        help="R and w the map fuses: each frame's own (raw, the default: the map already "
        "averages the overlapping patches in each cell, so fusing values smoothed along the "
        "path would count that correlation twice), or smoothed along the path by the "
        "Kalman smoother (the R_smooth, w_smooth columns of features.csv, which are "
        "written either way; isolated defects such as a manhole do not show then)",
    )
    p.add_argument("--no-png", action="store_true", help="skip the PNGs")
    p.add_argument(
        "--state",
        action="store_true",
        help="also write DIR/map_state.npz, the fusion sums (what rough-map batch adds up)",
    )
    p.add_argument(
        "--crg",
        action="store_true",
        help="also write DIR/map_road.crg: the elevation layer along the path as an OpenCRG "
        "road surface (KDBI; reference line from the poses, curved where they turn; grid "
        "steps the map's --resolution; NaN where unmeasured)",
    )
    p.add_argument(
        "--gridmap-bag",
        action="store_true",
        help="also write a grid_map_msgs/GridMap message in an MCAP bag",
    )
    add_jobs_arg(p)
    p.add_argument("--json", action="store_true", help="paths and figures as JSON on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Where they are installed, scikit-learn imports dask when the model's trial prediction
    # looks for array libraries (0.2 s, 10 MB), and pytest and rich when skops lists its
    # estimators (0.08 s, 8 MB): `map` uses none of them.
    with unused_optional_imports("dask", "pytest", "rich"):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from rough_map.features.frames import start_workers
    from rough_map.features.traverse import start_frame_pass
    from rough_map.map.grid_geometry import check_map_memory

    out: Path = args.out
    model = chosen_model(args)
    frames = None
    try:
        with start_up():
            start_workers(args.jobs)  # they import rough_map while this reads the traverse
            (traverse,) = open_traverses(args, args.traverse)
            check_map_memory(traverse.poses()[:, :2], args.resolution)
            # The workers start on the frames (the model's extraction is on its card) while
            # this process imports scikit-learn and loads the model; analyse checks that
            # they agree.
            frames = start_frame_pass(
                traverse,
                model,
                resolution=args.resolution,
                n_jobs=args.jobs,
                progress=args.progress,
            )
            with unused_optional_imports("pandas"):
                from rough_map.workflow import AnalysisOptions, analyse, summary, write_outputs
            if frames is not None and not args.no_png:
                import matplotlib.backends.backend_agg  # noqa: F401  # for the PNGs
    except BaseException:
        if frames is not None:
            frames.close()
        raise
    try:  # scikit-learn is imported now, while the workers start on the frames
        from rough_map.classify import load_terrain_model

        options = AnalysisOptions(**analysis_options(args))
        costmap = costmap_settings(args)
        terrain_model = load_terrain_model(model)
        classes = [str(c) for c in terrain_model.classes_]
        unknown = [c for c in costmap.lethal_classes if c not in classes]
        if unknown:  # say so before the long run
            raise InputError(
                f"--lethal-class {unknown[0]!r} is not a class of the model ({', '.join(classes)})"
            )
    except BaseException:
        if frames is not None:
            frames.close()
        raise
    result = analyse(traverse, terrain_model, options, frames=frames)
    written = write_outputs(
        result,
        out,
        png=not args.no_png,
        gridmap_bag=args.gridmap_bag,
        state=args.state,
        progress=args.progress,
        crg=args.crg,
        costmap=costmap,
    )
    if result.mapper is not None:
        result.mapper.close()  # its tiles on disk
    paths = {k: str(v) for k, v in written.items()}
    figures = summary(result, args.resolution)
    if args.json:
        emit_json({**figures, "outputs": paths})
        return 0
    rows = [[k, v] for k, v in paths.items()]
    print(table(rows, ["output", "path"]))
    if result.far_report:
        r = result.far_report
        status(
            args,
            f"near field {r['near_area_m2']:.1f} m², with near-to-far "
            f"{r['near_far_area_m2']:.1f} m² (×{r['area_ratio']:.1f})",
        )
    if "near_class_accuracy" in figures:
        far = figures.get("far_class_accuracy")
        status(
            args,
            f"against the simulator's truth: near-field class accuracy "
            f"{figures['near_class_accuracy']:.3f}"
            + ("" if far is None else f", far-field {far:.3f}"),
        )
    return 0
