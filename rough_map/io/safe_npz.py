"""``.npy`` arrays and ``.npz`` archives read without trusting them.

:func:`read_npy` and :class:`SafeNpz` parse the ``.npy`` header with a size limit (numpy's own
parser, whose failures, ``tokenize`` errors included, become a clean error), refuse object
arrays (they would need pickle), and check that the declared shape and dtype fit the bytes the
file or member really holds before allocating anything. An archive's members are also checked
for size and compression ratio (a deflated member cannot be more than about 1032 times its
compressed size), and all the arrays read from one archive together may hold at most
``LIMITS.archive_ratio`` times the archive's size (plus 4 MiB): real point clouds and worlds
compress 1.5-3 times, more is a zip bomb. Members inflate in 1 MiB pieces. Every failure is a
one-line :class:`~rough_map.errors.FileFormatError` naming the file and the member.

The crash the archive checks prevent: ``np.load`` inflates a member whole (an archive of
0.3 MB with 300 MiB of zeros took 300+ MiB; ``tests/test_library_crashes.py``), so an archive
of a hundred MB can end in the kernel's OOM killer. The header checks turn numpy's errors
into one line naming the member; they prevent no crash.
"""

from __future__ import annotations

import math
import zipfile
import zlib
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

from rough_map._bounded import clip
from rough_map.errors import FileFormatError
from rough_map.limits import LIMITS

__all__ = ["ZIP_ERRORS", "SafeNpz", "read_npy"]


_ARCHIVE_SLACK = 4 * 2**20

#: What can go wrong inside the zip and zlib modules on a damaged archive.
ZIP_ERRORS = (
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    NotImplementedError,
    RuntimeError,
    ValueError,
    OverflowError,
    KeyError,
    IndexError,
    TypeError,
)


def read_npy(path: Path) -> np.ndarray:
    """The array of an ``.npy`` file (plain or structured dtype).

    Raises
    ------
    FileFormatError
        Not an .npy file, a header numpy cannot parse, an object dtype, a shape that needs
        more bytes than the file holds ("truncated?"), or an .npz archive.
    """
    size = path.stat().st_size
    with path.open("rb") as fh:
        if fh.read(4) == b"PK\x03\x04":
            raise FileFormatError(path, "this is an .npz archive, not an .npy array")
        fh.seek(0)
        shape, fortran, dtype = _header(fh, path, None)
        count = _check_fits(path, None, shape, dtype, size - fh.tell(), LIMITS.archive_member * 64)
        data = np.fromfile(fh, dtype=dtype, count=count)
    if data.size != count:
        raise FileFormatError(
            path, f"not a readable .npy file (truncated?): {data.size} of {count} items"
        )
    return data.reshape(shape, order="F" if fortran else "C")


class SafeNpz:
    """An .npz archive opened for bounded reading (a context manager).

    Parameters
    ----------
    path : str or Path
        The archive.
    what : str
        What the file should be, for messages ("a rough_map world file").
    zf : zipfile.ZipFile, optional
        The archive already open (``path`` then only names it in messages).

    Raises
    ------
    FileFormatError
        Missing, unreadable or not a zip archive.
    """

    def __init__(
        self, path: str | Path, what: str = "an .npz archive", *, zf: zipfile.ZipFile | None = None
    ) -> None:
        self.path = Path(path)
        self.what = what
        try:
            self._zip = zipfile.ZipFile(self.path) if zf is None else zf
            self._infos = {info.filename: info for info in self._zip.infolist()}
            size = self.path.stat().st_size
        except ZIP_ERRORS as err:
            raise FileFormatError(self.path, f"not {what}: {clip(str(err), 80)}") from None
        except Exception as err:  # zipfile parses a hostile central directory: any failure
            raise FileFormatError(
                self.path, f"not {what}: {type(err).__name__}: {clip(str(err), 80)}"
            ) from None
        self._size = size
        self._budget = LIMITS.archive_ratio * size + _ARCHIVE_SLACK

    def __enter__(self) -> SafeNpz:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the archive."""
        self._zip.close()

    @property
    def files(self) -> list[str]:
        """Member names without ``.npy``."""
        return [n.removesuffix(".npy") for n in self._infos if n.endswith(".npy")]

    def __contains__(self, name: str) -> bool:
        return f"{name}.npy" in self._infos

    def error(self, name: str, message: str) -> FileFormatError:
        """A FileFormatError naming this file and member ``name`` (printable, short)."""
        return FileFormatError(self.path, message, clip(name, 60))

    def read(
        self,
        name: str,
        *,
        kinds: str = "biuf",
        ndim: int | tuple[int, ...] | None = None,
        max_bytes: int = LIMITS.archive_member,
        structured: bool = False,
    ) -> np.ndarray:
        """Member ``name`` (without ``.npy``) as an array.

        Parameters
        ----------
        name : str
            The member.
        kinds : str
            Allowed dtype kinds (numpy's ``dtype.kind``: ``b i u f U``...).
        ndim : int or tuple of int, optional
            Allowed numbers of dimensions.
        max_bytes : int
            Largest array accepted, bytes.
        structured : bool
            Accept a structured dtype (fields), whatever ``kinds`` says.

        Raises
        ------
        FileFormatError
            Missing member, declared size beyond the data or the limit, a damaged header
            or data, or a dtype or number of dimensions not allowed.
        """
        info = self._infos.get(f"{name}.npy")
        if info is None:
            raise self.error(name, f"missing (not {self.what})")
        limit = min(max_bytes, LIMITS.archive_member, self._budget)
        if info.compress_type == zipfile.ZIP_STORED:
            plausible = info.compress_size
        else:
            plausible = info.compress_size * LIMITS.deflate_ratio + 1024
        if info.compress_size > self._size or info.file_size > min(
            limit + LIMITS.npy_header, plausible
        ):
            raise self.error(
                name,
                f"declares {info.file_size} bytes from {info.compress_size} in a file of "
                f"{self._size}: more than its data or the limit hold (zip bomb?)",
            )
        try:
            with self._zip.open(info) as stream:
                array = self._array(stream, name, info.file_size, kinds, ndim, limit, structured)
                stream.read()  # reach the end of the member so that zipfile checks its CRC
        except FileFormatError:
            raise
        except ZIP_ERRORS as err:
            raise self.error(name, f"damaged: {type(err).__name__}: {clip(str(err), 80)}") from None
        self._budget -= array.nbytes
        return array

    def _array(
        self,
        stream: IO[bytes],
        name: str,
        size: int,
        kinds: str,
        ndim: int | tuple[int, ...] | None,
        limit: int,
        structured: bool,
    ) -> np.ndarray:
        shape, fortran, dtype = _header(stream, self.path, name)
        if not (structured and dtype.fields is not None) and (
            dtype.kind not in kinds or dtype.fields is not None
        ):
            raise self.error(name, f"unexpected dtype {clip(str(dtype), 40)}")
        if ndim is not None and len(shape) not in ((ndim,) if isinstance(ndim, int) else ndim):
            raise self.error(name, f"unexpected shape {clip(str(shape), 40)}")
        count = _check_fits(self.path, name, shape, dtype, size - stream.tell(), limit)
        nbytes = count * dtype.itemsize
        data = bytearray(nbytes)
        view, got = memoryview(data), 0
        while got < nbytes:  # in pieces: a zip stream inflates what is asked at once
            piece = stream.read(min(nbytes - got, 1 << 20))
            if not piece:
                raise self.error(name, f"truncated: {got} of {nbytes} bytes")
            view[got : got + len(piece)] = piece
            got += len(piece)
        array = np.frombuffer(data, dtype=dtype, count=count)
        return array.reshape(shape, order="F" if fortran else "C")


def _header(fh: IO[bytes], path: Path, field: str | None) -> tuple[tuple[int, ...], bool, Any]:
    """Shape, Fortran order and dtype of the .npy stream ``fh``, with a bounded header."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(fh, max_header_size=LIMITS.npy_header)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = fmt.read_array_header_2_0(fh, max_header_size=LIMITS.npy_header)
        else:
            raise ValueError(f"unsupported .npy format version {version}")
    except (zipfile.BadZipFile, zlib.error) as err:
        raise FileFormatError(
            path, f"damaged (truncated?): {type(err).__name__}: {clip(str(err), 80)}", field
        ) from None
    except Exception as err:  # numpy evaluates the header text: tokenize, ast, dtype errors
        raise FileFormatError(
            path,
            f"not a readable .npy file (truncated?): bad header: {type(err).__name__}: "
            f"{clip(str(err), 80)}",
            field=field,
        ) from None
    if not isinstance(shape, tuple) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise FileFormatError(path, f"bad shape {clip(repr(shape), 40)} in the header", field)
    if dtype.hasobject:
        raise FileFormatError(
            path,
            f"not a readable .npy file: dtype {clip(str(dtype), 40)} holds Python objects, "
            "which need allow_pickle "
            "(refused: unsafe)",
            field=field,
        )
    return shape, bool(fortran), dtype


def _check_fits(
    path: Path, field: str | None, shape: tuple[int, ...], dtype: Any, available: int, limit: int
) -> int:
    """The element count of ``shape``, refused unless its bytes fit ``available`` and ``limit``."""
    count = math.prod(shape)
    if dtype.itemsize == 0 and count:
        raise FileFormatError(path, f"dtype {clip(str(dtype), 40)} has no size", field=field)
    needed = count * dtype.itemsize
    if count > LIMITS.points or needed > min(available, limit):
        raise FileFormatError(
            path,
            f"shape {clip(repr(shape), 40)} does not fit (truncated?): {dtype.itemsize} B items "
            f"need {needed} B, the data holds {max(available, 0)} B",
            field=field,
        )
    return count
