"""LAS and LAZ point clouds: points in m, ASPRS classification and coordinate reference system.

The CRS of a file comes from its WKT (E)VLR, parsed by GDAL through :mod:`rasterio.crs`, and
from its GeoTIFF key VLR (ProjectedCSTypeGeoKey, ProjLinearUnitsGeoKey, VerticalUnitsGeoKey).
Coordinates in feet (or any linear unit other than the metre) are converted to m on reading.
LAS/LAZ files are written with laspy as integers of 0.1 mm.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import PathLike
from rough_map.errors import FileFormatError, InputError
from rough_map.io._check import check_readable

log = logging.getLogger(__name__)

Unit = tuple[str, float]
"""A length unit: its name and its length in m."""

_LAS_SCALE = 1e-4  # m per integer step: 0.1 mm, far below any roughness of interest

# EPSG unit of measure codes used by GeoTIFF keys, in m.
_EPSG_LENGTH_UNITS: dict[int, Unit] = {
    9001: ("metre", 1.0),
    9002: ("foot", 0.3048),
    9003: ("US survey foot", 1200 / 3937),
}
_METRE: Unit = ("metre", 1.0)
_USER_DEFINED = 32767
_GEOKEY_MODEL_TYPE, _GEOKEY_GEOGRAPHIC, _GEOKEY_PROJECTED = 1024, 2048, 3072
_GEOKEY_LINEAR_UNITS, _GEOKEY_VERTICAL_UNITS = 3076, 4099
_MODEL_TYPE_GEOGRAPHIC = 2


@dataclass(frozen=True)
class LasCrs:
    """Coordinate reference system of a LAS file.

    Attributes
    ----------
    wkt : str or None
        OGC WKT of the CRS (from the WKT VLR or EVLR), if the file has one.
    epsg : int or None
        EPSG code: the ``AUTHORITY``/``ID`` written in the WKT (of the CRS, or of the
        horizontal part of a compound CRS), or else the GeoTIFF key (ProjectedCSTypeGeoKey,
        or GeographicTypeGeoKey for a geographic CRS). No code is guessed from the
        definition.
    horizontal_unit_m : float
        Length in m of one unit of the file's x and y.
    vertical_unit_m : float
        Length in m of one unit of the file's z. When the file gives no vertical unit the
        horizontal one is assumed.
    unit_name : str
        Name of the horizontal unit, as GDAL names the WKT unit or as the GeoTIFF key
        gives it (``"metre"`` if none).
    """

    wkt: str | None
    epsg: int | None
    horizontal_unit_m: float
    vertical_unit_m: float
    unit_name: str


@dataclass(frozen=True, eq=False)
class LasCloud:
    """Points of a LAS/LAZ file, in m, with their classification and CRS.

    Attributes
    ----------
    points : ndarray, shape (N, 3), float64
        x, y, z in m: the file coordinates multiplied by the CRS units (a file in feet is
        converted). Use :meth:`crs_coordinates` to get the numbers of the CRS back.
    classification : ndarray, shape (N,), uint8
        ASPRS class per point (2 = ground).
    crs : LasCrs or None
        None when the file has no CRS record (then units are taken as m).
    """

    points: np.ndarray
    classification: np.ndarray
    crs: LasCrs | None

    def crs_coordinates(self) -> np.ndarray:
        """Points in the units of the CRS (e.g. US survey feet), shape (N, 3)."""
        if self.crs is None:
            return self.points.copy()
        scale = [self.crs.horizontal_unit_m, self.crs.horizontal_unit_m, self.crs.vertical_unit_m]
        return self.points / np.asarray(scale)


def read_las(path: PathLike) -> LasCloud:
    """Read a LAS or LAZ file with its classification and coordinate reference system.

    The WKT of the CRS is parsed by GDAL (rasterio). Linear units come from the WKT (the
    projected CRS, and the vertical CRS of a compound one) or else from the GeoTIFF keys
    ProjLinearUnitsGeoKey and VerticalUnitsGeoKey.

    Parameters
    ----------
    path : str or PathLike
        A ``.las`` or ``.laz`` file.

    Returns
    -------
    LasCloud
        Points in m (converted from the file's linear unit), classes and CRS.

    Raises
    ------
    FileFormatError
        Missing, empty, truncated or corrupt file; a geographic CRS (coordinates in degrees,
        which cannot be taken as m); or no points.
    """
    import laspy

    path = Path(path)
    check_readable(path)
    try:
        with laspy.open(path) as reader:
            expected = reader.header.point_count
            las = reader.read()
        xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        classification = np.asarray(las.classification, dtype=np.uint8)
    except _las_errors() as err:
        raise FileFormatError(
            path, f"not a readable LAS/LAZ file (truncated or corrupt?): {err}"
        ) from err
    if len(xyz) != expected:
        raise FileFormatError(
            path, f"truncated: {len(xyz)} of the {expected} points in the header", "points"
        )
    if len(xyz) == 0:
        raise FileFormatError(path, "the file holds no points", field="points")
    vlrs = list(las.header.vlrs) + list(getattr(las.header, "evlrs", None) or [])
    crs = _las_crs(path, vlrs)
    if crs is not None and (crs.horizontal_unit_m != 1.0 or crs.vertical_unit_m != 1.0):
        log.info(
            "%s: coordinates in %s converted to m (x, y * %.10g, z * %.10g)",
            path,
            crs.unit_name,
            crs.horizontal_unit_m,
            crs.vertical_unit_m,
        )
        xyz *= np.array([crs.horizontal_unit_m, crs.horizontal_unit_m, crs.vertical_unit_m])
    return LasCloud(points=xyz, classification=classification, crs=crs)


def write_las(path: Path, points: np.ndarray) -> None:
    """Write x, y, z (m) to a LAS 1.4 file (``.laz``: compressed) as integers of 0.1 mm.

    Parameters
    ----------
    path : Path
        The file (its suffix picks LAS or LAZ).
    points : ndarray, shape (N, 3)
        x, y, z in m, finite, spanning less than about 400 km.

    Raises
    ------
    InputError
        A coordinate is not finite, or the cloud is too wide for 0.1 mm integers.
    """
    import laspy

    if not np.isfinite(points).all():
        raise InputError("LAS cannot store NaN or infinite coordinates; drop those points first")
    lo, hi = points.min(axis=0), points.max(axis=0)
    offsets = np.round((lo + hi) / 2)
    reach = np.abs(np.stack([lo - offsets, hi - offsets])).max()
    if reach / _LAS_SCALE >= 2**31 - 1:
        raise InputError(
            f"the cloud spans {reach * 2:.0f} m, too wide for LAS at {_LAS_SCALE} m resolution"
        )
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, _LAS_SCALE)
    header.offsets = offsets
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.write(str(path))


def _las_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that laspy and its LAZ backend raise on a bad file."""
    import laspy

    errors: tuple[type[BaseException], ...] = (
        laspy.errors.LaspyException,
        ValueError,
        OSError,
        EOFError,
    )
    try:
        import lazrs
    except ImportError:
        return errors
    return (*errors, lazrs.LazrsError)


# --------------------------------------------------------------------------------------------
# Coordinate reference system


@dataclass(frozen=True)
class _WktCrs:
    """What a WKT tells about the units of a CRS."""

    horizontal: Unit | None
    vertical: Unit | None
    geographic: bool
    epsg: int | None


def _las_crs(path: Path, vlrs: list[Any]) -> LasCrs | None:
    """The CRS of a LAS file from its WKT and GeoTIFF key VLRs; None if it has neither."""
    wkt = next((str(v.string) for v in vlrs if hasattr(v, "string") and v.string), None)
    geokeys = _geokeys(vlrs)
    if wkt is None and not geokeys:
        log.info("%s: no CRS record; coordinates taken as m", path)
        return None
    parsed = _wkt_crs(path, wkt) if wkt is not None else None
    if parsed is None:
        geographic = geokeys.get(_GEOKEY_MODEL_TYPE) == _MODEL_TYPE_GEOGRAPHIC
        parsed = _WktCrs(horizontal=None, vertical=None, geographic=geographic, epsg=None)
    horizontal = parsed.horizontal or _EPSG_LENGTH_UNITS.get(geokeys.get(_GEOKEY_LINEAR_UNITS, 0))
    vertical = parsed.vertical or _EPSG_LENGTH_UNITS.get(geokeys.get(_GEOKEY_VERTICAL_UNITS, 0))
    epsg = parsed.epsg
    if epsg is None:
        code = geokeys.get(_GEOKEY_GEOGRAPHIC if parsed.geographic else _GEOKEY_PROJECTED)
        epsg = code if code and code != _USER_DEFINED else None
    if parsed.geographic:
        raise FileFormatError(
            path,
            "geographic CRS (longitude, latitude in degrees); reproject to a projected CRS in m",
            field="crs",
        )
    if horizontal is None:
        log.warning("%s: CRS without a linear unit; coordinates taken as m", path)
        horizontal = _METRE
    if vertical is None:
        log.debug("%s: no vertical unit; z taken in %s like x and y", path, horizontal[0])
        vertical = horizontal
    return LasCrs(
        wkt=wkt,
        epsg=epsg,
        horizontal_unit_m=horizontal[1],
        vertical_unit_m=vertical[1],
        unit_name=horizontal[0],
    )


def _geokeys(vlrs: list[Any]) -> dict[int, int]:
    """GeoTIFF keys whose value is stored in the key itself (not in the params VLRs)."""
    geokeys: dict[int, int] = {}
    for v in vlrs:
        for key in getattr(v, "geo_keys", None) or []:
            if key.tiff_tag_location == 0 and key.id:
                geokeys[key.id] = key.value_offset
    return geokeys


def _wkt_crs(path: Path, wkt: str) -> _WktCrs | None:
    """Units, kind and written EPSG code of a WKT1 or WKT2 CRS; None if GDAL cannot parse it.

    The horizontal unit is GDAL's linear unit of a projected CRS; the vertical unit and the
    EPSG code come from the PROJJSON form of the CRS (its ``VerticalCRS`` axis unit, the
    ``id`` of the CRS or of its horizontal component).
    """
    import rasterio
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    try:
        with rasterio.Env():  # GDAL's messages go to the rasterio logger, not to stderr
            crs = CRS.from_wkt(wkt)
            projjson: dict[str, Any] = crs.to_dict(projjson=True)
            horizontal = tuple(crs.linear_units_factor) if crs.is_projected else None
            geographic = bool(crs.is_geographic)
    except CRSError as err:
        log.warning("%s: could not parse the WKT of the CRS (%s): %.200s", path, err, wkt)
        return None
    parts = projjson.get("components") or [projjson]  # the parts of a CompoundCRS
    vertical = next((_axis_unit(p) for p in parts if p.get("type") == "VerticalCRS"), None)
    epsg = _projjson_epsg(projjson)
    for part in parts:
        if epsg is None and part.get("type") != "VerticalCRS":
            epsg = _projjson_epsg(part)
    return _WktCrs(
        horizontal=(str(horizontal[0]), float(horizontal[1])) if horizontal else None,
        vertical=vertical,
        geographic=geographic,
        epsg=epsg,
    )


def _projjson_epsg(node: dict[str, Any]) -> int | None:
    """The EPSG code written in a PROJJSON CRS (``id`` or ``ids``), if any."""
    ids = node.get("ids") or ([node["id"]] if "id" in node else [])
    for ident in ids:
        code = ident.get("code")
        if str(ident.get("authority", "")).upper() == "EPSG" and str(code).isdigit():
            return int(code)
    return None


def _axis_unit(node: dict[str, Any]) -> Unit | None:
    """The length unit of the first axis of a PROJJSON CRS, if it is a length."""
    axes = node.get("coordinate_system", {}).get("axis", [])
    unit = axes[0].get("unit", "metre") if axes else None
    if unit == "metre":  # PROJJSON writes the metre as a bare name
        return _METRE
    if isinstance(unit, dict) and unit.get("type") == "LinearUnit":
        return str(unit["name"]), float(unit["conversion_factor"])
    return None
