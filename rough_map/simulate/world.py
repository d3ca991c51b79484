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
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

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


# --------------------------------------------------------------------------- long worlds

#: Courses up to this long (m) are built in one piece by :func:`build_world`, bit for bit as
#: before long worlds were tiled (above every course's default length but ``random``'s).
WHOLE_LENGTH = 50.0
#: Length (m) of the tiles of a longer course (:class:`WorldTiles`). Building a tile peaks
#: at about 8 float64 copies of it (about 0.45 GB at 4 m wide and 2 mm).
TILE_LENGTH = 6.0
#: Half width (m) of the cross-fade where two tiles meet.
TILE_OVERLAP = 0.5


def is_tiled(segments: Sequence[Segment], whole_length: float = WHOLE_LENGTH) -> bool:
    """Whether a course is longer than ``whole_length`` m, so built by :class:`WorldTiles`."""
    return segments[-1].end - segments[0].start > whole_length


BlockSink = Callable[[int, np.ndarray, np.ndarray], None]
"""Receives each finished block of a :class:`WorldTiles`: its first column, its heights
(float32, m) and the class index of each of its columns."""


class WorldTiles:
    """A long world built tile by tile, read in windows that move along x.

    The world is the grid of :func:`build_world` for the same course (x from
    ``segments[0].start - lead`` to ``segments[-1].end + lead``, ``width`` m across), but
    its heights come from tiles of about ``tile_length`` m along x:

    * Tile ``k`` is built as :func:`build_world` builds a world (the course's surfaces
      blended where segments meet), over its own columns plus ``overlap`` m on either
      side, with its own random stream ``SeedSequence(seed, spawn_key=(k + 1,))``. The
      roughness envelope is one field over the whole world (its coarse grid, from
      ``SeedSequence(seed, spawn_key=(0,))``, is small), so it runs on across the tiles.
      A world of one tile is :func:`build_world`'s (its seed and envelope), in float32.
    * Where two tiles meet they overlap by ``2 * overlap`` m. There the heights are
      ``m + cos(a) (h0 - m0) + sin(a) (h1 - m1)``, ``a`` going from 0 to pi/2 across the
      overlap, ``m0`` and ``m1`` the mean of each tile over the overlap (per row) and ``m``
      going linearly from ``m0`` to ``m1``. The two tiles are independent, so the variance
      of the heights about their local level is the surface's at every point, and the
      spectrum of wavelengths shorter than the overlap is that of the surface across the
      join; the local level joins without a step. Wavelengths longer than a tile are
      missing (each tile is a periodic synthesis padded by 1 m, as a short segment of a
      world built whole: the 0.9 m patch's band is far shorter), and each tile draws its
      own structure (the period and angle of a ploughed tile's furrows, where a dirt
      road's ruts run, a concrete tile's joints).
    * Tile ends keep clear of the defects, so that each defect is carved whole into one
      tile (as :func:`build_world` carves it).

    Columns are finished in order: :meth:`window` builds the tiles it needs, and passes
    every finished block once to ``sink`` (e.g. a truth writer); :meth:`release` forgets
    the columns before a point, so that memory holds a few tiles whatever the length.
    The heights are float32.

    Parameters
    ----------
    segments, defects, width, spacing, seed, envelope_sigma, envelope_length, blend, lead
        As :func:`build_world`.
    tile_length : float
        Length of a tile in m (tiles are about as long; one is moved clear of a defect and
        the last takes the rest).
    overlap : float
        Half width in m of the cross-fade between tiles.
    sink : callable, optional
        ``sink(first_column, heights, column_classes)`` for every finished block.
    """

    def __init__(
        self,
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
        tile_length: float = TILE_LENGTH,
        overlap: float = TILE_OVERLAP,
        sink: BlockSink | None = None,
    ) -> None:
        if not segments:
            raise InputError("a world needs at least one segment")
        if not (math.isfinite(overlap) and overlap >= 0):
            raise InputError(f"overlap must be a length in m >= 0, got {overlap!r}")
        if not (math.isfinite(tile_length) and tile_length >= max(4 * overlap, 16 * spacing)):
            raise InputError(
                f"tile_length must be at least 4 overlaps and 16 cells "
                f"({max(4 * overlap, 16 * spacing):g} m), got {tile_length!r}"
            )
        self.segments = list(segments)
        self.defects = list(defects)
        self.spacing = spacing
        self.seed = seed
        self.envelope = (envelope_sigma, envelope_length)
        self.blend, self.lead = blend, lead
        self.sink = sink
        x0 = self.segments[0].start - lead
        x1 = self.segments[-1].end + lead
        nx = int(math.ceil((x1 - x0) / spacing)) + 1
        ny = int(math.ceil(width / spacing)) + 1
        self.shape = (ny, nx)
        self.origin = (x0, -0.5 * (ny - 1) * spacing)
        self.overlap = int(round(overlap / spacing))
        self._defect_tile: dict[int, list[Defect]] = {}
        self.edges = self._tile_edges(int(round(tile_length / spacing)))
        self._coarse: tuple[np.ndarray, int] | None = None
        if self.n_tiles > 1 and envelope_sigma > 0:
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,)))
            self._coarse = _coarse_envelope(self.shape, spacing, envelope_length, rng)
        for d in self.defects:
            j = int((d.x - x0) / spacing)
            k = int(np.searchsorted(self.edges, j, side="right")) - 1
            self._defect_tile.setdefault(min(max(k, 0), self.n_tiles - 1), []).append(d)
        self._next = 0  # next tile to build
        self._tail: np.ndarray | None = None  # the last tile past its finished columns
        self._blocks: list[tuple[int, np.ndarray]] = []  # finished columns kept
        self._done = 0  # columns finished
        self._released = 0  # columns before this one are forgotten

    @property
    def n_tiles(self) -> int:
        return len(self.edges) - 1

    def _tile_edges(self, step: int) -> list[int]:
        """First column of every tile, and the number of columns: tiles of ``step`` columns
        whose cross-fades keep two cells clear of every defect."""
        nx, ov = self.shape[1], self.overlap
        half = int(0.6 / self.spacing)  # the reach of _add_defect
        regions = []
        for d in self.defects:
            j = int((d.x - self.origin[0]) / self.spacing)
            regions.append((j - half - ov - 2, j + half + ov + 2))
        shortest = max(step // 2, 2 * ov, 8)
        edges = [0]
        while nx - edges[-1] >= step + shortest:
            cut = edges[-1] + step
            for lo, hi in sorted(regions):
                if lo < cut < hi:
                    cut = hi
            if nx - cut < shortest:
                break
            edges.append(cut)
        edges.append(nx)
        return edges

    def _x(self, c0: int, c1: int) -> np.ndarray:
        """World x in m of columns ``c0 <= c < c1``."""
        return self.origin[0] + self.spacing * np.arange(c0, c1)

    def _build(self, k: int) -> np.ndarray:
        """Heights (float32) of tile ``k`` over its columns and overlaps."""
        ny, nx = self.shape
        g0 = self.edges[k] - self.overlap if k > 0 else 0
        g1 = self.edges[k + 1] + self.overlap if k < self.n_tiles - 1 else nx
        xs = self._x(g0, g1)
        whole = self.n_tiles == 1
        seed = self.seed if whole else np.random.SeedSequence(self.seed, spawn_key=(k + 1,))
        rng = np.random.default_rng(seed)
        near = [
            seg
            for i, seg in enumerate(self.segments)
            if seg.start - (self.lead if i == 0 else self.blend) <= xs[-1]
            and seg.end + (self.lead if i == len(self.segments) - 1 else self.blend) >= xs[0]
        ]
        heights, _ = _blend_segments(
            near, xs, ny, self.spacing, rng, blend=self.blend, lead=self.lead
        )
        sigma, length = self.envelope
        if sigma > 0:
            if self._coarse is None:  # one tile: build_world's envelope
                env = _envelope((ny, xs.size), self.spacing, length, rng)
            else:  # the world's envelope, continuous across the tiles
                env = _envelope_columns(*self._coarse, ny, g0, g1)
            heights *= np.exp(0.5 * sigma * env)
            del env
        for d in self._defect_tile.get(k, []):
            _add_defect(heights, d, (float(xs[0]), self.origin[1]), self.spacing)
        return heights.astype(np.float32)

    def _build_next(self) -> None:
        """Build the next tile and finish its columns (up to the next cross-fade)."""
        k, ov = self._next, self.overlap
        raw = self._build(k)
        last = k == self.n_tiles - 1
        stop = raw.shape[1] if last else raw.shape[1] - 2 * ov  # the next cross-fade
        if k == 0:
            block = raw[:, :stop].copy()
            c0 = 0
        else:
            assert self._tail is not None
            fade = cross_fade(self._tail, raw[:, : 2 * ov])
            block = np.concatenate([fade, raw[:, 2 * ov : stop]], axis=1)
            c0 = self.edges[k] - ov
        self._tail = None if last else raw[:, stop:].copy()
        del raw
        self._next += 1
        self._done = c0 + block.shape[1]
        classes = column_classes(self.segments, self._x(c0, self._done))
        if self.sink is not None:
            self.sink(c0, block, classes)
        if self._done > self._released:
            self._blocks.append((c0, block))

    def columns(self, c0: int, c1: int, *, align: int = 1) -> HeightField:
        """The world's columns ``c0 <= c < c1`` (clipped to the world; ``c0`` rounded down
        to a multiple of ``align``) as a :class:`HeightField` of float32 heights whose
        class map is a read-only view.

        Raises
        ------
        InputError
            ``c0`` lies before the columns released.
        """
        nx = self.shape[1]
        c0 = max(0, min(c0, nx - 1))
        c0 -= c0 % max(1, align)
        c1 = max(c0 + 1, min(c1, nx))
        if c0 < self._released:
            raise InputError(
                f"columns from {c0} asked after those before {self._released} were released"
            )
        while self._done < c1:
            self._build_next()
        pieces = [
            block[:, max(c0, b0) - b0 : min(c1, b0 + block.shape[1]) - b0]
            for b0, block in self._blocks
            if b0 < c1 and b0 + block.shape[1] > c0
        ]
        heights = np.concatenate(pieces, axis=1) if len(pieces) > 1 else pieces[0].copy()
        classes = np.broadcast_to(
            column_classes(self.segments, self._x(c0, c1))[None, :], heights.shape
        )
        origin = (self.origin[0] + c0 * self.spacing, self.origin[1])
        return HeightField(heights, self.spacing, origin, classes, CLASS_NAMES)

    def window(self, x_lo: float, x_hi: float, *, align: int = 1) -> HeightField:
        """The columns covering world x from ``x_lo`` to ``x_hi`` m (see :meth:`columns`)."""
        c0 = int(math.floor((x_lo - self.origin[0]) / self.spacing))
        c1 = int(math.ceil((x_hi - self.origin[0]) / self.spacing)) + 1
        return self.columns(c0, c1, align=align)

    def release(self, x: float) -> None:
        """Forget the columns before world x (m); no later window may start before it."""
        nx = self.shape[1]
        c = int(math.floor((x - self.origin[0]) / self.spacing)) if x < math.inf else nx
        self._released = max(self._released, min(c, nx))
        self._blocks = [(b0, b) for b0, b in self._blocks if b0 + b.shape[1] > self._released]

    def finish(self) -> None:
        """Build the tiles not built yet (for the ``sink``), keeping none of them."""
        self.release(math.inf)
        while self._next < self.n_tiles:
            self._build_next()

    def whole(self) -> HeightField:
        """The whole world in one :class:`HeightField` (float32; for small worlds)."""
        world = self.columns(0, self.shape[1])
        assert world.classes is not None
        return HeightField(
            world.heights, world.spacing, world.origin, world.classes.copy(), CLASS_NAMES
        )


def cross_fade(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Join two independent height fields over the columns they share (float32).

    ``m + cos(t) (a - ma) + sin(t) (b - mb)`` with ``ma``, ``mb`` the mean of each row of
    ``a`` and ``b``, ``t`` from 0 (``a``) to pi/2 (``b``) across the columns and ``m``
    from ``ma`` to ``mb`` linearly: the variance about the level is kept at every column.
    """
    n = a.shape[1]
    if n == 0:
        return a.astype(np.float32)
    u = (np.arange(n) + 0.5) / n
    ma = a.mean(axis=1, dtype=np.float64, keepdims=True)
    mb = b.mean(axis=1, dtype=np.float64, keepdims=True)
    out = (1 - u) * ma + u * mb
    out += np.cos(0.5 * np.pi * u) * (a - ma)
    out += np.sin(0.5 * np.pi * u) * (b - mb)
    return out.astype(np.float32)


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
