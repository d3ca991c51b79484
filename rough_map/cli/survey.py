"""``rough-map survey RASTER --out DIR``: the roughness of a whole surface, as rasters.

Slide the paper's patch over a height raster (a DEM or DSM: GeoTIFF, COG, Esri ASCII grid,
VRT or any raster GDAL reads, in a projected CRS; a .npy grid with --spacing; an OpenCRG
road, along its reference line; a cloud in a world frame, gridded at the spacing its density
supports: LAS/LAZ in its own CRS, or .ply, .pcd, .csv/.xyz/.txt, KITTI .bin or a .npy of N x
3 points in metres, in --crs) and measure each window as a traverse's patch is measured: R
at 1 rad/m, w, their spread and standard errors, the rms heights, the power-law check and
the ISO 8608 class. Writes DIR/roughness.tif (a float32 band per quantity, in the raster's
CRS, one cell per window centred on it, nodata where a window could not be read),
DIR/roughness_class.tif (uint8 ISO class with a colour table), DIR/roughness.csv (one row
per window) and a PNG per layer with its legend, as one set: DIR holds either the old
outputs or the new ones; your own files in DIR are kept. The raster is read a band of
windows at a time, in bounded memory; -j N spreads the bands over N processes, --scheduler
over the workers of a Dask cluster (which read RASTER at the same path), with the numbers of
one process.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    add_cluster_args,
    add_command,
    add_jobs_arg,
    emit_json,
    existing_path,
    positive_float,
    status,
    xy_metres,
)
from rough_map.patch import DEFAULT_SIZE
from rough_map.patch.surface import AUTO_CELLS


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "survey", "roughness rasters of a whole surface (DEM, DSM, .npy)", __doc__)
    p.add_argument(
        "raster",
        type=existing_path,
        help="height raster (GeoTIFF, any GDAL, .npy, .crg) or world-frame cloud",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--window",
        type=positive_float("m"),
        metavar="M",
        help=f"side of a window in m (default {DEFAULT_SIZE}, the paper's patch, or "
        f"{AUTO_CELLS} cells of a coarser raster, such as a gridded airborne cloud)",
    )
    p.add_argument(
        "--stride",
        type=positive_float("m"),
        metavar="M",
        help="distance between window centres in m (default: half a window)",
    )
    p.add_argument(
        "--direction",
        choices=("rows", "columns"),
        default="rows",
        help="profiles along the raster's rows (west to east, the default) or its columns",
    )
    p.add_argument(
        "--both-directions",
        action="store_true",
        help="also measure the profiles across, and the anisotropy ln(R / R_across)",
    )
    p.add_argument(
        "--gridding",
        choices=("point", "cell_mean"),
        help="the raster's heights are samples of the surface (point: the default for a "
        "raster) or means of many points per cell (cell_mean: a DEM gridded from a dense "
        "cloud; the default for a LAS/LAZ cloud, which survey grids itself)",
    )
    npy = p.add_argument_group("a .npy grid (row 0 is the north edge)")
    npy.add_argument(
        "--spacing", type=positive_float("m"), metavar="M", help="cell size in m (required)"
    )
    npy.add_argument(
        "--origin",
        type=xy_metres,
        default=(0.0, 0.0),
        metavar="X,Y",
        help="world x, y in m of the grid's north-west corner (default 0,0)",
    )
    npy.add_argument(
        "--crs",
        default=None,
        metavar="EPSG:N",
        help="CRS of a .npy grid or of a cloud without one (default: local)",
    )
    p.add_argument("--no-png", action="store_true", help="skip the PNGs")
    add_cluster_args(p)
    add_jobs_arg(p)
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from rough_map.export.survey_files import write_roughness_raster
    from rough_map.io.raster import open_height_raster
    from rough_map.survey import SurveySpec, roughness_raster

    npy = args.raster.suffix.lower() == ".npy"
    raster = open_height_raster(
        args.raster,
        spacing=args.spacing if npy else None,
        origin=args.origin,
        crs=args.crs,
    )
    spec = SurveySpec(
        window=args.window,
        stride=args.stride,
        direction=args.direction,
        gridding=args.gridding,
        both_directions=args.both_directions,
    )
    size, step = spec.cells(raster.spacing)
    grid = roughness_raster(
        raster,
        spec,
        n_jobs=args.jobs,
        progress=args.progress,
        scheduler=args.scheduler,
        tls=tuple(args.tls) if args.tls else None,
    )
    written = write_roughness_raster(
        grid, args.out, png=not args.no_png, progress=args.progress, crs=raster.file_crs
    )
    valid = int(np.count_nonzero(grid["valid"]))
    R = grid["R"][grid["valid"] > 0]
    summary = {
        "raster": str(args.raster),
        "crs": raster.crs.code if raster.file_crs is None else raster.file_crs.to_string(),
        "spacing_m": raster.spacing,
        "window_m": size * raster.spacing,
        "stride_m": step * raster.spacing,
        "direction": spec.direction,
        "gridding": spec.gridding or raster.gridding,
        "windows": int(grid["valid"].size),
        "windows_read": valid,
        "median_R": float(np.median(R)) if R.size else None,
        "files": {k: str(v) for k, v in written.items()},
        **({"gridded": raster.note} if raster.note else {}),
    }
    if args.json:
        emit_json(summary, indent=2)
        return 0
    print(written["values"])
    if raster.note:
        status(args, f"{args.raster.name}: {raster.note}")
    status(
        args,
        f"{valid} of {grid['valid'].size} windows of {size} cells ({size * raster.spacing:.3g} m, "
        f"every {step * raster.spacing:.3g} m, profiles along the {spec.direction}) read; "
        f"wrote {args.out}",
    )
    return 0
