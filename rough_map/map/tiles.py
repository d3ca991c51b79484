"""A map of any extent in bounded memory: square tiles on the cell lattice, spilled to disk.

:class:`TiledMap` holds the accumulator layers of :mod:`rough_map.map.layers` in tiles of
``tile_cells`` x ``tile_cells`` cells. Patches and height samples are fused into the tiles
they touch; :meth:`TiledMap.evict` writes the tiles far from the vehicle to a folder, and a
tile needed again is read back (left unchanged, it is not written again: see below).
:meth:`TiledMap.merged` puts their estimates (not their sums) into one
:class:`~rough_map.map.grid.GridMap`. Fusion only adds to sums (and ``last_seen`` is a
max), so the tiled map equals the one fused in one grid, bit for bit.

The sums themselves are the map's *state*: :meth:`TiledMap.save` writes them (tile by tile,
never all in memory) to one ``.npz`` file, and :meth:`TiledMap.add_saved` adds a saved state
into a map, which is how the maps of many traverses fuse into one (``rough-map batch``).

A tile on disk
--------------
A tile goes to disk as the bounding box of its cells holding data (a cell holds data where a
sum is not zero; the latest times of :data:`LATEST` do not count) and only its layers that
hold any: three ``.npy`` arrays one after the other in one file (the window ``(row0, row1,
col0, col1)``, the layer names, and the layers' values stacked), written and read without
pickle and without the checksums and member headers of a zip. A layer or cell not in the
file is zero (a sum) or NaN (a latest time): the fill of every accumulator layer.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import tempfile
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._files import PathLike, clean_dead_temp_dirs, write_error
from rough_map.config import Crs
from rough_map.errors import FileFormatError, InputError
from rough_map.map.fusion import add_vote_layers
from rough_map.map.grid import GridMap
from rough_map.map.grid_geometry import GridGeometry, lattice_patch_box, patch_bounds
from rough_map.map.layers import LEVEL_NAMES, init_layers, patch_sums, update_estimates
from rough_map.map.state import (
    HEIGHT_LAYERS,
    StateTile,
    add_elevation_layer,
    iter_state_tiles,
    jsonable_attrs,
    read_state_meta,
    write_state,
)
from rough_map.patch import PatchSpec

log = logging.getLogger(__name__)

__all__ = [
    "COUNTS",
    "LATEST",
    "TiledMap",
    "by_tile",
    "data_part",
    "is_accumulator",
    "read_tile",
    "used_window",
    "write_tile",
]

#: Value layers that are sums of observations (fused by addition).
COUNTS = ("count", "far_count")
#: Layers holding the latest time seen (fused by a maximum).
LATEST = ("last_seen", "far_last_seen")
#: ``(row0, row1, col0, col1)`` of a tile's cells.
Window = tuple[int, int, int, int]
#: Prefix of the temporary folder of a map's tiles, followed by the process id.
_SPILL_PREFIX = "rough_map_tiles_"


def is_accumulator(grid: GridMap, name: str) -> bool:
    """Whether layer ``name`` is a sum (or latest time) that fusion adds to."""
    return grid.info(name).kind == "internal" or name in COUNTS or name in LATEST


class TiledMap:
    """Fusion layers in lattice tiles, the far ones kept on disk.

    Parameters
    ----------
    resolution : float
        Cell size, m.
    class_names : sequence of str
        Terrain classes of the probabilities to come (empty: roughness layers only).
    crs : optional
        CRS of the world frame (:meth:`rough_map.config.Crs.from_any`).
    spec : PatchSpec, optional
        Patch geometry of the frames (default the paper's).
    tile_cells : int
        Side of a tile in cells.
    level_names : sequence of str
        Roughness level names, smoothest first.
    prior : float
        Dirichlet prior of the class probabilities.
    spill_dir : path, optional
        Folder for evicted tiles (default: a temporary folder, removed by :meth:`close`).
    frame_id : str
        ROS frame name of the map.
    """

    def __init__(
        self,
        resolution: float = 0.1,
        class_names: Sequence[str] = (),
        *,
        crs: Any = None,
        spec: PatchSpec | None = None,
        tile_cells: int = 128,
        level_names: Sequence[str] = LEVEL_NAMES,
        prior: float = 1.0,
        spill_dir: str | Path | None = None,
        frame_id: str = "map",
    ) -> None:
        if not (isinstance(tile_cells, int) and tile_cells >= 8):
            raise InputError(f"tile_cells must be a whole number >= 8, got {tile_cells!r}")
        self.geometry = GridGeometry(resolution, crs=Crs.from_any(crs), frame_id=frame_id)
        self.class_names = tuple(str(c) for c in class_names)
        self.level_names = tuple(level_names)
        self.prior = float(prior)
        self.spec = spec or PatchSpec()
        self.tile_cells = tile_cells
        self._tiles: dict[tuple[int, int], GridMap] = {}
        # tiles with a file on disk, and those in memory unchanged since read (not rewritten)
        self._spilled: set[tuple[int, int]] = set()
        self._clean: set[tuple[int, int]] = set()
        self.groups: tuple[str, ...] = ("near",)
        self._template: list[tuple[str, Any]] | None = None
        self._attrs: dict[str, Any] = {}
        self._boxes: dict[tuple[float, float, float], Any] = {}  # kept for a second fusion
        self._own_dir = spill_dir is None
        if spill_dir is None:  # those of killed runs
            clean_dead_temp_dirs(_SPILL_PREFIX)
        try:
            self._dir = Path(
                tempfile.mkdtemp(prefix=f"{_SPILL_PREFIX}{os.getpid()}_")
                if spill_dir is None
                else spill_dir
            )
            self._dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(spill_dir or tempfile.gettempdir(), exc) from None
        if self._own_dir:  # removed with the map, at the latest when Python exits
            self._cleanup = weakref.finalize(self, shutil.rmtree, self._dir, True)
        self.bounds: tuple[float, float, float, float] | None = None

    # -- tiles -------------------------------------------------------------------------

    @property
    def resolution(self) -> float:
        """Cell size, m."""
        return self.geometry.resolution

    @property
    def tile_size(self) -> float:
        """Side of a tile, m."""
        return self.tile_cells * self.resolution

    def keys(self) -> list[tuple[int, int]]:
        """``(tile_row, tile_col)`` of every tile holding data, in memory or on disk."""
        return sorted(set(self._tiles) | self._spilled)

    def in_memory(self) -> int:
        """Number of tiles held in memory."""
        return len(self._tiles)

    def _tile_geometry(self, key: tuple[int, int]) -> GridGeometry:
        side, n, g = self.tile_size, self.tile_cells, self.geometry
        return GridGeometry(g.resolution, (key[1] * side, key[0] * side), (n, n), g.crs, g.frame_id)

    def _blank(self, geometry: GridGeometry) -> GridMap:
        """A grid with the accumulator layers only (what fusion adds to); their list is
        worked out once (a scratch grid is made for every patch)."""
        if self._template is None:
            grid = GridMap(geometry)
            self._init_layers(grid)
            add_vote_layers(grid)
            grid.add_layer(HEIGHT_LAYERS[0], units="m", fill=0.0, kind="internal")
            grid.add_layer(HEIGHT_LAYERS[1], units="1", fill=0.0, kind="internal")
            for name in grid.layers:
                if not is_accumulator(grid, name):
                    grid.drop_layer(name)
            self._template = [(n, grid.info(n)) for n in grid.layers]
            self._attrs = dict(grid.attrs)
        grid = GridMap(geometry, attrs=self._attrs)
        grid.add_layers_as(self._template)
        return grid

    def _init_layers(self, grid: GridMap) -> None:
        init_layers(
            grid,
            self.class_names,
            level_names=self.level_names,
            prior=self.prior,
            groups=self.groups,
        )

    def tile(self, key: tuple[int, int], *, write: bool = True) -> GridMap:
        """The tile ``key``: from memory, read back from disk, or new. Without ``write``
        the caller must not change it (it then goes without being written again)."""
        grid = self._tiles.get(key)
        if grid is None:
            grid = self._blank(self._tile_geometry(key))
            if key in self._spilled:
                read_tile(self._path(key), grid)
                self._clean.add(key)
            self._tiles[key] = grid
        if write:
            self._clean.discard(key)
        return grid

    def add_group(self, group: str) -> None:
        """Hold the accumulators of another provenance group (``"far"``) too."""
        if group in self.groups:
            return
        self.groups = (*self.groups, group)
        self._template = None
        self._clean.clear()  # the tiles in memory change
        for tile in self._tiles.values():
            init_layers(tile, self.class_names, groups=(group,))
            for name in tile.layers:
                if not is_accumulator(tile, name):
                    tile.drop_layer(name)

    def _path(self, key: tuple[int, int]) -> Path:
        return self._dir / f"tile_{key[0]}_{key[1]}.tile"

    def _keys_over(self, bounds: tuple[float, float, float, float]) -> Iterator[tuple[int, int]]:
        side = self.tile_size
        c0, c1 = math.floor(bounds[0] / side), math.floor(bounds[2] / side)
        r0, r1 = math.floor(bounds[1] / side), math.floor(bounds[3] / side)
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                yield (r, c)

    def _grow(self, bounds: tuple[float, float, float, float]) -> None:
        if self.bounds is None:
            self.bounds = bounds
        else:
            b = self.bounds
            self.bounds = (
                min(b[0], bounds[0]),
                min(b[1], bounds[1]),
                max(b[2], bounds[2]),
                max(b[3], bounds[3]),
            )

    # -- fusion ------------------------------------------------------------------------

    def add_frame(
        self,
        x: float,
        y: float,
        yaw: float,
        observation: dict[str, Any] | None = None,
        heights: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[Any], NDArray[Any]]
        | None = None,
        *,
        keep_box: bool = False,
        window: float = math.inf,
        margin: float | None = None,
    ) -> tuple[int, GridMap | None]:
        """Add one frame seen from pose ``(x, y)`` (m), ``yaw`` (rad).

        The map covers the frame's patch, fused or not (:meth:`merged` includes it). The
        patch's ``observation`` (as :func:`rough_map.map.fusion.fuse_patch`: ``t``,
        ``probs``, ``level``, ``count`` and the observed fields; None: none, an invalid
        patch) is fused into the tiles it covers, each cell getting the patch's sums
        (:func:`~rough_map.map.layers.patch_sums`). Its height sample ``(rows, cols, sums,
        counts)`` is added (:meth:`add_heights`). Then the tiles farther than ``window`` m
        go to disk (:meth:`evict`). ``keep_box``: keep this pose's cells for the next fusion
        at it, which takes them (a traverse's classes come in a second pass).

        Returns how many cells the patch covered, and, given ``margin`` (m), the map over
        the patch's box plus ``margin`` as it now stands (None without an observation).

        Raises
        ------
        InputError
            An observation at a pose that is not finite.
        """
        pose_ok = all(math.isfinite(v) for v in (x, y, yaw))
        if observation is not None and not pose_ok:
            raise InputError(f"pose must be finite (x, y in m, yaw in rad), got {(x, y, yaw)}")
        box = self._boxes.pop((x, y, yaw), None) if observation is not None else None
        if observation is not None and box is None:
            box = lattice_patch_box(x, y, yaw, self.spec, self.resolution)
        bounds = box[0] if box is not None else patch_bounds(x, y, yaw, self.spec)
        if pose_ok:
            self._grow(bounds)
        touched, area = 0, None
        if observation is not None and box is not None:
            if keep_box:
                self._boxes[(x, y, yaw)] = box
            _, r0, c0, inside = box
            sums = patch_sums(self.class_names, self.level_names, **observation)
            t = observation.get("t", math.nan)
            if inside.size and (sums or math.isfinite(t)):
                self._add_cells(r0, c0, inside, sums, t)
            touched = int(np.count_nonzero(inside))
        if heights is not None:
            self.add_heights(*heights)
        if observation is not None and margin is not None:
            xmin, ymin, xmax, ymax = bounds
            area = self.window((xmin - margin, ymin - margin, xmax + margin, ymax + margin))
        if pose_ok:
            self.evict(x, y, window)
        return touched, area

    def _add_cells(
        self,
        r0: int,
        c0: int,
        inside: NDArray[np.bool_],
        sums: Sequence[tuple[str, float]],
        t: float,
    ) -> None:
        """Add ``value`` to layer ``name`` for each ``(name, value)`` of ``sums``, and make
        ``last_seen`` at least ``t`` (s; NaN: unchanged), in the cells of a box on the
        lattice (its first cell ``(r0, c0)``) where ``inside``, tile by tile."""
        n = self.tile_cells
        height, width = inside.shape
        for tr in range(r0 // n, (r0 + height - 1) // n + 1):
            rs = max(r0, tr * n)
            rows = slice(rs - r0, min(r0 + height, (tr + 1) * n) - r0)
            for tc in range(c0 // n, (c0 + width - 1) // n + 1):
                cs = max(c0, tc * n)
                ii, jj = np.nonzero(inside[rows, cs - c0 : min(c0 + width, (tc + 1) * n) - c0])
                if ii.size == 0:
                    continue
                cells = (ii + (rs - tr * n)) * n + (jj + (cs - tc * n))  # in the flat tile
                tile = self.tile((tr, tc))
                tile.add_at(cells, sums)
                if math.isfinite(t) and "last_seen" in tile:
                    seen = tile["last_seen"].reshape(-1)
                    seen[cells] = np.fmax(seen[cells], t)

    def add_layers_from(self, part: GridMap, names: Sequence[str]) -> None:
        """Add layers ``names`` of a lattice-aligned grid (sums; latest times by maximum)
        into the tiles, e.g. the far-field accumulators fused into a merged map; the map
        grows to cover the cells where they hold data."""
        used = np.zeros(part.shape, dtype=bool)
        for name in names:
            if name not in LATEST:
                used |= part[name] != 0
        if used.any():
            rows, cols = np.flatnonzero(used.any(axis=1)), np.flatnonzero(used.any(axis=0))
            res, (x0, y0) = self.resolution, part.geometry.origin
            self._grow(
                (
                    x0 + cols[0] * res,
                    y0 + rows[0] * res,
                    x0 + (cols[-1] + 1) * res,
                    y0 + (rows[-1] + 1) * res,
                )
            )
        self._add_grid(part, names)

    def _add_grid(self, part: GridMap, names: Sequence[str] | None = None) -> None:
        """Add a lattice-aligned grid of accumulators into the tiles it overlaps."""
        n = self.tile_cells
        pr0 = round(part.geometry.origin[1] / self.resolution)
        pc0 = round(part.geometry.origin[0] / self.resolution)
        rows, cols = part.shape
        for tr in range(pr0 // n, (pr0 + rows - 1) // n + 1):
            for tc in range(pc0 // n, (pc0 + cols - 1) // n + 1):
                tile = self.tile((tr, tc))
                r0, r1 = max(pr0, tr * n), min(pr0 + rows, (tr + 1) * n)
                c0, c1 = max(pc0, tc * n), min(pc0 + cols, (tc + 1) * n)
                dst = (slice(r0 - tr * n, r1 - tr * n), slice(c0 - tc * n, c1 - tc * n))
                src = (slice(r0 - pr0, r1 - pr0), slice(c0 - pc0, c1 - pc0))
                for name in part.layers if names is None else names:
                    if name not in tile:
                        continue
                    if name in LATEST:
                        np.fmax(tile[name][dst], part[name][src], out=tile[name][dst])
                    else:
                        tile[name][dst] += part[name][src]

    def add_heights(
        self,
        rows: NDArray[np.int64],
        cols: NDArray[np.int64],
        sums: NDArray[np.float64],
        counts: NDArray[np.float64],
    ) -> None:
        """Add height sums (m) and point counts per lattice cell (a frame's
        :class:`~rough_map.features.HeightSample` at this map's resolution)."""
        if rows.size == 0:
            return
        for key, sel, r, c in by_tile(rows, cols, self.tile_cells):
            tile = self.tile(key)
            np.add.at(tile[HEIGHT_LAYERS[0]], (r, c), sums[sel])
            np.add.at(tile[HEIGHT_LAYERS[1]], (r, c), counts[sel])

    def evict(self, x: float, y: float, radius: float) -> int:
        """Write to disk, and forget, the tiles whose centre is farther than ``radius`` m
        (plus half a tile diagonal) from ``(x, y)``; returns how many."""
        side = self.tile_size
        reach = radius + side * math.sqrt(0.5)
        far = [
            k
            for k in self._tiles
            if math.hypot((k[1] + 0.5) * side - x, (k[0] + 0.5) * side - y) > reach
        ]
        for key in far:
            self._spill(key, self._tiles.pop(key))
        if far:
            log.debug(
                "%d tile(s) written to %s, %d in memory", len(far), self._dir, len(self._tiles)
            )
        return len(far)

    def _spill(self, key: tuple[int, int], grid: GridMap) -> None:
        """Write the tile's cells that hold data (their bounding box) to disk, unless its
        file holds it already."""
        if key in self._clean:
            self._clean.discard(key)
            return
        if write_tile(self._path(key), grid):
            self._spilled.add(key)
        elif key in self._spilled:  # (sums only grow: a tile on disk never empties)
            self._path(key).unlink(missing_ok=True)
            self._spilled.discard(key)

    # -- the state on disk ------------------------------------------------------------

    def save(self, path: PathLike, attrs: dict[str, Any] | None = None) -> Path:
        """Write the sums of every tile (the part holding data) to one state file
        (:mod:`rough_map.map.state`), atomically, one tile in memory at a time."""

        def tiles() -> Iterator[StateTile]:
            for key in self.keys():
                tile = self.tile(key, write=False)
                window = used_window(tile)
                arrays = {}
                if window is not None:
                    r0, r1, c0, c1 = window
                    arrays = {n: np.ascontiguousarray(tile[n][r0:r1, c0:c1]) for n in tile.layers}
                self._spill(key, self._tiles.pop(key))
                if window is not None:
                    yield key, window, arrays

        meta = self._meta(attrs)
        return write_state(path, meta, tiles())

    def _meta(self, attrs: dict[str, Any] | None) -> dict[str, Any]:
        return {
            "resolution": self.resolution,
            "tile_cells": self.tile_cells,
            "crs": self.geometry.crs.model_dump(mode="json"),
            "frame_id": self.geometry.frame_id,
            "class_names": list(self.class_names),
            "level_names": list(self.level_names),
            "prior": self.prior,
            "groups": list(self.groups),
            "bounds": None if self.bounds is None else [float(v) for v in self.bounds],
            "spec": {
                "ahead": self.spec.ahead,
                "size": self.spec.size,
                "lateral": self.spec.lateral,
            },
            "attrs": jsonable_attrs(attrs or {}),
        }

    @classmethod
    def open_saved(cls, path: PathLike, spill_dir: str | Path | None = None) -> TiledMap:
        """An empty map with the settings of a saved state (to add it, and others, to)."""
        meta = read_state_meta(path)
        try:
            return cls(
                float(meta["resolution"]),
                tuple(meta["class_names"]),
                crs=Crs.model_validate(meta["crs"]),
                spec=PatchSpec(**meta["spec"]),
                tile_cells=int(meta["tile_cells"]),
                level_names=tuple(meta["level_names"]),
                prior=float(meta["prior"]),
                spill_dir=spill_dir,
                frame_id=str(meta["frame_id"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FileFormatError(Path(path), f"meta.json: {exc}") from None

    def add_saved(self, path: PathLike) -> dict[str, Any]:
        """Add a state written by :meth:`save` (same lattice, CRS and classes) into this
        map, one tile in memory at a time; returns the ``attrs`` saved with it.

        Raises
        ------
        FileFormatError
            Not a state file, or an unreadable one.
        InputError
            A state of another cell size, tile size, CRS or class list.
        """
        meta = read_state_meta(path)
        try:
            theirs = (
                float(meta["resolution"]),
                int(meta["tile_cells"]),
                tuple(meta["class_names"]),
                tuple(meta["level_names"]),
            )
            crs = Crs.model_validate(meta["crs"])
            groups = [str(g) for g in meta["groups"]]
            bounds = meta["bounds"]
        except (KeyError, TypeError, ValueError) as exc:
            raise FileFormatError(Path(path), f"meta.json: {exc}") from None
        mine = (self.resolution, self.tile_cells, self.class_names, self.level_names)
        if mine != theirs or crs != self.geometry.crs:
            raise InputError(
                f"{path}: a map of {theirs[0]} m cells, {theirs[1]}-cell tiles, CRS "
                f"{crs.code}, classes {list(theirs[2])}; this one has {mine[0]} m, "
                f"{mine[1]}, {self.geometry.crs.code}, {list(mine[2])}"
            )
        for group in groups:
            self.add_group(group)
        if bounds is not None:
            b = [float(v) for v in bounds]
            self._grow((b[0], b[1], b[2], b[3]))
        for key, (r0, r1, c0, c1), arrays in iter_state_tiles(path, self.tile_cells):
            tile = self.tile(key)
            win = (slice(r0, r1), slice(c0, c1))
            for name, values in arrays.items():
                if name not in tile:
                    continue
                if name in LATEST:
                    tile[name][win] = np.fmax(tile[name][win], values)
                else:
                    tile[name][win] += values
            self._spill(key, self._tiles.pop(key))
        return dict(meta.get("attrs") or {})

    # -- the whole map -----------------------------------------------------------------

    def window(self, bounds: tuple[float, float, float, float]) -> GridMap:
        """The map over ``bounds`` (xmin, ymin, xmax, ymax in m) as it now stands, with its
        estimate layers and ``elevation``; the tiles are left as they are."""
        geo = GridGeometry.covering(
            bounds, self.resolution, crs=self.geometry.crs, frame_id=self.geometry.frame_id
        )
        part = self._blank(geo)  # the sums over the window, then its estimates
        r_off = round(geo.origin[1] / self.resolution)
        c_off = round(geo.origin[0] / self.resolution)
        n = self.tile_cells
        for key in self._keys_over(geo.bounds):
            if key in self._tiles or key in self._spilled:
                tile = self.tile(key, write=False)
                self._place(part, tile, key[0] * n - r_off, key[1] * n - c_off)
        return self._estimates(part)

    def merged(self, margin: float = 1.0, attrs: dict[str, Any] | None = None) -> GridMap:
        """One :class:`GridMap` covering every fused patch plus ``margin`` m, with the
        estimate layers and ``elevation`` (m, mean world z of the points per cell); the
        sums stay in the tiles (:meth:`save`). Tiles go to disk as they are placed, so
        memory holds the estimates and one tile."""
        b = self.bounds or (0.0, 0.0, 0.0, 0.0)
        geo = GridGeometry.covering(
            b,
            self.resolution,
            margin=margin,
            crs=self.geometry.crs,
            frame_id=self.geometry.frame_id,
        )
        return self._assemble(geo, attrs, consume=True)

    def _assemble(
        self, geo: GridGeometry, attrs: dict[str, Any] | None, *, consume: bool
    ) -> GridMap:
        """The estimate layers over ``geo``, computed tile by tile (the sums stay in the
        tiles; with ``consume`` each tile goes back to disk once placed)."""
        # the estimate layers only (a cell's worth of layers tells which, in which order)
        cell = GridMap(replace(geo, shape=(1, 1)), attrs=attrs)
        self._init_layers(cell)
        grid = GridMap(geo, attrs=cell.attrs)
        for name in cell.layers:
            if cell.info(name).kind != "internal":
                grid.add_layer_as(name, cell.info(name))
        r_off = round(geo.origin[1] / self.resolution)
        c_off = round(geo.origin[0] / self.resolution)
        n = self.tile_cells
        keys = [k for k in self._keys_over(geo.bounds) if k in self._tiles or k in self._spilled]
        for key in keys:
            tile = self.tile(key, write=False)
            found = data_part(tile)  # outside it, the estimates are the grid's fill
            if found is not None:
                r0, c0, part = found
                estimates = self._estimates(part)
                self._place(grid, estimates, key[0] * n - r_off + r0, key[1] * n - c_off + c0)
            if consume:
                self._spill(key, self._tiles.pop(key))
        if "elevation" not in grid:
            grid.add_layer("elevation", units="m", description="mean terrain height (world z)")
        return grid

    def _estimates(self, tile: GridMap) -> GridMap:
        """The estimate layers of one tile (a new grid, whose value layers among the
        tile's accumulators, ``count`` and ``last_seen``, are the tile's arrays: read only;
        the tile is left as it is)."""
        est = tile.shallow_copy()
        self._init_layers(est)
        update_estimates(est)
        add_elevation_layer(est)
        for name in est.layers:
            if est.info(name).kind == "internal":
                est.drop_layer(name)
        return est

    @staticmethod
    def _place(grid: GridMap, tile: GridMap, r0: int, c0: int) -> None:
        """Copy the part of ``tile`` (whose cell [0, 0] is the grid's [r0, c0]) inside the grid."""
        rows, cols = grid.shape
        gr0, gc0 = max(r0, 0), max(c0, 0)
        gr1, gc1 = min(r0 + tile.shape[0], rows), min(c0 + tile.shape[1], cols)
        if gr0 >= gr1 or gc0 >= gc1:
            return
        dst = (slice(gr0, gr1), slice(gc0, gc1))
        src = (slice(gr0 - r0, gr1 - r0), slice(gc0 - c0, gc1 - c0))
        for name in tile.layers:
            if name not in grid:
                grid.add_layer_as(name, tile.info(name))
            grid[name][dst] = tile[name][src]

    def close(self) -> None:
        """Remove the tiles written to disk (and the temporary folder)."""
        for key in list(self._spilled):
            self._path(key).unlink(missing_ok=True)
        self._spilled.clear()
        self._tiles.clear()
        self._boxes.clear()
        if self._own_dir:
            shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> TiledMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- a tile on disk ----------------------------------------------------------------------
def by_tile(
    rows: NDArray[np.int64], cols: NDArray[np.int64], n: int
) -> list[tuple[tuple[int, int], Any, NDArray[np.int64], NDArray[np.int64]]]:
    """Lattice cells ``(rows, cols)`` (not empty) by the tile of ``n`` x ``n`` cells holding
    them: ``(tile key, which of the cells, their rows in the tile, their cols)``, tiles in
    order, cells in their order."""
    tr, tc = rows // n, cols // n
    r0, r1, c0, c1 = int(tr.min()), int(tr.max()), int(tc.min()), int(tc.max())
    if r0 == r1 and c0 == c1:  # most patches: one tile
        return [((r0, c0), slice(None), rows - r0 * n, cols - c0 * n)]
    if (r1 - r0 + 1) * (c1 - c0 + 1) <= 4:  # a patch at a corner of tiles
        keys = [(r, c) for r in range(r0, r1 + 1) for c in range(c0, c1 + 1)]
    else:  # cells strewn widely (a cloud's heights): only the tiles holding some
        keys = sorted(set(zip(tr.tolist(), tc.tolist(), strict=True)))
    out = []
    for key in keys:
        sel = (tr == key[0]) & (tc == key[1])
        if sel.any():
            out.append((key, sel, rows[sel] - key[0] * n, cols[sel] - key[1] * n))
    return out


def _used(grid: GridMap) -> tuple[NDArray[np.bool_] | None, list[str]]:
    """The cells holding data (None: none) and the layers that hold any, in the grid's
    order (the latest times always)."""
    used: NDArray[np.bool_] | None = None
    names = []
    for name in grid.layers:
        if name in LATEST:
            names.append(name)
            continue
        nonzero = grid[name] != 0
        if nonzero.any():
            names.append(name)
            if used is None:
                used = nonzero
            else:
                used |= nonzero
    return used, names


def _window(used: NDArray[np.bool_]) -> Window:
    rows, cols = np.flatnonzero(used.any(axis=1)), np.flatnonzero(used.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def used_window(grid: GridMap) -> Window | None:
    """The bounding box of the tile's cells holding data (None: no cell does)."""
    used, _ = _used(grid)
    return None if used is None else _window(used)


def data_part(grid: GridMap) -> tuple[int, int, GridMap] | None:
    """The tile's cells holding data or a latest time, as a grid of their bounding box (a
    copy), with the tile's (row, col) of its first cell; None when no cell does. Outside
    the box every estimate of the tile is unknown (NaN, a count of 0)."""
    used, _ = _used(grid)
    for name in LATEST:
        if name in grid:
            seen = np.isfinite(grid[name])
            used = seen if used is None else used | seen
    if used is None or not used.any():
        return None
    r0, r1, c0, c1 = _window(used)
    geo, res = grid.geometry, grid.resolution
    origin = (geo.origin[0] + c0 * res, geo.origin[1] + r0 * res)
    part = GridMap(replace(geo, origin=origin, shape=(r1 - r0, c1 - c0)), attrs=grid.attrs)
    for name in grid.layers:
        part.add_layer_as(name, grid.info(name), grid[name][r0:r1, c0:c1])
    return r0, c0, part


def write_tile(path: Path, grid: GridMap) -> bool:
    """Write the tile's cells and layers holding data to ``path``; False (and nothing
    written) when it holds none.

    Raises
    ------
    FileFormatError
        The file could not be written (a full or read-only temporary folder).
    """
    used, names = _used(grid)
    if used is None:
        return False
    r0, r1, c0, c1 = _window(used)
    stack = np.empty((len(names), r1 - r0, c1 - c0), dtype=np.float64)
    for i, name in enumerate(names):
        stack[i] = grid[name][r0:r1, c0:c1]
    try:
        with open(path, "wb") as fh:
            np.save(fh, np.array([r0, r1, c0, c1], dtype=np.int64))
            np.save(fh, np.array(names, dtype=np.str_))
            np.save(fh, stack)
    except OSError as exc:
        path.unlink(missing_ok=True)
        raise write_error(path, exc) from None
    return True


def read_tile(path: Path, grid: GridMap) -> None:
    """Put a tile written by :func:`write_tile` into ``grid`` (a blank tile: accumulators
    at their fill), the layers it has."""
    with open(path, "rb") as fh:
        window = np.load(fh)
        names = np.load(fh)
        stack = np.load(fh)
    r0, r1, c0, c1 = (int(v) for v in window)
    for name, values in zip(names.tolist(), stack, strict=True):
        if name in grid:
            grid[name][r0:r1, c0:c1] = values
