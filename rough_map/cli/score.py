"""``rough-map score MAP_DIR --truth TRUTH.tif``: a written map scored against surveyed truth.

Score the class layers of a `rough-map map` folder (MAP_DIR/map_class.tif, map_far_class.tif
with near-to-far; count bands of map.tif; the path from labels.csv) against a class GeoTIFF
in any CRS and resolution, reprojected onto the map's grid. Class names of the truth: a
sidecar TRUTH.classes.json ({"0": "gravel", ...}) or TRUTH.classes.csv (value,name), band-1
tags CLASS_<value>=<name> (as rough-map writes them) or GDAL category names; matched by
name. Reports near-field (class) and far-field (far_class) accuracy, accuracy by distance
from the path, the confusion matrix and the abstention rate (cells a layer observed but left
unknown). `rough-map simulate` writes its true classes as world_truth.tif in this format.
"""

from __future__ import annotations

import argparse
import itertools
import math

from rough_map.cli._common import add_command, emit_json, existing_path, positive_float, status

#: Upper edges of the distance bins, m (rough_map.evaluation.score.DEFAULT_BINS; not
#: imported here, so that building the parser stays light).
_BINS = "0.5,1,2,3,4,6,8"


def _bins(text: str) -> tuple[float, ...]:
    """Argument type: increasing positive distances in m, comma-separated."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected distances in metres separated by commas, got {text!r}"
        ) from None
    if (
        not values
        or any(not (math.isfinite(v) and v > 0) for v in values)
        or any(b <= a for a, b in itertools.pairwise(values))
    ):
        raise argparse.ArgumentTypeError(
            f"expected increasing positive distances in metres, got {text!r}"
        )
    return values


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "score", "score a map folder against a surveyed class raster (GeoTIFF)", __doc__
    )
    p.add_argument("map_dir", type=existing_path, help="folder written by rough-map map")
    p.add_argument(
        "--truth",
        type=existing_path,
        required=True,
        metavar="TRUTH.tif",
        help="class raster (GeoTIFF, integer classes with names, nodata = no truth)",
    )
    p.add_argument(
        "--resampling",
        choices=("nearest", "mode"),
        default="nearest",
        help="truth onto the map grid: nearest (the class at each map cell's centre) or mode "
        "(the class covering most of the cell); default nearest",
    )
    p.add_argument(
        "--bins",
        type=_bins,
        default=_BINS,
        metavar="M,M,...",
        help=f"upper edges of the distance bins, m from the path (default {_BINS})",
    )
    p.add_argument(
        "--max-distance",
        type=positive_float("m"),
        metavar="M",
        help="score only cells up to this far from the path, m (default: all)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map.evaluation.score_files import score_map_dir

    bins = args.bins if isinstance(args.bins, tuple) else _bins(args.bins)
    score = score_map_dir(
        args.map_dir,
        args.truth,
        resampling=args.resampling,
        bins=bins,
        max_distance=math.inf if args.max_distance is None else args.max_distance,
    )
    if args.json:
        emit_json(score.to_dict(), indent=2)
        return 0
    print(score.to_text())
    near, far = score.near_field_accuracy, score.far_field_accuracy
    status(
        args,
        f"near-field accuracy {near:.3f}" + ("" if math.isnan(far) else f", far-field {far:.3f}"),
    )
    return 0
