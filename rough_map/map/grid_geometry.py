"""Where a grid map lies in the world: :class:`GridGeometry` (cell size, origin, shape, CRS),
and where a vehicle's patch of interest lies on it (its footprint: world corners and cells).

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

__all__ = [
    "GridGeometry",
    "check_map_memory",
    "lattice_patch_box",
    "lattice_patch_cells",
    "memory_budget",
    "patch_bounds",
    "patch_cells",
    "patch_corners",
]


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


# -- footprints: the world corners and the map cells of a vehicle's patch of interest ------


def patch_corners(x: float, y: float, yaw: float, spec: PatchSpec | None = None) -> NDArray:
    """World corners of the patch of a vehicle at (x, y) m heading ``yaw`` rad.

    Parameters
    ----------
    x, y : float
        Vehicle position in the world, m.
    yaw : float
        Vehicle heading, rad (0 = +x, counter-clockwise).
    spec : PatchSpec, optional
        Patch geometry (default: :class:`~rough_map.patch.PatchSpec`'s).

    Returns
    -------
    ndarray, shape (4, 2)
        x, y in m, counter-clockwise from the near right corner.
    """
    spec = spec or PatchSpec()
    h = spec.size / 2
    u = spec.ahead + np.array([-h, h, h, -h])  # along the heading
    v = spec.lateral + np.array([-h, -h, h, h])  # to the left
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([x + c * u - s * v, y + s * u + c * v])


def patch_cells(
    geometry: GridGeometry, x: float, y: float, yaw: float, spec: PatchSpec | None = None
) -> NDArray[np.int64]:
    """Cells ``(N, 2)`` as ``(row, col)`` whose centres lie in the patch (inside the map).

    A patch smaller than a cell that holds no cell centre covers the cell of its centre.

    Parameters
    ----------
    geometry : GridGeometry
        The map's geometry.
    x, y, yaw, spec
        As :func:`patch_corners` (m, rad).
    """
    spec = spec or PatchSpec()
    corners = patch_corners(x, y, yaw, spec)
    r0, c0 = geometry.cell_of(corners[:, 0].min(), corners[:, 1].min())
    r1, c1 = geometry.cell_of(corners[:, 0].max(), corners[:, 1].max())
    rows = np.arange(max(int(r0), 0), min(int(r1), geometry.shape[0] - 1) + 1)
    cols = np.arange(max(int(c0), 0), min(int(c1), geometry.shape[1] - 1) + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    xc, yc = geometry.cell_center(rr, cc)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = xc - x, yc - y
    u = c * dx + s * dy - spec.ahead
    v = -s * dx + c * dy - spec.lateral
    h = spec.size / 2
    inside = (np.abs(u) <= h) & (np.abs(v) <= h)
    cells = np.column_stack([rr[inside], cc[inside]]).astype(np.int64)
    if cells.size == 0:
        cx = x + c * spec.ahead - s * spec.lateral
        cy = y + s * spec.ahead + c * spec.lateral
        r, col = geometry.cell_of(cx, cy)
        if geometry.inside(r, col):
            cells = np.array([[int(r), int(col)]], dtype=np.int64)
    return cells


def _last_min(values: tuple[float, ...]) -> float:
    """``min`` as numpy's reduction of a few values gives it (the last of equal values, so
    that -0.0 and 0.0 come out as in :func:`patch_corners` ``.min()``)."""
    out = values[0]
    for v in values[1:]:
        if v <= out:
            out = v
    return out


def _last_max(values: tuple[float, ...]) -> float:
    out = values[0]
    for v in values[1:]:
        if v >= out:
            out = v
    return out


def patch_bounds(
    x: float, y: float, yaw: float, spec: PatchSpec
) -> tuple[float, float, float, float]:
    """``(xmin, ymin, xmax, ymax)`` in m of :func:`patch_corners`, bit for bit, without
    arrays (it runs twice a frame)."""
    h = spec.size / 2
    u0, u1 = spec.ahead + -h, spec.ahead + h
    v0, v1 = spec.lateral + -h, spec.lateral + h
    c, s = math.cos(yaw), math.sin(yaw)
    # the corners in patch_corners' order: (u0, v0), (u1, v0), (u1, v1), (u0, v1)
    xs = (x + c * u0 - s * v0, x + c * u1 - s * v0, x + c * u1 - s * v1, x + c * u0 - s * v1)
    ys = (y + s * u0 + c * v0, y + s * u1 + c * v0, y + s * u1 + c * v1, y + s * u0 + c * v1)
    return _last_min(xs), _last_min(ys), _last_max(xs), _last_max(ys)


def lattice_patch_box(
    x: float, y: float, yaw: float, spec: PatchSpec, resolution: float
) -> tuple[tuple[float, float, float, float], int, int, NDArray[np.bool_]]:
    """:func:`lattice_patch_cells` as a box: the bounds, the lattice ``(row, col)`` of the
    box's first cell and which of its cells the patch covers (a mask, row-major)."""
    bounds = xmin, ymin, xmax, ymax = patch_bounds(x, y, yaw, spec)
    res = float(resolution)
    # GridGeometry.covering(bounds, res) with no margin
    c0, r0 = math.floor((xmin - 0.0) / res), math.floor((ymin - 0.0) / res)
    n_cols = max(math.ceil((xmax + 0.0) / res), c0 + 1) - c0
    n_rows = max(math.ceil((ymax + 0.0) / res), r0 + 1) - r0
    ox, oy = float(c0 * res), float(r0 * res)
    # patch_cells on that geometry
    i0 = max(math.floor((ymin - oy) / res), 0)
    j0 = max(math.floor((xmin - ox) / res), 0)
    rows = np.arange(i0, min(math.floor((ymax - oy) / res), n_rows - 1) + 1)
    cols = np.arange(j0, min(math.floor((xmax - ox) / res), n_cols - 1) + 1)
    c, s = math.cos(yaw), math.sin(yaw)
    dx = (ox + (cols.astype(float) + 0.5) * res) - x
    dy = (oy + (rows.astype(float) + 0.5) * res) - y
    u = c * dx[None, :] + s * dy[:, None] - spec.ahead
    v = -s * dx[None, :] + c * dy[:, None] - spec.lateral
    h = spec.size / 2
    inside = (np.abs(u) <= h) & (np.abs(v) <= h)
    if inside.any():
        return bounds, r0 + i0, c0 + j0, inside
    # no cell centre in the patch: the cell of its centre
    cx = x + c * spec.ahead - s * spec.lateral
    cy = y + s * spec.ahead + c * spec.lateral
    r, col = math.floor((cy - oy) / res), math.floor((cx - ox) / res)
    inside = np.ones((1, 1) if 0 <= r < n_rows and 0 <= col < n_cols else (0, 0), dtype=bool)
    return bounds, r + r0, col + c0, inside


def lattice_patch_cells(
    x: float, y: float, yaw: float, spec: PatchSpec, resolution: float
) -> tuple[tuple[float, float, float, float], NDArray[np.int64], NDArray[np.int64]]:
    """The patch's bounds (:func:`patch_bounds`) and the lattice ``(rows, cols)`` (cell
    ``[i, j]`` spans ``j * resolution`` .. in x, ``i * resolution`` .. in y) of the cells
    :func:`patch_cells` gives on the smallest map covering the patch
    (:meth:`GridGeometry.covering` of its bounds), offset to the lattice: the same
    arithmetic, so the same cells bit for bit, without building the map."""
    bounds, r0, c0, inside = lattice_patch_box(x, y, yaw, spec, resolution)
    ii, jj = np.nonzero(inside)
    return bounds, ii + r0, jj + c0
