"""Cloud-Optimized GeoTIFFs of a grid map (rasterio).

A GeoTIFF holds one data type for all its bands, and a colour table only on band 1, so a
map becomes (profiles in :mod:`rough_map.export.profiles`):

``<name>.tif``
    float32, one band per value layer, described by the layer name (``R``, ``w``,
    ``sigma_R``, ``sigma_w``, ``level``, ``count``, ``last_seen``, ``roughness_rms``,
    ``novel``, ``p_<class>``, then the
    far-field ``far_count``, ``far_p_<class>``...), with GDAL unit types and band tags
    ``units``, ``long_name`` and ``layer``. Nodata: NaN.
``<name>_class.tif``, ``<name>_far_class.tif``
    uint8, one band described ``class`` (``far_class``): the class index, with a colour
    table, the class names in tags (``class_names`` as JSON and ``CLASS_<i>=<name>``).
    Nodata: 255. Beside it, GDAL's ``.tif.aux.xml`` with the category names and a raster
    attribute table, and a QGIS style ``.qml`` (:mod:`rough_map.export.sidecars`).

Rows are north-up (the map's rows flipped); the geotransform puts the map's south-west
corner at its origin. The CRS is the traverse's EPSG code; for a local frame with a
geodetic origin, a transverse Mercator centred on that origin; without origin, a local
engineering CRS (``LOCAL_CS``, metres). Dataset tags give ``layers`` (the layers of the
file's bands, in order), ``crs_code``, ``frame_id``,
``geodetic_origin`` (JSON ``[lat, lon, alt]``), ``class_names``, ``level_names``.

Files are written to a temporary name, checked (the GeoTIFF reopens and its last block
reads back) and moved into place; GDAL's errors, raised or only printed (a full disk), are
a :class:`~rough_map.errors.FileFormatError` naming the file
(:func:`rough_map._files.gdal_errors`), and the old file stays. The bands go there through an
intermediate tiled GTiff on disk beside it, a few tiles at a time with GDAL's cache bounded,
so that writing a long map needs little memory beyond the map itself.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import __version__
from rough_map._files import atomic_output, gdal_errors
from rough_map.errors import InputError
from rough_map.export.profiles import (
    CLASS_NODATA,
    LEADING_BANDS,
    ClassProfile,
    ValuesProfile,
    class_colour,
)
from rough_map.export.sidecars import write_category_names, write_qgis_style
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = [
    "block_side",
    "class_colours",
    "class_layers",
    "overview_factors",
    "value_layers",
    "write_class_geotiff",
    "write_values_geotiff",
]


def value_layers(grid: GridMap) -> list[str]:
    """The layers of the float file, in band order: :data:`LEADING_BANDS`, then the other
    ``kind="value"`` layers in the map's order."""
    exported = [n for n in grid.layers if grid.info(n).kind == "value"]
    return [n for n in LEADING_BANDS if n in exported] + [
        n for n in exported if n not in LEADING_BANDS
    ]


def class_layers(grid: GridMap) -> list[str]:
    """The ``kind="class"`` layers (each gets a uint8 file)."""
    return [n for n in grid.layers if grid.info(n).kind == "class"]


def overview_factors(shape: tuple[int, int], min_size: int = 16) -> list[int]:
    """Decimation factors 2, 4, ... until the raster is at most ``min_size`` pixels
    across (at least ``[2]``)."""
    biggest = max(shape)
    levels = max(1, math.ceil(math.log2(max(biggest, 2) / max(min_size, 1))))
    return [2**k for k in range(1, levels + 1)]


def class_colours(names: Sequence[str]) -> dict[int, tuple[int, int, int, int]]:
    """Colour table ``{index: (r, g, b, a)}`` of class names (:func:`class_colour`);
    255 (unknown) transparent."""
    table = {i: (*class_colour(name, i), 255) for i, name in enumerate(names)}
    table[CLASS_NODATA] = (0, 0, 0, 0)
    return table


def _dataset_tags(grid: GridMap, bands: Sequence[str]) -> dict[str, str]:
    """The dataset tags of a file whose bands are the layers ``bands``, in order."""
    crs = grid.crs
    tags = {
        "software": f"rough_map {__version__}",
        "layers": json.dumps(list(bands)),
        "crs_code": crs.code,
        "frame_id": grid.geometry.frame_id,
        "resolution_m": repr(grid.resolution),
    }
    if crs.origin is not None:
        o = crs.origin
        tags["geodetic_origin"] = json.dumps([o.lat, o.lon, o.alt])
    for key in ("class_names", "level_names"):
        if grid.attrs.get(key):
            tags[key] = json.dumps(list(grid.attrs[key]))
    if grid.attrs.get("name"):
        tags["traverse"] = str(grid.attrs["name"])
    if "class_prior" in grid.attrs:
        tags["class_prior"] = repr(float(grid.attrs["class_prior"]))
    return tags


def block_side(blocksize: Any, shape: tuple[int, int]) -> int:
    """The tile side in pixels of a file of ``shape`` (rows, columns) for the profile's
    ``blocksize``: that number, or for ``"auto"`` 256 unless the map is narrower, then the
    power of two (at least 64) that covers its short side. A long strip 30 cells wide in
    256 x 256 tiles would be 88 % padding, which GDAL compresses too: 0.6 s of a 1.8 km map's
    1.2 s."""
    if blocksize != "auto":
        return int(blocksize)
    short = max(1, min(shape))
    return 256 if short >= 256 else max(64, 1 << (short - 1).bit_length())


def _creation_options(
    profile: Mapping[str, Any], driver: str, shape: tuple[int, int]
) -> dict[str, Any]:
    threads = int(profile["threads"])  # the file is the same bytes for any number
    opts: dict[str, Any] = {"COMPRESS": profile["compress"], "NUM_THREADS": threads}
    bs = block_side(profile["blocksize"], shape)
    if driver == "COG":
        opts.update(
            BLOCKSIZE=bs,
            PREDICTOR=profile["predictor"],
            OVERVIEWS="FORCE_USE_EXISTING",
            BIGTIFF="IF_SAFER",
        )
    else:
        floating = np.dtype(profile["dtype"]).kind == "f"
        predictor = {"YES": 3 if floating else 2, "NO": 1}.get(
            str(profile["predictor"]).upper(), profile["predictor"]
        )
        opts.update(
            TILED="YES",
            BLOCKXSIZE=bs,
            BLOCKYSIZE=bs,
            PREDICTOR=predictor,
            COPY_SRC_OVERVIEWS="YES",
            BIGTIFF="IF_SAFER",
        )
    return opts


#: GDAL's block cache while a file is written, bytes. The bands go to a file on disk a few
#: tiles at a time, so a small cache is enough and keeps a long map's memory low.
_GDAL_CACHE_BYTES = 8 << 20

#: Cells of all bands handed to GDAL at once: about this many bytes, in whole tiles.
_CHUNK_BYTES = 4 << 20

#: ``cells(r0, r1, c0, c1)`` -> the bands' cells ``[r0:r1, c0:c1]`` (north-up) as an array
#: (count, r1 - r0, c1 - c0) of the file's data type.
_CellReader = Callable[[int, int, int, int], np.ndarray]


def _source_block(width: int) -> tuple[int, int]:
    """Tile (columns, rows) of the intermediate file: 16 rows, so that a long map's 30-odd
    rows are not padded much; at most 256 columns (a tile of the COG reads whole tiles of
    it), fewer for a narrow map (a multiple of 16, as TIFF tiles are)."""
    return min(256, -(-width // 16) * 16), 16


def _chunks(
    shape: tuple[int, int], block: tuple[int, int], cell_bytes: int
) -> list[tuple[int, int, int, int]]:
    """Windows ``(r0, r1, c0, c1)`` covering ``shape`` in whole tiles ``block`` (columns,
    rows) of ``cell_bytes`` a cell, each of about :data:`_CHUNK_BYTES` (at least a tile)."""
    height, width = shape
    block_x, block_y = block
    tile_row_bytes = width * block_y * cell_bytes
    if tile_row_bytes <= _CHUNK_BYTES:
        rows, cols = block_y * (_CHUNK_BYTES // tile_row_bytes), width
    else:
        rows = block_y
        cols = block_x * max(1, _CHUNK_BYTES // (block_x * block_y * cell_bytes))
    return [
        (r0, min(height, r0 + rows), c0, min(width, c0 + cols))
        for r0 in range(0, height, rows)
        for c0 in range(0, width, cols)
    ]


def _write(
    grid: GridMap,
    path: str | Path,
    count: int,
    cells: _CellReader,
    profile: Mapping[str, Any],
    describe: Callable[[Any], None],
    bands: Sequence[str],
    crs: Any = None,
) -> Path:
    """Write ``count`` bands of the map's shape, read a window at a time by ``cells``, to
    ``path`` as COG (or tiled GTiff) with overviews.

    The bands (never all of them at once in memory), their tags and overviews go to a tiled
    GTiff on disk next to ``path`` (not in memory, where a long map would be held twice),
    then copied to ``path`` as COG with those overviews; GDAL's cache is bounded meanwhile
    (:data:`_GDAL_CACHE_BYTES`). The result is byte for byte the file that writing all the
    bands at once to an in-memory GTiff gives: the intermediate file is pixel-interleaved
    like that one, so GDAL computes the overviews the same way (their values do not depend
    on the tiling, but band-interleaved, GDAL computes them band by band another way, and
    the small overviews of a narrow map come out different).
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.shutil import copy as rio_copy
    from rasterio.windows import Window

    height, width = grid.shape
    if height == 0 or width == 0:
        raise InputError(f"cannot write an empty map of shape {grid.shape}")
    driver = profile["driver"]
    block = _source_block(width)
    cell_bytes = count * np.dtype(profile["dtype"]).itemsize
    path = Path(path)
    with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_BYTES) as env:
        if driver == "COG" and "COG" not in env.drivers():
            log.info("GDAL has no COG driver; writing a tiled GTiff with overviews")
            driver = "GTiff"
        with atomic_output(path) as tmp, gdal_errors(path):
            src_path = tmp.with_name(f"{tmp.stem}.src.tif")
            try:
                with rasterio.open(
                    src_path,
                    "w",
                    driver="GTiff",
                    width=width,
                    height=height,
                    count=count,
                    dtype=profile["dtype"],
                    crs=grid.crs.rasterio() if crs is None else crs,
                    transform=grid.geometry.transform(),
                    nodata=profile["nodata"],
                    tiled=True,
                    blockxsize=block[0],
                    blockysize=block[1],
                    interleave="pixel",
                    bigtiff="if_safer",
                ) as ds:
                    for r0, r1, c0, c1 in _chunks((height, width), block, cell_bytes):
                        window = Window(c0, r0, c1 - c0, r1 - r0)
                        ds.write(cells(r0, r1, c0, c1), window=window)
                    ds.update_tags(**_dataset_tags(grid, bands))
                    describe(ds)
                    ds.build_overviews(
                        overview_factors((height, width), int(profile["overview_min_size"])),
                        Resampling[profile["overview_resampling"]],
                    )
                    ds.update_tags(ns="rio_overview", resampling=profile["overview_resampling"])
                with rasterio.open(src_path) as src:
                    rio_copy(
                        src, tmp, driver=driver, **_creation_options(profile, driver, grid.shape)
                    )
            finally:
                src_path.unlink(missing_ok=True)
                src_path.with_name(f"{src_path.name}.aux.xml").unlink(missing_ok=True)
    log.info("wrote %s (%d band(s) of %d x %d cells, %s)", path, count, height, width, driver)
    return path


def write_values_geotiff(
    grid: GridMap,
    path: str | Path,
    *,
    layers: list[str] | tuple[str, ...] | None = None,
    profile: dict[str, Any] | None = None,
    crs: Any = None,
) -> Path:
    """Write the value layers of a map as a float32 COG, one band per layer.

    Parameters
    ----------
    grid : GridMap
        The map.
    path : str or Path
        The ``.tif`` to write (its folder must exist).
    layers : sequence of str, optional
        Layers, in band order (default :func:`value_layers`).
    profile : dict, optional
        Overrides of :class:`~rough_map.export.profiles.ValuesProfile`.
    crs : rasterio CRS, optional
        The file's CRS where rough_map's :class:`~rough_map.config.Crs` cannot name the
        map's world frame (a WKT without an EPSG code); the map's geometry is then in that
        CRS's units. Default the map's.

    Returns
    -------
    Path
        ``path``.
    """
    prof = ValuesProfile(profile or {})
    names = list(layers) if layers is not None else value_layers(grid)
    if not names:
        raise InputError("the map has no value layer to write")
    height = grid.shape[0]

    def cells(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        # north-up rows r0:r1 are the map's rows height-r1:height-r0, flipped; converted
        # one layer at a time, never all layers as float64
        out = np.empty((len(names), r1 - r0, c1 - c0), dtype=prof["dtype"])
        for i, name in enumerate(names):
            out[i] = grid[name][height - r1 : height - r0, c0:c1][::-1]
        return out

    def describe(ds: Any) -> None:
        for b, name in enumerate(names, start=1):
            info = grid.info(name)
            ds.set_band_description(b, name)
            if info.units:
                ds.set_band_unit(b, info.units)  # GDAL's band unit type
            tags = {"units": info.units, "long_name": info.description, "layer": name}
            if info.categories:
                tags["categories"] = json.dumps(list(info.categories))
                tags.update({f"VALUE_{i}": c for i, c in enumerate(info.categories)})
            ds.update_tags(b, **tags)

    return _write(grid, path, len(names), cells, prof, describe, names, crs)


def write_class_geotiff(
    grid: GridMap,
    path: str | Path,
    layer: str = "class",
    *,
    profile: dict[str, Any] | None = None,
    crs: Any = None,
) -> Path:
    """Write a class layer as a uint8 COG with a colour table (nodata 255 = unknown).

    Parameters
    ----------
    grid : GridMap
        The map.
    path : str or Path
        The ``.tif`` to write.
    layer : str
        A ``kind="class"`` layer (``class`` or ``far_class``).
    profile : dict, optional
        Overrides of :class:`~rough_map.export.profiles.ClassProfile`.
    crs : rasterio CRS, optional
        The file's CRS where rough_map's :class:`~rough_map.config.Crs` cannot name the
        map's world frame (a WKT without an EPSG code); the map's geometry is then in that
        CRS's units. Default the map's.

    Returns
    -------
    Path
        ``path``.
    """
    prof = ClassProfile(profile or {})
    info = grid.info(layer)
    names = info.categories
    if info.kind != "class" or not names:
        raise InputError(f"layer {layer!r} is not a class layer with category names")
    if len(names) >= CLASS_NODATA:
        raise InputError(f"{len(names)} classes do not fit a uint8 band with nodata 255")
    height = grid.shape[0]

    def cells(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        values = grid[layer][height - r1 : height - r0, c0:c1][::-1]
        return np.where(np.isfinite(values), values, CLASS_NODATA).astype(np.uint8)[None]

    def describe(ds: Any) -> None:
        ds.set_band_description(1, layer)
        ds.set_band_unit(1, "1")
        ds.update_tags(
            1,
            units="1",
            long_name=info.description,
            layer=layer,
            class_names=json.dumps(list(names)),
            **{f"CLASS_{i}": c for i, c in enumerate(names)},
            **{f"CLASS_{CLASS_NODATA}": "unknown"},
        )
        ds.write_colormap(1, class_colours(names))

    written = _write(grid, path, 1, cells, prof, describe, [layer], crs)
    colours = [class_colour(n, i) for i, n in enumerate(names)]
    write_category_names(written, names, colours)
    write_qgis_style(written, names, colours)
    return written
