"""``rough-map simulate``: a traverse over synthetic terrain, as the paper's experiments.

Build a terrain world laid out as the paper's experiments, drive a rover over it and write a
traverse folder: range clouds in the vehicle frame, optionally the rendered stereo pair of
an XB3-like rig, IMU roll/pitch, true labels and the true height field. Courses: mixed
(concrete, dirt road, gravel, with a manhole), mixed-reverse, ploughed (42 m), compact (22
m), random (all five surfaces). Each cloud keeps the points the features and the map use:
the square of half side --cloud-extent (0.5 m) around the patch centre 1.0 m ahead, in the
vehicle frame (x 0.5 to 1.5 m, y -0.5 to 0.5 m: the 0.896 m patch plus 52 mm for tilt
compensation), recorded as metadata.cloud_extent in traverse.json. A 100 m course at 0.5 m/s
and 2 Hz writes about 0.9 GB of float32 .npy clouds and a 0.2 GB world_truth.npz (1000 m: 9
GB and 2 GB); --compress makes the clouds about 2.6 times smaller. A course up to 50 m is
built whole, as it always was (up to 3 GB of memory, for ploughed soil); a longer one in 6 m
tiles as the rover drives on, with world_truth.npz written in tiles of 8 m that readers take
one at a time, so that memory stays near 0.6 GB without images and 0.95 GB with them,
whatever the length.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rough_map.cli._common import (
    add_command,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    status,
)
from rough_map.errors import InputError
from rough_map.simulate.world import COURSES


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "simulate",
        "simulate a rover traverse (clouds, stereo images, labels, true terrain)",
        __doc__,
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="new folder")
    p.add_argument(
        "--no-truth-geotiff",
        action="store_true",
        help="skip DIR/world_truth.tif, the true classes as a class GeoTIFF (the truth "
        "`rough-map score` reads; uint8 at the world's 2 mm spacing, names in its tags)",
    )
    p.add_argument(
        "--dem",
        type=positive_float("m"),
        nargs="?",
        const=0.008,
        metavar="M",
        help="also write DIR/world_dem.tif, the true heights as a GeoTIFF DEM sampled every M "
        "m (default 0.008, the paper's grid), for `rough-map survey`",
    )
    _add_course_args(p)
    _add_sensor_args(p)
    _add_recording_args(p)
    p.set_defaults(func=run)


def _add_course_args(p: argparse.ArgumentParser) -> None:
    """The course, the drive and the world: --course, --length, --speed, --rate, --seed,
    --width."""
    p.add_argument("--course", choices=COURSES, default="mixed", help="layout of the surfaces")
    p.add_argument(
        "--length",
        type=positive_float("m"),
        metavar="M",
        help="course length in m (default: the course's own length)",
    )
    p.add_argument(
        "--speed",
        type=positive_float("m/s"),
        default=0.5,
        metavar="M/S",
        help="rover speed in m/s (default 0.5)",
    )
    p.add_argument(
        "--rate",
        type=positive_float("Hz"),
        default=2.0,
        metavar="HZ",
        help="frame rate in Hz (default 2.0)",
    )
    p.add_argument(
        "--seed", type=non_negative_int(), default=0, help="seed of the world and the drive"
    )
    p.add_argument(
        "--width",
        type=positive_float("m"),
        default=4.0,
        metavar="M",
        help="width of the terrain across the course in m (default 4.0)",
    )


def _add_sensor_args(p: argparse.ArgumentParser) -> None:
    """The sensors: --no-images, --image-every, --points-per-cell, --noise,
    --cloud-extent."""
    p.add_argument(
        "--no-images", action="store_true", help="skip rendering the stereo pairs (much faster)"
    )
    p.add_argument(
        "--image-every",
        type=positive_int(),
        default=1,
        metavar="N",
        help="render the stereo pair of every N-th frame only (default 1)",
    )
    p.add_argument(
        "--points-per-cell",
        type=positive_float(""),
        default=12.0,
        metavar="N",
        help="density of the simulated range cloud per 8 mm cell (default 12.0)",
    )
    p.add_argument(
        "--noise",
        type=non_negative_float("m"),
        default=0.0003,
        metavar="M",
        help="range noise of the cloud in m (default 0.0003)",
    )
    p.add_argument(
        "--cloud-extent",
        type=positive_float("m"),
        default=0.5,
        metavar="M",
        help="half side in m of the square of points kept around the patch centre, in the "
        "vehicle frame (default 0.5: x 0.5-1.5 m, y -0.5-0.5 m; 0.55 keeps the sensor's "
        "whole 1.1 m footprint)",
    )


def _add_recording_args(p: argparse.ArgumentParser) -> None:
    """How the traverse is written: --compress, --bag, --bag-storage."""
    p.add_argument(
        "--compress",
        action="store_true",
        help="write the clouds as compressed .npz (16-bit steps of 15 um or less, far "
        "below the range noise; about 2.6x smaller than float32 .npy); every command reads "
        "them",
    )
    p.add_argument(
        "--bag",
        type=Path,
        metavar="BAG",
        help="also record the traverse as a ROS bag at BAG, as a rover's logger would: "
        "/points (PointCloud2), /odom, /imu and /tf_static (try it with `rough-map inspect` "
        "and `rough-map import`)",
    )
    p.add_argument(
        "--bag-storage",
        choices=("mcap", "sqlite3", "ros1"),
        default="mcap",
        help="format of --bag: a ROS 2 bag folder (mcap, sqlite3) or a ROS 1 .bag file",
    )


#: What ``simulate`` writes at the top of ``--out``: an existing folder has these replaced as
#: a set, the user's other files kept.
SIMULATE_OUTPUTS = ("traverse.json", "traverse.yaml", "traverse.yml", "clouds", "left", "right",
                    "world_truth*", "world_dem*")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from rough_map._files import output_set
    from rough_map.simulate.course import SensorSpec, simulate

    if args.bag is not None and args.bag.exists():
        raise InputError(f"{args.bag} exists; write the bag to a new path")

    sensor = SensorSpec(
        points_per_cell=args.points_per_cell, noise=args.noise, cloud_half_extent=args.cloud_extent
    )
    # an existing --out has the traverse replaced as a set: staged beside it, swapped in whole
    with output_set(args.out, owned=SIMULATE_OUTPUTS) as stage:
        staged = simulate(
            stage,
            args.course,
            length=args.length,
            speed=args.speed,
            rate=args.rate,
            seed=args.seed,
            images=not args.no_images,
            image_every=args.image_every,
            width=args.width,
            sensor=sensor,
            compress=args.compress,
            progress=args.progress,
        )
        truth = None if args.no_truth_geotiff else _write_truth_geotiff(stage)
        dem = None if args.dem is None else _write_dem_geotiff(stage, args.dem)
    path = args.out / staged.relative_to(stage)
    print(path)
    status(args, f"simulated the {args.course} course into {args.out}")
    if truth is not None:
        written = args.out / truth.relative_to(stage)
        status(args, f"wrote its true classes to {written} (for rough-map score --truth)")
    if dem is not None:
        status(args, f"wrote its true heights to {args.out / dem.relative_to(stage)}")
    if args.bag is not None:
        from rough_map.io.rosbag import write_example_bag

        bag = write_example_bag(
            args.out, args.bag, storage=args.bag_storage, progress=args.progress
        )
        print(bag)
        status(args, f"recorded it as a ROS bag ({args.bag_storage}) in {bag}")
    return 0


def _write_truth_geotiff(folder: Path) -> Path:
    """Write the simulated world's classes as ``folder/world_truth.tif`` (the truth format
    of ``rough-map score``), in the traverse's CRS."""
    from rough_map.io.traverse import load_traverse
    from rough_map.io.truth import traverse_truth
    from rough_map.io.truth_raster import TRUTH_GEOTIFF, write_truth_geotiff

    traverse = load_traverse(folder)
    world = traverse_truth(traverse)
    if world is None:
        raise InputError(f"{folder}: the simulated traverse has no world truth")
    return write_truth_geotiff(world, folder / TRUTH_GEOTIFF, traverse.spec.crs.rasterio())


def _write_dem_geotiff(folder: Path, spacing: float) -> Path:
    """Write the simulated world's heights as ``folder/world_dem.tif``, sampled every
    ``spacing`` m, in the traverse's CRS."""
    from rough_map.io.traverse import load_traverse
    from rough_map.io.truth import traverse_truth
    from rough_map.io.truth_raster import DEM_GEOTIFF, write_dem_geotiff

    traverse = load_traverse(folder)
    world = traverse_truth(traverse)
    if world is None:
        raise InputError(f"{folder}: the simulated traverse has no world truth")
    return write_dem_geotiff(world, folder / DEM_GEOTIFF, traverse.spec.crs.rasterio(), spacing)
