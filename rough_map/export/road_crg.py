"""The surface measured along a traverse as an OpenCRG road (``map_road.crg``).

A vehicle simulator drives on a CRG file: heights on a ``(u, v)`` grid along a reference
line. :func:`write_road_crg` lays that line along the vehicle's path (the poses, every
``du`` m from the centre of the first pose's cell; curved, with a heading channel, unless
the path is straight) and fills the grid
from the map's ``elevation`` layer: each node takes the height of the map cell it falls in,
NaN where the map has none. The grid steps are the map's cell size; the long sections reach
as far to each side as the layer has heights (up to :data:`MAX_HALF_WIDTH`). The file is
KDBI (big-endian float64) holding the heights as ``map.tif`` stores them (float32), so
reading it back (:func:`rough_map.io.crg.read_crg`, its nodes placed by
:meth:`~rough_map.io.crg.CrgSurface.node_xy`) gives the GeoTIFF's elevation exactly.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map._files import PathLike
from rough_map.errors import InputError
from rough_map.io.crg import CrgSurface, write_crg
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = ["MAX_HALF_WIDTH", "write_road_crg"]

#: Farthest a long section lies from the path, m.
MAX_HALF_WIDTH = 10.0
#: Headings that differ by less than this (rad) make a straight reference line.
_STRAIGHT = 1e-9


def write_road_crg(
    grid: GridMap, x: ArrayLike, y: ArrayLike, out: PathLike, *, form: str = "KDBI"
) -> Path:
    """Write ``grid``'s elevation along the path ``(x, y)`` (m, in the map's frame) as an
    OpenCRG file ``out`` (see the module docstring).

    Raises
    ------
    InputError
        A map without an ``elevation`` layer, or a path shorter than one cell.
    """
    if "elevation" not in grid:
        raise InputError("the map has no elevation layer to write as a CRG road")
    du = grid.resolution
    line = _reference_line(np.asarray(x, dtype=float), np.asarray(y, dtype=float), du)
    u, phi, (x0, y0, phi0) = line
    # the line starts on the centre of the cell of the first pose (at most half a cell
    # away), so that a path along the map's rows or columns has every node on a cell
    # centre, none on a boundary between two cells
    r0, c0 = grid.geometry.cell_of(x0, y0)
    west, south = grid.geometry.origin
    start = (west + (int(c0) + 0.5) * du, south + (int(r0) + 0.5) * du, phi0)
    k = math.ceil(MAX_HALF_WIDTH / du)
    v = np.arange(-k, k + 1) * du
    straight = bool(np.ptp(phi) < _STRAIGHT)
    where = CrgSurface(
        Path(out), u, v, np.zeros((u.size, v.size)), None if straight else phi, start=start
    )
    # the heights as map.tif stores them (float32), so that the road and the GeoTIFF agree
    z = _sample(grid, *where.node_xy()).astype(np.float32).astype(np.float64)
    held = np.flatnonzero(np.isfinite(z).any(axis=0))
    if not held.size:
        raise InputError("the map has no elevation along the path")
    keep = slice(int(held[0]), int(held[-1]) + 1)
    path = write_crg(
        out,
        z[:, keep],
        du,
        v[keep],
        phi=None if straight else phi,
        form=form,
        start=start,
        comment=f"rough_map: map elevation along the path ({grid.crs.code})",
    )
    log.info(
        "%s: %d x %d nodes of %.3g m, %s reference line",
        path.name,
        u.size,
        int(held[-1] - held[0] + 1),
        du,
        "straight" if straight else "curved",
    )
    return path


def _reference_line(
    x: NDArray[np.float64], y: NDArray[np.float64], du: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], tuple[float, float, float]]:
    """``u`` every ``du`` m along the polyline ``(x, y)``, the heading there, and the
    line's start ``(x, y, phi)``."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    steps = np.hypot(np.diff(x), np.diff(y))
    moved = np.concatenate([[True], steps > 0])
    x, y = x[moved], y[moved]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    if s.size < 2 or s[-1] < du:
        raise InputError(f"the path is shorter than one map cell ({du:g} m): no CRG road")
    u = np.arange(math.floor(s[-1] / du + 1e-9) + 1) * du
    heading = np.unwrap(np.arctan2(np.diff(y), np.diff(x)))
    seg = np.clip(np.searchsorted(s, u, side="right") - 1, 0, heading.size - 1)
    phi = heading[seg]
    return u, phi, (float(x[0]), float(y[0]), float(phi[0]))


def _sample(grid: GridMap, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """The elevation of the map cell each point falls in; NaN off the map."""
    rows, cols = grid.geometry.cell_of(x, y)
    inside = grid.geometry.inside(rows, cols)
    z = np.full(x.shape, np.nan)
    z[inside] = grid["elevation"][rows[inside], cols[inside]]
    return z
