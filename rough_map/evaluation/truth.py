"""Scores of a map against a known world (the simulator's truth).

The world is a :class:`~rough_map.types.HeightField` with a class map or a
:class:`~rough_map.io.truth.TiledWorld` (a long world, read a tile at a time), e.g. from
:func:`rough_map.io.truth.traverse_truth` on a simulated traverse.
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.errors import InputError
from rough_map.io.truth import TiledWorld, World
from rough_map.map.grid import GridMap
from rough_map.types import HeightField

__all__ = ["map_accuracy", "truth_accuracy"]


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
        The fraction, NaN when no cell is classified.
    """
    if isinstance(world, HeightField) and world.classes is None:
        raise InputError("the world has no class map to score a map against")
    names = grid.info(layer).categories or tuple(grid.attrs.get("class_names", ()))
    arr = grid[layer]
    rows, cols = np.nonzero(np.isfinite(arr))
    if rows.size == 0:
        return math.nan
    x, y = grid.geometry.cell_center(rows, cols)
    j = np.clip(np.round((x - world.origin[0]) / world.spacing).astype(int), 0, world.shape[1] - 1)
    i = np.clip(np.round((y - world.origin[1]) / world.spacing).astype(int), 0, world.shape[0] - 1)
    if isinstance(world, TiledWorld):
        index = world.lookup(i, j)[0]
    else:
        assert world.classes is not None
        index = world.classes[i, j]
    truth = np.asarray(world.class_names, dtype=object)[index]
    pred = np.asarray(names, dtype=object)[arr[rows, cols].astype(int)]
    return float(np.mean(truth == pred))


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
