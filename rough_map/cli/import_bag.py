"""``rough-map import BAG ...``: a traverse folder from a ROS bag (no ROS needed).

Write one frame per PointCloud2 message: the cloud in the vehicle frame (clouds/NNNNNN.npy)
and the vehicle pose interpolated at its stamp (traverse.json). The poses come from
odometry, a PoseStamped or PoseWithCovarianceStamped topic, the /tf tree, or GNSS fixes
(NavSatFix: heading from the direction of travel). Prints the path of traverse.json.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from rough_map.cli._common import add_command, existing_path, positive_int
from rough_map.errors import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(subparsers, "import", "make a traverse folder from a ROS bag", __doc__)
    parser.add_argument(
        "bag", type=existing_path, help="ROS 1 .bag file, ROS 2 bag folder, or .db3/.mcap file"
    )
    parser.add_argument(
        "--points-topic", required=True, metavar="TOPIC", help="sensor_msgs/PointCloud2 topic"
    )
    parser.add_argument(
        "--pose-topic",
        "--odom-topic",
        dest="pose_topic",
        required=True,
        metavar="TOPIC",
        help="the vehicle's poses: a nav_msgs/Odometry, geometry_msgs/PoseStamped or "
        "PoseWithCovarianceStamped, tf2_msgs/TFMessage (/tf) or sensor_msgs/NavSatFix topic",
    )
    parser.add_argument(
        "--vehicle-frame",
        default="base_link",
        metavar="FRAME",
        help="the vehicle's frame: whose pose /tf gives, and the frame of PoseStamped and "
        "NavSatFix poses (default: base_link; odometry names its own child frame)",
    )
    parser.add_argument(
        "--crs",
        type=crs_code,
        default="local",
        metavar="CODE",
        help="CRS of the poses' world frame: 'local' or EPSG:<code> of a projected CRS in m "
        "(NavSatFix fixes are projected to it) (default: local)",
    )
    parser.add_argument(
        "--origin",
        type=geodetic_origin,
        metavar="LAT,LON[,ALT]",
        help="geodetic origin (degrees, m) of a local world frame, so that the map is "
        "georeferenced (default: none; for NavSatFix, the first fix)",
    )
    parser.add_argument(
        "--imu-topic", metavar="TOPIC", help="sensor_msgs/Imu topic (roll and pitch per frame)"
    )
    parser.add_argument(
        "--every",
        type=positive_int(),
        default=1,
        metavar="N",
        help="keep one cloud in N (default 1)",
    )
    parser.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="traverse folder to create"
    )
    parser.set_defaults(func=run)


def crs_code(text: str) -> str:
    """``local`` or ``EPSG:<code>`` (an integer alone is an EPSG code)."""
    code = text.strip()
    if code.isdigit():
        code = f"EPSG:{code}"
    if code.lower() == "local":
        return "local"
    if not (code.upper().startswith("EPSG:") and code[5:].isdigit() and int(code[5:]) > 0):
        raise argparse.ArgumentTypeError(f"a CRS is 'local' or EPSG:<code>, got {text!r}")
    return f"EPSG:{int(code[5:])}"


def geodetic_origin(text: str) -> dict[str, float]:
    """``LAT,LON[,ALT]`` in degrees and m."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"an origin is LAT,LON[,ALT] (degrees, m), got {text!r}")
    lat, lon = values[0], values[1]
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError(f"latitude {lat} or longitude {lon} is out of range")
    return {"lat": lat, "lon": lon, "alt": values[2] if len(values) == 3 else 0.0}


#: What ``import`` writes at the top of ``--out``: an existing folder has these replaced as a
#: set, the user's other files kept.
IMPORT_OUTPUTS = ("traverse.json", "traverse.yaml", "traverse.yml", "clouds")


def run(args: argparse.Namespace) -> int:
    from rough_map._files import output_set
    from rough_map.io.rosbag import import_bag

    if args.origin is not None and args.crs != "local":
        raise InputError(f"--origin places a local frame; --crs {args.crs} has its own")
    crs = {"code": "local", "origin": args.origin} if args.origin is not None else args.crs
    # an existing --out has the traverse replaced as a set: staged beside it, swapped in whole
    with output_set(args.out, owned=IMPORT_OUTPUTS) as stage:
        traverse = import_bag(
            args.bag,
            stage,
            points_topic=args.points_topic,
            pose_topic=args.pose_topic,
            imu_topic=args.imu_topic,
            every=args.every,
            progress=args.progress,
            crs=crs,
            vehicle_frame=args.vehicle_frame,
        )
    print(args.out / traverse.source.relative_to(stage))
    return 0
