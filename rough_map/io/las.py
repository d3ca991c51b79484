"""LAS and LAZ point clouds: points in m, ASPRS classification and coordinate reference system.

The CRS of a file comes from its WKT (E)VLR, parsed by GDAL through :mod:`rasterio.crs`, and
from its GeoTIFF key VLR (ProjectedCSTypeGeoKey, ProjLinearUnitsGeoKey, VerticalUnitsGeoKey).
Coordinates in feet (or any linear unit other than the metre) are converted to m on reading.
LAS/LAZ files are written with laspy as integers of 0.1 mm.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import clip
from rough_map._files import PathLike
from rough_map.errors import FileFormatError, InputError
from rough_map.io._check import check_readable
from rough_map.limits import LIMITS

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
    check_las_header(path)
    try:
        # One thread: the parallel LAZ decoder trusts the chunk table's point counts.
        single = laspy.LazBackend.Lazrs
        with laspy.open(path, laz_backend=single if single.is_available() else None) as reader:
            header = reader.header
            expected = header.point_count
            parts, classes = [], []
            # In chunks: memory follows the points really decoded, not the declared count.
            for chunk in reader.chunk_iterator(_READ_CHUNK):
                with np.errstate(over="ignore", invalid="ignore"):  # forged scales: inf
                    parts.append(np.column_stack([chunk.x, chunk.y, chunk.z]).astype(np.float64))
                classes.append(np.asarray(chunk.classification, dtype=np.uint8))
        xyz = np.concatenate(parts) if len(parts) != 1 else parts[0]
        classification = np.concatenate(classes) if classes else np.zeros(0, np.uint8)
    except _las_errors() as err:
        raise FileFormatError(
            path, f"not a readable LAS/LAZ file (truncated or corrupt?): {clip(err)}"
        ) from err
    except BaseException as err:
        if type(err).__name__ != "PanicException":  # a Rust panic in lazrs, not an exit
            raise
        raise FileFormatError(
            path, f"not a readable LAS/LAZ file (the LAZ decoder failed): {clip(err)}"
        ) from err
    except Exception as err:  # laspy parses hostile VLRs (extra bytes, ...): any failure
        raise FileFormatError(
            path, f"not a readable LAS/LAZ file: {type(err).__name__}: {clip(err)}"
        ) from err
    if len(xyz) != expected:
        raise FileFormatError(
            path, f"truncated: {len(xyz)} of the {expected} points in the header", "points"
        )
    if len(xyz) == 0:
        raise FileFormatError(path, "the file holds no points", field="points")
    vlrs = list(header.vlrs) + list(getattr(header, "evlrs", None) or [])
    try:
        crs = _las_crs(path, vlrs)
    except FileFormatError:
        raise
    except Exception as err:  # hostile GeoTIFF keys or WKT in the VLRs
        raise FileFormatError(
            path, f"unreadable CRS record: {type(err).__name__}: {clip(err)}", field="crs"
        ) from err
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


# Smallest record of each LAS point data format 0-10, in bytes.
_RECORD_SIZES = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
_HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}  # by minor version
_VLR_HEADER, _EVLR_HEADER = 54, 60
_READ_CHUNK = 1_000_000  # points decoded at a time


def check_las_header(path: Path) -> None:
    """Check the public header block of a LAS/LAZ file against the file size before laspy
    (and the LAZ decoder, which aborts the process on absurd counts) sees it.

    The crashes it prevents (``tests/test_library_crashes.py``, laspy 2.7 with lazrs 0.8):
    lazrs allocates a chunk table of the declared number of chunks before reading it, and
    each layer of a layered (LAS 1.4) chunk at its declared size, and aborts the process
    (SIGABRT) when that fails (2^31 - 1 chunks; a 4 GiB layer in a file of 912 B, which
    otherwise takes 4 GiB and 13 s); laspy reads a declared 2^32 - 1 VLRs past the end of
    the file and does not return. Measured too, without being crashes: the EVLR and point
    counts make laspy raise MemoryError or OverflowError, and a LASzip VLR without items
    makes lazrs panic; these checks give them one line naming the field, as the others do
    laspy's errors.

    Checked: the signature, header size, offset to the point data, the VLRs (count and
    lengths), the point format and record length, the point count (LAS: the records fit in
    the file; LAZ: at most ``LIMITS.laz_ratio`` times the file size, and the chunk table),
    and the EVLRs of LAS 1.4.

    Raises
    ------
    FileFormatError
        The header is corrupt or declares more than the file can hold.
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(375)
        if head[:4] != b"LASF":
            raise FileFormatError(path, "not a LAS/LAZ file: no LASF signature", field="header")
        if len(head) < 227:
            raise FileFormatError(
                path, "not a readable LAS/LAZ file (truncated?): header cut short", "header"
            )
        major, minor = head[24], head[25]
        header_size, offset, n_vlrs, fmt_byte, record, legacy = struct.unpack_from(
            "<HIIBHI", head, 94
        )
        if major != 1 or minor not in _HEADER_SIZES:
            raise FileFormatError(path, f"unsupported LAS version {major}.{minor}", "version")
        if not _HEADER_SIZES[minor] <= header_size <= offset <= size:
            raise FileFormatError(
                path,
                f"header size {header_size} B and offset to points {offset} B do not fit "
                f"LAS {major}.{minor} in a file of {size} B",
                field="header",
            )
        count = legacy
        n_evlrs = first_evlr = 0
        if minor >= 4:
            first_evlr, n_evlrs, count64 = struct.unpack_from("<QIQ", head, 235)
            count = count64 or legacy
        compressed = bool(fmt_byte & 0x80) and not fmt_byte & 0x40  # as laspy decides
        fmt = fmt_byte & 0x3F
        if fmt >= len(_RECORD_SIZES) or not _RECORD_SIZES[fmt] <= record:
            raise FileFormatError(
                path, f"point format {fmt} with records of {record} B", field="point_format"
            )
        laszip = _check_vlrs(path, fh, header_size, offset, n_vlrs)
        data = size - offset
        if compressed:
            record = max(record, _laszip_item_size(path, laszip))
            if count > LIMITS.points or count * record > LIMITS.laz_ratio * data:
                raise FileFormatError(
                    path,
                    f"the header declares {count} points of {record} B in {data} B of LAZ data "
                    f"(limit {LIMITS.laz_ratio}x); corrupt",
                    field="points",
                )
            _check_chunk_table(path, fh, offset, size, count)
            if laszip is not None and struct.unpack_from("<H", laszip, 0)[0] == _LAYERED:
                _check_laz_layers(path, fh, offset, size, laszip, count)
        elif count * record > data:
            available = data // record
            if data % record and not n_evlrs:
                raise FileFormatError(
                    path,
                    "not a readable LAS/LAZ file (truncated or corrupt?): the point data ends "
                    f"inside a record; the header declares {count} points",
                )
            raise FileFormatError(
                path, f"truncated: {available} of the {count} points in the header", "points"
            )
        if n_evlrs:
            _check_evlrs(path, fh, first_evlr, n_evlrs, size)


def _check_vlrs(path: Path, fh: Any, start: int, end: int, count: int) -> bytes | None:
    """The VLRs between the header and the point data: each fits before the points.
    Returns the data of the LASzip VLR, if there is one."""
    if count * _VLR_HEADER > end - start:
        raise FileFormatError(
            path, f"{count} VLRs cannot fit in {end - start} B before the points", field="vlrs"
        )
    pos, laszip = start, None
    for i in range(count):
        fh.seek(pos)
        vlr = fh.read(_VLR_HEADER)
        length = struct.unpack_from("<H", vlr, 20)[0]
        if pos + _VLR_HEADER + length > end:
            raise FileFormatError(path, f"VLR {i} runs past the point data", field="vlrs")
        if vlr[2:18].rstrip(b"\0") == b"laszip encoded" and laszip is None:
            laszip = fh.read(length)
        pos += _VLR_HEADER + length
    return laszip


def _laszip_item_size(path: Path, vlr: bytes | None) -> int:
    """Bytes per point that the LAZ decoder will allocate, from the LASzip VLR's items."""
    if vlr is None or len(vlr) < 34:
        raise FileFormatError(path, "compressed points without a LASzip VLR", field="laszip")
    n_items = struct.unpack_from("<H", vlr, 32)[0]
    if n_items == 0:
        raise FileFormatError(path, "LASzip VLR without items", field="laszip")
    if 34 + 6 * n_items > len(vlr):
        raise FileFormatError(path, f"LASzip VLR with {n_items} items is cut short", "laszip")
    return sum(struct.unpack_from("<H", vlr, 34 + 6 * i + 2)[0] for i in range(n_items))


def _check_evlrs(path: Path, fh: Any, start: int, count: int, size: int) -> None:
    """The EVLRs of LAS 1.4: each one inside the file."""
    if not 0 < start <= size or count * _EVLR_HEADER > size - start:
        raise FileFormatError(
            path, f"{count} EVLRs at {start} B do not fit in {size} B", field="evlrs"
        )
    pos = start
    for i in range(count):
        if pos + _EVLR_HEADER > size:
            raise FileFormatError(path, f"EVLR {i} runs past the end of the file", "evlrs")
        fh.seek(pos + 20)
        length = struct.unpack("<Q", fh.read(8))[0]
        pos += _EVLR_HEADER + length
        if pos > size:
            raise FileFormatError(path, f"EVLR {i} runs past the end of the file", "evlrs")


def _check_chunk_table(path: Path, fh: Any, offset: int, size: int, count: int) -> None:
    """The LAZ chunk table: where the point data says, with at most one chunk per point."""
    fh.seek(offset)
    word = fh.read(8)
    if len(word) < 8:
        raise FileFormatError(path, "LAZ data cut short (truncated?)", field="chunk_table")
    table = struct.unpack("<q", word)[0]
    if table == -1:
        return  # written by a streaming encoder without a table: read in order
    if not offset + 8 <= table <= size - 8:
        raise FileFormatError(
            path, f"chunk table at {table} B outside the file of {size} B", field="chunk_table"
        )
    fh.seek(table)
    _, chunks = struct.unpack("<II", fh.read(8))
    if chunks > count + 1 or chunks > size - offset:
        raise FileFormatError(
            path, f"{chunks} chunks declared for {count} points; corrupt", field="chunk_table"
        )


# Layers of each LASzip 1.4 item type (point14, rgb14, rgbnir14, wavepacket14); byte14 has
# one layer per byte.
_LAYERS = {10: 9, 11: 1, 12: 2, 13: 1}
_LAYERED = 3  # LASzip compressor id of the layered chunked compression of LAS 1.4
_VARIABLE_CHUNKS = 0xFFFFFFFF  # LASzip chunk size of files with chunks of varying sizes


def _check_laz_layers(
    path: Path, fh: Any, offset: int, size: int, laszip: bytes, count: int
) -> None:
    """Each chunk of a layered (LAS 1.4) LAZ file declares the byte size of its layers, which
    the decoder allocates before reading them: walk the chunks as the decoder does (in order,
    whatever the chunk table says) and check that every chunk fits in the file."""
    items = [
        struct.unpack_from("<HHH", laszip, 34 + 6 * i)
        for i in range(struct.unpack_from("<H", laszip, 32)[0])
    ]
    chunk_size = struct.unpack_from("<I", laszip, 12)[0]
    raw = sum(item_size for _, item_size, _ in items)  # the first point of a chunk, raw
    layers = sum(item_size if kind == 14 else _LAYERS.get(kind, 0) for kind, item_size, _ in items)
    start, remaining, k = offset + 8, count, 0
    while remaining > 0:
        fh.seek(start + raw)
        head = fh.read(4 + 4 * layers)
        if len(head) < 4 + 4 * layers:
            raise FileFormatError(path, f"LAZ chunk {k} cut short (truncated?)", field="points")
        in_chunk, *sizes = struct.unpack(f"<I{layers}I", head)
        start += raw + len(head) + sum(sizes)
        if start > size:
            raise FileFormatError(
                path, f"LAZ chunk {k} declares more bytes than the file holds", field="points"
            )
        step = in_chunk if chunk_size == _VARIABLE_CHUNKS else chunk_size
        if step < 1:
            raise FileFormatError(path, f"LAZ chunk {k} holds no points; corrupt", "points")
        remaining -= step
        k += 1


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
