"""The world truth file of a simulated traverse: ``world_truth.npz``.

``rough-map simulate`` writes the true world beside the traverse (the traverse's
``height_field``): heights, class map, spacing and origin of a
:class:`~rough_map.types.HeightField`. The file is an .npz archive (zip) of .npy members in
one of two layouts.

Whole (a course built in one piece, up to 50 m; :func:`save_world`)
    ``heights`` (ny, nx) as int16 steps of at most :data:`HEIGHT_STEP` with a scale and an
    offset (``height_scale``, ``height_offset``: z in m is
    ``height_offset + height_scale * heights``), or float32 for a wider relief; the class
    map ``classes`` (int8 indices into ``class_names``; empty without one), deflated;
    ``spacing`` (m), ``origin`` (m, the centre of cell [0, 0]) and ``class_names``. Files
    of older versions with float heights are read too.

Tiled (a longer course, built tile by tile; :class:`TiledWorldWriter`)
    The columns in tiles of at most :data:`TILE_COLUMNS`: ``tile_columns`` (K + 1,) the
    first column of each tile and then the number of columns; ``heights_NNNNN`` (ny, n) of
    tile NNNNN as int16 steps with ``height_scale[k]`` and ``height_offset[k]`` (NaN: the
    tile is float32), stored as they are; ``classes_NNNNN`` (ny, n) int8, deflated;
    ``finite`` (K,) whether each tile's heights are all finite; ``shape`` (ny, nx);
    ``spacing``, ``origin`` and ``class_names`` as above. A reader needs one tile at a
    time (:class:`TiledWorld`), whatever the length of the world.

:func:`open_world` and :func:`traverse_truth` read the first as a
:class:`~rough_map.types.HeightField` and open the second as a :class:`TiledWorld`;
:func:`load_world` reads either whole. Heights are read as float32 and class maps as int8.
"""

from __future__ import annotations

import logging
import math
import zipfile
from collections import OrderedDict
from contextlib import ExitStack
from pathlib import Path
from types import TracebackType
from typing import Any, TypeAlias

import numpy as np

from rough_map._bounded import clip
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError, InputError
from rough_map.io.safe_npz import ZIP_ERRORS, SafeNpz
from rough_map.io.traverse import Traverse
from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = [
    "HEIGHT_STEP",
    "TILE_COLUMNS",
    "TRUTH_FILE",
    "TiledWorld",
    "TiledWorldWriter",
    "World",
    "load_world",
    "open_world",
    "save_world",
    "traverse_truth",
]

#: File name of the world truth in a simulated traverse folder.
TRUTH_FILE = "world_truth.npz"

HEIGHT_STEP = 1e-5
"""Coarsest step in m of the stored true heights; a wider relief is stored as float32."""

TILE_COLUMNS = 4096
"""Columns of a tile of a tiled world file (8.2 m at 2 mm; 16 MB of heights at 4 m wide)."""

_ROWS_BLOCK = 2**21  # cells converted at a time: small temporaries

_MAX_SIDE_CELLS = 2**31 - 1  # rows or columns of a world


def save_world(world: HeightField, path: PathLike) -> None:
    """Write a world as .npz (atomic), whole (see the module's docstring).

    The heights are int16 steps of ``(max - min) / 65534``, at most :data:`HEIGHT_STEP`
    (10 um; 6 um on a random course), with ``height_scale`` and ``height_offset`` in m:
    half the bytes of float32, and far below the 2 mm cells' roughness. A relief over
    0.65 m is stored as float32. The heights are not deflated (at 2 mm they hardly
    compress, by 10 %, and deflating them took longer than simulating the clouds); the
    class map is, to almost nothing.

    Parameters
    ----------
    world : HeightField
        Heights in m, spacing in m, origin in m, optional class map.
    path : str or Path
        Target ``.npz`` file; its folder must exist.
    """
    heights, scale, offset = _quantize(world.heights)
    members: dict[str, tuple[np.ndarray, bool]] = {"heights": (heights, False)}
    if scale is not None:
        members["height_scale"] = (np.asarray(scale, dtype=np.float64), False)
        members["height_offset"] = (np.asarray(offset, dtype=np.float64), False)
    classes = world.classes if world.classes is not None else np.zeros(0)
    members["classes"] = (classes.astype(np.int8), True)
    members["spacing"] = (np.asarray(world.spacing, dtype=np.float64), False)
    members["origin"] = (np.asarray(world.origin, dtype=np.float64), False)
    members["class_names"] = (np.asarray(world.class_names), False)
    _write_npz(Path(path), members)


def _quantize(heights: np.ndarray) -> tuple[np.ndarray, float | None, float | None]:
    """Heights as int16 steps, with the step and the offset in m; or as float32 (and
    None, None) when the relief needs steps over :data:`HEIGHT_STEP` or is not finite."""
    lo, hi = float(heights.min()), float(heights.max())  # NaN if any height is NaN
    step = (hi - lo) / 65534
    if not step <= HEIGHT_STEP:  # also NaN or inf
        log.info("world relief %.3f m: true heights stored as float32", hi - lo)
        return heights.astype(np.float32), None, None
    step = step or HEIGHT_STEP
    q = np.empty(heights.shape, dtype=np.int16)
    rows = max(1, _ROWS_BLOCK // max(1, heights.shape[1]))
    for r in range(0, heights.shape[0], rows):
        block = np.asarray(heights[r : r + rows], dtype=np.float64)
        q[r : r + rows] = np.rint((block - lo) / step) - 32767
    return q, step, lo + 32767 * step


def _dequantize(q: np.ndarray, scale: float, offset: float) -> np.ndarray:
    """Heights in m (float32) of int16 steps ``q``: ``offset + scale * q``."""
    out = np.empty(q.shape, dtype=np.float32)
    rows = max(1, _ROWS_BLOCK // max(1, q.shape[-1]))
    for r in range(0, q.shape[0], rows):
        out[r : r + rows] = q[r : r + rows] * scale + offset
    return out


def _write_member(zf: zipfile.ZipFile, name: str, array: np.ndarray, deflate: bool) -> None:
    """Write ``array`` as ``name.npy`` into an open archive, deflated or stored."""
    info = zipfile.ZipInfo(f"{name}.npy")
    info.compress_type = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zf.open(info, "w", force_zip64=True) as fh:
        np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)


def _write_npz(path: Path, members: dict[str, tuple[np.ndarray, bool]]) -> None:
    """An .npz archive (atomic) with each member deflated or stored as asked."""
    with atomic_output(path) as tmp, zipfile.ZipFile(tmp, "w", allowZip64=True) as zf:
        for name, (array, deflate) in members.items():
            _write_member(zf, name, array, deflate)


def load_world(path: PathLike) -> HeightField:
    """Read a whole world written by :func:`save_world` (float heights of older files too)
    or by :class:`TiledWorldWriter` (all its tiles: mind the memory, 6 bytes a cell; read
    a long world's windows with :func:`open_world` instead).

    Heights are float32 (m), the class map int8.

    Raises
    ------
    FileFormatError
        Not such a file (missing, not an .npz, a member missing).
    """
    path = Path(path)
    if _is_tiled(path):
        return TiledWorld(path).load()
    with SafeNpz(path, _WHAT) as d:
        stored = d.read("heights", kinds="iuf", ndim=2)
        if stored.shape[0] < 1 or stored.shape[1] < 1:
            raise d.error("heights", f"expected at least one cell, got shape {stored.shape}")
        if "height_scale" in d:
            scale = _scalar(d, "height_scale")
            offset = _scalar(d, "height_offset")
            heights = _dequantize(stored, scale, offset)
        else:
            heights = stored.astype(np.float32, copy=False)
        del stored
        classes = d.read("classes", kinds="iu", ndim=(1, 2), max_bytes=heights.size * 8)
        spacing, origin, names = _geometry(d)
    if classes.size and classes.shape != heights.shape:
        raise FileFormatError(
            path, f"shape {classes.shape} differs from the heights' {heights.shape}", "classes"
        )
    class_map = _class_map(classes, len(names), path) if classes.size else None
    return HeightField(heights, spacing, origin, class_map, names)


_WHAT = "a rough_map world file"


def _scalar(d: SafeNpz, name: str, positive: bool = False) -> float:
    """A finite float member (of one value)."""
    value = d.read(name, kinds="iuf", max_bytes=64)
    if value.size != 1 or not np.isfinite(value).all() or (positive and not value.item() > 0):
        kind = "a positive" if positive else "a finite"
        raise d.error(name, f"expected {kind} number, got {clip(str(value.tolist()), 40)}")
    return float(value.item())


def _geometry(d: SafeNpz) -> tuple[float, tuple[float, float], tuple[str, ...]]:
    """``spacing`` (m), ``origin`` (m) and ``class_names`` of a world file, checked."""
    spacing = _scalar(d, "spacing", positive=True)
    origin = d.read("origin", kinds="iuf", max_bytes=64)
    if origin.size != 2 or not np.isfinite(origin).all():
        raise d.error("origin", f"expected 2 finite numbers, got {clip(str(origin.tolist()), 40)}")
    names = d.read("class_names", kinds="U", ndim=1, max_bytes=_MAX_CLASS_NAMES * 400)
    if len(names) > _MAX_CLASS_NAMES:
        raise d.error("class_names", f"{len(names)} names (most {_MAX_CLASS_NAMES})")
    x0, y0 = (float(v) for v in origin.ravel())
    return spacing, (x0, y0), tuple(str(c) for c in names)


#: Most class names of a world file (its class map is int8).
_MAX_CLASS_NAMES = 127


def _class_map(classes: np.ndarray, n_names: int, path: Path) -> np.ndarray:
    """A stored class map as int8 (as written) or, for other integers, int64; every value
    is -1 (none) or an index into the ``n_names`` class names."""
    if classes.dtype.kind not in "iu":
        raise FileFormatError(path, f"must hold integers, not {classes.dtype}", "classes")
    if classes.size and (int(classes.min()) < -1 or int(classes.max()) >= n_names):
        raise FileFormatError(
            path,
            f"values {int(classes.min())}..{int(classes.max())} are not -1 or an index into "
            f"the {n_names} class_names",
            "classes",
        )
    return classes if classes.dtype == np.int8 else classes.astype(np.int64)


def _is_tiled(path: Path) -> bool:
    """Whether ``path`` is a zip archive with the tiled layout's ``tile_columns``."""
    try:
        with zipfile.ZipFile(path) as zf:
            return "tile_columns.npy" in zf.namelist()
    except ZIP_ERRORS:
        return False


class TiledWorld:
    """A world truth file of the tiled layout, read a tile at a time.

    Attributes
    ----------
    path : Path
        The file.
    shape : (int, int)
        Rows and columns of the whole world.
    spacing : float
        Cell size in m.
    origin : (float, float)
        World (x, y) in m of the centre of cell ``[0, 0]``.
    class_names : tuple of str
        Names of the class indices.
    tile_columns : ndarray of int64, shape (K + 1,)
        First column of each tile, then the number of columns.

    The last few tiles read are kept (:attr:`CACHE` of each kind, about 40 MB at 4 m wide
    and 2 mm), so that reading windows or cells along the course reads each tile about once.

    Raises
    ------
    FileFormatError
        Not a tiled world file.
    """

    CACHE = 2

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        with SafeNpz(self.path, "a rough_map tiled world file") as d:
            shape = d.read("shape", kinds="iu", ndim=1, max_bytes=64)
            if shape.size != 2 or shape.min() < 1 or shape.max() > _MAX_SIDE_CELLS:
                raise d.error(
                    "shape",
                    f"expected 2 sizes of 1..2**31-1 cells, got {clip(str(shape.tolist()), 40)}",
                )
            self.shape = (int(shape[0]), int(shape[1]))
            self.spacing, self.origin, self.class_names = _geometry(d)
            n_max = 8 * (self.shape[1] + 2)
            self.tile_columns = d.read("tile_columns", kinds="iu", ndim=1, max_bytes=n_max).astype(
                np.int64
            )
            self._scale = d.read("height_scale", kinds="f", ndim=1, max_bytes=n_max).astype(
                np.float64
            )
            self._offset = d.read("height_offset", kinds="f", ndim=1, max_bytes=n_max).astype(
                np.float64
            )
            self._finite = d.read("finite", kinds="biu", ndim=1, max_bytes=n_max).astype(bool)
        edges = self.tile_columns
        n = len(edges) - 1
        if (
            n < 1
            or edges[0] != 0
            or edges[-1] != self.shape[1]
            or np.any(np.diff(edges) <= 0)
            or not len(self._scale) == len(self._offset) == len(self._finite) == n
            or np.any(np.isinf(self._scale))
            or np.any(~np.isfinite(self._offset[~np.isnan(self._scale)]))
        ):
            raise FileFormatError(
                self.path,
                f"expected increasing columns from 0 to {self.shape[1]} and one finite "
                f"scale, offset and finite flag per tile; got {clip(str(edges.tolist()[:4]), 40)} "
                f"and {len(self._scale)}, {len(self._offset)}, {len(self._finite)}",
                "tile_columns",
            )
        self._cache: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()

    @property
    def n_tiles(self) -> int:
        return len(self.tile_columns) - 1

    def _member(self, name: str, kinds: str, max_bytes: int) -> np.ndarray:
        with SafeNpz(self.path, "a rough_map tiled world file") as d:
            return d.read(name, kinds=kinds, ndim=2, max_bytes=max_bytes)

    def _cached(self, kind: str, k: int) -> np.ndarray:
        key = (kind, k)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        n = int(self.tile_columns[k + 1] - self.tile_columns[k])
        kinds = "iuf" if kind == "heights" else "iu"
        stored = self._member(f"{kind}_{k:05d}", kinds, self.shape[0] * n * 8)
        if stored.shape != (self.shape[0], n):
            raise FileFormatError(
                self.path,
                f"{kind}_{k:05d}: expected shape {(self.shape[0], n)}, got {stored.shape}",
            )
        if kind == "heights":
            if math.isnan(self._scale[k]):
                array = stored.astype(np.float32, copy=False)
            else:
                array = _dequantize(stored, float(self._scale[k]), float(self._offset[k]))
        else:
            array = _class_map(stored, len(self.class_names), self.path).astype(np.int8, copy=False)
        self._cache[key] = array
        if sum(kk == kind for kk, _ in self._cache) > self.CACHE:
            oldest = next(key for key in self._cache if key[0] == kind)
            del self._cache[oldest]
        return array

    def tile_heights(self, k: int) -> np.ndarray:
        """Heights in m (float32, (ny, n)) of tile ``k``."""
        return self._cached("heights", k)

    def tile_classes(self, k: int) -> np.ndarray:
        """Class indices (int8, (ny, n)) of tile ``k``."""
        return self._cached("classes", k)

    def columns(self, c0: int, c1: int) -> HeightField:
        """The columns ``c0 <= c < c1`` (clipped to the world) as a :class:`HeightField`
        (float32 heights, int8 class map)."""
        nx = self.shape[1]
        c0 = max(0, min(int(c0), nx - 1))
        c1 = max(c0 + 1, min(int(c1), nx))
        k0 = int(np.searchsorted(self.tile_columns, c0, side="right")) - 1
        k1 = int(np.searchsorted(self.tile_columns, c1, side="left"))
        heights, classes = [], []
        for k in range(k0, k1):
            t0 = int(self.tile_columns[k])
            a, b = max(c0, t0) - t0, min(c1, int(self.tile_columns[k + 1])) - t0
            heights.append(self.tile_heights(k)[:, a:b])
            classes.append(self.tile_classes(k)[:, a:b])
        origin = (self.origin[0] + c0 * self.spacing, self.origin[1])
        return HeightField(
            np.concatenate(heights, axis=1),
            self.spacing,
            origin,
            np.concatenate(classes, axis=1),
            self.class_names,
        )

    def window(self, x0: float, x1: float) -> HeightField:
        """The columns covering world x from ``x0`` to ``x1`` m (see :meth:`columns`)."""
        c0 = int(math.floor((x0 - self.origin[0]) / self.spacing))
        c1 = int(math.ceil((x1 - self.origin[0]) / self.spacing)) + 1
        return self.columns(c0, c1)

    def load(self) -> HeightField:
        """The whole world (float32 heights, int8 class map: 5 bytes a cell)."""
        return self.columns(0, self.shape[1])

    def cells(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Row and column (int64, maybe outside the world) of the cell nearest each point
        (x, y) in m."""
        col = np.rint((np.asarray(x, dtype=float) - self.origin[0]) / self.spacing)
        row = np.rint((np.asarray(y, dtype=float) - self.origin[1]) / self.spacing)
        return row.astype(np.int64), col.astype(np.int64)

    def lookup(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Class index (int64) and whether the height is finite, of the cells ``(rows,
        cols)`` (inside the world), reading the tiles they lie in one after the other."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        classes = np.empty(rows.shape, dtype=np.int64)
        finite = np.ones(rows.shape, dtype=bool)
        if rows.size == 0:
            return classes, finite
        ny, nx = self.shape
        if rows.min() < 0 or rows.max() >= ny or cols.min() < 0 or cols.max() >= nx:
            raise InputError(f"cells outside the world of {ny} x {nx} cells")
        flat_r, flat_c = rows.ravel(), cols.ravel()
        tile = np.searchsorted(self.tile_columns, flat_c, side="right") - 1
        order = np.argsort(tile, kind="stable")
        bounds = np.searchsorted(tile[order], np.arange(self.n_tiles + 1))
        out_c, out_f = classes.reshape(-1), finite.reshape(-1)
        for k in np.flatnonzero(np.diff(bounds)):
            sel = order[bounds[k] : bounds[k + 1]]
            r, c = flat_r[sel], flat_c[sel] - self.tile_columns[k]
            out_c[sel] = self.tile_classes(int(k))[r, c]
            if not self._finite[k]:
                out_f[sel] = np.isfinite(self.tile_heights(int(k))[r, c])
        return classes, finite


World: TypeAlias = HeightField | TiledWorld
"""A world truth as read: whole in memory, or a tiled file read a tile at a time."""


def open_world(path: PathLike) -> World:
    """A world truth file: a whole one read (:func:`load_world`), a tiled one opened
    (:class:`TiledWorld`, read a tile at a time).

    Raises
    ------
    FileFormatError
        Not a world file.
    """
    path = Path(path)
    return TiledWorld(path) if _is_tiled(path) else load_world(path)


def traverse_truth(traverse: Traverse) -> World | None:
    """The true world of a traverse (its ``height_field``, e.g. the simulator's
    ``world_truth.npz``; :func:`open_world`), or None when it names none or the file is not
    there.

    Raises
    ------
    FileFormatError
        The file is there but is not a world file.
    """
    if traverse.spec.height_field is None:
        return None
    path = traverse.resolve(traverse.spec.height_field, "height_field")
    try:
        there = path.is_file()
    except OSError:  # a name too long
        there = False
    return open_world(path) if there else None


class TiledWorldWriter:
    """Write a world of the tiled layout column block after column block, as a simulator
    builds it (a context manager; atomic: the file appears complete or not at all).

    Parameters
    ----------
    path : str or Path
        Target ``.npz`` file; its folder must exist.
    shape : (int, int)
        Rows and columns of the whole world.
    spacing : float
        Cell size in m.
    origin : (float, float)
        World (x, y) in m of the centre of cell ``[0, 0]``.
    class_names : sequence of str
        Names of the class indices.
    tile_columns : int, optional
        Columns of a tile (the last takes the rest); :data:`TILE_COLUMNS` by default.

    Each tile is quantised as :func:`save_world` quantises a whole world (int16 steps of at
    most :data:`HEIGHT_STEP` over the tile's own relief, else float32). Memory holds a
    tile and the block being appended.
    """

    def __init__(
        self,
        path: PathLike,
        shape: tuple[int, int],
        spacing: float,
        origin: tuple[float, float],
        class_names: tuple[str, ...] | list[str],
        *,
        tile_columns: int | None = None,
    ) -> None:
        tile_columns = TILE_COLUMNS if tile_columns is None else tile_columns
        if tile_columns < 1:
            raise InputError(f"tile_columns must be at least 1, got {tile_columns}")
        self.path = Path(path)
        self.shape = (int(shape[0]), int(shape[1]))
        self.spacing = float(spacing)
        self.origin = (float(origin[0]), float(origin[1]))
        self.class_names = tuple(class_names)
        self.tile_columns = int(tile_columns)
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_columns = 0
        self._edges = [0]
        self._scale: list[float] = []
        self._offset: list[float] = []
        self._finite: list[bool] = []
        self._stack: ExitStack | None = None
        self._zip: zipfile.ZipFile | None = None

    def __enter__(self) -> TiledWorldWriter:
        with ExitStack() as stack:
            tmp = stack.enter_context(atomic_output(self.path))
            self._zip = stack.enter_context(zipfile.ZipFile(tmp, "w", allowZip64=True))
            self._stack = stack.pop_all()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        stack, self._stack = self._stack, None
        if stack is None:
            return
        if exc_type is not None:  # the file is dropped
            stack.__exit__(exc_type, exc, tb)
            return
        with stack:  # closes the archive, then moves it in place (or drops it on error)
            self._finish()

    def append(self, first_column: int, heights: np.ndarray, classes: np.ndarray) -> None:
        """Add the columns from ``first_column`` on (the next ones): ``heights`` (ny, n) in
        m and ``classes``, the class index of each column (n,) or each cell (ny, n)."""
        if self._zip is None:
            raise InputError("append to a TiledWorldWriter inside its `with` block")
        ny, n = heights.shape
        expected = self._edges[-1] + self._pending_columns
        if ny != self.shape[0] or first_column != expected or expected + n > self.shape[1]:
            raise InputError(
                f"expected columns from {expected} of {self.shape[0]} rows (of "
                f"{self.shape[1]} columns); got {n} from {first_column} of {ny} rows"
            )
        if classes.shape not in ((n,), (ny, n)):
            raise InputError(f"classes must have shape ({n},) or ({ny}, {n}), got {classes.shape}")
        self._pending.append((heights, classes))
        self._pending_columns += n
        while self._pending_columns >= self.tile_columns:
            self._write_tile(self.tile_columns)

    def _write_tile(self, n: int) -> None:
        """Write the first ``n`` pending columns as the next tile."""
        assert self._zip is not None
        heights, classes, taken = [], [], 0
        while taken < n:
            h, c = self._pending[0]
            use = min(n - taken, h.shape[1])
            heights.append(h[:, :use])
            classes.append(np.broadcast_to(c[..., :use], (self.shape[0], use)))
            if use == h.shape[1]:
                self._pending.pop(0)
            else:
                self._pending[0] = (h[:, use:], c[..., use:])
            taken += use
        self._pending_columns -= n
        k = len(self._scale)
        tile = np.concatenate(heights, axis=1) if len(heights) > 1 else heights[0]
        stored, scale, offset = _quantize(tile)
        self._finite.append(bool(np.isfinite(tile).all()))
        del tile, heights
        _write_member(self._zip, f"heights_{k:05d}", stored, False)
        del stored
        _write_member(
            self._zip, f"classes_{k:05d}", np.concatenate(classes, axis=1).astype(np.int8), True
        )
        self._scale.append(math.nan if scale is None else scale)
        self._offset.append(math.nan if offset is None else offset)
        self._edges.append(self._edges[-1] + n)

    def _finish(self) -> None:
        """Write the last tile and the layout."""
        assert self._zip is not None
        if self._pending_columns:
            self._write_tile(self._pending_columns)
        if self._edges[-1] != self.shape[1]:
            raise InputError(
                f"{self.path}: {self._edges[-1]} of the world's {self.shape[1]} columns written"
            )
        members: dict[str, np.ndarray] = {
            "tile_columns": np.asarray(self._edges, dtype=np.int64),
            "height_scale": np.asarray(self._scale, dtype=np.float64),
            "height_offset": np.asarray(self._offset, dtype=np.float64),
            "finite": np.asarray(self._finite, dtype=bool),
            "shape": np.asarray(self.shape, dtype=np.int64),
            "spacing": np.asarray(self.spacing, dtype=np.float64),
            "origin": np.asarray(self.origin, dtype=np.float64),
            "class_names": np.asarray(self.class_names),
        }
        for name, array in members.items():
            _write_member(self._zip, name, array, False)
        self._zip = None
