"""Class rasters of surveyed (or simulated) ground truth: GeoTIFFs with class names.

A truth raster is a single-band GeoTIFF (any CRS GDAL knows, any resolution) of integer
class values, with a nodata value for cells without truth. Its class names come from the
first of these that exists (the same convention as the map's ``*_class.tif``):

1. a sidecar beside it, ``<stem>.classes.json`` — ``{"0": "gravel", "1": "concrete"}``
   or a list of names (value = position) — or ``<stem>.classes.csv`` with the columns
   ``value,name``;
2. band-1 tags ``CLASS_<value>=<name>`` (GDAL metadata; ``gdal_edit.py -mo CLASS_3=gravel``
   sets one), or a band/dataset tag ``class_names`` holding a JSON list (value = position);
3. GDAL category names (``GDALSetRasterCategoryNames``: ``<CategoryNames>`` in the
   ``<file>.aux.xml`` beside it, as GDAL and QGIS write them; value = position; empty names
   are skipped).

Names are compared lower-cased with spaces and dashes as underscores (``Dirt road`` is
``dirt_road``). A value named ``unknown``, ``nodata`` or ``none`` means no truth, as does
the nodata value.

``rough-map simulate`` writes its world's classes so (:data:`TRUTH_GEOTIFF`, via
:func:`write_truth_geotiff`): uint8, nodata 255, at the world's spacing (2 mm), north-up,
in the traverse's CRS, names in the band-1 tags.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import clip, parse_document, parse_json, read_document_text
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError, InputError
from rough_map.io.truth import TiledWorld, World
from rough_map.limits import LIMITS

log = logging.getLogger(__name__)

__all__ = [
    "DEM_GEOTIFF",
    "NO_TRUTH_NAMES",
    "TRUTH_GEOTIFF",
    "TRUTH_NODATA",
    "canonical_name",
    "read_class_names",
    "write_dem_geotiff",
    "write_truth_geotiff",
]

#: File name of the class truth GeoTIFF in a simulated traverse folder.
TRUTH_GEOTIFF = "world_truth.tif"

#: File name of the true heights as a GeoTIFF DEM (``rough-map simulate --dem``).
DEM_GEOTIFF = "world_dem.tif"

#: Nodata of the truth GeoTIFFs rough_map writes (uint8).
TRUTH_NODATA = 255

#: Class names that mean "no truth here".
NO_TRUTH_NAMES = frozenset({"unknown", "nodata", "none", "no_data"})


def canonical_name(name: str) -> str:
    """A class name as compared: stripped, lower case, spaces and dashes as underscores."""
    return re.sub(r"[\s\-]+", "_", str(name).strip().lower())


def _sidecars(path: Path) -> list[Path]:
    stem = path.with_suffix("")
    return [stem.with_name(f"{stem.name}.classes.json"), stem.with_name(f"{stem.name}.classes.csv")]


#: The largest class value of a truth raster (absolute).
_MAX_VALUE = 2**31 - 1


def _checked(names: dict[int, str], path: Path, field: str) -> dict[int, str]:
    """``names`` if their number and values are sane, else a FileFormatError."""
    if len(names) > LIMITS.raster_class_names:
        raise FileFormatError(
            path, f"{len(names)} class names (most {LIMITS.raster_class_names})", field
        )
    if names and max(abs(v) for v in names) > _MAX_VALUE:
        raise FileFormatError(path, f"class values must be within +-{_MAX_VALUE}", field)
    return names


def _int_key(key: object) -> int:
    text = str(key).strip()
    if not re.fullmatch(r"[+-]?\d{1,10}", text):
        raise ValueError(key)
    return int(text)


def _from_json_sidecar(path: Path) -> dict[int, str]:
    data = parse_document(path, kind="json")
    if isinstance(data, list):
        return _checked({i: str(n) for i, n in enumerate(data)}, path, "names")
    if isinstance(data, dict):
        try:
            return _checked({_int_key(k): str(v) for k, v in data.items()}, path, "keys")
        except ValueError:
            raise FileFormatError(path, "keys must be integer class values", "keys") from None
    raise FileFormatError(path, "expected a list of names or an object {value: name}")


def _from_csv_sidecar(path: Path) -> dict[int, str]:
    try:
        text = read_document_text(path)
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise FileFormatError(path, f"cannot read: {clip(str(exc), 80)}") from None
    if not rows or not {"value", "name"} <= set(rows[0]):
        raise FileFormatError(path, "expected the columns value,name", "value,name")
    try:
        return _checked({_int_key(r["value"]): str(r["name"]) for r in rows}, path, "value")
    except (TypeError, ValueError):
        raise FileFormatError(path, "values must be integers", "value") from None


def _from_tags(tags: Mapping[str, str], path: Path) -> dict[int, str]:
    pattern = r"CLASS_\d{1,10}"
    names = {int(k[6:]): v for k, v in tags.items() if re.fullmatch(pattern, k, re.IGNORECASE)}
    if names:
        return _checked(names, path, "CLASS_<value>")
    if "class_names" in tags:
        listed = parse_json(str(tags["class_names"]), path)
        if not isinstance(listed, list):
            raise FileFormatError(path, "not a JSON list", "class_names")
        return _checked({i: str(n) for i, n in enumerate(listed)}, path, "class_names")
    return {}


def _from_aux_xml(path: Path) -> dict[int, str]:
    aux = path.with_name(f"{path.name}.aux.xml")
    if not aux.is_file():
        return {}
    try:
        root = ET.fromstring(read_document_text(aux))
    except ET.ParseError as exc:
        raise FileFormatError(aux, f"not GDAL PAM XML: {clip(str(exc), 80)}") from None
    except RecursionError:
        raise FileFormatError(aux, "not GDAL PAM XML: nested too deeply") from None
    band = root.find("PAMRasterBand[@band='1']")
    cats = None if band is None else band.find("CategoryNames")
    if cats is None:
        return {}
    names = {i: (c.text or "") for i, c in enumerate(cats.findall("Category")) if c.text}
    return _checked(names, aux, "CategoryNames")


def read_class_names(path: PathLike, dataset: Any = None) -> dict[int, str]:
    """Class value -> name of a truth raster (the module docstring's conventions).

    Parameters
    ----------
    path : str or Path
        The GeoTIFF.
    dataset : rasterio dataset, optional
        ``path`` opened (else opened here).

    Raises
    ------
    FileFormatError
        No class names found, or a sidecar that cannot be read.
    """
    path = Path(path)
    json_side, csv_side = _sidecars(path)
    if json_side.is_file():
        return _from_json_sidecar(json_side)
    if csv_side.is_file():
        return _from_csv_sidecar(csv_side)
    if dataset is None:
        import rasterio
        from rasterio._err import CPLE_BaseError
        from rasterio.errors import RasterioError

        try:
            with rasterio.open(path) as ds:
                return read_class_names(path, ds)
        except (RasterioError, CPLE_BaseError) as exc:
            raise FileFormatError(path, f"not a readable raster: {clip(str(exc), 80)}") from None
    names = _from_tags(dataset.tags(1), path) or _from_tags(dataset.tags(), path)
    names = names or _from_aux_xml(path)
    if not names:
        raise FileFormatError(
            path,
            f"no class names: add {json_side.name} ({{value: name}}), band-1 tags "
            "CLASS_<value>=<name>, or GDAL category names",
            "class names",
        )
    return names


def write_truth_geotiff(
    world: World,
    path: PathLike,
    crs: Any,
    *,
    class_names: Sequence[str] | None = None,
) -> Path:
    """Write a world's class map as a truth GeoTIFF (uint8, nodata 255, DEFLATE, tiled).

    Parameters
    ----------
    world : HeightField or TiledWorld
        The world, with a class map; cell ``[i, j]`` is centred at ``origin + (j, i) *
        spacing`` (m). A tiled world is written a tile at a time.
    path : str or Path
        The ``.tif`` to write (atomic).
    crs : rasterio CRS or str
        The CRS of the world's x, y (the traverse's).
    class_names : sequence of str, optional
        Names of the class indices (default ``world.class_names``).

    Returns
    -------
    Path
        ``path``.
    """
    from rasterio.transform import Affine
    from rasterio.windows import Window

    if not isinstance(world, TiledWorld) and world.classes is None:
        raise InputError("the world has no class map to write as truth")
    names = list(class_names if class_names is not None else world.class_names)
    if len(names) >= TRUTH_NODATA:
        raise InputError(f"{len(names)} classes do not fit a uint8 band with nodata 255")
    ny, nx = world.shape
    s = world.spacing
    transform = Affine(s, 0.0, world.origin[0] - s / 2, 0.0, -s, world.origin[1] + (ny - 0.5) * s)
    blocks: Iterator[tuple[int, np.ndarray]]
    if isinstance(world, TiledWorld):
        # one tile in memory at a time: a list of them all held 1 GB for a 1 km course
        tiled = world
        blocks = ((int(tiled.tile_columns[k]), tiled.tile_classes(k)) for k in range(tiled.n_tiles))
    else:
        assert world.classes is not None
        step = 4096  # columns at a time: small temporaries
        blocks = ((c, world.classes[:, c : c + step]) for c in range(0, nx, step))
    path = Path(path)
    with _band_file(path, (nx, ny), "uint8", crs, transform, TRUTH_NODATA) as ds:
        for c0, classes in blocks:
            data = np.where(classes >= 0, classes, TRUTH_NODATA).astype(np.uint8)[::-1]
            ds.write(data[None], window=Window(c0, 0, data.shape[1], ny))
        ds.set_band_description(1, "class")
        ds.update_tags(
            1,
            layer="class",
            long_name="true terrain class index",
            class_names=json.dumps(names),
            **{f"CLASS_{i}": n for i, n in enumerate(names)},
        )
    log.info("wrote %s (%d x %d truth cells of %g m)", path, ny, nx, s)
    return path


def write_dem_geotiff(world: World, path: PathLike, crs: Any, spacing: float = 0.008) -> Path:
    """Write a world's heights as a GeoTIFF DEM sampled every ``spacing`` m (float32 m,
    nodata NaN, DEFLATE, tiled), as a survey would give them: the world's cells every
    ``round(spacing / world.spacing)``-th row and column, a tile of a tiled world at a time.

    Parameters
    ----------
    world : HeightField or TiledWorld
        The world; cell ``[i, j]`` is centred at ``origin + (j, i) * spacing`` (m).
    path : str or Path
        The ``.tif`` to write (atomic).
    crs : rasterio CRS or str
        The CRS of the world's x, y (the traverse's).
    spacing : float
        Cell size of the DEM in m, a whole multiple of the world's (rounded to one).

    Returns
    -------
    Path
        ``path``.
    """
    from rasterio.transform import Affine
    from rasterio.windows import Window

    ny, nx = world.shape
    s = world.spacing
    step = max(1, round(spacing / s))
    rows = np.arange(0, ny, step)
    n_cols = (nx - 1) // step + 1
    cell = step * s
    north = world.origin[1] + rows[-1] * s + cell / 2
    transform = Affine(cell, 0.0, world.origin[0] - cell / 2, 0.0, -cell, north)
    blocks: Iterator[tuple[int, np.ndarray]]
    if isinstance(world, TiledWorld):
        tiled = world
        blocks = ((int(tiled.tile_columns[k]), tiled.tile_heights(k)) for k in range(tiled.n_tiles))
    else:
        blocks = ((c, world.heights[:, c : c + 4096 * step]) for c in range(0, nx, 4096 * step))
    path = Path(path)
    with _band_file(path, (n_cols, len(rows)), "float32", crs, transform, float("nan")) as ds:
        for c0, heights in blocks:
            first = -c0 % step  # the block's first column on the DEM's lattice
            part = np.asarray(heights[rows, first::step], dtype=np.float32)[::-1]
            if part.shape[1]:
                ds.write(
                    part[None], window=Window((c0 + first) // step, 0, part.shape[1], len(rows))
                )
        ds.set_band_description(1, "elevation")
        ds.set_band_unit(1, "m")
        ds.update_tags(1, layer="elevation", long_name="true terrain height (world z)", units="m")
    log.info("wrote %s (%d x %d heights every %g m)", path, len(rows), n_cols, cell)
    return path


@contextmanager
def _band_file(
    path: Path, size: tuple[int, int], dtype: str, crs: Any, transform: Any, nodata: float
) -> Iterator[Any]:
    """A one-band tiled, deflated GeoTIFF of ``size`` (width, height) being written to
    ``path`` (atomically: in place when the block ends without error)."""
    import rasterio

    with (
        atomic_output(path) as tmp,
        rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=size[0],
            height=size[1],
            count=1,
            dtype=dtype,
            crs=crs,
            transform=transform,
            nodata=nodata,
            tiled=True,
            blockxsize=256,
            blockysize=256,
            compress="deflate",
            bigtiff="if_safer",
        ) as ds,
    ):
        yield ds
