"""``rough-map stereo``: a stereo pair -> point cloud in the vehicle frame, and optionally the
disparity map and the camera-frame points.

Match a stereo pair with semi-global matching (rectifying it first if the calibration has
distortion or rotations), triangulate, filter outliers and write the points in the vehicle
frame (x forward, y left, z up, metres). By default only the image rows and disparities that
see the patch of interest are matched and only the points over the patch are written;
--full-frame matches every pixel over the disparities of --min-depth..--max-depth.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from rough_map._files import atomic_output
from rough_map.cli._common import add_command, existing_path, finite_float, positive_float
from rough_map.errors import FileFormatError, PatchError
from rough_map.io.pointcloud import write_cloud
from rough_map.patch import PatchSpec

#: The default patch of interest (the paper's).
_PATCH = PatchSpec()


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "stereo", "point cloud of the patch ahead from a stereo pair (SGM)", __doc__
    )
    p.add_argument(
        "left", type=existing_path, help="left (reference) image, any format OpenCV reads"
    )
    p.add_argument("right", type=existing_path, help="right image, same size")
    p.add_argument(
        "--calib",
        type=existing_path,
        required=True,
        nargs="+",
        metavar="FILE",
        help="rig calibration: rough_map's YAML/JSON (fx fy cx cy [cx_right] width height in "
        "px, baseline and camera_to_vehicle in m; configs/stereo_calibration.yaml is the rig "
        "of `rough-map simulate`), an OpenCV FileStorage file (M1 D1 M2 D2 R T, T in m), or "
        "two ROS CameraInfo YAML files, left then right",
    )
    p.add_argument(
        "--camera-to-vehicle",
        type=existing_path,
        metavar="FILE",
        help="YAML/JSON with `camera_to_vehicle`: the 4x4 transform (m) of the (raw) left "
        "camera to the vehicle, for OpenCV/CameraInfo calibrations (default: at the vehicle "
        "origin, looking along x) or to replace a rough_map calibration's",
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
    _add_frame_args(p)
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


def _add_frame_args(p: argparse.ArgumentParser) -> None:
    """The depths searched and the whole-frame outputs."""
    p.add_argument(
        "--min-depth",
        type=positive_float("m"),
        metavar="M",
        help="nearest depth searched (full frame, --disparity, --camera-points); default: "
        "the config's numDisparities beyond the farthest",
    )
    p.add_argument(
        "--max-depth",
        type=positive_float("m"),
        metavar="M",
        help="farthest depth searched; default: infinity with --full-frame, else (with "
        "neither depth) the depths of the patch",
    )
    p.add_argument(
        "--disparity",
        type=Path,
        metavar="FILE.npy",
        help="also write the full-frame disparity map: .npy, float32, px of the rectified "
        "left image (u_left - u_right), NaN where invalid",
    )
    p.add_argument(
        "--camera-points",
        type=Path,
        metavar="FILE",
        help="also write the full frame's points in the rectified left camera frame (OpenCV: "
        "x right, y down, z forward; N x 3, m); the suffix picks the format",
    )


def run(args: argparse.Namespace) -> int:
    # Deferred: pydantic (config) and scipy.stats (stereo) would double the start-up time of
    # every command (the CLI imports all command modules to build its parser).
    from rough_map.config import load_mapping
    from rough_map.stereo import (
        StereoConfig,
        load_calibration,
        read_image,
        stereo_frame,
        stereo_to_cloud,
    )

    log = logging.getLogger("rough_map.cli.stereo")
    if args.disparity is not None and args.disparity.suffix.lower() != ".npy":
        raise FileFormatError(args.disparity, "the disparity map is written as .npy", "suffix")
    pose = None
    if args.camera_to_vehicle is not None:
        pose = load_mapping(args.camera_to_vehicle).get("camera_to_vehicle")
        if pose is None:
            raise FileFormatError(args.camera_to_vehicle, "missing", "camera_to_vehicle")
    calib = load_calibration(args.calib, pose)
    config = StereoConfig.from_file(args.config) if args.config else StereoConfig()
    left, right = read_image(args.left), read_image(args.right)
    patch = PatchSpec(ahead=args.ahead, size=args.size, lateral=args.lateral)
    depths = {"min_depth": args.min_depth, "max_depth": args.max_depth}
    t0 = time.perf_counter()
    frame = None
    if args.full_frame or args.disparity is not None or args.camera_points is not None:
        # The depths asked for; else the full frame the config's, the patch path the patch's.
        by_patch = not args.full_frame and args.min_depth is None and args.max_depth is None
        frame = stereo_frame(
            left, right, calib, config, patch=patch if by_patch else None, **depths
        )
        log.info("disparities %d + %d px searched", *frame.disparities)
    if args.full_frame:
        assert frame is not None
        points = frame.vehicle_points()
    else:
        points = stereo_to_cloud(left, right, calib, config, patch=patch)
    log.info("%d points in %.3f s", len(points), time.perf_counter() - t0)
    if len(points) == 0:
        raise PatchError(f"{args.left}: no valid stereo match over the patch; nothing written")
    write_cloud(args.out, points)
    print(f"{args.out}: {len(points)} points")
    if frame is not None and args.disparity is not None:
        with atomic_output(args.disparity) as tmp:
            np.save(tmp, frame.disparity.astype(np.float32))
        print(f"{args.disparity}: {int(np.isfinite(frame.disparity).sum())} valid disparities")
    if frame is not None and args.camera_points is not None:
        camera = frame.camera_points()
        write_cloud(args.camera_points, camera)
        print(f"{args.camera_points}: {len(camera)} points")
    return 0
