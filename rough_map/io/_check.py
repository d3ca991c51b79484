"""Checks shared by the file readers of :mod:`rough_map.io`."""

from __future__ import annotations

import stat
from pathlib import Path

from rough_map.errors import FileFormatError

__all__ = ["MAX_MEMBER_BYTES", "MAX_POINTS", "check_count", "check_readable"]

MAX_POINTS = 2_000_000_000
"""Most points (or array elements) any reader accepts from a header, whatever the file size."""

MAX_MEMBER_BYTES = 4 * 2**30
"""Largest uncompressed member of an archive (.npz) that is read, in bytes."""


def check_readable(path: Path) -> None:
    """Raise a :class:`FileFormatError` unless ``path`` is a non-empty regular file (also for
    a name the system refuses: too long, a NUL byte, no permission)."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise FileFormatError(path, "no such file") from None
    except (OSError, ValueError) as err:
        why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise FileFormatError(path, f"cannot be read: {why}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FileFormatError(path, "not a regular file")
    if st.st_size == 0:
        raise FileFormatError(path, "the file is empty")


def check_count(path: Path, count: int, what: str, field: str, *, limit: int = MAX_POINTS) -> None:
    """Raise a :class:`FileFormatError` unless ``0 <= count <= limit``."""
    if not 0 <= count <= limit:
        raise FileFormatError(
            path, f"the header declares {count} {what}, outside 0 to {limit}", field=field
        )
