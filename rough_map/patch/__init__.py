"""From a point cloud in the vehicle frame to the height grid of the patch of interest.

The paper (section 3.2) looks at the patch 0.90 m x 0.90 m about 1 m ahead of the rover,
sampled every B = 8 mm. :func:`grid_points` cuts a ``size`` x ``size`` metre square centred
``ahead`` metres in front of the vehicle origin (and ``lateral`` metres to the left), and
averages the z of the points falling in each ``spacing`` x ``spacing`` cell. Rows of the grid
are longitudinal profiles (along x, the direction of travel); row 0 is the rightmost
(most negative y) profile and column 0 the nearest sample.

Tilt (paper Eq. 11): the cloud is expressed in the vehicle frame, which rolls and pitches
with the terrain. :func:`compensate_tilt` rotates it into a gravity-aligned frame with the
IMU's roll and pitch; the PSD is little affected by tilts of a few degrees, so this is
optional.

Sparse clouds: :func:`auto_spacing` chooses a coarser step of :func:`spacing_ladder` over
the same square when the cloud has too few points per cell (``Extraction(auto_spacing=True)``,
``--spacing auto``); over ground that is the same across the track, :func:`pooled_rows`
keeps the step and widens the cells across it instead.

Lattices: a cloud whose points lie on a regular lattice (a height map exported as points)
is read on that lattice, at its own step, with one node per cell (:func:`find_lattice`,
:func:`grid_lattice`), not re-binned onto cells that misalign with it.

Layout: :mod:`rough_map.patch.spec` (:class:`PatchSpec`, the grid steps, :class:`Extraction`),
:mod:`rough_map.patch.lattice` (:class:`Lattice`) and :mod:`rough_map.patch.grid`
(:func:`grid_points`, :func:`grid_lattice`, :class:`GriddedPatch`).
"""

from rough_map.geometry import compensate_tilt
from rough_map.patch._params import options_of
from rough_map.patch.grid import (
    GriddedPatch,
    check_points,
    extract_patch,
    grid_lattice,
    grid_points,
)
from rough_map.patch.lattice import Lattice, find_lattice, lattice_patch
from rough_map.patch.spec import (
    AUTO_STEPS,
    DEFAULT_AHEAD,
    DEFAULT_SIZE,
    DEFAULT_SPACING,
    METHODS,
    MIN_POINTS_PER_CELL,
    POOLED_POINTS_PER_CELL,
    Extraction,
    PatchSpec,
    auto_spacing,
    points_in_patch,
    pooled_rows,
    spacing_ladder,
    where_the_cloud_lies,
)

__all__ = [
    "AUTO_STEPS",
    "DEFAULT_AHEAD",
    "DEFAULT_SIZE",
    "DEFAULT_SPACING",
    "METHODS",
    "MIN_POINTS_PER_CELL",
    "POOLED_POINTS_PER_CELL",
    "Extraction",
    "GriddedPatch",
    "Lattice",
    "PatchSpec",
    "auto_spacing",
    "check_points",
    "compensate_tilt",
    "extract_patch",
    "find_lattice",
    "grid_lattice",
    "grid_points",
    "lattice_patch",
    "options_of",
    "points_in_patch",
    "pooled_rows",
    "spacing_ladder",
    "where_the_cloud_lies",
]
