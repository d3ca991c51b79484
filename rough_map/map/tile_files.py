"""The tiles of a :class:`~rough_map.map.tiles.TiledMap` on disk while the vehicle is away.

A tile goes to disk as the bounding box of its cells holding data (a cell holds data where a
sum is not zero; the latest times of :data:`LATEST` do not count) and only its layers that
hold any: three ``.npy`` arrays one after the other in one file (the window ``(row0, row1,
col0, col1)``, the layer names, and the layers' values stacked), written and read without
pickle and without the checksums and member headers of a zip. A layer or cell not in the
file is zero (a sum) or NaN (a latest time): the fill of every accumulator layer.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._files import write_error
from rough_map.map.grid import GridMap

__all__ = ["LATEST", "by_tile", "data_part", "read_tile", "used_window", "write_tile"]

#: Layers holding the latest time seen (fused by a maximum).
LATEST = ("last_seen", "far_last_seen")

#: ``(row0, row1, col0, col1)`` of a tile's cells.
Window = tuple[int, int, int, int]


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
