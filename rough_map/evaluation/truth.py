"""Scores of a map against a known world (the simulator's truth).

The world is a :class:`~rough_map.types.HeightField` with a class map or a
:class:`~rough_map.io.truth.TiledWorld` (a long world, read a tile at a time), e.g. from
:func:`rough_map.io.truth.traverse_truth` on a simulated traverse.

It is scored by the code that scores a written map against a surveyed truth GeoTIFF
(:func:`rough_map.evaluation.score.score_cells`, ``rough-map score``): the world's class at
each map cell's centre (:func:`world_on_cells`, the ``nearest`` resampling of
:mod:`rough_map.evaluation.score_files`) against the map's class layers. ``rough-map
simulate`` also writes the world's classes as ``world_truth.tif``
(:func:`rough_map.io.truth_raster.write_truth_geotiff`), and ``rough-map score MAP
--truth world_truth.tif`` gives the same accuracy as :func:`map_accuracy` here.
"""

from __future__ import annotations

import numpy as np

from rough_map.errors import InputError
from rough_map.evaluation.score import (
    DEFAULT_BINS,
    LayerPrediction,
    MapScore,
    observed_mask,
    path_distance,
    score_cells,
)
from rough_map.io.truth import TiledWorld, World
from rough_map.map.grid import GridMap
from rough_map.types import HeightField

__all__ = ["map_accuracy", "score_grid", "truth_accuracy", "world_on_cells"]


def world_on_cells(world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Class index (into ``world.class_names``, int64) of the world's cell holding each
    point (x, y) in m; points beyond the world's edge take the nearest edge cell.

    This is the ``nearest`` resampling of :mod:`rough_map.evaluation.score_files` (the
    class at each map cell's centre), done on the world in memory (a tiled world a tile at
    a time), so that the simulator's truth scores as its GeoTIFF does.
    """
    if isinstance(world, HeightField) and world.classes is None:
        raise InputError("the world has no class map to score a map against")
    j = np.clip(np.round((x - world.origin[0]) / world.spacing).astype(int), 0, world.shape[1] - 1)
    i = np.clip(np.round((y - world.origin[1]) / world.spacing).astype(int), 0, world.shape[0] - 1)
    if isinstance(world, TiledWorld):
        return world.lookup(i, j)[0]
    assert world.classes is not None
    return world.classes[i, j].astype(np.int64)


def score_grid(
    grid: GridMap,
    world: World,
    layers: tuple[str, ...] | None = None,
    *,
    path_xy: np.ndarray | None = None,
    bins: tuple[float, ...] = DEFAULT_BINS,
    require_common: bool = True,
) -> MapScore:
    """Score a map in memory against the true world (:func:`~rough_map.evaluation.score.
    score_cells`, over the cells any of ``layers`` classifies).

    Parameters
    ----------
    grid : GridMap
        The map, with class layers (indices into their categories, or into
        ``grid.attrs["class_names"]``).
    world : HeightField or TiledWorld
        The true world, with a class map.
    layers : tuple of str, optional
        Class layers (default: ``class`` and ``far_class`` where present).
    path_xy : ndarray (n, 2), optional
        The path (m), for the accuracy by distance from it.
    bins : tuple of float
        Upper edges of the distance bins, m.
    """
    if layers is None:
        layers = tuple(n for n in ("class", "far_class") if n in grid.layers)
    if not layers:
        raise InputError("the map has no class layer to score")

    def band(name: str) -> np.ndarray | None:
        return grid[name] if name in grid.layers else None

    known = np.zeros(grid.shape, dtype=bool)
    seen = {name: observed_mask(name, band) for name in layers}
    for name in layers:
        known |= np.isfinite(grid[name])
        if seen[name] is not None:
            known |= seen[name]
    rows, cols = np.nonzero(known)
    x, y = grid.geometry.cell_center(rows, cols)
    truth = world_on_cells(world, x, y)
    preds = {}
    for name in layers:
        arr = grid[name][rows, cols]
        names = grid.info(name).categories or tuple(grid.attrs.get("class_names", ()))
        mask = seen[name]
        observed = None if mask is None else np.isfinite(arr) | mask[rows, cols]
        values = np.where(np.isfinite(arr), np.nan_to_num(arr, nan=-1), -1).astype(np.int64)
        preds[name] = LayerPrediction(values, tuple(names), observed)
    distance = None
    if path_xy is not None and rows.size:
        distance = path_distance(x, y, path_xy, grid.resolution / 4)
    return score_cells(
        preds,
        truth,
        dict(enumerate(world.class_names)),
        distance=distance,
        bins=bins,
        cell_area_m2=grid.resolution**2,
        require_common=require_common,
    )


def map_accuracy(grid: GridMap, world: World, layer: str = "class") -> float:
    """Fraction of classified map cells whose class is the world's class at the cell centre.

    Parameters
    ----------
    grid : GridMap
        The map, with the class layer ``layer`` (indices into its categories, or into
        ``grid.attrs["class_names"]``).
    world : HeightField or TiledWorld
        The true world, with a class map (cells beyond its edge take the nearest edge cell).
    layer : str
        ``"class"`` (near field) or ``"far_class"`` (near-to-far).

    Returns
    -------
    float
        The fraction (:func:`score_grid`'s accuracy of the layer), NaN when no cell is
        classified.
    """
    if isinstance(world, HeightField) and world.classes is None:
        raise InputError("the world has no class map to score a map against")
    return score_grid(grid, world, (layer,), require_common=False).layers[layer].accuracy


def truth_accuracy(grid: GridMap, world: World | None) -> dict[str, float]:
    """Map class accuracy against the true world.

    Returns
    -------
    dict of str to float
        ``near_class_accuracy`` (the ``class`` layer) and, with near-to-far,
        ``far_class_accuracy`` (the ``far_class`` layer): fractions of the classified cells
        whose class is the world's class at the cell centre (:func:`map_accuracy`). Empty
        without a world, without a class map in it, or without a ``class`` layer (a map
        made without a terrain model).
    """
    if world is None or "class" not in grid.layers:
        return {}
    if isinstance(world, HeightField) and world.classes is None:
        return {}
    out = {"near_class_accuracy": map_accuracy(grid, world)}
    if "far_class" in grid.layers:
        out["far_class_accuracy"] = map_accuracy(grid, world, "far_class")
    return out
