"""A route over a height raster: the drive a team plans over a survey, as a traverse.

:func:`read_route` reads the route, in the raster's CRS (m):

* a GeoJSON ``LineString`` (bare, as a ``Feature`` or the one line of a
  ``FeatureCollection``): a frame every ``every`` m along it from its first vertex, heading
  along the segment it is on;
* a CSV of poses with a header naming ``x`` and ``y`` (m), and optionally ``yaw`` (rad,
  anticlockwise from +x; default along the route to the next pose) and ``t`` (s, increasing).

Without times the vehicle drives at :data:`ROUTE_SPEED`. :func:`route_traverse` makes the
route a :class:`~rough_map.io.traverse.Traverse` whose frames have no sensor data: its
``surface`` names the raster, and each frame's patch is cut from it at the frame's pose
(:func:`rough_map.patch.surface.cut_patch`), so ``features``, ``map`` and ``report`` run on
it unchanged.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._bounded import clip
from rough_map._files import PathLike
from rough_map.config import Crs, FrameSpec, Pose, SurfaceSpec, TraverseSpec
from rough_map.errors import FileFormatError, InputError
from rough_map.io._check import check_readable
from rough_map.io.raster import open_height_raster, shared_height_raster
from rough_map.io.traverse import Traverse

__all__ = ["MAX_ROUTE_FRAMES", "ROUTE_SPEED", "read_route", "route_traverse"]

#: Speed in m/s of a route without times.
ROUTE_SPEED = 1.0
#: Most frames a route may make.
MAX_ROUTE_FRAMES = 1_000_000
#: Largest |x|, |y| (m) and |yaw| (rad) of a route: beyond any projected CRS.
MAX_COORDINATE = 1e9
#: Largest route file read, bytes.
_MAX_BYTES = 256 * 2**20
_EPSG = re.compile(r"EPSG:{1,2}(\d+)\s*$", re.I)


def read_route(path: PathLike, *, every: float = 0.448) -> NDArray[np.float64]:
    """The frames of a route: rows ``(t, x, y, yaw)`` in s, m, m, rad.

    Parameters
    ----------
    path : path
        ``.geojson``/``.json`` (a LineString) or ``.csv`` (poses).
    every : float
        Distance in m between the frames along a LineString (default half the paper's
        patch, as a survey's stride).

    Raises
    ------
    FileFormatError
        An unreadable file, or one without a route (naming the file and the field).
    InputError
        A bad ``every``.
    """
    path = Path(path)
    if not (math.isfinite(every) and every > 0):
        raise InputError(f"every must be a distance > 0 in m, got {every!r}")
    check_readable(path)
    if path.stat().st_size > _MAX_BYTES:
        raise FileFormatError(path, f"{path.stat().st_size} bytes: a route is at most {_MAX_BYTES}")
    text = _text(path)
    if path.suffix.lower() == ".csv":
        return _csv_poses(path, text)
    if path.suffix.lower() in (".geojson", ".json"):
        return _along(path, _line(path, text), every)
    raise FileFormatError(path, "a route is a .geojson LineString or a .csv of poses")


def route_crs(path: PathLike) -> str | None:
    """The ``EPSG:n`` a GeoJSON route names in its (pre-2016) ``crs`` member, else None."""
    try:
        data = json.loads(_text(Path(path)))
        name = data["crs"]["properties"]["name"]
    except (OSError, ValueError, KeyError, TypeError, FileFormatError):
        return None
    found = _EPSG.search(str(name))
    return f"EPSG:{found.group(1)}" if found else None


def route_traverse(
    raster: PathLike,
    route: PathLike,
    *,
    every: float = 0.448,
    spacing: float | None = None,
    origin: tuple[float, float] | None = None,
    crs: Any = None,
    allow_outside: Iterable[PathLike] = (),
) -> Traverse:
    """The traverse of a drive along ``route`` over ``raster`` (see the module docstring).

    Parameters
    ----------
    raster : path
        The height raster (:func:`rough_map.io.raster.open_height_raster`).
    route : path
        The route (:func:`read_route`), in the raster's CRS.
    every : float
        Distance in m between the frames along a LineString.
    spacing, origin, crs
        For a ``.npy`` raster: its cell size (m), north-west corner (m) and CRS.
    allow_outside : folders
        As :func:`rough_map.io.traverse.load_traverse`'s.

    Raises
    ------
    FileFormatError, InputError
        An unreadable raster or route, a route in another CRS than the raster's, or a
        raster not in metres.
    """
    raster, route = Path(raster), Path(route)
    if crs is None:  # the frames open the same raster: read (and grid) it once
        surface = shared_height_raster(raster, spacing, origin)
    else:
        surface = open_height_raster(raster, spacing=spacing, origin=origin or (0.0, 0.0), crs=crs)
    if surface.unit_m != 1.0:
        raise InputError(
            f"{raster.name}: a route needs a raster in metres, not in units of "
            f"{surface.unit_m:g} m; reproject it (gdalwarp -t_srs) to a metric CRS"
        )
    named = route_crs(route) if route.suffix.lower() != ".csv" else None
    if named is not None and surface.crs.code not in ("local", named):
        raise InputError(f"{route.name}: the route is in {named}, the raster in {surface.crs.code}")
    poses = read_route(route, every=every)
    frames = [
        FrameSpec(t=float(t), pose=Pose(x=float(x), y=float(y), yaw=float(yaw)))
        for t, x, y, yaw in poses
    ]
    spec = TraverseSpec(
        schema_version="1.0",
        name=route.stem,
        crs=surface.crs if surface.crs.code != "local" else Crs(code="local"),
        surface=SurfaceSpec(
            path=raster.name,
            spacing=spacing if raster.suffix.lower() == ".npy" else None,
            origin=origin if raster.suffix.lower() == ".npy" else None,
        ),
        metadata={"route": str(route), "surface": str(raster)},
        frames=frames,
    )
    return Traverse.from_spec(spec, raster.parent, allow_outside=allow_outside)


def _text(path: Path) -> str:
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FileFormatError(path, f"not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise FileFormatError(path, exc.strerror or str(exc)) from None


def _line(path: Path, text: str) -> NDArray[np.float64]:
    """The vertices (x, y) of the one LineString of a GeoJSON text."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise FileFormatError(path, f"not JSON: {clip(str(exc), 80)}") from None
    geometry = data
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        features = data.get("features")
        lines = [
            f.get("geometry")
            for f in features or ()
            if isinstance(f, dict)
            and isinstance(f.get("geometry"), dict)
            and f["geometry"].get("type") == "LineString"
        ]
        if len(lines) != 1:
            raise FileFormatError(path, f"features: a route is one LineString, found {len(lines)}")
        geometry = lines[0]
    elif isinstance(data, dict) and data.get("type") == "Feature":
        geometry = data.get("geometry")
    kind = geometry.get("type") if isinstance(geometry, dict) else type(geometry).__name__
    if kind != "LineString":
        raise FileFormatError(path, f"type: a route is a LineString, not {clip(str(kind), 40)}")
    coords = geometry.get("coordinates")
    if not isinstance(coords, list) or len(coords) < 2:
        raise FileFormatError(path, "coordinates: a LineString needs 2 or more positions")
    try:
        xy = np.array([[float(c[0]), float(c[1])] for c in coords], dtype=np.float64)
    except (TypeError, ValueError, IndexError, KeyError):
        raise FileFormatError(
            path, "coordinates: every position is [x, y] or [x, y, z] numbers"
        ) from None
    if not np.isfinite(xy).all():
        raise FileFormatError(path, "coordinates: NaN or infinite")
    if np.abs(xy).max() > MAX_COORDINATE:
        raise FileFormatError(path, f"coordinates: beyond {MAX_COORDINATE:g} m of the origin")
    return xy


def _along(path: Path, xy: NDArray[np.float64], every: float) -> NDArray[np.float64]:
    """Frames every ``every`` m along a polyline, heading along the segment they are on."""
    steps = np.diff(xy, axis=0)
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    keep = lengths > 0
    steps, lengths = steps[keep], lengths[keep]
    if not lengths.size:
        raise FileFormatError(path, "coordinates: the LineString has no length")
    ends = np.concatenate([[0.0], np.cumsum(lengths)])
    total = float(ends[-1])
    if total / every >= MAX_ROUTE_FRAMES:
        raise FileFormatError(
            path,
            f"coordinates: {total:.6g} m every {every:g} m is more than {MAX_ROUTE_FRAMES} "
            "frames; give a larger --every",
        )
    s = np.arange(math.floor(total / every + 1e-9) + 1) * every
    seg = np.clip(np.searchsorted(ends, s, side="right") - 1, 0, lengths.size - 1)
    start = xy[:-1][keep]
    frac = (s - ends[seg]) / lengths[seg]
    x = start[seg, 0] + frac * steps[seg, 0]
    y = start[seg, 1] + frac * steps[seg, 1]
    yaw = np.arctan2(steps[seg, 1], steps[seg, 0])
    return np.column_stack([s / ROUTE_SPEED, x, y, yaw])


def _csv_poses(path: Path, text: str) -> NDArray[np.float64]:
    """Rows (t, x, y, yaw) of a CSV of poses."""
    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        raise FileFormatError(path, "empty: a CSV of poses needs a header naming x and y")
    header = [h.strip().lower() for h in rows[0]]
    missing = [n for n in ("x", "y") if n not in header]
    if missing:
        raise FileFormatError(
            path, f"header: no column {', '.join(missing)} (it names {clip(','.join(header), 60)})"
        )
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not body:
        raise FileFormatError(path, "no poses under the header")
    if len(body) > MAX_ROUTE_FRAMES:
        raise FileFormatError(path, f"more than {MAX_ROUTE_FRAMES} poses")
    columns = {}
    for name in ("t", "x", "y", "yaw"):
        if name not in header:
            continue
        k = header.index(name)
        values = np.empty(len(body))
        for i, r in enumerate(body):
            try:
                values[i] = float(r[k])
            except (IndexError, ValueError):
                raise FileFormatError(path, f"line {i + 2}, column {name}: not a number") from None
        if not np.isfinite(values).all():
            bad = int(np.flatnonzero(~np.isfinite(values))[0])
            raise FileFormatError(path, f"line {bad + 2}, column {name}: NaN or infinite")
        if name != "t" and np.abs(values).max() > MAX_COORDINATE:
            bad = int(np.flatnonzero(np.abs(values) > MAX_COORDINATE)[0])
            raise FileFormatError(
                path, f"line {bad + 2}, column {name}: beyond {MAX_COORDINATE:g} (m or rad)"
            )
        columns[name] = values
    x, y = columns["x"], columns["y"]
    if "yaw" in columns:
        yaw = columns["yaw"]
    else:
        if len(x) < 2:
            raise FileFormatError(path, "one pose without yaw: give a yaw column (rad)")
        dx, dy = np.diff(x), np.diff(y)
        yaw = np.arctan2(dy, dx)
        yaw = np.append(yaw, yaw[-1])
    if "t" in columns:
        t = columns["t"]
        if len(t) > 1 and not (np.diff(t) > 0).all():
            bad = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise FileFormatError(path, f"line {bad + 2}, column t: time does not increase")
    else:
        step = np.hypot(np.diff(x), np.diff(y))
        if (step <= 0).any():
            bad = int(np.flatnonzero(step <= 0)[0]) + 1
            raise FileFormatError(path, f"line {bad + 2}: the pose repeats the one before")
        t = np.concatenate([[0.0], np.cumsum(step)]) / ROUTE_SPEED
    return np.column_stack([t, x, y, yaw])
