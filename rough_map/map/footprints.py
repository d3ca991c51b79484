"""Footprints: the world corners and the map cells of a vehicle's patch of interest."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from rough_map.map.grid_geometry import GridGeometry
from rough_map.patch import PatchSpec

__all__ = ["patch_cells", "patch_corners"]


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
