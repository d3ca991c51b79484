"""``rough-map features``: roughness features of one cloud, or of every frame of a traverse.

Cut the patch of interest out of a point cloud in the vehicle frame (x forward, y left, z
up, metres), grid it, and estimate its PSD roughness parameters. CLOUD is .npy (N x 3),
.csv/.xyz/.txt, .ply/.pcd, .las/.laz or KITTI .bin. A traverse folder instead writes one row
per frame to --out.
"""

from __future__ import annotations

import argparse
import math
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rough_map.cli._common import (
    add_allow_outside_arg,
    add_command,
    add_jobs_arg,
    add_patch_args,
    add_psd_args,
    add_route_args,
    add_vehicle_args,
    chosen_vehicle,
    emit_json,
    existing_path,
    finite_float,
    patch_spec,
    table,
)
from rough_map.errors import InputError
from rough_map.patch import Extraction, GriddedPatch, PatchSpec

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from rough_map.psd import PatchRoughness


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "features",
        "R, w, sigma and ISO class of the patch ahead, for a cloud or a traverse",
        __doc__,
    )
    p.add_argument(
        "source",
        metavar="CLOUD|TRAVERSE_DIR",
        type=existing_path,
        help="a point cloud file, or a traverse folder (or its traverse.json)",
    )
    add_patch_args(p, auto=True)
    p.add_argument(
        "--roll",
        type=finite_float("deg"),
        metavar="DEG",
        help="vehicle roll in degrees: compensate tilt (paper Eq. 11)",
    )
    p.add_argument(
        "--pitch",
        type=finite_float("deg"),
        metavar="DEG",
        help="vehicle pitch in degrees: compensate tilt (paper Eq. 11)",
    )
    cloud = p.add_argument_group("a cloud not in the vehicle frame or not in metres")
    cloud.add_argument(
        "--units",
        choices=tuple(UNITS),
        default="m",
        help="units of the cloud's coordinates (a LAS/LAZ file with a CRS takes its own)",
    )
    cloud.add_argument(
        "--columns",
        type=_columns,
        metavar="X,Y,Z",
        help="for a text cloud: the header names or 1-based numbers of its x, y, z columns",
    )
    cloud.add_argument(
        "--frame",
        choices=("vehicle", "world"),
        help="frame of the cloud's points: vehicle (the default without --at) or world (read "
        "at --at; the default with it); a traverse names it in traverse.json (cloud_frame)",
    )
    cloud.add_argument(
        "--at",
        type=_pose,
        metavar="X,Y[,YAW]",
        help="read a world-frame or georeferenced cloud as seen by a vehicle standing at X, Y "
        "(m, in the cloud's frame or CRS) heading YAW degrees anticlockwise from +x (default 0)",
    )
    add_psd_args(p)
    add_jobs_arg(p)
    add_route_args(p)
    add_vehicle_args(p)
    add_allow_outside_arg(p)
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--out",
        type=Path,
        metavar="FILE",
        help="for a traverse: features table (.csv, or .parquet with pyarrow); its "
        "metadata (name, wavenumbers of the psd_NN columns) goes to FILE.json beside it",
    )
    p.add_argument(
        "--no-tilt",
        action="store_true",
        help="for a traverse: ignore the IMU roll/pitch of the frames",
    )
    p.add_argument(
        "--points-from",
        choices=("auto", "cloud", "stereo"),
        default="auto",
        help="for a traverse: the frames' clouds, or their stereo pairs "
        "(auto: the cloud when there is one); a frame without one is marked invalid",
    )
    p.set_defaults(func=run)


#: ``--units``: metres per unit.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "us-ft": 1200.0 / 3937.0}


def _columns(text: str) -> tuple[str, ...]:
    """``--columns X,Y,Z`` as its names (``read_cloud`` checks them)."""
    return tuple(text.split(","))


def _pose(text: str) -> tuple[float, float, float]:
    try:
        values = [float(t) for t in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f"expected X,Y or X,Y,YAW (m, m, degrees), got {text!r:.60}"
        )
    x, y, *yaw = values
    return x, y, math.radians(yaw[0] if yaw else 0.0)


def run(args: argparse.Namespace) -> int:
    from rough_map.io.traverse import TRAVERSE_FILES

    if args.frame == "world" and args.at is None:
        raise InputError(
            "--frame world: a world-frame cloud is read where a vehicle stands: give --at "
            "X,Y[,YAW] (m, in the cloud's frame or CRS; degrees)"
        )
    if args.frame == "vehicle" and args.at is not None:
        raise InputError("--at reads a world-frame cloud; --frame vehicle says it is not one")
    if args.route is not None or args.source.is_dir() or args.source.name in TRAVERSE_FILES:
        given = [o for o, v in (("--units", args.units != "m"), ("--columns", args.columns),
                                ("--at", args.at), ("--frame", args.frame)) if v]  # fmt: skip
        if given:
            raise InputError(
                f"{' and '.join(given)} read one cloud; a traverse gives its frames' poses"
            )
        from rough_map.cli._traverse_features import run_traverse

        return run_traverse(args)
    return run_cloud(args)


def _load(args: argparse.Namespace) -> NDArray[np.float64]:
    """The cloud of ``features CLOUD``, in m, in the vehicle frame (``--at`` moves a
    world-frame one there: the patch ahead of a vehicle at that place and heading)."""
    import numpy as np

    from rough_map.io.pointcloud import read_cloud

    args.cloud_crs = None
    if args.source.suffix.lower() in (".las", ".laz") and args.columns is None:
        from rough_map.io.las import read_las

        las = read_las(args.source)  # once: its points and its CRS
        points = las.points
        args.cloud_crs = _crs_name(las.crs)
    else:
        points = read_cloud(args.source, columns=args.columns)
    if args.units != "m":
        if args.source.suffix.lower() in (".las", ".laz"):
            if args.cloud_crs is not None:
                raise InputError(
                    f"{args.source.name}: its CRS gives its units; --units is for clouds "
                    "without one"
                )
        points = points * UNITS[args.units]
    if args.at is not None:
        x, y, yaw = args.at
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = points[:, 0] - x, points[:, 1] - y
        z = points[:, 2] - np.median(points[:, 2])  # heights about the cloud's own level
        points = np.column_stack([c * dx + s * dy, -s * dx + c * dy, z])
    return points


def _crs_name(crs: Any) -> str | None:
    """A LAS file's CRS as a person names it: ``EPSG:32104``, or the name in its WKT."""
    if crs is None:
        return None
    if crs.epsg:
        return f"EPSG:{crs.epsg}"
    found = re.search(r'^\w+\["([^"]{1,60})"', crs.wkt or "")
    return found.group(1) if found else "its CRS"


def run_cloud(args: argparse.Namespace) -> int:
    from rough_map.features import cloud_roughness

    extraction = Extraction(
        patch=patch_spec(args),
        method=args.method,
        subtract_noise=not args.keep_noise,
        auto_spacing=args.spacing == "auto",
    )
    vehicle = chosen_vehicle(args)
    t0 = time.perf_counter()
    points = _load(args)
    t1 = time.perf_counter()
    tilt = args.roll is not None or args.pitch is not None
    try:
        grid, rough = cloud_roughness(
            points,
            extraction,
            roll=math.radians(args.roll or 0.0) if tilt else None,
            pitch=math.radians(args.pitch or 0.0) if tilt else None,
        )
    except InputError as err:
        if args.cloud_crs is None or " m: a world-frame cloud?" not in str(err):
            raise
        # a georeferenced file: say in which CRS its points lie, and that --at takes it
        text = str(err).replace(" m: a world-frame cloud?", f" m in {args.cloud_crs}:", 1)
        raise InputError(text) from None
    t2 = time.perf_counter()
    spec = grid.spec  # the step used (--spacing auto may have coarsened it)
    timing_ms = {"load": 1e3 * (t1 - t0), "process": 1e3 * (t2 - t1)}
    result = {
        "file": str(args.source),
        **rough.as_dict(),
        "n_points": int(len(points)),
        "n_points_patch": grid.n_points,
        "fill_fraction": grid.fill_fraction,
        "points_per_cell": grid.points_per_cell,
        "gridding": grid.gridding,
        "point_noise": grid.point_noise,
        "noise_psd": grid.noise_psd,
        "noise_subtracted": rough.noise_subtracted,
        "spacing": spec.spacing,
        "row_spacing": spec.row_step,
        "size": spec.n * spec.spacing,
        "ahead": spec.ahead,
        "band_rad_per_m": [float(rough.omega[0]), float(rough.omega[-1])],
        "tilt_compensated": args.roll is not None or args.pitch is not None,
        "timing_ms": timing_ms,
    }
    advice = None if vehicle is None else _speed_advice(vehicle, rough, args.speed)
    if advice is not None:
        result["speed_advice"] = advice
    if args.json:
        emit_json(result)
        return 0
    rows = _cloud_rows(args.source, len(points), grid, rough, timing_ms)
    if advice is not None:
        rows.append(["speed", _advice_text(advice)])
    print(table(rows))
    return 0


def _speed_advice(vehicle: Any, rough: PatchRoughness, speed: float | None) -> dict[str, Any]:
    """The vehicle's v_max over the patch and, at ``speed``, its responses, the band's
    temporal frequencies and the resonances outside them."""
    from rough_map.vehicle import SpeedTable

    speeds = SpeedTable(vehicle, (float(rough.omega[0]), float(rough.omega[-1])))
    out: dict[str, Any] = {
        "vehicle": vehicle.name,
        "top_speed_m_s": vehicle.limits.top_speed,
        "v_max_m_s": float(speeds.v_max(rough.R, rough.w)[0]),
        "v_max_95_m_s": float(speeds.v_max(rough.R, rough.w, rough.se_lnR, rough.se_w)[0]),
    }
    if speed is not None:
        r = speeds.response(rough.R, rough.w, speed)
        out["at_speed"] = {
            "speed_m_s": speed,
            "weighted_acceleration_m_s2": float(r.weighted_acceleration[0]),
            "suspension_travel_m": float(r.suspension_travel[0]),
            "dynamic_load_ratio": float(r.dynamic_load_ratio[0]),
            "band_hz": list(r.band_hz),
            "resonances_outside_band": r.outside,
        }
    return out


def _advice_text(advice: dict[str, Any]) -> str:
    text = (
        f"{advice['vehicle']}: v_max {advice['v_max_m_s']:.2f} m/s "
        f"({advice['v_max_95_m_s']:.2f} with 95 % confidence; top {advice['top_speed_m_s']:g})"
    )
    at = advice.get("at_speed")
    if at:
        lo, hi = at["band_hz"]
        outside = at["resonances_outside_band"]
        text += (
            f"; at {at['speed_m_s']:g} m/s: {at['weighted_acceleration_m_s2']:.3g} m/s² "
            f"weighted, travel {at['suspension_travel_m'] * 1e3:.3g} mm, load ratio "
            f"{at['dynamic_load_ratio']:.3g}; the band covers {lo:.3g}-{hi:.3g} Hz"
            + (f" ({' and '.join(outside)} mode outside it)" if outside else "")
        )
    return text


def _cloud_rows(
    source: Path, n_points: int, grid: GriddedPatch, rough: PatchRoughness, timing_ms: dict
) -> list[list[str]]:
    """The rows of ``rough-map features CLOUD``'s table."""
    spec = grid.spec
    return [
        ["cloud", f"{source} ({n_points:,} points, {grid.n_points:,} in the patch)"],
        [
            "patch",
            f"{spec.n * spec.spacing:.3f} m square, {spec.ahead:.3f} m ahead, "
            f"{_grid_text(spec)}, "
            f"{grid.fill_fraction:.0%} of cells filled, "
            f"{grid.points_per_cell:.1f} points per cell ({grid.gridding})",
        ],
        ["band", f"{rough.omega[0]:.2f} to {rough.omega[-1]:.1f} rad/m" + _reach(rough)],
        [
            "R",
            f"{rough.R:.3e} m³/rad  (sigma {rough.sigma_R:.2e}, se of ln R {rough.se_lnR:.2f})"
            f"  ISO {rough.iso_class}",
        ],
        ["w", f"{rough.w:.3f}  (sigma {rough.sigma_w:.3f}, se {rough.se_w:.3f})"],
        ["rms", f"{rough.rms * 1e3:.2f} mm"],
        [
            "in band",
            f"rms {rough.band_rms * 1e3:.2f} mm, PSD {rough.centre_psd:.3e} m³/rad at its "
            f"log centre {rough.omega_centre:.1f} rad/m (no extrapolation)",
        ],
        ["shape", _shape(rough)],
        ["lateral", _lateral(rough.lateral_scale)],
        ["profiles", f"{rough.n_profiles} used, {rough.n_dropped} dropped"],
        [
            "noise",
            f"{grid.point_noise * 1e3:.2f} mm per point -> floor "
            f"{grid.noise_psd:.2e} m³/rad" + (" (subtracted)" if rough.noise_subtracted else ""),
        ],
        ["method", rough.method],
        [
            "time",
            f"{timing_ms['process']:.1f} ms after loading ({timing_ms['load']:.1f} ms to load)",
        ],
    ]


def _grid_text(spec: PatchSpec) -> str:
    """The grid of the patch: its step, and its rows when they are wider than the step."""
    if spec.row_spacing is None:
        return f"{spec.spacing * 1e3:g} mm grid ({spec.n} x {spec.n})"
    return (
        f"{spec.spacing * 1e3:g} mm grid in rows {spec.row_step * 1e3:g} mm wide "
        f"({spec.rows} x {spec.n}: the ground is alike across the track)"
    )


def _reach(rough: PatchRoughness) -> str:
    """How far up the band the ground stays above the noise floor, if the noise ends it."""
    top = rough.omega_noise
    if not math.isfinite(top) or top >= rough.omega[rough.fit_mask][-1]:
        return ""
    if top == 0.0:
        return "; the noise floor has more power than the ground over the whole band"
    return f"; ground above the noise floor to {top:.1f} rad/m"


def _shape(rough: PatchRoughness) -> str:
    """Whether the fit is a power law over the band, and whether it describes the patch."""
    from rough_map.features import inconsistency

    if not rough.consistent:
        return "CHECK FAILED: " + inconsistency(rough)
    z = rough.curvature_z
    if not rough.power_law:
        bend = "falls ever faster" if z < 0 else "flattens"
        return (
            f"not a power law: the log PSD {bend} across the band (curvature z {z:+.1f}); "
            "R at 1 rad/m depends on the fit, compare the band's PSD"
        )
    return (
        f"power law over the band (curvature z {z:+.1f}, fit rms / band rms {rough.rms_ratio:.2f})"
    )


def _lateral(scale: float) -> str:
    """The lateral scale row: how alike neighbouring profiles are."""
    if not math.isfinite(scale):
        return "not read (the paper's method, or Welch segments)"
    return (
        f"scale {scale:.2f} (1: isotropic ground, 0: the same across the patch, up to 5: "
        "rougher across; corrected for in the cell means)"
    )
