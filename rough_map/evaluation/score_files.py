"""``rough-map score``: a written map folder scored against a truth GeoTIFF.

The map folder is what ``rough-map map`` writes: ``<stem>.tif`` (float bands, among them
``count`` and, with near-to-far, ``far_count``, maybe ``far_confidence``), one
``<stem>_<layer>.tif`` per class layer (uint8, nodata 255, class names in band-1 tags:
``class``, ``far_class``, ...) and
``labels.csv`` (the frames' positions, the path). The truth is a class GeoTIFF in any CRS
and resolution (:mod:`rough_map.io.truth_raster`), reprojected onto the map's grid with
:func:`rasterio.warp.reproject`:

``nearest`` (default)
    each map cell takes the true class at its centre — the class a point survey of the
    cell centre gives, and exactly what the accuracy against the simulator's world uses
    (:mod:`rough_map.evaluation.truth`), so both give the same numbers. Classes are
    categories: averaging (bilinear, ...) would invent classes between codes.
``mode``
    each map cell takes the class covering most of it (GDAL's mode over the truth cells
    inside it): for a truth much finer than the map, the cell's dominant ground.

Truth nodata (and truth cells named ``unknown``) are not scored. The truth needs a CRS; a
truth in a local engineering CRS (rough_map's ``LOCAL_CS`` of a traverse without geodetic
origin) is taken to lie in the map's local frame when the map's CRS is local too (PROJ
relates no engineering CRS), and is refused on a georeferenced map.
"""

from __future__ import annotations

import csv
import io
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import clip, read_document_text
from rough_map._files import PathLike
from rough_map.errors import FileFormatError, InputError
from rough_map.evaluation.score import (
    DEFAULT_BINS,
    LayerPrediction,
    MapScore,
    observed_mask,
    path_distance,
    score_cells,
)
from rough_map.io.truth_raster import read_class_names
from rough_map.limits import LIMITS

log = logging.getLogger(__name__)

__all__ = ["RESAMPLING", "read_map_dir", "resample_truth", "score_map_dir"]

#: Resampling methods of the truth onto the map's grid (module docstring).
RESAMPLING = ("nearest", "mode")


def resample_truth(
    path: PathLike,
    shape: tuple[int, int],
    transform: Any,
    crs: Any,
    resampling: str = "nearest",
) -> tuple[np.ndarray, dict[int, str]]:
    """The truth GeoTIFF ``path`` on a grid: (rows, cols) int64 class values (-1: no
    truth) and the value -> name map.

    Parameters
    ----------
    path : str or Path
        Truth GeoTIFF (band 1, integer classes; names as in
        :mod:`rough_map.io.truth_raster`).
    shape : (int, int)
        Rows and columns of the target grid.
    transform : affine.Affine
        The target grid's geotransform (m).
    crs : rasterio CRS
        The target grid's CRS.
    resampling : str
        ``nearest`` or ``mode`` (module docstring).

    Raises
    ------
    FileFormatError
        Missing or unreadable file, no CRS, not integer, values without a name, no overlap.
    """
    import rasterio
    from rasterio._err import CPLE_BaseError
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioError
    from rasterio.warp import reproject

    path = Path(path)
    if resampling not in RESAMPLING:
        raise InputError(f"resampling must be one of {', '.join(RESAMPLING)}, got {resampling!r}")
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    try:
        with rasterio.open(path) as src:
            if src.crs is None:
                raise FileFormatError(path, "no CRS: cannot place the truth on the map", "crs")
            dtype = np.dtype(src.dtypes[0])
            if dtype.kind not in "iu":
                raise FileFormatError(
                    path, f"band 1 is {dtype}; class values must be integers", "dtype"
                )
            names = read_class_names(path, src)
            nodata = src.nodata
            if nodata is None:
                nodata = int(np.iinfo(dtype).max)
                if nodata in names:
                    raise FileFormatError(path, "no nodata value and every value named", "nodata")
            dst = np.full(shape, nodata, dtype=dtype)
            src_crs, dst_crs = _warp_crs(path, src.crs, crs)
            source: Any = rasterio.band(src, 1)
            src_transform = src.transform
            if src_crs is not src.crs:  # two local frames: GDAL would use the file's CRS
                source, src_transform = _local_window(src, shape, transform)
            reproject(
                source,
                dst,
                src_crs=src_crs,
                src_transform=src_transform,
                src_nodata=nodata,
                dst_transform=transform,
                dst_crs=dst_crs,
                dst_nodata=nodata,
                resampling=Resampling[resampling],
            )
    except (RasterioError, CPLE_BaseError) as exc:
        msg = " ".join(str(exc).split())[:300]
        raise FileFormatError(path, f"cannot read or reproject: {msg}") from None
    values = dst.astype(np.int64)
    values[dst == nodata] = -1
    present = set(np.unique(values[values >= 0]).tolist())
    unnamed = sorted(present - set(names))
    if unnamed:
        raise FileFormatError(
            path, f"class values {unnamed} have no name (known: {names})", "class names"
        )
    if not present:
        raise FileFormatError(path, "no true class inside the map's extent (no overlap)", "extent")
    return values, names


def _is_local(crs: Any) -> bool:
    """A local engineering CRS (neither geographic nor projected), as rough_map writes for
    a traverse without a geodetic origin."""
    return not (crs.is_geographic or crs.is_projected)


#: Stands for both sides of a warp between two local frames (metres; the same CRS on both
#: sides is an identity): PROJ relates no engineering CRS, not even to itself.
_LOCAL_STAND_IN = "+proj=tmerc +lat_0=0 +lon_0=0 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m"


def _warp_crs(path: Path, src: Any, dst: Any) -> tuple[Any, Any]:
    """The (truth, map) CRSs for the warp. A local engineering CRS of the truth is taken
    as the map's own local frame when the map's is local too (both become
    :data:`_LOCAL_STAND_IN`, so the warp is the identity between the frames)."""
    if _is_local(src) and _is_local(dst):
        log.info("%s: local CRS, taken as the map's local frame", path)
        return _LOCAL_STAND_IN, _LOCAL_STAND_IN
    if _is_local(src) != _is_local(dst):
        raise FileFormatError(
            path,
            "a local (engineering) CRS cannot be placed on a georeferenced map or the other "
            "way round; give the truth in the map's CRS",
            "crs",
        )
    return src, dst


def _local_window(src: Any, shape: tuple[int, int], transform: Any) -> tuple[Any, Any]:
    """The truth's cells under a grid of ``shape`` and ``transform`` in the same frame
    (a margin of one cell), as an array and its transform."""
    from rasterio.transform import Affine
    from rasterio.windows import Window

    rows, cols = shape
    inv = ~src.transform
    corners = []
    for r in (0, rows):
        for c in (0, cols):
            x = transform.c + c * transform.a + r * transform.b
            y = transform.f + c * transform.d + r * transform.e
            corners.append((inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f))
    c0 = max(0, math.floor(min(p[0] for p in corners)) - 1)
    r0 = max(0, math.floor(min(p[1] for p in corners)) - 1)
    c1 = min(src.width, math.ceil(max(p[0] for p in corners)) + 1)
    r1 = min(src.height, math.ceil(max(p[1] for p in corners)) + 1)
    if c1 <= c0 or r1 <= r0:  # no overlap: one cell of nodata
        return np.full((1, 1), src.nodata or 0, dtype=src.dtypes[0]), src.transform
    window = Window(c0, r0, c1 - c0, r1 - r0)
    t = src.transform
    shifted = Affine(t.a, t.b, t.c + c0 * t.a + r0 * t.b, t.d, t.e, t.f + c0 * t.d + r0 * t.e)
    return src.read(1, window=window), shifted


def _tags_layer(ds: Any) -> str | None:
    return ds.tags(1).get("layer") or (ds.descriptions[0] if ds.descriptions else None)


def read_map_dir(map_dir: PathLike) -> dict[str, Any]:
    """The class layers of a map folder written by ``rough-map map``.

    Returns
    -------
    dict
        ``shape``, ``transform``, ``crs``, ``resolution_m``, ``layers`` (name ->
        (values int64 north-up, -1 unknown; names; observed bool or None)), ``path_xy``
        ((n, 2) m or None), ``files``.

    Raises
    ------
    FileFormatError
        Not a map folder (no ``*_class.tif``), or class files of different grids.
    """
    from rasterio._err import CPLE_BaseError
    from rasterio.errors import RasterioError

    map_dir = Path(map_dir)
    if not map_dir.is_dir():
        raise FileFormatError(map_dir, "no such map folder")
    try:
        return _read_map_dir(map_dir)
    except (RasterioError, CPLE_BaseError) as exc:
        msg = clip(str(exc), 100)
        raise FileFormatError(map_dir, f"cannot read a map file: {msg}") from None


def _check_size(path: Path, ds: Any) -> None:
    """Refuse a raster whose declared size its file cannot hold (compressed) or beyond
    ``LIMITS.raster_cells``, before reading it."""
    cells = int(ds.width) * int(ds.height) * int(ds.count)
    limit = min(LIMITS.raster_cells, path.stat().st_size * LIMITS.deflate_ratio + 2**20)
    if cells > limit:
        raise FileFormatError(
            path, f"declares {ds.width} x {ds.height} x {ds.count} cells, more than it holds"
        )


def _read_map_dir(map_dir: Path) -> dict[str, Any]:
    import rasterio

    stems = sorted({f.name[: -len("_class.tif")] for f in map_dir.glob("*_class.tif")} - {""})
    stems = [s for s in stems if not s.endswith("_far")]
    if not stems:
        raise FileFormatError(map_dir, "no <name>_class.tif: not a `rough-map map` folder")
    stem = "map" if "map" in stems else stems[0]
    out: dict[str, Any] = {"layers": {}, "files": {}}
    for f in sorted(map_dir.glob(f"{stem}_*.tif")):
        with rasterio.open(f) as ds:
            layer = _tags_layer(ds)
            if ds.count != 1 or ds.dtypes[0] != "uint8" or not layer:
                continue
            _check_size(f, ds)
            try:
                names = read_class_names(f, ds)
            except FileFormatError:
                continue  # a uint8 file that is not a class layer
            if "shape" not in out:
                out.update(shape=ds.shape, transform=ds.transform, crs=ds.crs)
                out["resolution_m"] = abs(ds.transform.a)
            elif ds.shape != out["shape"] or ds.transform != out["transform"]:
                raise FileFormatError(f, "not on the grid of the other class files", "transform")
            names = {k: v for k, v in names.items() if k != ds.nodata and 0 <= k <= 255}
            if not names:
                continue  # names only for values a uint8 layer cannot hold
            raw = ds.read(1)
            values = raw.astype(np.int64)
            values[(raw == ds.nodata) | ~np.isin(raw, list(names))] = -1
            ordered = tuple(names.get(i, f"value_{i}") for i in range(max(names) + 1))
            out["layers"][layer] = [values, ordered, None]
            out["files"][layer] = str(f)
    if not out["layers"]:
        raise FileFormatError(map_dir, f"no class layer in {stem}_*.tif")
    values_file = map_dir / f"{stem}.tif"
    if values_file.is_file():
        with rasterio.open(values_file) as ds:
            _check_size(values_file, ds)
            bands = {d: i + 1 for i, d in enumerate(ds.descriptions) if d}
            if ds.shape == out["shape"]:
                for layer, entry in out["layers"].items():
                    entry[2] = observed_mask(
                        layer, lambda n: ds.read(bands[n]) if n in bands else None
                    )
    out["path_xy"] = _read_path(map_dir / "labels.csv")
    return out


def _read_path(path: Path) -> np.ndarray | None:
    if not path.is_file():
        log.warning("%s: not found; no accuracy by distance from the path", path)
        return None
    try:
        rows = list(csv.DictReader(io.StringIO(read_document_text(path), newline="")))
    except csv.Error as exc:
        raise FileFormatError(path, f"not a CSV table: {clip(str(exc), 60)}") from None
    try:
        xy = np.array([[float(r["x"]), float(r["y"])] for r in rows], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise FileFormatError(path, "expected numeric columns x, y (m)", "x,y") from None
    return xy if len(xy) else None


def score_map_dir(
    map_dir: PathLike,
    truth: PathLike,
    *,
    resampling: str = "nearest",
    bins: tuple[float, ...] = DEFAULT_BINS,
    max_distance: float = math.inf,
) -> MapScore:
    """Score the class layers of a ``rough-map map`` folder against a truth GeoTIFF.

    Parameters
    ----------
    map_dir : str or Path
        The map folder (:func:`read_map_dir`).
    truth : str or Path
        The truth GeoTIFF (:func:`resample_truth`).
    resampling : str
        ``nearest`` (default) or ``mode``.
    bins : tuple of float
        Upper edges of the distance bins, m from the path.
    max_distance : float
        Score only cells up to this far from the path, m (default: all).

    Returns
    -------
    MapScore
        See :mod:`rough_map.evaluation.score`.
    """
    m = read_map_dir(map_dir)
    values, names = resample_truth(truth, m["shape"], m["transform"], m["crs"], resampling)
    res = float(m["resolution_m"])
    distance = None
    if m["path_xy"] is not None:
        rows, cols = np.indices(m["shape"])
        t = m["transform"]
        c, r = cols.ravel() + 0.5, rows.ravel() + 0.5
        x, y = t.c + c * t.a + r * t.b, t.f + c * t.d + r * t.e
        distance = path_distance(x, y, m["path_xy"], res / 4)
    elif math.isfinite(max_distance):
        raise FileFormatError(Path(map_dir) / "labels.csv", "no path: cannot apply max_distance")
    layers = {
        name: LayerPrediction(v.ravel(), n, None if o is None else o.ravel())
        for name, (v, n, o) in m["layers"].items()
    }
    score = score_cells(
        layers,
        values.ravel(),
        names,
        distance=distance,
        bins=bins,
        max_distance=max_distance,
        cell_area_m2=round(res * res, 12),
        resampling=resampling,
    )
    score.sources.update(map=str(map_dir), truth=str(truth), **{
        f"{k}_file": v for k, v in m["files"].items()})  # fmt: skip
    return score
