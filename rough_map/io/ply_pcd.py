"""PLY and PCD point clouds read with numpy, without open3d.

open3d's readers trust their files: its PCD reader dies (SIGSEGV, open3d 0.20) on a
well-formed PCD whose fields are x, y, z and ``normal_x`` alone, and its PLY reader makes up
the points a truncated file does not hold, with a warning only (both in
``tests/test_library_crashes.py``). So the readers here parse the header themselves, check
every declared count against the bytes the file really holds before allocating, and read
the points with numpy.
Writing stays with open3d (:func:`rough_map.io.pointcloud.write_cloud`).

Supported:

* PLY ``ascii``, ``binary_little_endian`` and ``binary_big_endian``: the ``vertex`` element
  with scalar ``x``, ``y``, ``z`` properties of any numeric type; other properties are
  skipped, and so are the elements after it (faces, ...) and fixed-size elements before it.
* PCD ``ascii``, ``binary`` and ``binary_compressed`` (LZF): fields ``x``, ``y``, ``z`` with
  ``COUNT`` 1, any other fields skipped.
"""

from __future__ import annotations

import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from rough_map._bounded import clip, short
from rough_map.errors import FileFormatError
from rough_map.io._check import check_count
from rough_map.limits import LIMITS

__all__ = ["lzf_decompress", "read_pcd", "read_ply"]


SHORT = "truncated: the file is shorter than its header declares"

_LZF_RATIO = 140
"""LZF turns 2 input bytes into at most 264 output bytes: a larger declared ratio is forged."""

_PLY_TYPES = {
    **dict.fromkeys(["char", "int8"], "i1"),
    **dict.fromkeys(["uchar", "uint8"], "u1"),
    **dict.fromkeys(["short", "int16"], "i2"),
    **dict.fromkeys(["ushort", "uint16"], "u2"),
    **dict.fromkeys(["int", "int32"], "i4"),
    **dict.fromkeys(["uint", "uint32"], "u4"),
    **dict.fromkeys(["float", "float32"], "f4"),
    **dict.fromkeys(["double", "float64"], "f8"),
}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_END = re.compile(rb"(?:^|\n)end_header[ \t]*\r?\n")
_PCD_DATA = re.compile(rb"(?:^|\n)DATA[ \t]+(\S+)[ \t]*\r?\n")


# --------------------------------------------------------------------------------------------
# PLY


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str | None]] = field(default_factory=list)  # (name, dtype or None=list)


def read_ply(path: Path) -> np.ndarray:
    """x, y, z of the vertices of a PLY file, shape (N, 3), in the file's numeric type.

    Raises
    ------
    FileFormatError
        A header that is not PLY or not understood, a vertex element without scalar x, y, z,
        counts beyond the file size ("truncated"), or numbers that do not parse.
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(LIMITS.cloud_header)
        if not head.startswith(b"ply"):
            raise FileFormatError(path, f"not a PLY file: starts {short(head[:12])}", "header")
        end = _PLY_END.search(head)
        if end is None:
            raise FileFormatError(path, _no_end(head, "end_header"), field="header")
        offset = end.end()
        fmt, elements = _ply_header(path, _header_text(path, head[:offset]))
        index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
        if index is None:
            raise FileFormatError(path, "no 'element vertex' in the header", field="vertex")
        vertex = elements[index]
        names = [name for name, _ in vertex.props]
        for c in "xyz":
            if c not in names or dict(vertex.props)[c] is None:
                raise FileFormatError(
                    path, f"the vertex element has no scalar property {c!r}", field=c
                )
        if any(kind is None for _, kind in vertex.props):
            raise FileFormatError(
                path, "list properties in the vertex element are not supported", field="vertex"
            )
        remaining = size - offset
        if fmt is None:
            return _ply_ascii(path, fh, offset, remaining, elements[:index], vertex)
        return _ply_binary(path, fh, offset, remaining, fmt, elements[:index], vertex)


def _ply_header(path: Path, text: str) -> tuple[str | None, list[_Element]]:
    fmt: str | None = None
    seen_format = False
    elements: list[_Element] = []
    for line in text.splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format" and len(words) == 3 and words[1] in _PLY_FORMATS:
            fmt, seen_format = _PLY_FORMATS[words[1]], True
        elif key == "element" and len(words) == 3:
            count = _int(path, words[2], "element count", f"element {short(words[1], 20)}")
            check_count(path, count, f"{short(words[1], 20)} elements", "count")
            elements.append(_Element(words[1], count))
        elif key == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1].props.append((words[2], _PLY_TYPES[words[1]]))
        elif (
            key == "property"
            and elements
            and len(words) == 5
            and words[1] == "list"
            and words[2] in _PLY_TYPES
            and words[3] in _PLY_TYPES
        ):
            elements[-1].props.append((words[4], None))
        else:
            raise FileFormatError(path, f"header line not understood: {short(line)}", "header")
    if not seen_format:
        raise FileFormatError(path, "no valid 'format' line in the header", field="format")
    return fmt, elements


def _ply_binary(
    path: Path,
    fh: IO[bytes],
    offset: int,
    remaining: int,
    order: str,
    before: list[_Element],
    vertex: _Element,
) -> np.ndarray:
    skip = 0
    for element in before:
        if any(kind is None for _, kind in element.props):
            raise FileFormatError(
                path,
                f"element {short(element.name, 20)} with list properties before the vertices "
                "is not supported",
                field="vertex",
            )
        skip += element.count * sum(np.dtype(kind).itemsize for _, kind in element.props)
    dtype = _struct_dtype("p", [(order + str(kind), 1) for _, kind in vertex.props])
    if skip + vertex.count * dtype.itemsize > remaining:
        raise FileFormatError(path, SHORT, field="points")
    fh.seek(offset + skip)
    rows = np.fromfile(fh, dtype=dtype, count=vertex.count)
    if len(rows) != vertex.count:  # the file changed under us
        raise FileFormatError(path, SHORT, field="points")
    names = [name for name, _ in vertex.props]
    with np.errstate(invalid="ignore"):
        return np.column_stack([rows[f"p{names.index(c)}"] for c in "xyz"])


def _ply_ascii(
    path: Path,
    fh: IO[bytes],
    offset: int,
    remaining: int,
    before: list[_Element],
    vertex: _Element,
) -> np.ndarray:
    skip = sum(e.count for e in before)
    # A row holds at least one character and one separator per property.
    if (skip + vertex.count * len(vertex.props)) * 2 > remaining + 1:
        raise FileFormatError(path, SHORT, field="points")
    names = [name for name, _ in vertex.props]
    fh.seek(offset)
    usecols = [names.index(c) for c in "xyz"]
    return _loadtxt(path, fh, vertex.count, usecols, skip)


# --------------------------------------------------------------------------------------------
# PCD


def read_pcd(path: Path) -> np.ndarray:
    """x, y, z of a PCD file, shape (N, 3), in the file's numeric type.

    Raises
    ------
    FileFormatError
        A header that is not understood, no x, y or z field, counts beyond the file size
        ("truncated"), numbers that do not parse, or corrupt compressed data.
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(LIMITS.cloud_header)
        end = _PCD_DATA.search(head)
        if end is None:
            raise FileFormatError(path, _no_end(head, "DATA"), field="header")
        offset = end.end()
        kind = end.group(1).decode("ascii", "replace")
        header = _pcd_header(path, _header_text(path, head[: end.start()]))
        names, types, counts, points = header
        remaining = size - offset
        dtype = _struct_dtype("f", [("<" + t, c) for t, c in zip(types, counts, strict=True)])
        columns = [names.index(c) for c in "xyz"]
        if kind == "ascii":
            if points * 2 * sum(counts) > remaining + 1:
                raise FileFormatError(path, SHORT, field="points")
            fh.seek(offset)
            usecols = [sum(counts[:i]) for i in columns]
            return _loadtxt(path, fh, points, usecols, 0)
        if kind == "binary":
            if points * dtype.itemsize > remaining:
                raise FileFormatError(path, SHORT, field="points")
            fh.seek(offset)
            rows = np.fromfile(fh, dtype=dtype, count=points)
            if len(rows) != points:
                raise FileFormatError(path, SHORT, field="points")
            with np.errstate(invalid="ignore"):
                return np.column_stack([rows[f"f{i}"] for i in columns])
        if kind == "binary_compressed":
            fh.seek(offset)
            return _pcd_compressed(path, fh, remaining, dtype, points, columns)
        raise FileFormatError(path, f"unknown DATA kind {short(kind, 30)}", field="DATA")


def _pcd_header(path: Path, text: str) -> tuple[list[str], list[str], list[int], int]:
    header: dict[str, list[str]] = {}
    for line in text.splitlines():
        words = line.split()
        if words and not words[0].startswith("#"):
            header[words[0].upper()] = words[1:]
    names = header.get("FIELDS") or header.get("COLUMNS")
    if not names:
        raise FileFormatError(path, "no FIELDS line in the header", field="FIELDS")
    n = len(names)
    sizes = [_int(path, s, "size", "SIZE") for s in header.get("SIZE", [])]
    letters = header.get("TYPE", [])
    counts = [_int(path, s, "count", "COUNT") for s in header.get("COUNT", ["1"] * n)]
    for key, values in (("SIZE", sizes), ("TYPE", letters), ("COUNT", counts)):
        if len(values) != n:
            raise FileFormatError(path, f"{len(values)} values for {n} FIELDS", field=key)
    types = []
    for size, letter, count in zip(sizes, letters, counts, strict=True):
        if (
            letter not in ("F", "I", "U")
            or size not in (1, 2, 4, 8)
            or (letter == "F" and size not in (4, 8))
        ):
            raise FileFormatError(
                path, f"unsupported TYPE {short(letter, 10)} with SIZE {size}", field="TYPE"
            )
        check_count(path, count, "values per field", "COUNT", limit=1_000_000)
        types.append(f"{letter.lower()}{size}")
    for c in "xyz":
        if c not in names:
            raise FileFormatError(path, f"no field {c!r} in FIELDS", field=c)
        if counts[names.index(c)] != 1:
            raise FileFormatError(path, f"field {c!r} has COUNT != 1", field=c)
    if "POINTS" in header:
        points = _int(path, (header["POINTS"] or [""])[0], "point count", "POINTS")
    else:
        width = _int(path, (header.get("WIDTH") or [""])[0], "width", "WIDTH")
        height = _int(path, (header.get("HEIGHT") or ["1"])[0], "height", "HEIGHT")
        points = width * height
    check_count(path, points, "points", "POINTS")
    return names, types, counts, points


def _pcd_compressed(
    path: Path,
    fh: IO[bytes],
    remaining: int,
    dtype: np.dtype,
    points: int,
    columns: list[int],
) -> np.ndarray:
    sizes = fh.read(8)
    if len(sizes) < 8:
        raise FileFormatError(path, SHORT, field="points")
    compressed, uncompressed = struct.unpack("<II", sizes)
    if compressed > remaining - 8:
        raise FileFormatError(path, SHORT, field="points")
    if uncompressed != points * dtype.itemsize:
        raise FileFormatError(
            path,
            f"compressed data of {uncompressed} B for {points} points of {dtype.itemsize} B",
            field="POINTS",
        )
    if uncompressed > _LZF_RATIO * compressed + 1024:
        raise FileFormatError(
            path, f"{compressed} B cannot inflate to {uncompressed} B (LZF)", field="DATA"
        )
    try:
        data = lzf_decompress(fh.read(compressed), uncompressed)
    except ValueError as err:
        raise FileFormatError(path, f"corrupt compressed data: {clip(err)}", "DATA") from err
    # The data is stored field by field: all x, then all y, ...
    starts = [0]
    for name in dtype.names or ():
        starts.append(starts[-1] + points * dtype[name].itemsize)
    out = np.empty((points, 3), dtype=np.float64)
    for k, i in enumerate(columns):
        with np.errstate(invalid="ignore"):  # a signalling NaN in float32 warns when widened
            out[:, k] = np.frombuffer(data, dtype=dtype[i], count=points, offset=starts[i])
    return out


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Inflate LZF data (liblzf's format, as PCL writes it) to exactly ``size`` bytes.

    Raises
    ------
    ValueError
        The data is corrupt, or inflates to more or fewer than ``size`` bytes.
    """
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            run = ctrl + 1
            if i + run > n or len(out) + run > size:
                raise ValueError(f"literal run past the end at byte {i}")
            out += data[i : i + run]
            i += run
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                raise ValueError("back reference cut short")
            length += data[i]
            i += 1
        length += 2
        if i >= n:
            raise ValueError("back reference cut short")
        back = ((ctrl & 0x1F) << 8) + data[i] + 1
        i += 1
        if back > len(out) or len(out) + length > size:
            raise ValueError(f"back reference out of range at byte {i}")
        start = len(out) - back
        if length <= back:
            out += out[start : start + length]
        else:  # the copy overlaps what it writes: the last `back` bytes repeat
            chunk = bytes(out[start:])
            out += (chunk * (length // back + 1))[:length]
    if len(out) != size:
        raise ValueError(f"inflated to {len(out)} B instead of {size} B")
    return bytes(out)


# --------------------------------------------------------------------------------------------
# Shared


def _header_text(path: Path, head: bytes) -> str:
    try:
        return head.decode("ascii")
    except UnicodeDecodeError as err:
        raise FileFormatError(
            path, f"the header is not ASCII text (byte {err.start})", field="header"
        ) from err


def _no_end(head: bytes, marker: str) -> str:
    if len(head) >= LIMITS.cloud_header:
        return f"no {marker} line in the first {LIMITS.cloud_header} B: not a header"
    return f"no {marker} line: not a header, or truncated"


def _int(path: Path, word: str, what: str, field_: str) -> int:
    if not word.isascii() or not word.isdigit() or len(word) > 19:
        raise FileFormatError(path, f"{what} {short(word, 30)} is not a count", field=field_)
    return int(word)


def _struct_dtype(prefix: str, kinds: list[tuple[str, int]]) -> np.dtype:
    """Packed record of fields ``{prefix}0, {prefix}1, ...`` (file names may repeat)."""
    return np.dtype(
        [
            (f"{prefix}{i}", kind, (count,)) if count != 1 else (f"{prefix}{i}", kind)
            for i, (kind, count) in enumerate(kinds)
        ]
    )


def _loadtxt(path: Path, fh: IO[bytes], rows: int, usecols: list[int], skip: int) -> np.ndarray:
    """``rows`` rows of numbers from the open file, columns ``usecols``."""
    start = fh.tell()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # blank lines, no data
            table = np.loadtxt(
                fh,
                dtype=np.float64,
                comments=None,
                skiprows=skip,
                max_rows=rows,
                usecols=usecols,
                ndmin=2,
                encoding="ascii",
            )
    except ValueError as err:  # UnicodeDecodeError included
        if _complete_lines(fh, start) < skip + rows:  # the last row is cut
            raise FileFormatError(path, SHORT, field="points") from err
        raise FileFormatError(path, f"not a table of numbers: {clip(err)}", "points") from err
    if len(table) < rows:
        raise FileFormatError(path, SHORT, field="points")
    return table


def _complete_lines(fh: IO[bytes], start: int) -> int:
    """Newline-terminated lines from ``start`` to the end of the file."""
    fh.seek(start)
    lines = 0
    while chunk := fh.read(1 << 20):
        lines += chunk.count(b"\n")
    return lines
