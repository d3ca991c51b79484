"""``rough-map inspect BAG``: the topics of a ROS bag, their message types and counts.

List the topics of a ROS 1 bag or ROS 2 bag (folder, .db3 or .mcap) with their message types
and counts.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict

from rough_map.cli._common import add_command, emit_json, existing_path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(subparsers, "inspect", "list the topics of a ROS bag", __doc__)
    parser.add_argument(
        "bag", type=existing_path, help="ROS 1 .bag file, ROS 2 bag folder, or .db3/.mcap file"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map.io.rosbag import inspect_bag

    info = inspect_bag(args.bag)
    if args.json:
        data = {
            "path": str(info.path),
            "start": info.start,
            "end": info.end,
            "duration": info.duration,
            "message_count": info.message_count,
            "topics": [asdict(t) for t in info.topics],
        }
        emit_json(data, indent=2)
        return 0
    rows = [("topic", "type", "count")] + [(t.name, t.msgtype, str(t.count)) for t in info.topics]
    widths = [max(len(r[i]) for r in rows) for i in range(2)]
    for name, msgtype, count in rows:
        print(f"{name:<{widths[0]}}  {msgtype:<{widths[1]}}  {count:>5}")
    print(f"{len(info.topics)} topics, {info.message_count} messages, {info.duration:.3f} s")
    return 0
