"""Footprints: the world corners and the map cells of a vehicle's patch of interest."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from rough_map.map.grid_geometry import GridGeometry
from rough_map.patch import PatchSpec

__all__ = [
    "lattice_patch_box",
    "lattice_patch_cells",
    "patch_bounds",
    "patch_cells",
    "patch_corners",
]


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
