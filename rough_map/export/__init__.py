"""Export a grid map: Cloud-Optimized GeoTIFFs, PNGs per layer, a grid_map bag.

:func:`export_map` writes everything a map has; the writers live in
:mod:`rough_map.export.geotiff`, :mod:`rough_map.export.png` (laid out by
:mod:`rough_map.export.layout`) and :mod:`rough_map.export.gridmap_msg`, their defaults in
:mod:`rough_map.export.profiles`. The report is :mod:`rough_map.export.report` (figures of
:mod:`rough_map.export.figures`, page of :mod:`rough_map.export.report_html`). Heavy
libraries (rasterio, matplotlib, rosbags) are imported only when a writer runs.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rough_map._files import make_dir
from rough_map.errors import InputError
from rough_map.export.geotiff import (
    class_layers,
    value_layers,
    write_class_geotiff,
    write_values_geotiff,
)
from rough_map.export.gridmap_msg import write_gridmap_bag
from rough_map.export.png import write_pngs
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = ["export_map", "import_writers"]

#: What the writers import when they first run, and the grid_map bag's writer.
_WRITER_MODULES = ("rasterio", "rasterio.enums", "rasterio.shutil", "rasterio.windows")
_BAG_MODULES = ("rosbags.typesys", "rosbags.rosbag2")


def import_writers(gridmap_bag: bool = False) -> None:
    """Import the libraries :func:`export_map` uses on this thread, before it runs on
    another. A Ctrl-C that breaks an import on this thread can leave CPython's import lock
    held (the ``KeyboardInterrupt`` lands between taking and releasing it), and a thread
    importing meanwhile would wait for it for ever."""
    for name in _WRITER_MODULES + (_BAG_MODULES if gridmap_bag else ()):
        importlib.import_module(name)


def export_map(
    grid: GridMap,
    out_dir: str | Path,
    *,
    name: str = "map",
    png: bool = True,
    gridmap_bag: bool = False,
    threads: int = 2,
    gridmap_updates: Iterable[tuple[float, GridMap]] = (),
    occupancy: NDArray[np.int8] | None = None,
) -> dict[str, Path]:
    """Write a map's files to ``out_dir`` (created if missing).

    Parameters
    ----------
    grid : GridMap
        The map (e.g. from :func:`rough_map.map.fuse_traverse`).
    out_dir : str or Path
        Output folder.
    name : str
        Stem of the file names.
    png : bool
        Also draw one PNG per exported layer.
    gridmap_bag : bool
        Also write ``grid_map_msgs/msg/GridMap`` messages in a ROS 2 MCAP bag: one per
        update of ``gridmap_updates``, then the whole map.
    threads : int
        GDAL threads compressing each GeoTIFF (the profiles' ``threads``; one when
        something else keeps the other core busy). The files are the same for any number.
    gridmap_updates : iterable of (float, GridMap)
        The map around each update as it then stood, with its time in s
        (:meth:`rough_map.online.OnlineMapper.replay`), for the bag.
    occupancy : ndarray of int8, optional
        Costs of the map's cells (:func:`rough_map.export.costmap.cost_layer`), also in the
        bag as a ``nav_msgs/OccupancyGrid`` on ``/rough_map/costmap``.

    Returns
    -------
    dict of str to Path
        ``"geotiff"``: ``<name>.tif`` (float32 value layers);
        ``"geotiff_<layer>"``: ``<name>_<layer>.tif`` per class layer (``class``,
        ``far_class``; uint8 with colour table), with ``"categories_<layer>"``, GDAL's
        ``.tif.aux.xml`` of its category names, and ``"qgis_style_<layer>"``, its ``.qml``;
        ``"png_<layer>"``: ``<name>_<layer>.png`` per layer;
        ``"gridmap_bag"``: the bag folder ``<name>_gridmap``.
    """
    out = Path(out_dir)
    make_dir(out)
    paths: dict[str, Path] = {}
    if not isinstance(threads, int) or isinstance(threads, bool) or not 1 <= threads <= 256:
        raise InputError(f"threads must be a number of threads from 1 to 256, got {threads!r}")
    profile = {"threads": threads}
    if value_layers(grid):
        paths["geotiff"] = write_values_geotiff(grid, out / f"{name}.tif", profile=profile)
    for layer in class_layers(grid):
        tif = write_class_geotiff(grid, out / f"{name}_{layer}.tif", layer, profile=profile)
        paths[f"geotiff_{layer}"] = tif
        paths[f"categories_{layer}"] = Path(f"{tif}.aux.xml")
        paths[f"qgis_style_{layer}"] = tif.with_suffix(".qml")
    if png:
        for layer, p in write_pngs(grid, out, name).items():
            paths[f"png_{layer}"] = p
    if gridmap_bag:
        paths["gridmap_bag"] = write_gridmap_bag(
            grid, out / f"{name}_gridmap", updates=gridmap_updates, occupancy=occupancy
        )
    log.info("exported map %r: %d files in %s", name, len(paths), out)
    return paths
