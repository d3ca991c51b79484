"""``rough-map stereo``: a rectified stereo pair -> point cloud in the vehicle frame."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from rough_map.cli._common import existing_path, finite_float, positive_float
from rough_map.errors import PatchError
from rough_map.io.pointcloud import write_cloud
from rough_map.patch import PatchSpec

#: The default patch of interest (the paper's).
_PATCH = PatchSpec()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stereo",
        help="point cloud of the patch ahead from a rectified stereo pair (SGM)",
        description=(
            "Match a rectified stereo pair with semi-global matching, triangulate, filter "
            "height outliers and write the points in the vehicle frame (x forward, y left, z "
            "up, metres). By default only the image rows and disparities that see the patch "
            "of interest are matched and only the points over the patch are written."
        ),
    )
    p.add_argument(
        "left", type=existing_path, help="left (reference) image, any format OpenCV reads"
    )
    p.add_argument("right", type=existing_path, help="right image, same size")
    p.add_argument(
        "--calib",
        type=existing_path,
        required=True,
        metavar="FILE",
        help="rig calibration, YAML or JSON: fx fy cx cy (px), width height (px), baseline "
        "(m), camera_to_vehicle (4x4, m); configs/stereo_calibration.yaml is the rig of "
        "`rough-map simulate`",
    )
    p.add_argument(
        "--config",
        type=existing_path,
        metavar="FILE",
        help="matcher/filter settings like configs/stereo.yaml (default: built-in)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="FILE",
        help="output cloud; the suffix picks the format (.npy, .ply, .las, ...)",
    )
    p.add_argument(
        "--full-frame",
        action="store_true",
        help="match the whole image and keep every point (slower)",
    )
    g = p.add_argument_group("patch of interest (vehicle frame, metres)")
    g.add_argument(
        "--ahead",
        type=finite_float("m"),
        default=_PATCH.ahead,
        metavar="M",
        help=f"distance of the patch centre ahead of the vehicle (default {_PATCH.ahead})",
    )
    g.add_argument(
        "--size",
        type=positive_float("m"),
        default=_PATCH.size,
        metavar="M",
        help=f"side of the square patch (default {_PATCH.size})",
    )
    g.add_argument(
        "--lateral",
        type=finite_float("m"),
        default=_PATCH.lateral,
        metavar="M",
        help=f"offset of the patch centre to the left (default {_PATCH.lateral})",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Deferred: pydantic (config) and scipy.stats (stereo) would double the start-up time of
    # every command (the CLI imports all command modules to build its parser).
    from rough_map.config import StereoCalibration
    from rough_map.stereo import StereoConfig, read_image, stereo_to_cloud

    log = logging.getLogger("rough_map.cli.stereo")
    calib = StereoCalibration.from_file(args.calib)
    config = StereoConfig.from_file(args.config) if args.config else StereoConfig()
    left, right = read_image(args.left), read_image(args.right)
    patch = PatchSpec(ahead=args.ahead, size=args.size, lateral=args.lateral)
    t0 = time.perf_counter()
    points = stereo_to_cloud(
        left, right, calib, config, patch=patch, restrict_to_patch=not args.full_frame
    )
    log.info("%d points in %.3f s", len(points), time.perf_counter() - t0)
    if len(points) == 0:
        raise PatchError(f"{args.left}: no valid stereo match over the patch; nothing written")
    write_cloud(args.out, points)
    print(f"{args.out}: {len(points)} points")
    return 0
