"""Terrain worlds laid out as the paper's experiments, and a rover driving over them.

A world is a :class:`~rough_map.types.HeightField` (x along the course, y across it) with a
class map. It is built from segments of the named surfaces of :mod:`rough_map.terrain`,
blended over ``blend`` metres where two segments meet, and modulated by a slowly varying
roughness envelope so that R drifts along a uniform stretch (about a factor 2 at 1 sigma,
as the paper's standard deviations show).

Courses (paper section 5.1):

* ``ploughed``: 42 m straight on ploughed soil;
* ``compact``: 22 m on compact soil;
* ``mixed``: concrete -> dirt road -> gravel, with a manhole on the concrete at 12 m;
* ``mixed-reverse``: the same surfaces from gravel to concrete;
* ``random``: a random sequence of all five surfaces in 8-25 m segments (training data).

A course up to :data:`WHOLE_LENGTH` (50 m) is built in one piece (:func:`build_world`); a
longer one in tiles of :data:`TILE_LENGTH` m, cross-faded where they meet and built as the
rover drives on (:class:`WorldTiles`), so that memory holds a few tiles whatever the length.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_map import terrain
from rough_map.errors import InputError
from rough_map.types import HeightField

log = logging.getLogger(__name__)

CLASS_NAMES: tuple[str, ...] = tuple(terrain.SURFACES)
COURSES = ("mixed", "mixed-reverse", "ploughed", "compact", "random")


@dataclass(frozen=True)
class Segment:
    """A stretch of one surface: ``surface`` from ``start`` to ``end`` m along x."""

    surface: str
    start: float
    end: float


@dataclass(frozen=True)
class Defect:
    """An isolated defect (manhole, pit, rock) centred at world (x, y) m."""

    kind: str
    x: float
    y: float


def course_layout(
    course: str, length: float | None = None, seed: int = 0
) -> tuple[list[Segment], list[Defect]]:
    """Segments and defects of a named course; ``length`` in m overrides the default."""
    if course not in COURSES:
        raise InputError(f"unknown course {course!r}; expected one of {COURSES}")
    if length is not None and not (math.isfinite(length) and length >= 2.0):
        raise InputError(f"length must be at least 2 m, got {length!r}")
    if course == "ploughed":
        total = length or 42.0
        return [Segment("ploughed_soil", 0.0, total)], []
    if course == "compact":
        total = length or 22.0
        return [Segment("compact_soil", 0.0, total)], []
    if course in ("mixed", "mixed-reverse"):
        total = length or 36.0
        third = total / 3
        names = ["concrete", "dirt_road", "gravel"]
        if course == "mixed-reverse":
            names = names[::-1]
        segs = [Segment(n, i * third, (i + 1) * third) for i, n in enumerate(names)]
        concrete = next(s for s in segs if s.surface == "concrete")
        # The paper's manhole sits about 12 m along the concrete pathway.
        at = concrete.start + min(12.0, 0.65 * (concrete.end - concrete.start))
        if course == "mixed-reverse":
            at = concrete.end - min(12.0, 0.65 * (concrete.end - concrete.start))
        return segs, [Defect("manhole", at, 0.0)]
    rng = np.random.default_rng(seed)
    total = length or 120.0
    segs = []
    x = 0.0
    previous = None
    while x < total:
        choices = [c for c in CLASS_NAMES if c != previous]
        name = str(rng.choice(choices))
        seg_len = float(rng.uniform(8.0, 25.0))
        end = min(total, x + seg_len)
        if total - end < 4.0:
            end = total
        segs.append(Segment(name, x, end))
        previous, x = name, end
    return segs, []


def build_world(
    segments: Sequence[Segment],
    defects: Sequence[Defect] = (),
    *,
    width: float = 4.0,
    spacing: float = 0.004,
    seed: int = 0,
    envelope_sigma: float = 0.5,
    envelope_length: float = 1.5,
    blend: float = 0.3,
    lead: float = 3.0,
) -> HeightField:
    """Build the world height field of a course.

    Parameters
    ----------
    segments : list of Segment
        Surfaces along x (m).
    defects : list of Defect
        Isolated defects.
    width : float
        Extent across the course in m (centred on y = 0).
    spacing : float
        Cell size in m; 4 mm keeps wavelengths down to the 8 mm patch grid's Nyquist.
    seed : int
        Seed of everything random.
    envelope_sigma : float
        Standard deviation of ln R along a uniform stretch (the roughness envelope).
    envelope_length : float
        Correlation length of the envelope in m.
    blend : float
        Width in m of the cross-fade between segments.
    lead : float
        Extra terrain in m before the start and after the end (the sensor looks ahead).

    Returns
    -------
    HeightField
        With ``classes`` indexing :data:`CLASS_NAMES`.
    """
    if not segments:
        raise InputError("a world needs at least one segment")
    rng = np.random.default_rng(seed)
    x0 = segments[0].start - lead
    x1 = segments[-1].end + lead
    nx = int(math.ceil((x1 - x0) / spacing)) + 1
    ny = int(math.ceil(width / spacing)) + 1
    xs = x0 + spacing * np.arange(nx)
    heights, class_idx = _blend_segments(segments, xs, ny, spacing, rng, blend=blend, lead=lead)
    if envelope_sigma > 0:
        env = _envelope((ny, nx), spacing, envelope_length, rng)
        heights *= np.exp(0.5 * envelope_sigma * env)
    origin = (x0, -0.5 * (ny - 1) * spacing)
    for d in defects:
        _add_defect(heights, d, origin, spacing)
    classes = np.broadcast_to(class_idx[None, :], (ny, nx)).copy()
    return HeightField(heights, spacing, origin, classes, CLASS_NAMES)


def _blend_segments(
    segments: Sequence[Segment],
    xs: np.ndarray,
    ny: int,
    spacing: float,
    rng: np.random.Generator,
    *,
    blend: float,
    lead: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Heights (ny, len(xs)) in m of the segments' surfaces, cross-faded over ``blend`` m
    where they meet, and the class index of each column (x ``xs`` in m)."""
    nx = xs.size
    x0 = xs[0]
    heights = np.zeros((ny, nx))
    weight_sum = np.zeros(nx)
    for k, seg in enumerate(segments):
        first, last = k == 0, k == len(segments) - 1
        lo = seg.start - (lead if first else blend)
        hi = seg.end + (lead if last else blend)
        j0 = max(0, int((lo - x0) / spacing))
        j1 = min(nx, int(math.ceil((hi - x0) / spacing)) + 1)
        # Generate on a padded, FFT-friendly extent so the segment is not periodic.
        n_cols = j1 - j0
        pad = int(1.0 / spacing)
        field = terrain.generate(seg.surface, (ny, n_cols + pad), spacing, seed=rng)[:, :n_cols]
        ramp = np.clip(
            np.minimum(xs[j0:j1] - (seg.start - blend), (seg.end + blend) - xs[j0:j1])
            / (2 * blend),
            0.0,
            1.0,
        )
        if first:
            ramp[xs[j0:j1] < seg.start] = 1.0
        if last:
            ramp[xs[j0:j1] > seg.end] = 1.0
        heights[:, j0:j1] += field * ramp[None, :]
        weight_sum[j0:j1] += ramp
    heights /= np.maximum(weight_sum, 1e-9)[None, :]
    return heights, column_classes(segments, xs)


def column_classes(segments: Sequence[Segment], xs: np.ndarray) -> np.ndarray:
    """Class index (into :data:`CLASS_NAMES`, int16) of the world columns at x ``xs`` (m):
    the segment each lies in; before the first segment the first, after the last the last."""
    class_idx = np.zeros(xs.size, dtype=np.int16)
    for k, seg in enumerate(segments):
        inside = (xs >= seg.start) & (xs < seg.end)
        if k == 0:
            inside |= xs < seg.start
        if k == len(segments) - 1:
            inside |= xs >= seg.end
        class_idx[inside] = CLASS_NAMES.index(terrain.surface_spec(seg.surface).name)
    return class_idx


def _add_defect(
    heights: np.ndarray, defect: Defect, origin: tuple[float, float], spacing: float
) -> None:
    """Carve ``defect`` into ``heights`` (in place; cell [0, 0] at world ``origin``, m)."""
    add = terrain.DEFECTS.get(defect.kind)
    if add is None:
        raise InputError(
            f"unknown defect {defect.kind!r}; expected one of {sorted(terrain.DEFECTS)}"
        )
    j = int((defect.x - origin[0]) / spacing)
    i = int((defect.y - origin[1]) / spacing)
    half = int(0.6 / spacing)
    sl = (slice(max(0, i - half), i + half), slice(max(0, j - half), j + half))
    local = heights[sl]
    cx = (j - sl[1].start) * spacing
    cy = (i - sl[0].start) * spacing
    heights[sl] = add(local, spacing, (cx, cy))


def _envelope(
    shape: tuple[int, int], spacing: float, length: float, rng: np.random.Generator
) -> np.ndarray:
    """Unit-variance smooth Gaussian field (correlation length ``length`` m)."""
    g, step = _coarse_envelope(shape, spacing, length, rng)
    return _envelope_columns(g, step, shape[0], 0, shape[1])


def _coarse_envelope(
    shape: tuple[int, int], spacing: float, length: float, rng: np.random.Generator
) -> tuple[np.ndarray, int]:
    """The coarse grid of :func:`_envelope` over a world of ``shape`` cells, and its step
    in cells (a few per correlation length)."""
    from scipy import ndimage  # here: every command's parser reads COURSES from this module

    step = max(1, int(length / 8 / spacing))
    coarse_shape = (shape[0] // step + 3, shape[1] // step + 3)
    g = ndimage.gaussian_filter(
        rng.standard_normal(coarse_shape), length / (step * spacing), mode="wrap"
    )
    g /= g.std() or 1.0
    return g, step


def _envelope_columns(g: np.ndarray, step: int, ny: int, c0: int, c1: int) -> np.ndarray:
    """The envelope of the coarse grid ``g`` (step ``step`` cells) at the columns
    ``c0 <= c < c1`` of a world of ``ny`` rows."""
    # Bilinear interpolation to the fine grid, one axis at a time (as
    # ndimage.map_coordinates(order=1) at the fine grid's points, at a fraction of the cost).
    i0, fc = _linear_index(np.arange(c0, c1), step, g.shape[1])
    along = g[:, i0] * (1.0 - fc) + g[:, i0 + 1] * fc
    r0, fr = _linear_index(np.arange(ny), step, g.shape[0])
    return along[r0] * (1.0 - fr)[:, None] + along[r0 + 1] * fr[:, None]


def _linear_index(idx: np.ndarray, step: int, n_coarse: int) -> tuple[np.ndarray, np.ndarray]:
    """Left coarse index and fraction of the fine positions ``idx / step``."""
    pos = idx / step
    i0 = np.minimum(np.floor(pos).astype(int), n_coarse - 2)
    return i0, pos - i0


# --------------------------------------------------------------------------- the rover


@dataclass(frozen=True)
class RoverGeometry:
    """Wheel layout of the rover (paper: 0.7 m long, 0.5 m wide), m."""

    wheelbase: float = 0.5
    track: float = 0.45
    wheel_radius: float = 0.1


def drive(
    world: HeightField,
    start: float,
    end: float,
    *,
    speed: float = 0.5,
    rate: float = 2.0,
    lateral_wander: float = 0.15,
    seed: int = 0,
    rover: RoverGeometry | None = None,
) -> np.ndarray:
    """Poses of a rover driving along x from ``start`` to ``end`` m.

    Roll and pitch follow the terrain under the four wheels (heights smoothed over the
    wheel's contact length). Returns rows ``(t, x, y, z, roll, pitch, yaw)`` (s, m, rad).
    :func:`drive_track` and :func:`attitude` are its two halves, for a world read in
    windows.
    """
    rover = rover or RoverGeometry()
    t, x, y, yaw = drive_track(
        start, end, speed=speed, rate=rate, lateral_wander=lateral_wander, seed=seed
    )
    y_reach = float(np.abs(y).max(initial=0.0))
    z, roll, pitch = attitude(world, x, y, yaw, rover=rover, y_reach=y_reach)
    return np.column_stack([t, x, y, z, roll, pitch, yaw])


def drive_track(
    start: float,
    end: float,
    *,
    speed: float = 0.5,
    rate: float = 2.0,
    lateral_wander: float = 0.15,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), x, y (m) and yaw (rad) of the drive of :func:`drive`: along x from
    ``start`` to ``end`` m at ``speed`` m/s, a pose every 1 / ``rate`` s, with a gentle
    lateral wander of amplitude ``lateral_wander`` m."""
    if not (speed > 0 and rate > 0):
        raise InputError(f"speed (m/s) and rate (Hz) must be positive, got {speed}, {rate}")
    rng = np.random.default_rng(seed)
    step = speed / rate
    n = int(math.floor((end - start) / step)) + 1
    t = np.arange(n) / rate
    x = start + step * np.arange(n)
    # Gentle lateral wander, as a remote-controlled drive along a straight line.
    phase = rng.uniform(0, 2 * np.pi)
    y = lateral_wander * np.sin(2 * np.pi * x / rng.uniform(15, 30) + phase)
    yaw = np.arctan(np.gradient(y, x)) if n > 1 else np.zeros(n)
    return t, x, y, yaw


def attitude_reach(rover: RoverGeometry, spacing: float) -> float:
    """Distance in m from the rover's centre within which :func:`attitude` reads the world
    (the wheels and the reach of the smoothing) on a world of cell ``spacing`` m."""
    sigma = max(1.0, rover.wheel_radius / 2 / spacing)
    return math.hypot(rover.wheelbase / 2, rover.track / 2) + (4 * sigma + 2) * spacing


def attitude(
    world: HeightField,
    x: np.ndarray,
    y: np.ndarray,
    yaw: np.ndarray,
    *,
    rover: RoverGeometry,
    y_reach: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height z (m), roll and pitch (rad) of the rover at (x, y, yaw) on ``world``: from the
    heights under its four wheels, smoothed over the wheel's contact length.

    ``y_reach`` (m, the largest ``|y|`` of the whole drive) fixes the band of rows
    smoothed, so that a window of the world (covering :func:`attitude_reach` around every
    pose) gives the values the whole world gives.
    """
    from scipy import ndimage  # see _coarse_envelope

    sigma = max(1.0, rover.wheel_radius / 2 / world.spacing)
    c, s = np.cos(yaw), np.sin(yaw)
    hw, ht = rover.wheelbase / 2, rover.track / 2
    # Smooth only the band of rows the wheels cross (plus the filter's reach): the same
    # values there as smoothing the whole world, which is mostly terrain the rover never
    # touches.
    reach = math.hypot(hw, ht) + y_reach + (4 * sigma + 2) * world.spacing
    r0 = max(0, int(math.floor((-reach - world.origin[1]) / world.spacing)))
    r1 = min(world.heights.shape[0], int(math.ceil((reach - world.origin[1]) / world.spacing)) + 1)
    smooth = HeightField(
        ndimage.gaussian_filter(world.heights[r0:r1], sigma),
        world.spacing,
        (world.origin[0], world.origin[1] + r0 * world.spacing),
    )
    wheels = {}
    for name, (dx, dy) in {
        "fl": (hw, ht),
        "fr": (hw, -ht),
        "rl": (-hw, ht),
        "rr": (-hw, -ht),
    }.items():
        wheels[name] = smooth.sample(x + c * dx - s * dy, y + s * dx + c * dy)
    front = 0.5 * (wheels["fl"] + wheels["fr"])
    rear = 0.5 * (wheels["rl"] + wheels["rr"])
    left = 0.5 * (wheels["fl"] + wheels["rl"])
    right = 0.5 * (wheels["fr"] + wheels["rr"])
    pitch = np.arctan2(rear - front, rover.wheelbase)  # nose down is positive
    roll = np.arctan2(left - right, rover.track)  # left side up is positive
    z = 0.25 * (front + rear + left + right)
    return z, roll, pitch
