"""Grid maps of roughness and terrain class: geometry, named layers, fusion.

:mod:`rough_map.map.grid` holds the geometry and layer container (and the conversion to
grid_map's conventions); :mod:`rough_map.map.fusion` fuses the patches of a traverse and
far-field predictions into layers.
"""

from rough_map.map.fusion import (
    GROUPS,
    LEVEL_NAMES,
    EmptyMapWarning,
    apply_levels,
    fuse_cell_probabilities,
    fuse_patch,
    fuse_traverse,
    init_layers,
    patch_cells,
    patch_corners,
    update_estimates,
)
from rough_map.map.grid import (
    GridGeometry,
    GridMap,
    GridMapData,
    LayerInfo,
    from_grid_map,
    to_grid_map,
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
