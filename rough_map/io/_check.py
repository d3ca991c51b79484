"""Checks shared by the file readers of :mod:`rough_map.io`."""

from __future__ import annotations

import stat
from pathlib import Path

from rough_map.errors import FileFormatError
from rough_map.limits import LIMITS

__all__ = ["check_count", "check_readable"]


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


def check_count(
    path: Path, count: int, what: str, field: str, *, limit: int = LIMITS.points
) -> None:
    """Raise a :class:`FileFormatError` unless ``0 <= count <= limit``."""
    if not 0 <= count <= limit:
        raise FileFormatError(
            path, f"the header declares {count} {what}, outside 0 to {limit}", field=field
        )
