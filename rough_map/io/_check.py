"""Checks shared by the file readers of :mod:`rough_map.io`."""

from __future__ import annotations

from pathlib import Path

from rough_map.errors import FileFormatError


def check_readable(path: Path) -> None:
    """Raise a :class:`FileFormatError` unless ``path`` is a non-empty regular file."""
    if not path.exists():
        raise FileFormatError(path, "no such file")
    if not path.is_file():
        raise FileFormatError(path, "not a regular file")
    if path.stat().st_size == 0:
        raise FileFormatError(path, "the file is empty")
