"""A map's fusion state on disk: the sums of its tiles, in one ``.npz`` file.

A fused map is its accumulators (:mod:`rough_map.map.layers`): sums, Dirichlet evidence,
votes, counts, the latest time seen, and the sums of point heights. They add up, so the
maps of several traverses on one lattice fuse into the map all their frames would have
given together (:meth:`rough_map.map.tiles.TiledMap.add_saved`; ``rough-map batch``).

The file is a zip (an ``.npz``) of ``meta.json`` (format, lattice, CRS, classes, layer
units) and, per tile holding data, ``tile_<row>_<col>/<layer>.npy``: the bounding box of its
cells with data, placed by ``tile_<row>_<col>/_window.npy`` (row0, row1, col0, col1). It is
written one tile at a time and read the same way, without pickle.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._bounded import clip, parse_json
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError
from rough_map.io.safe_npz import SafeNpz
from rough_map.limits import LIMITS
from rough_map.map.grid import GridMap

__all__ = [
    "HEIGHT_LAYERS",
    "STATE_FORMAT",
    "add_elevation_layer",
    "iter_state_tiles",
    "jsonable_attrs",
    "read_state_meta",
    "write_state",
]

#: Internal layers of the elevation: sum of heights (m) and number of points per cell.
HEIGHT_LAYERS = ("sum_height", "n_height")

#: Format of a state file.
STATE_FORMAT = "rough_map.tiled_state/1"

#: The tiles' arrays: ``(tile_row, tile_col)``, window, and layer name -> values.
StateTile = tuple[tuple[int, int], tuple[int, int, int, int], dict[str, NDArray[np.float64]]]


def add_elevation_layer(grid: GridMap) -> None:
    """(Re)compute ``elevation`` (m, mean world z of the points per cell) from the height
    sums, when the map has them."""
    if HEIGHT_LAYERS[1] not in grid:
        return
    counts = grid[HEIGHT_LAYERS[1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.where(counts > 0, grid[HEIGHT_LAYERS[0]] / counts, np.nan)
    if "elevation" in grid:
        grid["elevation"] = elev
    else:
        grid.add_layer(
            "elevation", units="m", description="mean terrain height (world z)", data=elev
        )


def jsonable_attrs(attrs: dict[str, Any]) -> dict[str, Any]:
    """The entries of a map's ``attrs`` that JSON holds as they are (text, numbers, flags,
    lists of them), for a state's ``meta.json``."""
    out: dict[str, Any] = {}
    for k, v in attrs.items():
        if isinstance(v, str | int | float | bool) or v is None:
            out[k] = v
        elif isinstance(v, tuple | list) and all(isinstance(x, str | int | float) for x in v):
            out[k] = list(v)
    return out


def write_state(path: PathLike, meta: dict[str, Any], tiles: Iterable[StateTile]) -> Path:
    """Write a state file atomically from ``meta`` and the tiles (consumed one by one)."""
    path = Path(path)
    with (
        atomic_output(path) as tmp,
        zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf,
    ):
        for key, window, arrays in tiles:
            prefix = f"tile_{key[0]}_{key[1]}"
            for name, values in {"_window": np.asarray(window, dtype=np.int64), **arrays}.items():
                with zf.open(_entry(f"{prefix}/{name}.npy"), "w", force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asarray(values), allow_pickle=False)
        text = json.dumps({**meta, "format": STATE_FORMAT}, sort_keys=True)
        zf.writestr(_entry("meta.json"), text)
    return path


def _entry(name: str) -> zipfile.ZipInfo:
    """A zip entry with a fixed date: the same state gives the same bytes, any day."""
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED  # level 1: most of the gain, fast
    return info


def read_state_meta(path: PathLike) -> dict[str, Any]:
    """The ``meta.json`` of a state file.

    Raises
    ------
    FileFormatError
        Not a readable zip, no ``meta.json``, or another format.
    """
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo("meta.json")
            if info.file_size > min(
                LIMITS.document, info.compress_size * LIMITS.deflate_ratio + 1024
            ):
                raise FileFormatError(path, "meta.json declares too many bytes", "meta.json")
            data = zf.read(info)
    except KeyError:
        raise FileFormatError(path, "not a readable map state: no meta.json", "meta.json") from None
    except (
        OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error, NotImplementedError,
        RuntimeError,
    ) as exc:  # fmt: skip
        if isinstance(exc, FileFormatError):
            raise
        raise FileFormatError(path, f"not a readable map state: {clip(str(exc), 80)}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise FileFormatError(path, "not UTF-8 text", "meta.json") from None
    meta = parse_json(text, path)
    if not isinstance(meta, dict) or meta.get("format") != STATE_FORMAT:
        raise FileFormatError(path, f"not a {STATE_FORMAT} file", field="meta.json format")
    return meta


def iter_state_tiles(path: PathLike, tile_cells: int) -> Iterator[StateTile]:
    """The tiles of a state file, one at a time, checked against ``tile_cells``.

    Raises
    ------
    FileFormatError
        A member that cannot be read, or whose window or shape does not fit the tile.
    """
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            groups: dict[str, list[str]] = {}
            for member in zf.namelist():
                if member.startswith("tile_") and member.endswith(".npy") and "/" in member:
                    groups.setdefault(member.split("/")[0], []).append(member)
            for prefix in sorted(groups):
                yield _read_tile(zf, prefix, groups[prefix], tile_cells)
    except FileFormatError:
        raise
    except (
        OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error,
        NotImplementedError, RuntimeError,
    ) as exc:  # fmt: skip
        raise FileFormatError(path, f"not a readable map state: {clip(str(exc), 100)}") from None


def _read_tile(zf: zipfile.ZipFile, prefix: str, members: list[str], n: int) -> StateTile:
    _, r, c = prefix.split("_")
    if not (r.lstrip("-").isdigit() and c.lstrip("-").isdigit() and len(r + c) < 30):
        raise ValueError(f"{prefix}: not a tile name")
    # each member read within bounds (its declared size checked, no pickle): at most a
    # tile of float64, the window four integers
    npz = SafeNpz(Path(str(zf.filename)), "a map state", zf=zf)
    arrays: dict[str, NDArray[np.float64]] = {}
    for member in members:
        name = member[len(prefix) + 1 : -4]
        is_window = name == "_window"
        arrays[name] = npz.read(
            member[:-4],
            kinds="iu" if is_window else "f",
            ndim=1 if is_window else 2,
            max_bytes=64 if is_window else n * n * 8,
        )
    if "_window" not in arrays:
        raise ValueError(f"{prefix}: no _window")
    window = arrays.pop("_window")
    if window.shape != (4,):
        raise ValueError(f"{prefix}/_window: shape {window.shape}, expected (4,)")
    r0, r1, c0, c1 = (int(v) for v in window)
    if not (0 <= r0 < r1 <= n and 0 <= c0 < c1 <= n):
        raise ValueError(f"{prefix}: window {(r0, r1, c0, c1)} outside a {n}-cell tile")
    for name, values in arrays.items():
        if values.shape != (r1 - r0, c1 - c0) or values.dtype.kind != "f":
            raise ValueError(f"{prefix}/{name}: {values.dtype} {values.shape} for its window")
    return (int(r), int(c)), (r0, r1, c0, c1), arrays
