"""File helpers shared by every writer: atomic replacement of a file.

A writer writes a temporary file in the same folder and ``os.replace`` s it onto the target,
so a reader never sees half a file and an interrupted run leaves the old file as it was.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rough_map.errors import FileFormatError

__all__ = ["PathLike", "atomic_output"]

PathLike = str | os.PathLike[str]


@contextmanager
def atomic_output(path: PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path``.

    The temporary name keeps the suffix of ``path`` (backends such as open3d and laspy pick
    the format from it) and starts with a dot. On error the temporary file is removed and
    ``path`` is left untouched.

    Parameters
    ----------
    path : str or PathLike
        The final file. Its folder must exist.

    Yields
    ------
    Path
        Where to write.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileFormatError(path, f"cannot write: folder {path.parent} does not exist")
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
