"""Height rasters: a surface given as a grid of heights, read on its own grid.

A survey, a DEM or DSM from photogrammetry or lidar, is a grid of heights, not a cloud:
:func:`open_height_raster` opens it as a :class:`HeightRaster`, which reads a band of rows
at a time (:meth:`HeightRaster.rows`), so a survey of any size is read in bounded memory.

Formats
    Any raster GDAL reads, through rasterio (GeoTIFF, COG, Esri ASCII grid, VRT, ...): band
    1 as heights, its nodata as missing cells (NaN), integer or float, with the band's scale
    and offset applied. The raster must be north-up with square cells (no rotation), in a
    projected CRS: in metres or feet (cells and heights are then converted to m for the
    estimator; the outputs stay in the raster's CRS and units), named by an EPSG code or
    else kept as the file's own (:attr:`HeightRaster.file_crs`). A geographic CRS (degrees)
    is refused, naming the reprojection that fixes it (``gdalwarp``). A raster without a CRS
    is read in a local frame, its cells in m.

    A NumPy ``.npy`` grid of heights in m, with its ``spacing`` (m) given: row 0 is the
    north edge (as in an image or a GeoTIFF), its north-west corner at ``origin``.

    A cloud in a world frame: LAS/LAZ (:func:`rough_map.io.las.read_las`) with its CRS,
    its ground points (ASPRS class 2, all points if it has none); or any other cloud
    :func:`rough_map.io.pointcloud.read_cloud` reads (.ply, .pcd, .csv/.xyz/.txt, KITTI
    .bin, a ``.npy`` of N x 3 points given without a spacing), every point, in metres, in
    the CRS given. The points are gridded at the finest spacing their density supports,
    :data:`CLOUD_POINTS_PER_CELL` points per cell on average over the area they cover,
    rounded up to two digits (airborne lidar at 50 points per m²: 0.21 m), as the mean
    height per cell; :attr:`HeightRaster.note` says what was chosen.

Every problem is a one-line :class:`~rough_map.errors.FileFormatError` naming the file and
the field, or an :class:`~rough_map.errors.InputError` for a bad argument.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import clip
from rough_map._files import PathLike
from rough_map.config import Crs
from rough_map.errors import FileFormatError, InputError
from rough_map.io._check import check_readable
from rough_map.io.crg import read_crg
from rough_map.io.las import read_las
from rough_map.io.pointcloud import read_cloud
from rough_map.io.safe_npz import read_npy
from rough_map.limits import LIMITS

log = logging.getLogger(__name__)

__all__ = ["CLOUD_POINTS_PER_CELL", "HeightRaster", "open_height_raster", "shared_height_raster"]


@dataclass(frozen=True)
class HeightRaster:
    """A grid of heights on disk, read a band of rows at a time.

    Attributes
    ----------
    path : Path
        The file.
    shape : tuple of int
        ``(n_rows, n_cols)``; row 0 is the north edge, columns run east.
    spacing : float
        Side of a cell in m.
    origin : tuple of float
        World ``(x, y)`` of the north-west corner of cell ``[0, 0]``, in the CRS's units.
    crs : Crs
        The world frame of ``origin`` (``local`` where :class:`~rough_map.config.Crs`
        cannot name it: see ``file_crs``).
    unit_m : float
        Metres per unit of the CRS (0.3048 in feet); a GDAL raster's heights are taken in
        the same unit.
    file_crs : rasterio CRS, optional
        The file's own CRS where ``crs`` cannot name it (a WKT without an EPSG code): the
        outputs are written in it.
    gridding : {"point", "cell_mean"}
        How the heights were sampled (:class:`rough_map.psd.Options`): samples of the
        surface (a raster), or the mean of the points in each cell (a gridded cloud).
    note : str
        How a cloud was gridded (its density and the spacing chosen), for the reports.
    """

    path: Path
    shape: tuple[int, int]
    spacing: float
    origin: tuple[float, float]
    crs: Crs = field(default_factory=lambda: Crs(code="local"))
    _array: np.ndarray | None = field(default=None, repr=False, compare=False)
    unit_m: float = 1.0
    file_crs: Any = field(default=None, compare=False)
    gridding: str = "point"
    note: str = ""

    @property
    def cell(self) -> float:
        """Side of a cell in the CRS's units."""
        return self.spacing / self.unit_m

    def rows(self, first: int, count: int) -> np.ndarray:
        """Heights in m of rows ``first .. first + count - 1`` (float64, NaN: missing).

        Raises
        ------
        FileFormatError
            The file cannot give those rows (truncated or damaged).
        """
        if not (0 <= first and count >= 0 and first + count <= self.shape[0]):
            raise InputError(f"rows {first}..{first + count} outside the {self.shape[0]} rows")
        return self._read(first, 0, count, self.shape[1])

    def window(self, row: int, col: int, height: int, width: int) -> np.ndarray:
        """Heights in m of the ``height`` x ``width`` cells from cell ``[row, col]`` on
        (float64), NaN where missing or off the raster (the window may overhang it).

        Raises
        ------
        FileFormatError
            The file cannot give those cells (truncated or damaged).
        """
        out = np.full((max(height, 0), max(width, 0)), np.nan)
        r0, c0 = max(row, 0), max(col, 0)
        r1, c1 = min(row + height, self.shape[0]), min(col + width, self.shape[1])
        if r1 > r0 and c1 > c0:
            out[r0 - row : r1 - row, c0 - col : c1 - col] = self._read(r0, c0, r1 - r0, c1 - c0)
        return out

    def _read(self, row: int, col: int, height: int, width: int) -> np.ndarray:
        """The cells of a window inside the raster, in m (NaN: missing)."""
        if self._array is not None:
            return np.array(self._array[row : row + height, col : col + width], dtype=np.float64)
        with _rasterio_errors(self.path), _open(self.path) as ds:
            from rasterio.enums import MaskFlags
            from rasterio.windows import Window

            window = Window(col, row, width, height)
            raw = ds.read(1, window=window)
            heights = raw.astype(np.float64)
            scale, offset = ds.scales[0], ds.offsets[0]
            if scale not in (None, 1.0):
                heights *= scale
            if offset not in (None, 0.0):
                heights += offset
            if self.unit_m != 1.0:
                heights *= self.unit_m
            missing = ~np.isfinite(heights)
            nodata = ds.nodata
            if nodata is not None and math.isfinite(nodata):
                missing |= raw == nodata
            if any(f in (MaskFlags.per_dataset, MaskFlags.alpha) for f in ds.mask_flag_enums[0]):
                missing |= ds.read_masks(1, window=window) == 0
        heights[missing] = np.nan
        return heights

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` in the CRS's units."""
        x0, y0 = self.origin
        return x0, y0 - self.shape[0] * self.cell, x0 + self.shape[1] * self.cell, y0


def open_height_raster(
    path: PathLike,
    *,
    spacing: float | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    crs: Any = None,
) -> HeightRaster:
    """Open a height raster (see the module docstring for the formats).

    Parameters
    ----------
    path : str or PathLike
        A raster GDAL reads, or a ``.npy`` grid.
    spacing : float, optional
        Cell side in m of a ``.npy`` grid (required there; refused for a GDAL raster,
        which says its own).
    origin : tuple of float
        World ``(x, y)`` in m of the north-west corner of a ``.npy`` grid.
    crs : optional
        The CRS of a ``.npy`` grid (:meth:`rough_map.config.Crs.from_any`; default local).

    Raises
    ------
    FileFormatError
        Missing, unreadable or hostile file, a geographic or rotated raster, a CRS without
        an EPSG code, cells that are not square.
    InputError
        ``spacing`` missing for a ``.npy`` grid or given for another raster, or not > 0.
    """
    path = Path(path)
    check_readable(path)
    suffix = path.suffix.lower()
    if suffix == ".npy" and spacing is None and _is_cloud_npy(path):
        return _open_cloud(path, crs)
    if suffix == ".npy":
        return _open_npy(path, spacing, origin, crs)
    if path.suffix.lower() == ".crg":
        if spacing is not None:
            raise InputError(f"{path.name}: a CRG file gives its own grid; drop spacing")
        return _open_crg(path)
    if suffix in CLOUD_SUFFIXES:
        if spacing is not None:
            raise InputError(f"{path.name}: a cloud's spacing is chosen from its density")
        return _open_cloud(path, crs)
    if spacing is not None:
        raise InputError(f"{path.name}: a GDAL raster gives its own cell size; drop spacing")
    with _rasterio_errors(path), _open(path) as ds:
        return _describe(path, ds)


def shared_height_raster(
    path: PathLike, spacing: float | None = None, origin: tuple[float, float] | None = None
) -> HeightRaster:
    """:func:`open_height_raster`, opened once per process while the file is unchanged (a
    gridded cloud or a text CRG is read and gridded once, however many frames cut from it)."""
    try:
        st = os.stat(path)
        stamp = (st.st_mtime_ns, st.st_size)
    except (OSError, ValueError):
        stamp = (0, 0)  # open_height_raster says what is wrong
    return _shared(os.path.realpath(path), spacing, origin, stamp)


@functools.lru_cache(maxsize=2)
def _shared(
    path: str, spacing: float | None, origin: tuple[float, float] | None, stamp: tuple[int, int]
) -> HeightRaster:
    return open_height_raster(path, spacing=spacing, origin=origin or (0.0, 0.0))


def _open_npy(path: Path, spacing: float | None, origin: Any, crs: Any) -> HeightRaster:
    if spacing is None:
        raise InputError(f"{path.name}: a .npy height grid needs its spacing in m")
    if not (isinstance(spacing, int | float) and math.isfinite(spacing) and 0 < spacing <= 1e4):
        raise InputError(f"spacing must be a cell size in m > 0, got {spacing!r}")
    x0, y0 = (float(v) for v in origin)
    if not (math.isfinite(x0) and math.isfinite(y0)):
        raise InputError(f"origin must be finite (x, y) in m, got {origin!r}")
    heights = read_npy(path)
    if heights.ndim != 2 or heights.dtype.kind not in "fiu" or min(heights.shape) < 1:
        raise FileFormatError(
            path,
            f"expected a 2-D numeric grid of heights in m; got shape {clip(heights.shape, 40)}, "
            f"dtype {clip(heights.dtype, 40)}",
            field="shape",
        )
    shape = (int(heights.shape[0]), int(heights.shape[1]))
    return HeightRaster(path, shape, float(spacing), (x0, y0), Crs.from_any(crs), heights)


def _open_crg(path: Path) -> HeightRaster:
    """An OpenCRG surface as a raster in its ``(u, v)`` road coordinates: columns along the
    reference line, row 0 its left edge, so that profiles along the rows run along ``u``."""
    surface = read_crg(path)
    du, dv = surface.du, surface.dv
    if not (math.isfinite(dv) and math.isclose(du, dv, rel_tol=1e-6)):
        raise FileFormatError(
            path,
            f"cells of {du:g} m along by {dv:g} m across (or long sections unevenly spaced): "
            "a survey needs square cells",
            field="LONG_SECTION_V_INCREMENT",
        )
    heights = surface.heights()[:, ::-1].T  # rows: v from the left edge; columns: u
    origin = (float(surface.u[0] - du / 2), float(surface.v[-1] + dv / 2))
    note = (
        f"OpenCRG: {len(surface.u)} x {len(surface.v)} heights every {du:g} m; the rasters "
        "are in its (u, v) road coordinates, profiles along the reference line"
    )
    return HeightRaster(
        path, heights.shape, float(du), origin, Crs(code="local"), heights, note=note
    )


#: Points per cell a gridded cloud has on average: the finest spacing its density supports.
CLOUD_POINTS_PER_CELL = 2.0
#: Clouds :func:`open_height_raster` grids (and a ``.npy`` of N x 3 points without a spacing).
CLOUD_SUFFIXES = (".las", ".laz", ".ply", ".pcd", ".csv", ".xyz", ".txt", ".bin")


def _is_cloud_npy(path: Path) -> bool:
    """A ``.npy`` of N x 3 numbers is a cloud (x, y, z), not a grid of heights."""
    array = read_npy(path)
    return array.ndim == 2 and array.shape[1] == 3 and array.shape[0] > 3


def _open_cloud(path: Path, crs_given: Any = None) -> HeightRaster:
    """A cloud in a world frame gridded at the finest spacing its density supports: a
    LAS/LAZ file's ground points (ASPRS class 2, when it has any) in its own CRS, or every
    point of another cloud (metres, in ``crs_given``, default local), averaged per cell,
    NaN where none fell."""
    from rasterio.crs import CRS

    crs, file_crs = Crs(code="local"), None
    if path.suffix.lower() in (".las", ".laz"):
        cloud = read_las(path)
        ground = cloud.classification == 2
        use = ground if ground.any() else np.ones(len(cloud.points), dtype=bool)
        unit = cloud.crs.horizontal_unit_m if cloud.crs is not None else 1.0
        xy = cloud.crs_coordinates()[use, :2]  # the CRS's units
        z = cloud.points[use, 2]  # m
        which = "ground (class 2)" if ground.any() else "all"
        total = len(cloud.points)
        if cloud.crs is not None and cloud.crs.epsg is not None:
            crs = Crs(code=f"EPSG:{cloud.crs.epsg}")
        elif cloud.crs is not None and cloud.crs.wkt:
            file_crs = CRS.from_wkt(cloud.crs.wkt)
            if file_crs.is_geographic:
                raise FileFormatError(path, "in a geographic CRS (degrees)", field="crs")
    else:
        points = read_cloud(path)
        xy, z, unit, which, total = points[:, :2], points[:, 2], 1.0, "all", len(points)
        crs = Crs.from_any(crs_given)
    n = len(z)
    if n < 16:
        raise FileFormatError(path, f"{n} points: too few to grid", field="points")
    xy_m = xy * unit
    span = np.ptp(xy_m, axis=0)
    if not np.all(span > 0):
        raise FileFormatError(path, "the points lie on a line: no surface", field="points")
    # the area the points cover: cells of about 4 points' share of the bounding box
    side = 2.0 * math.sqrt(float(span[0] * span[1]) / n)
    occupied = np.unique(np.floor((xy_m - xy_m.min(axis=0)) / side).astype(np.int64), axis=0)
    area = len(occupied) * side * side
    density = n / area
    spacing = _round_up(math.sqrt(CLOUD_POINTS_PER_CELL / density))
    cell = spacing / unit
    x0 = math.floor(xy[:, 0].min() / cell) * cell
    north = math.ceil(xy[:, 1].max() / cell) * cell
    cols = ((xy[:, 0] - x0) / cell).astype(np.int64)
    rows = ((north - xy[:, 1]) / cell).astype(np.int64)
    shape = (int(rows.max()) + 1, int(cols.max()) + 1)
    if shape[0] * shape[1] > LIMITS.raster_cells:
        raise FileFormatError(path, f"a grid of {shape[0]} x {shape[1]} cells", field="points")
    flat = rows * shape[1] + cols
    counts = np.bincount(flat, minlength=shape[0] * shape[1])
    sums = np.bincount(flat, weights=z, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        heights = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan).reshape(shape)
    note = (
        f"{n} {which} points of {total}, {density:.3g} per m^2 over {area:.4g} m^2: "
        f"gridded at {spacing:g} m ({CLOUD_POINTS_PER_CELL:g} points per cell)"
    )
    log.info("%s: %s", path.name, note)
    return HeightRaster(
        path,
        shape,
        spacing,
        (x0, north),
        crs,
        heights,
        unit_m=unit,
        file_crs=file_crs,
        gridding="cell_mean",
        note=note,
    )


def _round_up(value: float) -> float:
    """``value`` rounded up to two significant digits."""
    exp = math.floor(math.log10(value)) - 1
    return math.ceil(value / 10**exp - 1e-9) * 10**exp


@contextmanager
def _open(path: Path) -> Iterator[Any]:
    import rasterio

    with rasterio.open(path) as ds:
        yield ds


@contextmanager
def _rasterio_errors(path: Path) -> Iterator[None]:
    """rasterio's and GDAL's errors on ``path`` as one-line :class:`FileFormatError`."""
    from rasterio._err import CPLE_BaseError
    from rasterio.errors import RasterioError

    try:
        yield
    except (RasterioError, CPLE_BaseError, OSError) as exc:
        message = " ".join(str(exc).split())
        raise FileFormatError(path, f"not a readable raster: {clip(message, 120)}") from None


def _describe(path: Path, ds: Any) -> HeightRaster:
    """The :class:`HeightRaster` of an open rasterio dataset, its header checked."""
    if ds.count < 1:
        raise FileFormatError(path, "no band of heights", field="bands")
    cells = int(ds.width) * int(ds.height)
    limit = min(LIMITS.raster_cells, path.stat().st_size * LIMITS.deflate_ratio + 2**20)
    if ds.driver not in ("VRT",) and cells > limit:
        raise FileFormatError(
            path, f"declares {ds.width} x {ds.height} cells, more than it holds", field="size"
        )
    if np.dtype(ds.dtypes[0]).kind not in "fiu":
        raise FileFormatError(path, f"band 1 is {ds.dtypes[0]}, not heights", field="dtype")
    t = ds.transform
    if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
        raise FileFormatError(
            path,
            "not a north-up raster (rotated or flipped geotransform); warp it north-up first "
            "(gdalwarp)",
            field="transform",
        )
    if not math.isclose(t.a, -t.e, rel_tol=1e-9):
        raise FileFormatError(
            path, f"cells of {t.a:g} x {-t.e:g} are not square", field="transform"
        )
    crs, unit, file_crs = Crs(code="local"), 1.0, None
    if ds.crs is not None:
        if ds.crs.is_geographic:
            raise FileFormatError(
                path,
                "in a geographic CRS (degrees): its cells are not a length; reproject it to a "
                "projected CRS in m (e.g. gdalwarp -t_srs EPSG:326NN for UTM)",
                field="crs",
            )
        if ds.crs.is_projected:
            unit = float(ds.crs.linear_units_factor[1])
        try:
            crs = Crs.from_rasterio(ds.crs)
        except InputError:
            file_crs = ds.crs  # a WKT without an EPSG code: the outputs are written in it
    scale, offset = ds.scales[0], ds.offsets[0]
    if not (math.isfinite(scale or 1.0) and math.isfinite(offset or 0.0)):
        raise FileFormatError(path, f"scale {scale} and offset {offset}", field="scale")
    return HeightRaster(
        path,
        (int(ds.height), int(ds.width)),
        float(t.a) * unit,
        (float(t.c), float(t.f)),
        crs,
        unit_m=unit,
        file_crs=file_crs,
    )
