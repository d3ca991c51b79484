"""Small frozen dataclasses passed between stages.

Conventions used everywhere in rough_map
----------------------------------------
* Vehicle frame: x forward, y left, z up, metres.
* World frame: x east (or local x), y north (or local y), z up, metres.
* Camera frame (OpenCV): x right, y down, z forward, metres.
* Poses are "vehicle in world": ``p_world = Rz(yaw) @ Ry(pitch) @ Rx(roll) @ p_vehicle + t``.
* Rasters (:class:`HeightField`, height grids of a patch) are indexed ``[row, col]`` with
  ``row`` along y and ``col`` along x; cell ``[i, j]`` has its centre at
  ``(origin_x + j * spacing, origin_y + i * spacing)``.
* A patch height grid has its rows as *longitudinal* profiles (along the direction of
  travel): ``heights[i, :]`` is the profile at lateral offset ``i``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class HeightField:
    """A terrain raster in the world frame.

    Attributes
    ----------
    heights : ndarray, shape (ny, nx)
        Elevation z in m at cell centres; NaN where unknown.
    spacing : float
        Cell size in m.
    origin : tuple of float
        World (x, y) in m of the centre of cell ``[0, 0]``.
    classes : ndarray of int, shape (ny, nx), optional
        Index into ``class_names`` per cell; -1 for none.
    class_names : tuple of str
        Terrain class names.
    """

    heights: np.ndarray
    spacing: float
    origin: tuple[float, float] = (0.0, 0.0)
    classes: np.ndarray | None = None
    class_names: tuple[str, ...] = field(default_factory=tuple)

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    def xy(self) -> tuple[np.ndarray, np.ndarray]:
        """World x (per column) and y (per row) of the cell centres, in m."""
        ny, nx = self.heights.shape
        return (
            self.origin[0] + self.spacing * np.arange(nx),
            self.origin[1] + self.spacing * np.arange(ny),
        )

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height in m at world points (x, y) in m; NaN outside."""
        from scipy.ndimage import map_coordinates

        col = (np.asarray(x, float) - self.origin[0]) / self.spacing
        row = (np.asarray(y, float) - self.origin[1]) / self.spacing
        return map_coordinates(self.heights, [row, col], order=1, mode="constant", cval=np.nan)
