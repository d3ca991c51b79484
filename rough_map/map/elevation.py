"""The elevation layer of a map: mean height of a traverse's points per cell."""

from __future__ import annotations

import logging

import numpy as np

from rough_map.errors import RoughMapError
from rough_map.io.traverse import Traverse
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = ["add_elevation"]


def add_elevation(
    grid: GridMap, traverse: Traverse, *, sample: int = 20_000, progress: bool = False
) -> None:
    """Add the layer ``elevation`` (m, world z): mean height of the frames' points per cell.

    Points outside the map (it covers the patch footprints plus a margin) are left out;
    a frame without a cloud, or whose cloud cannot be read, is skipped (logged at debug
    level). Reading the clouds again is one of the long steps of a map.

    Parameters
    ----------
    grid : GridMap
        The map; the layer is added to it.
    traverse : Traverse
        Its frames' clouds, moved to the world frame with their poses.
    sample : int
        Most points drawn from one cloud (a fixed random subset, seeded).
    progress : bool
        Progress bar on stderr.
    """
    from tqdm import tqdm

    geo = grid.geometry
    sums = np.zeros(geo.shape)
    counts = np.zeros(geo.shape)
    rng = np.random.default_rng(0)
    for i in tqdm(range(len(traverse)), desc="elevation", unit="frame", disable=not progress):
        if traverse.frames[i].cloud is None:
            continue
        try:
            pts = traverse.load_cloud(i, frame="world")
        except RoughMapError as exc:
            log.debug("elevation: frame %d skipped: %s", i, exc)
            continue
        if len(pts) > sample:
            pts = pts[rng.choice(len(pts), sample, replace=False)]
        rows, cols = geo.cell_of(pts[:, 0], pts[:, 1])
        ok = geo.inside(rows, cols) & np.isfinite(pts[:, 2])
        np.add.at(sums, (rows[ok], cols[ok]), pts[ok, 2])
        np.add.at(counts, (rows[ok], cols[ok]), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.where(counts > 0, sums / counts, np.nan)
    grid.add_layer("elevation", units="m", description="mean terrain height (world z)", data=elev)
