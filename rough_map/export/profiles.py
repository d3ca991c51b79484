"""Default export profiles, as data (after ``rasterio.profiles``).

A GeoTIFF keeps one data type for all its bands (and a colour table only on band 1 of a
one-band Byte image), so a map is written as

* ``<name>.tif``: float32, one band per value layer (:data:`LEADING_BANDS` first, then the
  class probabilities and the far-field layers), nodata NaN;
* ``<name>_class.tif`` (and ``<name>_far_class.tif``): uint8, one band of class indices
  with a colour table, nodata 255.

Both are Cloud-Optimized GeoTIFFs with internal overviews.
"""

from __future__ import annotations

import math
from collections import UserDict
from typing import Any, ClassVar

__all__ = [
    "CLASS_COLOURS",
    "CLASS_NODATA",
    "LEADING_BANDS",
    "LEVEL_COLOURS",
    "OTHER_CLASS_COLOURS",
    "PNG_STYLE",
    "ClassProfile",
    "Profile",
    "ValuesProfile",
    "class_colour",
]


class Profile(UserDict):
    """Export options: the class ``defaults`` overridden by the given items."""

    defaults: ClassVar[dict[str, Any]] = {}

    def __init__(self, data: dict[str, Any] | None = None, **kwds: Any) -> None:
        super().__init__(dict(self.defaults))
        self.update(data or {})
        self.update(kwds)


class ValuesProfile(Profile):
    """The float32 file of value layers (R, w, sigma_R, sigma_w, level, ...).

    Keys: ``driver`` (``"COG"``; ``"GTiff"`` with tiles and copied overviews where GDAL has
    no COG driver), ``dtype``, ``nodata``, ``compress``, ``predictor`` (COG: ``"YES"``
    picks the floating-point predictor), ``blocksize`` (tile side in pixels, or ``"auto"``:
    256, or less for a map narrower than that, :func:`rough_map.export.geotiff.block_side`),
    ``overview_resampling`` (a :class:`rasterio.enums.Resampling` name),
    ``overview_min_size`` (overviews halve the raster until it is at most this many
    pixels across; at least one level is always built) and ``threads`` (GDAL threads
    compressing the tiles; the file is the same bytes for any number).
    """

    defaults: ClassVar[dict[str, Any]] = {
        "driver": "COG",
        "dtype": "float32",
        "nodata": math.nan,
        "compress": "DEFLATE",
        "predictor": "YES",
        "blocksize": "auto",
        "overview_resampling": "average",
        "overview_min_size": 16,
        "threads": 2,
    }


class ClassProfile(Profile):
    """The uint8 file of a class layer (colour table, nodata 255, mode overviews)."""

    defaults: ClassVar[dict[str, Any]] = {
        "driver": "COG",
        "dtype": "uint8",
        "nodata": 255,
        "compress": "DEFLATE",
        "predictor": "NO",
        "blocksize": "auto",
        "overview_resampling": "mode",
        "overview_min_size": 16,
        "threads": 2,
    }


#: Nodata value of the uint8 class files: "unknown".
CLASS_NODATA = 255

#: Value layers written first, in this order, when the map has them; other exported value
#: layers follow in the map's order.
LEADING_BANDS: tuple[str, ...] = (
    "R",
    "w",
    "sigma_R",
    "sigma_w",
    "level",
    "count",
    "last_seen",
)

#: Colours (RGB 0-255) of the terrain classes of :mod:`rough_map.terrain`, in every
#: export (GeoTIFF colour tables, PNGs, report figures); other classes take
#: :data:`OTHER_CLASS_COLOURS` by their index (:func:`class_colour`). Safe for colour-blind
#: readers: the CIELAB lightness L* of any two differs by at least 13 (dirt_road 89,
#: concrete 76, compact_soil 54, gravel 37, ploughed_soil 15), so they stay apart in grey
#: too, and under simulated protanopia, deuteranopia and tritanopia (Machado et al. 2009)
#: any two are at least 22 CIELAB units apart (tests/test_export.py checks both).
CLASS_COLOURS: dict[str, tuple[int, int, int]] = {
    "concrete": (187, 187, 187),
    "dirt_road": (240, 228, 66),
    "gravel": (0, 90, 150),
    "compact_soil": (213, 94, 0),
    "ploughed_soil": (60, 30, 10),
}

#: Colours (RGB 0-255) of classes not in :data:`CLASS_COLOURS`: matplotlib's ``tab10``.
OTHER_CLASS_COLOURS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)


def class_colour(name: str, index: int = 0) -> tuple[int, int, int]:
    """RGB (0-255) of the class ``name``, the ``index``-th of its list."""
    return CLASS_COLOURS.get(name, OTHER_CLASS_COLOURS[index % len(OTHER_CLASS_COLOURS)])


#: Colours of the roughness levels, smoothest first: pale yellow, orange, dark red (the
#: paper's Fig. 19 runs green to red, which colour-blind readers cannot tell apart; these
#: differ by at least 28 in lightness L*).
LEVEL_COLOURS: tuple[tuple[int, int, int], ...] = ((255, 230, 140), (235, 125, 35), (140, 20, 40))

#: PNG rendering: figure size (in), dpi, colour maps per layer (default ``viridis``), the
#: layers drawn with a logarithmic colour scale, the count layers (drawn as discrete
#: levels; also with the ``far_`` prefix), and the pages a long map is cut into along the
#: path: ``page_length`` m of path each (None: one view), at most ``max_pages``.
PNG_STYLE: dict[str, Any] = {
    "figsize": (8.0, 4.5),
    "dpi": 120,
    "cmap": {
        "R": "magma",
        "sigma_R": "magma",
        "w": "cividis",
        "sigma_w": "cividis",
        "last_seen": "plasma",
        "far_last_seen": "plasma",
    },
    "default_cmap": "viridis",
    "log_layers": ("R", "sigma_R"),
    "count_layers": ("count",),
    "track_colour": "black",
    "page_length": 10.0,
    "max_pages": 8,
}
