"""``rough-map import BAG ...``: a traverse folder from a ROS bag (no ROS needed)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import existing_path, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "import",
        help="make a traverse folder from a ROS bag",
        description="Write one frame per PointCloud2 message: the cloud in the vehicle frame "
        "(clouds/NNNNNN.npy) and the odometry pose interpolated at its stamp (traverse.json). "
        "Prints the path of traverse.json.",
    )
    parser.add_argument(
        "bag", type=existing_path, help="ROS 1 .bag file, ROS 2 bag folder, or .db3/.mcap file"
    )
    parser.add_argument(
        "--points-topic", required=True, metavar="TOPIC", help="sensor_msgs/PointCloud2 topic"
    )
    parser.add_argument(
        "--odom-topic", required=True, metavar="TOPIC", help="nav_msgs/Odometry topic"
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


def run(args: argparse.Namespace) -> int:
    from rough_map.io.rosbag import import_bag

    traverse = import_bag(
        args.bag,
        args.out,
        points_topic=args.points_topic,
        odom_topic=args.odom_topic,
        imu_topic=args.imu_topic,
        every=args.every,
        progress=args.progress,
    )
    print(traverse.source)
    return 0
