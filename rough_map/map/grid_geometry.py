"""Where a grid map lies in the world: :class:`GridGeometry` (cell size, origin, shape, CRS).

The conventions (world frame, south-west origin on the cell lattice, rows northwards,
columns eastwards) are those of :mod:`rough_map.map.grid`.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.config import Crs
from rough_map.errors import InputError
from rough_map.patch import PatchSpec

if TYPE_CHECKING:
    from rasterio.transform import Affine

__all__ = ["GridGeometry", "check_map_memory", "memory_budget"]


@dataclass(frozen=True)
class GridGeometry:
    """Where a grid map lies in the world (see the module docstring for conventions).

    Attributes
    ----------
    resolution : float
        Side of a cell in m.
    origin : tuple of float
        World (x, y) in m of the south-west corner of the map (lower-left corner of cell
        ``[0, 0]``).
    shape : tuple of int
        ``(n_rows, n_cols)``: rows along +y (north), columns along +x (east).
    crs : Crs
        What the world frame is.
    frame_id : str
        Name of the world frame for ROS (``header.frame_id`` of a grid_map message).
    """

    resolution: float
    origin: tuple[float, float] = (0.0, 0.0)
    shape: tuple[int, int] = (1, 1)
    crs: Crs = field(default_factory=lambda: Crs(code="local"))
    frame_id: str = "map"

    def __post_init__(self) -> None:
        r = self.resolution
        if not (isinstance(r, int | float) and math.isfinite(r) and r > 0):
            raise InputError(f"resolution must be a positive cell size in m, got {r!r}")
        object.__setattr__(self, "resolution", float(r))
        ox, oy = (float(v) for v in self.origin)
        if not (math.isfinite(ox) and math.isfinite(oy)):
            raise InputError(f"origin must be finite (x, y) in m, got {self.origin!r}")
        object.__setattr__(self, "origin", (ox, oy))
        rows, cols = (int(v) for v in self.shape)
        if rows < 0 or cols < 0:
            raise InputError(f"shape must be (n_rows, n_cols) >= 0, got {self.shape!r}")
        object.__setattr__(self, "shape", (rows, cols))
        object.__setattr__(self, "crs", Crs.from_any(self.crs))

    @classmethod
    def covering(
        cls,
        bounds: tuple[float, float, float, float],
        resolution: float,
        *,
        margin: float = 0.0,
        crs: Any = None,
        frame_id: str = "map",
    ) -> GridGeometry:
        """The smallest lattice-aligned geometry covering ``bounds`` grown by ``margin``.

        Parameters
        ----------
        bounds : tuple of float
            ``(xmin, ymin, xmax, ymax)`` in m.
        resolution : float
            Cell size in m.
        margin : float
            Extra distance in m on every side.
        crs, frame_id
            As the attributes.
        """
        xmin, ymin, xmax, ymax = (float(v) for v in bounds)
        if not (xmin <= xmax and ymin <= ymax):
            raise InputError(f"bounds must be (xmin, ymin, xmax, ymax), got {bounds!r}")
        if not (math.isfinite(margin) and margin >= 0):
            raise InputError(f"margin must be a distance >= 0 in m, got {margin!r}")
        res = float(resolution)
        # lattice indices of the west, south, east and north edges
        c0 = math.floor((xmin - margin) / res)
        r0 = math.floor((ymin - margin) / res)
        c1 = max(math.ceil((xmax + margin) / res), c0 + 1)
        r1 = max(math.ceil((ymax + margin) / res), r0 + 1)
        return cls(res, (c0 * res, r0 * res), (r1 - r0, c1 - c0), crs, frame_id)

    # -- extent -------------------------------------------------------------------------

    @property
    def length(self) -> tuple[float, float]:
        """``(length_x, length_y)``: size of the map in m."""
        return self.shape[1] * self.resolution, self.shape[0] * self.resolution

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the map's outer edges, m."""
        lx, ly = self.length
        return self.origin[0], self.origin[1], self.origin[0] + lx, self.origin[1] + ly

    @property
    def center(self) -> tuple[float, float]:
        """World (x, y) of the map centre, m (grid_map's ``position``)."""
        lx, ly = self.length
        return self.origin[0] + lx / 2, self.origin[1] + ly / 2

    # -- cells <-> world ----------------------------------------------------------------

    def xy(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World x (per column) and y (per row) of the cell centres, m."""
        res = self.resolution
        x = self.origin[0] + res * (np.arange(self.shape[1], dtype=np.float64) + 0.5)
        y = self.origin[1] + res * (np.arange(self.shape[0], dtype=np.float64) + 0.5)
        return x.astype(np.float64, copy=False), y.astype(np.float64, copy=False)

    def cell_center(
        self, rows: ArrayLike, cols: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World (x, y) in m of the centres of cells ``[rows, cols]``."""
        res = self.resolution
        x = self.origin[0] + (np.asarray(cols, float) + 0.5) * res
        y = self.origin[1] + (np.asarray(rows, float) + 0.5) * res
        return x, y

    def cell_of(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(rows, cols) of the cells holding world points (x, y) in m.

        Indices may fall outside the map; see :meth:`inside`.
        """
        res = self.resolution
        cols = np.floor((np.asarray(x, float) - self.origin[0]) / res).astype(np.int64)
        rows = np.floor((np.asarray(y, float) - self.origin[1]) / res).astype(np.int64)
        return rows, cols

    def inside(self, rows: ArrayLike, cols: ArrayLike) -> NDArray[np.bool_]:
        """Whether cell indices are within the map."""
        r, c = np.asarray(rows), np.asarray(cols)
        return (r >= 0) & (r < self.shape[0]) & (c >= 0) & (c < self.shape[1])

    def contains(self, bounds: tuple[float, float, float, float]) -> bool:
        """Whether the box ``(xmin, ymin, xmax, ymax)`` in m lies within the map."""
        x0, y0, x1, y1 = self.bounds
        return bounds[0] >= x0 and bounds[1] >= y0 and bounds[2] <= x1 and bounds[3] <= y1

    def grown_to_cover(
        self, bounds: tuple[float, float, float, float], margin: float
    ) -> tuple[GridGeometry, tuple[int, int]]:
        """A larger geometry covering this one and ``bounds`` (+ ``margin`` m), on this
        map's lattice.

        Returns
        -------
        geometry : GridGeometry
            The new geometry (this one if ``bounds`` is already inside).
        offset : tuple of int
            ``(rows, cols)`` added on the south and west sides: old cell ``[i, j]`` is new
            cell ``[i + offset[0], j + offset[1]]``.
        """
        if self.contains(bounds):
            return self, (0, 0)
        res = self.resolution
        x0, y0, x1, y1 = self.bounds
        add_w = max(0, math.ceil((x0 - (bounds[0] - margin)) / res)) if bounds[0] < x0 else 0
        add_s = max(0, math.ceil((y0 - (bounds[1] - margin)) / res)) if bounds[1] < y0 else 0
        add_e = max(0, math.ceil(((bounds[2] + margin) - x1) / res)) if bounds[2] > x1 else 0
        add_n = max(0, math.ceil(((bounds[3] + margin) - y1) / res)) if bounds[3] > y1 else 0
        geometry = replace(
            self,
            origin=(self.origin[0] - add_w * res, self.origin[1] - add_s * res),
            shape=(self.shape[0] + add_s + add_n, self.shape[1] + add_w + add_e),
        )
        return geometry, (add_s, add_w)

    def transform(self) -> Affine:
        """The :class:`affine.Affine` of the map's north-up raster (rows flipped: row 0 of
        the raster is the northern edge): :func:`rasterio.transform.from_origin` of the
        north-west corner (m) and the cell size (m). ``.to_gdal()`` gives GDAL's
        geotransform ``(x_west, res, 0, y_north, 0, -res)``."""
        from rasterio.transform import from_origin

        west, _, _, north = self.bounds
        with warnings.catch_warnings():
            # rasterio 1.4 multiplies Affines with `*`, which affine 3 marks as pending removal
            warnings.simplefilter("ignore", PendingDeprecationWarning)
            return from_origin(west, north, self.resolution, self.resolution)


#: Memory a map cell takes while ``map`` builds and writes it, in bytes: its layers, the
#: fusion's sums, the merged GeoTIFF bands and the PNG buffers (about 140 measured at
#: 2 mm on an 8 m course, with room for the class layers of larger models).
MAP_BYTES_PER_CELL = 400
#: Most memory a map may take, in bytes, whatever the machine (and at most half of it).
MAP_MEMORY_CAP = 8 * 2**30


def memory_budget() -> int:
    """Bytes a map may take here: half of the physical memory, at most
    :data:`MAP_MEMORY_CAP`."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):  # not POSIX: the cap alone
        total = 2 * MAP_MEMORY_CAP
    return int(min(MAP_MEMORY_CAP, total // 2))


def check_map_memory(xy: ArrayLike, resolution: float, reach: float | None = None) -> None:
    """Refuse a map of cell size ``resolution`` (m) over vehicle positions ``xy`` (m, shape
    (N, 2)) whose patches reach ``reach`` m from them (default the paper's patch: its
    distance ahead plus its side), when its cells would take more than
    :func:`memory_budget`: an :class:`InputError` naming the finest resolution that fits,
    before any frame is read."""
    if reach is None:
        spec = PatchSpec()
        reach = spec.ahead + spec.size
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.size == 0:
        return
    width, height = (pts.max(axis=0) - pts.min(axis=0)) + 2.0 * reach
    cells = math.ceil(width / resolution) * math.ceil(height / resolution)
    budget = memory_budget()
    if cells * MAP_BYTES_PER_CELL <= budget:
        return
    finest = math.sqrt(width * height * MAP_BYTES_PER_CELL / budget)
    raise InputError(
        f"resolution {resolution:g} m: the map over this traverse ({width:.1f} m x "
        f"{height:.1f} m) would hold {cells:.2g} cells, about "
        f"{cells * MAP_BYTES_PER_CELL / 2**30:.0f} GB, beyond the "
        f"{budget / 2**30:.1f} GB a map may take here; use a resolution of at least "
        f"{_round_up(finest)} m"
    )


def _round_up(value: float) -> str:
    """``value`` rounded up to two significant digits, as text."""
    exp = math.floor(math.log10(value)) - 1
    return f"{math.ceil(value / 10**exp) * 10**exp:.{max(0, -exp)}f}"
