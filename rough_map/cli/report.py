"""``rough-map report TRAVERSE --out DIR``: the paper's figures and an index.html.

Run the whole chain on a traverse (features, classes, filter, map, near-to-far when there
are images) and write DIR/index.html with: R and w along the path with sigma bands and ISO
lines (paper Figs. 7/9/12), the PSD of one profile with its fit (Fig. 4), the per-profile
(R, w) scatter (Fig. 5), the fitted PSD lines against the ISO classes (Fig. 10), (R, w) by
class with the roughness levels (Fig. 19), the elevation, roughness and class layers with
the path (Figs. 20/21) and, when the frames are labelled, the confusion matrices; each
figure with a caption, the numbers as tables, and links to the map's GeoTIFFs and one PNG
per layer (written to DIR too).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    add_command,
    add_jobs_arg,
    add_map_args,
    add_model_arg,
    add_route_args,
    add_traverses_arg,
    add_vehicle_args,
    analysis_options,
    chosen_model,
    open_traverses,
    status,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "report",
        "draw the paper's figures for a traverse, with the map and the evaluation",
        __doc__,
    )
    add_traverses_arg(p, tables=False)
    p.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="folder for index.html and figures"
    )
    add_model_arg(p)
    add_map_args(p)
    add_route_args(p)
    add_vehicle_args(p)
    add_jobs_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map._files import output_set
    from rough_map.evaluation import evaluate_model
    from rough_map.export import export_map
    from rough_map.export.report import write_report
    from rough_map.workflow import (
        MAP_OUTPUTS,
        AnalysisOptions,
        analyse_model_file,
        level_edges,
        write_tables,
    )

    owned = (*MAP_OUTPUTS, "index.html", "fig_*.png", "evaluation.json")

    model_path = chosen_model(args)
    (traverse,) = open_traverses(args, args.traverse)
    options = AnalysisOptions(**analysis_options(args))
    result = analyse_model_file(traverse, model_path, options)
    evaluation = None
    if any(result.features["label"]):
        evaluation = evaluate_model(result.model, [result.features])
    out: Path = args.out
    with output_set(out, owned=owned) as stage:  # the folder swapped in whole
        export_map(result.map, stage, name="map", png=True)  # the page links the layer PNGs
        write_tables(result, stage)
        write_report(result, stage, evaluation=evaluation, level_edges=level_edges(result))
    print(out / "index.html")
    status(args, f"report of {result.traverse.name} in {out}")
    return 0
