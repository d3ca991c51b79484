"""Grid maps of roughness and terrain class: geometry, named layers, fusion.

:mod:`rough_map.map.grid_geometry` says where a map lies (:class:`GridGeometry`) and
which of its cells a vehicle's patch covers; :mod:`rough_map.map.grid` holds the layer
container and the conversion to grid_map's conventions;
:mod:`rough_map.map.layers` defines the fused layers and computes their estimates;
:mod:`rough_map.map.fusion` fuses the patches of a traverse and far-field predictions into
them; :mod:`rough_map.map.tiles` holds a map of any extent in lattice tiles kept on disk
when far from the vehicle (:class:`~rough_map.map.tiles.TiledMap`), and
:mod:`rough_map.map.state` their sums in one file. The near-to-far stage,
:mod:`rough_map.near_far`, is a learned stage of its own above this one.
"""

from rough_map.errors import EmptyMapWarning
from rough_map.map.fusion import fuse_cell_probabilities, fuse_patch, fuse_traverse
from rough_map.map.grid import GridMap, GridMapData, LayerInfo, from_grid_map, to_grid_map
from rough_map.map.grid_geometry import GridGeometry, patch_cells, patch_corners
from rough_map.map.layers import (
    GROUPS,
    LEVEL_NAMES,
    apply_levels,
    init_layers,
    update_estimates,
)

__all__ = [
    "GROUPS",
    "LEVEL_NAMES",
    "EmptyMapWarning",
    "GridGeometry",
    "GridMap",
    "GridMapData",
    "LayerInfo",
    "apply_levels",
    "from_grid_map",
    "fuse_cell_probabilities",
    "fuse_patch",
    "fuse_traverse",
    "init_layers",
    "patch_cells",
    "patch_corners",
    "to_grid_map",
    "update_estimates",
]
