"""A command's output folder written as a set: staged beside it, swapped in whole.

:func:`output_set` yields a hidden staging folder ``.<DIR>.tmp.<hex>`` next to ``DIR``; the
writer puts every file there, and only when all are written (and checked, see
:func:`rough_map._files.atomic_output`) is the staging folder exchanged with ``DIR`` in one
step: ``renameat2(RENAME_EXCHANGE)`` on Linux (glibc >= 2.28), else ``DIR`` renamed aside
to ``.<DIR>.old.<hex>``, the new folder renamed in, the old one removed; a run killed
between those two renames is repaired by the next (the old folder is put back). So a
reader, or a run killed at any moment, sees either the whole old set or the whole new one.

Files of ``DIR`` that the run does not write are carried over into the new folder (hard
links, or copies across file systems) unless they are ``owned``: names the command writes
(e.g. ``map_*.png``), which, when this run does not write them (``--no-png``), are old
outputs and are dropped so that the folder holds one run's set. The user's own files and
folders are kept. rough_map's temporary names (:func:`rough_map._files.is_temp_name`)
are never carried over.

When ``DIR`` cannot be swapped (it is a mount point, the current folder or one of its
parents, or its parent is not writable) the files are moved into ``DIR`` one at a time
instead: each file is whole, the set is not (logged as a warning).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fnmatch
import logging
import os
import shutil
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from rough_map._files import (
    PENDING,
    RUN_START,
    PathLike,
    clean_stale,
    fsync_dir,
    is_temp_name,
    pending_folder,
    write_error,
)
from rough_map.errors import FileFormatError

log = logging.getLogger(__name__)

__all__ = ["exchange", "output_set", "recover", "replace_folder"]

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_renameat2: object | None = None


def _libc_renameat2() -> object | None:
    global _renameat2
    if _renameat2 is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
            fn = libc.renameat2
        except (OSError, AttributeError):
            _renameat2 = False
            return None
        fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
        fn.restype = ctypes.c_int
        _renameat2 = fn
    return _renameat2 or None


def exchange(a: PathLike, b: PathLike) -> bool:
    """Swap two existing paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``).

    Returns
    -------
    bool
        False when the system or the file system cannot (nothing changed then).

    Raises
    ------
    OSError
        Any other failure.
    """
    fn = _libc_renameat2()
    if fn is None:
        return False
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)  # type: ignore[operator]
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), os.fspath(b))


def _token() -> str:
    return uuid.uuid4().hex[:12]


def recover(folder: PathLike) -> None:
    """Repair what a run killed while replacing ``folder`` left, and remove its leftovers.

    ``folder`` missing but set aside (``.<name>.old.<hex>``, killed between the two renames
    of the fallback swap): the old folder is put back. Then staged and set-aside folders of
    ``folder`` older than this process are removed.
    """
    folder = Path(folder)
    parent, name = folder.parent, folder.name
    aside_prefix = f".{name}.old."
    if not os.path.lexists(folder):
        try:
            asides = [
                e
                for e in os.scandir(parent)
                if e.name.startswith(aside_prefix)
                and is_temp_name(e.name)
                and e.is_dir(follow_symlinks=False)
                and e.stat(follow_symlinks=False).st_mtime < RUN_START
            ]
        except OSError:
            asides = []
        if asides:
            newest = max(asides, key=lambda e: e.stat(follow_symlinks=False).st_mtime)
            try:
                os.rename(newest.path, folder)
                log.warning("restored %s, set aside by an interrupted run", folder)
            except OSError as exc:
                log.warning("cannot restore %s from %s: %s", folder, newest.name, exc)
    prefixes = (f".{name}.tmp.", aside_prefix)
    clean_stale(parent, lambda n: n.startswith(prefixes))


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _carry_over(old: Path, new: Path, owned: Sequence[str]) -> None:
    """Link into ``new`` what ``old`` holds that ``new`` does not, except ``owned`` names
    and temporary ones."""
    for entry in sorted(os.scandir(old), key=lambda e: e.name):
        name = entry.name
        # a pending commit of an old set (rough_map._files.atomic_outputs) is not carried:
        # rolled forward later, it would put the old files back over this run's
        if is_temp_name(name) or PENDING.match(name) or os.path.lexists(new / name):
            continue
        if any(fnmatch.fnmatchcase(name, pattern) for pattern in owned):
            log.info("dropping %s: an output of an earlier run that this run did not write", name)
            continue
        target = new / name
        if entry.is_symlink():
            os.symlink(os.readlink(entry.path), target)
        elif entry.is_dir():
            shutil.copytree(entry.path, target, symlinks=True, copy_function=_link_or_copy)
        else:
            _link_or_copy(entry.path, str(target))


def _is_mount_point(folder: Path) -> bool:
    """``folder`` is a mount point, bind mounts within one file system included (which
    :func:`os.path.ismount` misses: same device as the parent; renaming one gives EBUSY)."""
    if os.path.ismount(folder):
        return True
    real = os.path.realpath(folder)
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="surrogateescape") as fh:
            for line in fh:
                fields = line.split(" ", 5)
                if len(fields) > 4 and _unescape_mount(fields[4]) == real:
                    return True
    except OSError:
        pass
    return False


def _unescape_mount(text: str) -> str:
    for code, char in (("\\040", " "), ("\\011", "\t"), ("\\012", "\n"), ("\\134", "\\")):
        text = text.replace(code, char)
    return text


def _swappable(folder: Path) -> bool:
    if not folder.exists():
        return True
    if _is_mount_point(folder):
        return False
    real = folder.resolve()
    cwd = Path.cwd().resolve()
    return real != cwd and real not in cwd.parents


def replace_folder(staged: Path, folder: Path) -> Path | None:
    """Put ``staged`` at ``folder``'s place in one step; the old folder's new name (to
    remove), or None when there was none.

    Both are in the same parent. Exchange where supported, else rename aside and in (see
    :func:`recover`).
    """
    if not os.path.lexists(folder):
        os.rename(staged, folder)
        return None
    if exchange(staged, folder):
        return staged  # holds the old folder now
    aside = folder.with_name(f".{folder.name}.old.{_token()}")
    os.rename(folder, aside)
    os.rename(staged, folder)
    return aside


def _fsync_tree(root: Path) -> None:
    for dirpath, _, _ in os.walk(root):
        fsync_dir(dirpath)


@contextmanager
def output_set(folder: PathLike, *, owned: Sequence[str] = ()) -> Iterator[Path]:
    """Yield a staging folder; on success make it ``folder`` in one step (module docstring).

    Parameters
    ----------
    folder : str or PathLike
        The output folder (created, with its parents, if missing).
    owned : sequence of str
        Glob patterns of the names the command writes at the top of ``folder``: an old
        file of those names that this run does not write is dropped; every other file of
        ``folder`` is carried over. ``("*",)``: the folder is all the command's.

    Yields
    ------
    Path
        Where to write the files (an empty folder).

    Raises
    ------
    FileFormatError
        ``folder`` is a file, or writing failed (full disk, read-only): naming the folder,
        which keeps its old files.
    """
    folder = Path(os.path.abspath(folder))
    if folder.is_symlink():
        folder = folder.resolve()
    if os.path.lexists(folder) and not folder.is_dir():
        raise FileFormatError(folder, "cannot write: not a folder")
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(folder.parent, exc) from None
    recover(folder)
    whole = _swappable(folder)
    stage = folder.with_name(f".{folder.name}.tmp.{_token()}")
    try:
        if whole:
            try:
                stage.mkdir()
            except PermissionError:  # a folder of ours in a parent that is not
                if not folder.is_dir():
                    raise
                whole = False
        if not whole:
            clean_stale(folder)
            stage = folder / stage.name
            stage.mkdir()
    except OSError as exc:
        raise write_error(folder, exc) from None
    old: Path | None = None
    try:
        try:
            yield stage
        except OSError as exc:
            raise write_error(folder, exc) from None
        except FileFormatError as exc:
            raise _renamed(exc, stage, folder) from None
        try:
            if whole:
                if folder.is_dir():
                    _carry_over(folder, stage, owned)
                _fsync_tree(stage)
                old = replace_folder(stage, folder)
                fsync_dir(folder.parent)
            else:
                _move_in(stage, folder, owned)
        except OSError as exc:
            raise write_error(folder, exc) from None
    finally:
        for leftover in (stage, old):
            if leftover is not None and os.path.lexists(leftover):
                shutil.rmtree(leftover, ignore_errors=True)


def _renamed(exc: FileFormatError, stage: Path, folder: Path) -> FileFormatError:
    """``exc`` naming the final file instead of the staged one."""
    if exc.path != stage and stage not in exc.path.parents:
        return exc
    new = type(exc).__new__(type(exc))
    Exception.__init__(new, str(exc).replace(str(stage), str(folder), 1))
    new.path = folder / exc.path.relative_to(stage)
    new.field = exc.field
    return new


def _move_in(stage: Path, folder: Path, owned: Sequence[str]) -> None:
    """The fallback for a folder that cannot be swapped: its files moved in one by one."""
    log.warning(
        "%s is a mount point, the current folder or in a folder not writable: its files are "
        "replaced one at a time, not as a set",
        folder,
    )
    new = {e.name for e in os.scandir(stage)}
    for entry in os.scandir(folder):
        if entry.name in new or entry.path == str(stage) or is_temp_name(entry.name):
            continue
        if any(fnmatch.fnmatchcase(entry.name, p) for p in owned) and owned != ("*",):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
    for name in sorted(new):
        src, dst = stage / name, folder / name
        stale = pending_folder(dst)  # an old set's pending commit must not outlive it
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
        if src.is_dir() and dst.is_dir() and not dst.is_symlink():
            trash = folder / f".{name}.old.{_token()}"
            os.rename(dst, trash)
            os.rename(src, dst)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(src, dst)
    fsync_dir(folder)
