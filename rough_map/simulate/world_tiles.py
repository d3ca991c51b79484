"""Long simulated worlds, built in tiles as the rover drives (bounded memory).

A course up to :data:`WHOLE_LENGTH` m is built whole by
:func:`rough_map.simulate.world.build_world`. A longer one is built by :class:`WorldTiles`
in tiles of :data:`TILE_LENGTH` m, each like ``build_world`` over its own columns with its
own seed, joined over a cross-fade that keeps the variance (:func:`cross_fade`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import numpy as np

from rough_map.errors import InputError
from rough_map.simulate.world import (
    CLASS_NAMES,
    Defect,
    Segment,
    _add_defect,
    _blend_segments,
    _coarse_envelope,
    _envelope,
    _envelope_columns,
    column_classes,
)
from rough_map.types import HeightField

log = logging.getLogger(__name__)

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
