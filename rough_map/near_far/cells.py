"""Ground cells in view: the world lattice cells an image sees beyond the near field, and
the tile features of each.

Predictions are given on the world lattice of cell centres ``((i + 0.5) * step,
(j + 0.5) * step)`` (the lattice of :class:`rough_map.map.grid.GridMap` maps of that
resolution), for cells in view within ``max_range`` of the vehicle and outside the near
field: a cell averages the tiles whose centres fall in it, or takes the tile its centre
projects into when none does (far away one tile covers several cells). Flat ground: a
cell's centre is placed on the vehicle's ``z = 0`` plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.geometry import ground_to_pixel
from rough_map.near_far.tiles import TileGeometry
from rough_map.patch import Extraction, PatchSpec

__all__ = ["GroundCells", "NearField", "cells_in_view"]


@dataclass(frozen=True)
class NearField:
    """The near field in the vehicle frame: the patch that geometry classifies.

    Attributes
    ----------
    ahead : (float, float)
        Nearest and farthest x of the patch, m (:attr:`rough_map.patch.Extraction.near_range`).
    lateral : (float, float)
        Rightmost and leftmost y of the patch, m.
    """

    ahead: tuple[float, float]
    lateral: tuple[float, float]

    @classmethod
    def of(cls, patch: PatchSpec | Extraction) -> NearField:
        """The near field of a patch (or of an extraction's patch)."""
        extraction = patch if isinstance(patch, Extraction) else Extraction(patch=patch)
        spec = extraction.patch
        return cls(extraction.near_range, (spec.y0, spec.y0 + spec.rows * spec.row_step))

    def contains(self, ahead: NDArray[np.float64], lateral: NDArray[np.float64]) -> NDArray:
        """Whether vehicle-frame points (``ahead``, ``lateral`` in m) lie in the near field
        (edges included; NaN: no)."""
        with np.errstate(invalid="ignore"):
            return (
                (ahead >= self.ahead[0])
                & (ahead <= self.ahead[1])
                & (lateral >= self.lateral[0])
                & (lateral <= self.lateral[1])
            )


@dataclass(frozen=True)
class GroundCells:
    """Ground cells of one prediction: lattice keys, positions (m) and features.

    Attributes
    ----------
    keys : ndarray of int, shape (N, 2)
        Lattice indices along world x and y.
    x, y : ndarray, shape (N,)
        World coordinates of the cell centres, m.
    ahead, lateral : ndarray, shape (N,)
        The same points in the vehicle frame, m.
    distance : ndarray, shape (N,)
        Horizontal distance from the vehicle, m.
    features : ndarray, shape (N, F)
        Tile features of each cell.
    """

    keys: NDArray[np.int64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    ahead: NDArray[np.float64]
    lateral: NDArray[np.float64]
    distance: NDArray[np.float64]
    features: NDArray[np.float64]

    def row(self, k: int) -> NDArray[np.float64]:
        """x, y, ahead, lateral, distance and the features of cell ``k`` as one array."""
        head = [self.x[k], self.y[k], self.ahead[k], self.lateral[k], self.distance[k]]
        return np.concatenate([head, self.features[k]])

    @classmethod
    def from_rows(cls, keys: NDArray[np.int64], rows: NDArray[np.float64]) -> GroundCells:
        """Cells from their keys and :meth:`row` arrays stacked, shape (N, 5 + F)."""
        return cls(
            keys.reshape(-1, 2), rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4],
            rows[:, 5:],
        )  # fmt: skip

    @classmethod
    def empty(cls, n_features: int) -> GroundCells:
        """No cell."""
        z = np.zeros(0)
        return cls(np.zeros((0, 2), dtype=np.int64), z, z, z, z, z, np.zeros((0, n_features)))

    @classmethod
    def concat(cls, a: GroundCells, b: GroundCells) -> GroundCells:
        """The cells of ``a`` then those of ``b``."""
        return cls(
            *(np.concatenate([getattr(a, f), getattr(b, f)]) for f in cls.__dataclass_fields__)
        )


def cells_in_view(
    calib: StereoCalibration,
    geometry: TileGeometry,
    tile_px: int,
    transform: NDArray[np.float64],
    usable: NDArray[np.bool_],
    features: NDArray[np.float64],
    *,
    step: float,
    max_range: float,
    near: NearField,
) -> GroundCells:
    """Ground cells in view and their features (see the module notes).

    Parameters
    ----------
    calib : StereoCalibration
        The rig.
    geometry : TileGeometry
        Its tiles of ``tile_px`` px.
    tile_px : int
        Side of a tile, px.
    transform : ndarray, shape (4, 4)
        Vehicle -> world pose (:func:`rough_map.geometry.pose_matrix`), m.
    usable : ndarray of bool, shape (T,)
        Tiles that may be used.
    features : ndarray, shape (T, F)
        Tile features.
    step : float
        Lattice step, m.
    max_range : float
        Largest horizontal distance of a cell from the vehicle, m.
    near : NearField
        Cells in it are left out.

    Raises
    ------
    InputError
        A pose that tilts the vehicle's ground plane vertical.
    """
    rot, trans = transform[:3, :3], transform[:3, 3]
    # World bounding box of the vehicle-frame area in reach, on the cell lattice.
    corners = np.array([[x, y, 0.0] for x in (0.0, max_range) for y in (-max_range, max_range)])
    world = corners @ rot.T + trans
    i0 = math.floor(world[:, 0].min() / step)
    i1 = math.ceil(world[:, 0].max() / step)
    j0 = math.floor(world[:, 1].min() / step)
    j1 = math.ceil(world[:, 1].max() / step)
    gi, gj = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1))
    keys = np.column_stack([gi.ravel(), gj.ravel()])
    wx, wy = (keys[:, 0] + 0.5) * step, (keys[:, 1] + 0.5) * step
    # The point of the vehicle's z = 0 plane above/below each world (x, y).
    try:
        inv = np.linalg.inv(rot[:2, :2])
    except np.linalg.LinAlgError:
        raise InputError("the pose tilts the vehicle's ground plane vertical") from None
    vxy = np.column_stack([wx - trans[0], wy - trans[1]]) @ inv.T
    ahead, lateral = vxy[:, 0], vxy[:, 1]
    keep = (ahead > 0) & (np.hypot(ahead, lateral) <= max_range) & ~near.contains(ahead, lateral)
    u, v = ground_to_pixel(
        calib, np.column_stack([ahead[keep], lateral[keep], np.zeros(int(keep.sum()))])
    )
    with np.errstate(invalid="ignore"):
        col = np.floor((u + 0.5) / tile_px)
        row = np.floor((v + 0.5) / tile_px)
        inside = (col >= 0) & (col < geometry.n_cols) & (row >= 0) & (row < geometry.n_rows)
    tile = np.full(u.shape, -1, dtype=np.int64)
    tile[inside] = row[inside].astype(np.int64) * geometry.n_cols + col[inside].astype(np.int64)
    inside[inside] = usable[tile[inside]]
    keep[keep] = inside
    keys, ahead, lateral, wx, wy = (a[keep] for a in (keys, ahead, lateral, wx, wy))
    cell_features = features[tile[inside]]
    _average_tiles_in_cells(keys, cell_features, geometry, rot, trans, usable, features, step)
    return GroundCells(keys, wx, wy, ahead, lateral, np.hypot(ahead, lateral), cell_features)


def _average_tiles_in_cells(
    keys: NDArray[np.int64],
    cell_features: NDArray[np.float64],
    geometry: TileGeometry,
    rot: NDArray[np.float64],
    trans: NDArray[np.float64],
    usable: NDArray[np.bool_],
    features: NDArray[np.float64],
    step: float,
) -> None:
    """Cells holding tile centres take the mean of those tiles instead (near the rover a cell
    spans many tiles); ``cell_features`` is changed in place."""
    if not len(keys):
        return
    centres = geometry.ground[usable] @ rot.T + trans
    centre_keys = np.floor(centres[:, :2] / step).astype(np.int64)
    _, inverse = np.unique(np.concatenate([keys, centre_keys]), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    n_cells = len(keys)
    sums = np.zeros((int(inverse.max()) + 1, features.shape[1]))
    counts = np.zeros(len(sums))
    np.add.at(sums, inverse[n_cells:], features[usable])
    np.add.at(counts, inverse[n_cells:], 1.0)
    hits = counts[inverse[:n_cells]]
    filled = hits > 0
    cell_features[filled] = sums[inverse[:n_cells]][filled] / hits[filled, None]
