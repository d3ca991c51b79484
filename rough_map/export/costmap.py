"""A costmap a navigation stack loads: the map's speed advice as a ROS map_server map.

:func:`cost_layer` turns the ``v_max`` layer (m/s, :mod:`rough_map.features.driving`) into
occupancy costs 0-100: ``100 (1 - v_max / top_speed)``, 0 where the vehicle may go at its top
speed, 100 (lethal) where ``v_max`` is at or below :attr:`CostmapSettings.lethal_speed` or the
cell's class is one of :attr:`CostmapSettings.lethal_classes`, and -1 (unknown) where the map
has no reading: never free.

:func:`write_costmap` writes it as a map_server map, ``NAME.pgm`` and ``NAME.yaml``
(``image``, ``resolution`` in m, ``origin`` [x, y, yaw] of the lower-left pixel, ``negate``,
``occupied_thresh``, ``free_thresh``, ``mode``), which Nav2's map_server and ROS 1's load:

``raw`` (default)
    Each pixel is the cost itself (0-100), 255 unknown: Nav2 reads lightness 0-100 as the
    occupancy and 101 and above as unknown.
``trinary``
    Pixel ``255 (1 - cost / 100)``, so that map_server's ``p = (255 - pixel) / 255`` is the
    cost over 100: occupied above ``occupied_thresh``, free below ``free_thresh``, unknown
    between (an unknown cell's pixel sits between the two).

:func:`occupancy_grid_message` builds the same costs as a ``nav_msgs/OccupancyGrid``, which
``map --gridmap-bag`` adds to its MCAP bag.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._files import atomic_output
from rough_map.errors import InputError
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = [
    "MODES",
    "OCCUPANCY_GRID",
    "CostmapSettings",
    "cost_layer",
    "occupancy_grid_message",
    "write_costmap",
]

#: map_server modes written.
MODES = ("raw", "trinary")
#: The ROS message type of :func:`occupancy_grid_message`.
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
_UNKNOWN_RAW = 255


@dataclass(frozen=True)
class CostmapSettings:
    """How speed advice becomes cost.

    Attributes
    ----------
    lethal_speed : float
        Cells whose ``v_max`` is at or below this (m/s) are lethal (100).
    lethal_classes : tuple of str
        Terrain classes that are lethal whatever their roughness.
    mode : {"raw", "trinary"}
        The map_server mode of the image (:data:`MODES`).
    occupied_thresh, free_thresh : float
        map_server's thresholds on ``p`` (cost / 100 in ``trinary``).
    """

    lethal_speed: float = 0.0
    lethal_classes: tuple[str, ...] = ()
    mode: str = "raw"
    occupied_thresh: float = 0.65
    free_thresh: float = 0.25

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not 0 <= self.free_thresh < self.occupied_thresh <= 1:
            raise InputError(
                f"need 0 <= free_thresh < occupied_thresh <= 1, got {self.free_thresh!r} and "
                f"{self.occupied_thresh!r}"
            )
        if not (np.isfinite(self.lethal_speed) and self.lethal_speed >= 0):
            raise InputError(f"lethal_speed must be >= 0 m/s, got {self.lethal_speed!r}")


def cost_layer(
    grid: GridMap, top_speed: float, settings: CostmapSettings | None = None
) -> NDArray[np.int8]:
    """Costs (int8, rows as the map's: row 0 the south edge): 0-100, -1 unknown.

    Raises
    ------
    InputError
        A map without a ``v_max`` layer (made without a vehicle).
    """
    settings = settings or CostmapSettings()
    if "v_max" not in grid:
        raise InputError("the map has no v_max layer: make it with a --vehicle")
    v = np.asarray(grid["v_max"], dtype=float)
    known = np.isfinite(v)
    cost = np.full(v.shape, -1, dtype=np.int8)
    scaled = np.clip(np.rint(100 * (1 - v[known] / top_speed)), 0, 100)
    cost[known] = scaled.astype(np.int8)
    cost[known & (v <= settings.lethal_speed)] = 100
    if settings.lethal_classes and "class" in grid:
        categories = list(grid.info("class").categories or ())
        unknown = [c for c in settings.lethal_classes if c not in categories]
        if unknown:
            raise InputError(
                f"lethal class {unknown[0]!r} is not one of the map's ({', '.join(categories)})"
            )
        codes = [categories.index(c) for c in settings.lethal_classes]
        cost[np.isin(grid["class"], codes)] = 100
    return cost


def write_costmap(
    grid: GridMap,
    out_dir: str | Path,
    top_speed: float,
    *,
    name: str = "map_costmap",
    settings: CostmapSettings | None = None,
) -> dict[str, Path]:
    """Write ``NAME.pgm`` and ``NAME.yaml`` (see the module docstring); returns their paths
    as ``costmap_image`` and ``costmap_yaml``."""
    settings = settings or CostmapSettings()
    cost = cost_layer(grid, top_speed, settings)
    if settings.mode == "raw":
        pixels = np.where(cost < 0, _UNKNOWN_RAW, cost).astype(np.uint8)
    else:
        middle = (settings.occupied_thresh + settings.free_thresh) / 2
        shade = np.where(cost < 0, middle, cost / 100.0)
        pixels = np.rint(255 * (1 - shade)).astype(np.uint8)
    image = pixels[::-1]  # the image's first row is the map's north edge
    out = Path(out_dir)
    pgm, yaml_path = out / f"{name}.pgm", out / f"{name}.yaml"
    height, width = image.shape
    with atomic_output(pgm) as tmp:
        tmp.write_bytes(f"P5\n{width} {height}\n255\n".encode("ascii") + image.tobytes())
    west, south = grid.geometry.origin
    text = (
        f"image: {pgm.name}\n"
        f"resolution: {grid.resolution:.12g}\n"
        f"origin: [{west:.12g}, {south:.12g}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {settings.occupied_thresh!r}\n"
        f"free_thresh: {settings.free_thresh!r}\n"
        f"mode: {settings.mode}\n"
    )
    with atomic_output(yaml_path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    log.info("wrote %s (%d x %d cells, mode %s)", yaml_path, width, height, settings.mode)
    return {"costmap_image": pgm, "costmap_yaml": yaml_path}


def occupancy_grid_message(
    grid: GridMap, cost: NDArray[np.int8], typestore: Any, *, stamp_ns: int = 0
) -> Any:
    """``cost`` (:func:`cost_layer`) as a ``nav_msgs/OccupancyGrid`` of ``typestore``."""
    t = typestore.types
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    west, south = grid.geometry.origin
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(west), y=float(south), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    height, width = cost.shape
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp,
        resolution=float(grid.resolution),
        width=width,
        height=height,
        origin=pose,
    )
    header = t["std_msgs/msg/Header"](stamp=stamp, frame_id=grid.geometry.frame_id)
    data = np.ascontiguousarray(cost, dtype=np.int8).ravel()  # row-major from the origin
    return t[OCCUPANCY_GRID](header=header, info=info, data=data)
