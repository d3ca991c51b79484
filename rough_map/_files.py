"""File helpers shared by every writer: atomic replacement of a file, write errors, leftovers.

A writer writes a temporary file in the same folder and ``os.replace`` s it onto the target,
so a reader never sees half a file and an interrupted run leaves the old file as it was.
Before the rename the temporary file is checked (it exists, is not empty, a GeoTIFF reopens
and its last block reads back) and flushed to the disk (``fsync``): a full disk that a
library reported without raising (GDAL) never leaves a truncated file under the final name.
An ``OSError`` while writing (full disk, read-only folder) becomes a one-line
:class:`~rough_map.errors.FileFormatError` naming the file.

Temporary names start with a dot and hold ``.tmp`` (:data:`TMP_FILE`, and the staged
folders of :func:`output_set`); those a killed run left behind are removed by the next run
that writes to the same place (only those older than this process).

The one place rough_map writes atomically, at three sizes:

* a file: :func:`atomic_output` (a temporary file beside it, checked, renamed onto it);
* a set of files in a user's folder, such as a table and its metadata or a model and its
  card: :func:`atomic_outputs` (a pending folder beside them, a commit marker, then the
  renames; every reader calls :func:`resolve_pending` first);
* a command's whole output folder (a map, a report, a simulated traverse, an imported
  bag): :func:`output_set`, below.

A command's output folder
-------------------------
A command's output folder written as a set: staged beside it, swapped in whole.

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
import re
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from rough_map._bounded import clip
from rough_map.errors import FileFormatError, InputError

log = logging.getLogger(__name__)

__all__ = [
    "RUN_START",
    "TMP_FILE",
    "PathLike",
    "atomic_output",
    "atomic_outputs",
    "clean_dead_temp_dirs",
    "clean_stale",
    "exchange",
    "fsync_dir",
    "fsync_file",
    "gdal_errors",
    "is_temp_name",
    "make_dir",
    "output_set",
    "pending_folder",
    "recover",
    "replace_folder",
    "resolve_pending",
    "verify_file",
    "write_error",
]

PathLike = str | os.PathLike[str]

#: When this process started writing (s since the epoch): leftovers older than this are
#: removed, those of a run going on at the same time are not.
RUN_START = time.time()

#: Temporary file of :func:`atomic_output` (and its side files, e.g. a GeoTIFF's
#: intermediate ``.<stem>.<hex>.tmp.src.tif``): ``.<stem>.<12 hex>.tmp<anything>``.
TMP_FILE = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp(\..*)?$")
#: Staged or set-aside folders (:func:`output_set`): ``.<name>.tmp.<12 hex>`` and
#: ``.<name>.old.<12 hex>``; and those of rough_map 0.x's batch (``.<name>.<8 hex>.partial``
#: / ``.old``).
TMP_DIR = re.compile(r"^\..+\.(tmp|old)\.[0-9a-f]{12}$|^\..+\.[0-9a-f]{8}\.(partial|old)$")


#: Suffixes of files that cannot be empty (a CSV or a text cloud of nothing can).
_NEVER_EMPTY = frozenset(
    (".tif", ".tiff", ".png", ".json", ".npz", ".npy", ".skops", ".zip", ".html", ".yaml")
    + (".las", ".laz", ".ply", ".pcd", ".mcap", ".parquet")
)
#: Folders whose leftovers :func:`atomic_output` removed already in this process.
_CLEANED: set[str] = set()


def is_temp_name(name: str) -> bool:
    """Whether ``name`` is one of rough_map's temporary names (file or folder)."""
    return bool(TMP_FILE.match(name) or TMP_DIR.match(name))


def write_error(path: PathLike, exc: BaseException) -> FileFormatError:
    """The one-line error of a failed write of ``path`` (from an ``OSError`` or a GDAL error)."""
    if isinstance(exc, FileFormatError):
        return exc
    if isinstance(exc, OSError) and exc.strerror:
        reason = exc.strerror
    else:
        reason = " ".join(str(exc).split()) or type(exc).__name__
    if len(reason) > 120:
        reason = reason[:117] + "..."
    return FileFormatError(Path(path), f"cannot write: {reason}")


@contextmanager
def gdal_errors(path: PathLike) -> Iterator[None]:
    """Turn what GDAL (rasterio) reports while writing ``path`` into a one-line error.

    rasterio's exceptions (:class:`rasterio.errors.RasterioError`, GDAL's ``CPLE_*``) and
    ``OSError`` become :class:`~rough_map.errors.FileFormatError` naming ``path``. GDAL and
    libtiff also print some errors straight to the process's standard error without
    raising (a full disk: ``_tiffWriteProc: No space left on device``): the native standard
    error is captured meanwhile, and such a message (:data:`_GDAL_ERROR`) is an error too,
    whether or not anything raised; other lines are shown on standard error as they were.

    Raises
    ------
    FileFormatError
        Naming ``path``.
    """
    import tempfile

    from rasterio._err import CPLE_BaseError
    from rasterio.errors import RasterioError

    captured = None
    saved = -1
    try:
        captured = tempfile.TemporaryFile()
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)
    except OSError:  # no room for the capture: GDAL's messages go to stderr as they are
        if captured is not None:
            captured.close()
        captured = None
    failure: BaseException | None = None
    try:
        yield
    except (OSError, RasterioError, CPLE_BaseError) as exc:
        failure = exc
    finally:
        text = ""
        if captured is not None:
            os.dup2(saved, 2)
            os.close(saved)
            try:
                captured.seek(0)
                text = captured.read(64_000).decode("utf-8", "replace")
            except OSError:
                text = ""
            captured.close()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if _GDAL_ERROR.search(ln)]
    others = [ln for ln in lines if ln not in errors]
    if others:  # not ours to judge (a log line, a GDAL warning): shown as it was
        try:
            os.write(2, ("\n".join(others) + "\n").encode())
        except OSError:
            pass
    if failure is not None:
        reason = failure if not errors else OSError(0, _gdal_reason(errors))
        raise write_error(path, reason) from None
    if errors:
        raise FileFormatError(Path(path), f"cannot write: {_gdal_reason(errors)}")


#: What GDAL or libtiff print when a write fails without raising.
_GDAL_ERROR = re.compile(
    r"^ERROR \d+:|No space left|Read-only file system|Permission denied|Disk quota|"
    r"I/O error|IO error|[Ww]rite error|Input/output error|Cannot (write|open)"
)


def _gdal_reason(lines: list[str]) -> str:
    """The most telling of GDAL's error lines (the system's reason, when one says it)."""
    for ln in lines:
        if ":" in ln and any(w in ln for w in ("No space", "Read-only", "Permission", "quota")):
            return ln.rsplit(":", 1)[1].strip().rstrip(".") or ln
    return lines[0]


def make_dir(folder: PathLike) -> Path:
    """Create ``folder`` and its parents (if missing); a failure is a one-line error.

    Raises
    ------
    FileFormatError
        Naming ``folder`` (a file in the way, a read-only or full disk).
    """
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(path, exc) from None
    return path


def fsync_dir(folder: PathLike) -> None:
    """Flush a folder's entries (after a rename in it); ignored where unsupported."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # the rename is done; a folder that cannot be flushed is no error
    finally:
        os.close(fd)


def fsync_file(path: PathLike) -> None:
    """Flush a written file to the disk; ignored where the file system cannot."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.EBADF, errno.ENOTSUP):
            raise
    finally:
        os.close(fd)


def verify_file(path: Path, final: Path) -> None:
    """Check a written temporary file before it takes ``final`` 's name.

    It must exist and not be empty (unless a CSV or text file); a GeoTIFF (``.tif``,
    ``.tiff``) must reopen and its last block of every band read back; a PNG must pass
    PIL's check of its chunks. Then it is flushed to the disk.

    Raises
    ------
    FileFormatError
        Naming ``final``.
    """
    if not path.is_file():
        raise FileFormatError(final, "cannot write: the file was not written")
    if path.stat().st_size == 0 and final.suffix.lower() in _NEVER_EMPTY:
        raise FileFormatError(final, "cannot write: the file came out empty (disk full?)")
    suffix = final.suffix.lower()
    if suffix in (".tif", ".tiff"):
        _verify_geotiff(path, final)
    elif suffix == ".png":
        _verify_png(path, final)
    fsync_file(path)


def _verify_geotiff(path: Path, final: Path) -> None:
    import rasterio
    from rasterio.windows import Window

    try:
        with rasterio.Env(), rasterio.open(path) as ds:
            bx, by = ds.block_shapes[0][1], ds.block_shapes[0][0]
            c0, r0 = ((ds.width - 1) // bx) * bx, ((ds.height - 1) // by) * by
            window = Window(c0, r0, ds.width - c0, ds.height - r0)
            ds.read(window=window)
            ds.read(1, window=Window(0, 0, min(bx, ds.width), min(by, ds.height)))
    except Exception as exc:  # rasterio's and GDAL's errors of a truncated file
        raise FileFormatError(
            final, f"cannot write: the GeoTIFF does not read back ({_reason(exc)})"
        ) from None


def _verify_png(path: Path, final: Path) -> None:
    from PIL import Image

    try:
        with Image.open(path) as img:
            img.verify()
    except Exception as exc:  # PIL's errors of a truncated file
        raise FileFormatError(
            final, f"cannot write: the PNG does not read back ({_reason(exc)})"
        ) from None


def _reason(exc: BaseException) -> str:
    """An exception's message on one line, cut to 80 characters (its type when empty)."""
    return clip(str(exc) or type(exc).__name__, 80)


def clean_stale(folder: PathLike, match: Callable[[str], bool] | None = None) -> int:
    """Remove rough_map's temporary files and folders in ``folder`` left by killed runs.

    Only names of :func:`is_temp_name` (and, when given, ``match``), and only those last
    modified before this process started (:data:`RUN_START`), so a run going on at the same
    time keeps its own.

    Returns
    -------
    int
        How many were removed.
    """
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    for entry in entries:
        if not is_temp_name(entry.name) or (match is not None and not match(entry.name)):
            continue
        try:
            if entry.stat(follow_symlinks=False).st_mtime >= RUN_START:
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
        except OSError as exc:
            log.debug("cannot remove %s: %s", entry.path, exc)
            continue
        log.info("removed %s, left by an interrupted run", entry.path)
        removed += 1
    return removed


def clean_dead_temp_dirs(prefix: str) -> int:
    """Remove folders ``<prefix><pid>_*`` of the system's temporary folder whose process is
    gone (a killed run's); those of live processes are kept.

    Returns
    -------
    int
        How many were removed.
    """
    import tempfile

    removed = 0
    pattern = re.compile(re.escape(prefix) + r"(\d+)_")
    try:
        entries = list(os.scandir(tempfile.gettempdir()))
    except OSError:
        return 0
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None or not entry.is_dir(follow_symlinks=False):
            continue
        pid = int(m.group(1))
        if pid == os.getpid() or _alive(pid):
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        log.info("removed %s, left by an interrupted run", entry.path)
        removed += 1
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def temp_name(path: Path) -> Path:
    """A fresh temporary name next to ``path`` keeping its suffix (see :data:`TMP_FILE`)."""
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")


@contextmanager
def atomic_output(path: PathLike, *, verify: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success check it and move it onto ``path``.

    The temporary name keeps the suffix of ``path`` (backends such as open3d and laspy pick
    the format from it) and starts with a dot. On error the temporary file is removed and
    ``path`` is left untouched. Temporary files of ``path`` that a killed run left are
    removed first.

    Parameters
    ----------
    path : str or PathLike
        The final file. Its folder must exist.
    verify : bool
        Check the file before the rename (:func:`verify_file`); False for a folder.

    Yields
    ------
    Path
        Where to write.

    Raises
    ------
    FileFormatError
        The folder is missing, or writing failed (full disk, read-only folder: the message
        names ``path`` and the reason).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileFormatError(path, f"cannot write: folder {path.parent} does not exist")
    folder = os.path.abspath(path.parent)
    if folder not in _CLEANED:  # once a folder per process: a folder of many files stays fast
        _CLEANED.add(folder)
        clean_stale(folder, lambda name: bool(TMP_FILE.match(name)))
    tmp = temp_name(path)
    try:
        try:
            yield tmp
            if verify:
                verify_file(tmp, path)
            os.replace(tmp, path)
        except OSError as exc:
            raise write_error(path, exc) from None
        fsync_dir(path.parent)
    finally:
        try:
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
        except OSError:
            pass


# -- a set of files, committed together ------------------------------------------------------

#: Name of the file written last into a pending folder: the commit is complete.
MARKER = "complete"
#: A pending-commit folder ``.<first file>.pending`` (:func:`atomic_outputs`).
PENDING = re.compile(r"^\..+\.pending$")


def pending_folder(first: PathLike) -> Path:
    """The pending folder of a set of files whose first is ``first``: ``.<name>.pending``
    beside it."""
    first = Path(first)
    return first.with_name(f".{first.name}.pending")


def resolve_pending(paths: Sequence[PathLike]) -> None:
    """Finish or discard an interrupted commit of the set ``paths`` (:func:`atomic_outputs`).

    A complete commit (its marker written) is rolled forward, idempotently: each staged file
    still in the pending folder is renamed onto its final name. An incomplete one is
    deleted, and the old files stay. Every writer and reader of the set calls this first.

    Raises
    ------
    FileFormatError
        The pending folder cannot be resolved (permissions, a file in its place).
    """
    finals = [Path(p) for p in paths]
    pending = pending_folder(finals[0])
    if not pending.exists() and not pending.is_symlink():
        return
    try:
        if not pending.is_dir() or pending.is_symlink():
            raise FileFormatError(
                pending, "expected a pending-commit folder; remove it by hand", field="pending"
            )
        if (pending / MARKER).is_file():
            _roll_forward(pending, finals)
            log.info("%s: completed an interrupted write of %d files", finals[0], len(finals))
        else:
            log.warning("%s: discarded an incomplete write; the previous files stay", finals[0])
            shutil.rmtree(pending)
    except OSError as err:
        raise FileFormatError(
            pending, f"cannot resolve an interrupted write ({_reason(err)})", field="pending"
        ) from err


def _roll_forward(pending: Path, finals: Sequence[Path]) -> None:
    """Rename each staged file still in the committed ``pending`` folder onto its final
    name (idempotent), then remove the folder."""
    for target in finals:
        staged = pending / target.name
        if staged.is_file():
            os.replace(staged, target)
    fsync_dir(finals[0].parent)
    shutil.rmtree(pending)


@contextmanager
def atomic_outputs(paths: Sequence[PathLike], *, verify: bool = True) -> Iterator[list[Path]]:
    """Yield staged paths for a set of files of one folder; on success they replace the
    files together, or not at all.

    The staged files live in a pending folder ``.<first>.pending`` beside the first file;
    when all are written they are checked (:func:`verify_file`) and flushed to disk, a
    marker is written last, and each is renamed into place. A process killed before the
    marker leaves the old set (the next access deletes the pending folder); after it, the
    next access (:func:`resolve_pending`) finishes the renames. So a reader that resolves
    first sees the whole old set or the whole new one, never a mix: a table with another
    run's metadata, a model with another model's card.

    Raises
    ------
    FileFormatError
        The files are not in one existing folder, or writing failed (full disk, read-only
        folder): the old files stay.
    """
    finals = [Path(p) for p in paths]
    if (
        not finals
        or len({f.parent for f in finals}) != 1
        or len({f.name for f in finals}) != len(finals)
    ):
        raise InputError(f"a set of files is one or more distinct files of one folder: {finals}")
    if not finals[0].parent.is_dir():
        raise FileFormatError(finals[0], f"cannot write: folder {finals[0].parent} does not exist")
    resolve_pending(finals)
    pending = pending_folder(finals[0])
    try:
        pending.mkdir()
    except OSError as err:
        raise write_error(finals[0], err) from None
    staged = [pending / f.name for f in finals]
    try:
        yield staged
        for tmp, final in zip(staged, finals, strict=True):
            if verify:
                verify_file(tmp, final)  # and flushed to disk
            else:
                fsync_file(tmp)
        (pending / MARKER).write_bytes(b"")
        fsync_file(pending / MARKER)
        fsync_dir(pending)
    except OSError as err:  # a full disk, a read-only folder: one line naming the set
        shutil.rmtree(pending, ignore_errors=True)
        raise write_error(finals[0], err) from None
    except BaseException:
        shutil.rmtree(pending, ignore_errors=True)
        raise
    try:
        _roll_forward(pending, finals)  # the commit itself: a kill from here on is finished
    except OSError as err:  # by the next access (resolve_pending)
        raise FileFormatError(
            pending, f"cannot finish the write ({_reason(err)})", field="pending"
        ) from err


# ------------------------------------------------------------------------------------------
# A command's output folder, staged beside it and swapped in whole
# ------------------------------------------------------------------------------------------

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
