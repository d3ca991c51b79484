"""Point clouds from files, and back.

Every reader returns the points as a float64 array of shape (N, 3): x, y, z in m, in the
frame the file was written in. Rows with a NaN or infinite coordinate are dropped (logged at
debug level); a file without a single finite point is an error. Readers and writers are found
by file suffix in the registries ``READERS`` and ``WRITERS``:

=================  =============================================================
suffix             content
=================  =============================================================
.npy               (N, >=3) numeric array, or a structured array with x, y, z
.npz               ``points`` as in .npy, or 1-D columns ``x``, ``y``, ``z``; an integer
                   column ``c`` with ``c_scale`` and ``c_offset`` (m) reads as
                   ``c_offset + c_scale * c`` (read only; ``rough-map simulate --compress``)
.csv .xyz .txt     text, comma/semicolon/whitespace separated, optional header
.ply .pcd          read with numpy (:mod:`rough_map.io.ply_pcd`: open3d's readers can crash
                   on corrupt files), written with open3d
.las .laz          read and written with laspy (.laz needs the lazrs backend), see
                   :mod:`rough_map.io.las` for the classification and CRS
.bin               KITTI velodyne scan: float32 x, y, z, reflectance (read only)
=================  =============================================================

Writers replace the target atomically: they write a temporary file in the same folder and
``os.replace`` it, so a reader never sees half a file.
"""

from __future__ import annotations

import logging
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from rough_map._bounded import clip, short
from rough_map._files import PathLike, atomic_output
from rough_map.errors import FileFormatError, InputError
from rough_map.io._check import check_readable
from rough_map.io.las import read_las, write_las
from rough_map.io.ply_pcd import read_pcd, read_ply
from rough_map.io.safe_npz import SafeNpz, read_npy

__all__ = [
    "READERS",
    "WRITERS",
    "CloudReader",
    "CloudWriter",
    "read_cloud",
    "read_kitti_poses",
    "write_cloud",
]

log = logging.getLogger(__name__)


class CloudReader(Protocol):
    """Reads one file into an array whose first three columns are x, y, z in m."""

    def __call__(self, path: Path) -> np.ndarray: ...


class CloudWriter(Protocol):
    """Writes an (N, 3) float64 array of x, y, z in m to ``path`` (a temporary name)."""

    def __call__(self, path: Path, points: np.ndarray) -> None: ...


# --------------------------------------------------------------------------------------------
# Public API


def read_cloud(path: PathLike, *, columns: Sequence[str] | None = None) -> np.ndarray:
    """Read a point cloud file.

    Parameters
    ----------
    path : str or PathLike
        A file with one of the suffixes in ``READERS`` (case-insensitive).
    columns : sequence of 3 str, optional
        For a text cloud: the header names (case-insensitive) or 1-based numbers of the
        columns that hold x, y and z. Default: the columns headed x, y, z, or the only
        three, or the first three of a file without a header.

    Returns
    -------
    ndarray, shape (N, 3), float64
        x, y, z in m, finite, N >= 1. LAS/LAZ coordinates in feet are converted to m
        (see :func:`rough_map.io.las.read_las`).

    Raises
    ------
    FileFormatError
        Unknown suffix, missing or empty file, truncated or corrupt content, wrong shape or
        dtype, no finite point, or a header whose columns are not x, y, z (without
        ``columns``) or lack one of ``columns``.
    InputError
        ``columns`` for a format that is not text, or not three names or numbers.
    """
    path = Path(path)
    reader = READERS.get(path.suffix.lower())
    picked = None if columns is None else _check_columns(columns)
    if picked is not None and reader is not _read_text:
        raise InputError(f"{path.name}: columns pick the fields of text clouds only")
    if reader is None:
        known = ", ".join(sorted(READERS))
        raise FileFormatError(
            path, f"unknown point-cloud suffix {path.suffix!r}; known: {known}", field="suffix"
        )
    check_readable(path)
    return _finite_xyz(path, reader(path) if picked is None else _read_text(path, picked))


def write_cloud(path: PathLike, points: np.ndarray) -> Path:
    """Write a point cloud, replacing ``path`` atomically.

    Parameters
    ----------
    path : str or PathLike
        Target file; its suffix (.npy, .csv, .xyz, .txt, .ply, .pcd, .las, .laz) picks the
        format. The folder must exist.
    points : array_like, shape (N, 3)
        x, y, z in m. LAS/LAZ store them as integers of 0.1 mm (scale 1e-4 m), so the cloud
        must span less than about 400 km and be finite.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    InputError
        ``points`` is not a non-empty numeric (N, 3) array.
    FileFormatError
        Unknown suffix, missing folder, or the backend could not write the file.
    """
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        known = ", ".join(sorted(WRITERS))
        raise FileFormatError(
            path, f"cannot write suffix {path.suffix!r}; known: {known}", field="suffix"
        )
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "fiu" or len(pts) == 0:
        raise InputError(
            f"points must be a non-empty numeric (N, 3) array of x, y, z in m; "
            f"got shape {pts.shape} and dtype {pts.dtype}"
        )
    with atomic_output(path) as tmp:
        writer(tmp, pts.astype(np.float64, copy=False))
    log.debug("wrote %d points to %s", len(pts), path)
    return path


def read_kitti_poses(path: PathLike) -> np.ndarray:
    """Read a KITTI odometry ``poses.txt``.

    Parameters
    ----------
    path : str or PathLike
        Text file, one pose per line: the 12 numbers of a 3×4 matrix, row-major.

    Returns
    -------
    ndarray, shape (N, 4, 4), float64
        Homogeneous transforms (rotation, translation in m), last row ``[0, 0, 0, 1]``.

    Raises
    ------
    FileFormatError
        Missing or empty file, non-numeric text, or not 12 numbers per line.
    """
    path = Path(path)
    check_readable(path)
    rows = _loadtxt(path, delimiter=None, skiprows=0, usecols=None)
    if rows.size == 0:
        raise FileFormatError(path, "the file holds no poses", field="poses")
    if rows.shape[1] != 12:
        raise FileFormatError(
            path, f"expected 12 numbers (a 3x4 matrix) per line, got {rows.shape[1]}", "columns"
        )
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    return poses


# --------------------------------------------------------------------------------------------
# Readers


def _read_npy(path: Path) -> np.ndarray:
    return read_npy(path)


def _read_npz(path: Path) -> np.ndarray:
    """``points`` of an .npz archive, or its columns x, y, z (integers scaled to m)."""
    with path.open("rb") as fh:
        if fh.read(6) == b"\x93NUMPY":
            raise FileFormatError(path, "this is an .npy array, not an .npz archive")
    with SafeNpz(path, "a readable .npz archive (truncated?)") as archive:
        if "points" in archive:
            return archive.read("points", structured=True)
        missing = [c for c in "xyz" if c not in archive]
        if missing:
            raise FileFormatError(
                path,
                f"an .npz cloud holds 'points' (N x 3) or columns x, y, z; this one holds "
                f"{short(sorted(archive.files), 80)}",
                field=missing[0],
            )
        keys = [k for c in "xyz" for k in (c, f"{c}_scale", f"{c}_offset") if k in archive]
        arrays = {key: archive.read(key) for key in keys}
    for c in "xyz":
        col = arrays[c]
        if col.ndim != 1 or col.dtype.kind not in "fiu":
            raise FileFormatError(
                path,
                f"expected a 1-D numeric column; got shape {clip(col.shape, 40)}, "
                f"dtype {clip(col.dtype, 40)}",
                field=c,
            )
        for key in (f"{c}_scale", f"{c}_offset"):
            value = arrays.get(key)
            if value is not None and (value.ndim != 0 or value.dtype.kind not in "fiu"):
                raise FileFormatError(
                    path, f"expected a number in m; got shape {clip(value.shape, 40)}", field=key
                )
    if len({len(arrays[c]) for c in "xyz"}) > 1:
        lengths = ", ".join(f"{c} {len(arrays[c])}" for c in "xyz")
        raise FileFormatError(path, f"columns of different lengths: {lengths}", field="shape")
    # Filled column by column: no temporary float64 copy of the whole cloud.
    xyz = np.empty((len(arrays["x"]), 3), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite rows are dropped later
        for k, c in enumerate("xyz"):
            xyz[:, k] = arrays[c]
            if f"{c}_scale" in arrays:
                xyz[:, k] *= float(arrays[f"{c}_scale"])
            if f"{c}_offset" in arrays:
                xyz[:, k] += float(arrays[f"{c}_offset"])
    return xyz


_MAX_LINE = 65536
"""Longest first line of a text cloud that is looked at for a header, in characters."""
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.I)
_LOADTXT_WHERE = re.compile(
    r"could not convert string (?P<value>.*) to \w+ at row (?P<row>\d+), column (?P<column>\d+)"
)


def _check_columns(columns: Sequence[str]) -> tuple[str, str, str]:
    """Three column names or 1-based numbers, or :class:`InputError`."""
    picked = tuple(str(c).strip().lower() for c in columns) if not isinstance(columns, str) else ()
    if len(picked) != 3 or not all(picked) or len(set(picked)) != 3:
        raise InputError(
            f"columns must name the x, y and z columns (3 distinct names or numbers); got "
            f"{short(columns, 60)}"
        )
    return picked[0], picked[1], picked[2]


def _read_text(path: Path, columns: tuple[str, str, str] | None = None) -> np.ndarray:
    """x, y, z from a delimited text file: the ``columns`` named (header names or 1-based
    numbers), else those headed x, y, z, else the only three of a header."""
    first, line_no = "", 0
    with path.open("r", encoding="utf-8", errors="replace") as fh:
        while line := fh.readline(_MAX_LINE):
            if len(line) >= _MAX_LINE and not line.endswith("\n"):
                raise FileFormatError(
                    path, f"line {line_no + 1} is longer than {_MAX_LINE} characters", "text"
                )
            if line.strip() and not line.lstrip().startswith("#"):
                first = line.strip()
                break
            line_no += 1
    delimiter = "," if "," in first else ";" if ";" in first else None
    tokens = [t.strip().strip("\"'") for t in first.split(delimiter)]
    has_header = not all(_NUMBER.match(t) for t in tokens if t)
    names = [t.lstrip("/#").strip().lower() for t in tokens] if has_header else []
    usecols = _text_columns(path, names, len(tokens), columns)
    return _loadtxt(
        path, delimiter=delimiter, skiprows=line_no + 1 if has_header else 0, usecols=usecols
    )


def _text_columns(
    path: Path, names: list[str], n_columns: int, columns: tuple[str, str, str] | None
) -> list[int] | None:
    """0-based x, y, z columns of a text cloud whose header has ``names`` (none: no header)."""
    if columns is not None:
        out = []
        for c in columns:
            if c in names:
                out.append(names.index(c))
            elif c.isdigit() and 1 <= int(c) <= n_columns:
                out.append(int(c) - 1)
            else:
                have = ", ".join(names) if names else f"{n_columns} columns, no header"
                raise FileFormatError(path, f"no column {c!r} (has {short(have, 80)})", "header")
        return out
    if not names or {"x", "y", "z"} <= set(names):
        return [names.index(c) for c in "xyz"] if names else None
    if len(names) <= 3:
        return None  # three named columns (e, n, h...) are x, y, z; fewer: a shape error
    raise FileFormatError(
        path,
        f"header {short(', '.join(names), 50)} has no x, y, z: name them (--columns X,Y,Z)",
        field="header",
    )


def _loadtxt(
    path: Path, delimiter: str | None, skiprows: int, usecols: list[int] | None
) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            return np.loadtxt(
                path,
                delimiter=delimiter,
                comments="#",
                skiprows=skiprows,
                usecols=usecols,
                ndmin=2,
                dtype=np.float64,
                encoding="utf-8",
            )
    except ValueError as err:  # includes UnicodeDecodeError
        where = _LOADTXT_WHERE.search(str(err))
        if where is None:
            raise FileFormatError(
                path, f"not a table of numbers: {clip(err)}", field="text"
            ) from err
        # numpy counts data rows from 0 (after header, comments, blank lines), columns from 1.
        row, column = int(where["row"]) + 1, int(where["column"])
        raise FileFormatError(
            path,
            f"not a table of numbers: {short(where['value'], 40)} in data row {row}, "
            f"column {column}",
            field=f"row {row}, column {column}",
        ) from err


def _open3d_path(path: Path) -> Any:
    """``path`` as open3d takes it: a str (open3d 0.18 takes only str; later stubs say
    ``os.PathLike``, which a str also is at run time)."""
    return str(path)


def _read_las_xyz(path: Path) -> np.ndarray:
    return read_las(path).points


def _read_kitti_bin(path: Path) -> np.ndarray:
    size = path.stat().st_size
    if size % 16:
        raise FileFormatError(
            path,
            f"size {size} B is not a multiple of 16 B (float32 x, y, z, reflectance); truncated?",
            field="size",
        )
    return np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]


def _finite_xyz(path: Path, arr: np.ndarray) -> np.ndarray:
    """Check shape and dtype, keep x, y, z as float64 and drop non-finite rows."""
    if arr.dtype.names is not None:
        lower = {n.lower(): n for n in arr.dtype.names}
        missing = [c for c in "xyz" if c not in lower]
        if missing:
            raise FileFormatError(
                path,
                f"structured array without field(s) {missing}; has {list(arr.dtype.names)}",
                field=missing[0],
            )
        arr = np.stack([arr[lower[c]] for c in "xyz"], axis=-1).reshape(-1, 3)
    if arr.dtype.kind not in "fiu":
        raise FileFormatError(
            path, f"expected numbers, got dtype {arr.dtype} ({arr.dtype.kind!r})", "dtype"
        )
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise FileFormatError(
            path, f"expected an (N, 3) or (N, >=3) array of x, y, z; got shape {arr.shape}", "shape"
        )
    if arr.shape[0] == 0:
        raise FileFormatError(path, "the file holds no points", field="points")
    # A fresh (N, 3) float64 array from a reader is kept as it is; anything else is copied.
    with np.errstate(invalid="ignore"):  # a signalling NaN in float32 warns when widened
        xyz = np.ascontiguousarray(arr[:, :3], dtype=np.float64)
    # One cheap pass: the sum of all coordinates is NaN or infinite whenever one of them is
    # (and, rarely, when finite ones overflow); only then is the row mask built.
    with np.errstate(over="ignore", invalid="ignore"):
        total = xyz.sum()
    if np.isfinite(total):
        return xyz
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        n_bad = int((~finite).sum())
        if n_bad == len(xyz):
            raise FileFormatError(path, f"all {n_bad} points are NaN or infinite", field="xyz")
        log.debug("%s: dropped %d of %d points with NaN or inf", path, n_bad, len(xyz))
        xyz = xyz[finite]
    return xyz


# --------------------------------------------------------------------------------------------
# Writers


def _write_npy(path: Path, points: np.ndarray) -> None:
    with path.open("wb") as fh:
        np.save(fh, points, allow_pickle=False)


def _write_text(path: Path, points: np.ndarray) -> None:
    np.savetxt(path, points, fmt="%.17g", delimiter=",", header="x,y,z", comments="")


def _write_open3d(path: Path, points: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor.from_numpy(np.ascontiguousarray(points)))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.t.io.write_point_cloud(_open3d_path(path), cloud)
    if not ok:
        raise FileFormatError(path, "open3d could not write the file")


READERS: dict[str, CloudReader] = {
    ".npy": _read_npy,
    ".npz": _read_npz,
    ".csv": _read_text,
    ".xyz": _read_text,
    ".txt": _read_text,
    ".ply": read_ply,
    ".pcd": read_pcd,
    ".las": _read_las_xyz,
    ".laz": _read_las_xyz,
    ".bin": _read_kitti_bin,
}
"""Point-cloud readers by lower-case suffix."""

WRITERS: dict[str, CloudWriter] = {
    ".npy": _write_npy,
    ".csv": _write_text,
    ".xyz": _write_text,
    ".txt": _write_text,
    ".ply": _write_open3d,
    ".pcd": _write_open3d,
    ".las": write_las,
    ".laz": write_las,
}
"""Point-cloud writers by lower-case suffix."""
