"""``rough-map simulate``: a traverse over synthetic terrain, as the paper's experiments."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from rough_map.simulate.world import COURSES

    p = sub.add_parser(
        "simulate",
        help="simulate a rover traverse (clouds, stereo images, labels, true terrain)",
        description=(
            "Build a terrain world laid out as the paper's experiments, drive a rover over it "
            "and write a traverse folder: range clouds in the vehicle frame, optionally the "
            "rendered stereo pair of an XB3-like rig, IMU roll/pitch, true labels and the "
            "true height field. Courses: mixed (concrete, dirt road, gravel, with a manhole), "
            "mixed-reverse, ploughed (42 m), compact (22 m), random (all five surfaces)."
        ),
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="new folder")
    p.add_argument("--course", choices=COURSES, default="mixed")
    p.add_argument("--length", type=float, metavar="M", help="course length in m")
    p.add_argument(
        "--speed", type=float, default=0.5, metavar="M/S", help="rover speed in m/s (default 0.5)"
    )
    p.add_argument(
        "--rate", type=float, default=2.0, metavar="HZ", help="frame rate in Hz (default 2)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--width",
        type=float,
        default=4.0,
        metavar="M",
        help="width of the terrain across the course in m (default 4)",
    )
    p.add_argument(
        "--no-images", action="store_true", help="skip rendering the stereo pairs (much faster)"
    )
    p.add_argument(
        "--image-every",
        type=int,
        default=1,
        metavar="N",
        help="render the stereo pair of every N-th frame only (default 1)",
    )
    p.add_argument(
        "--points-per-cell",
        type=float,
        default=12.0,
        metavar="N",
        help="density of the simulated range cloud per 8 mm cell (default 12)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0003,
        metavar="M",
        help="range noise of the cloud in m (default 0.0003)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map.simulate.course import SensorSpec, simulate

    sensor = SensorSpec(points_per_cell=args.points_per_cell, noise=args.noise)
    path = simulate(
        args.out,
        args.course,
        length=args.length,
        speed=args.speed,
        rate=args.rate,
        seed=args.seed,
        images=not args.no_images,
        image_every=args.image_every,
        width=args.width,
        sensor=sensor,
        progress=args.progress,
    )
    print(path)
    print(f"simulated the {args.course} course into {args.out}", file=sys.stderr)
    return 0
