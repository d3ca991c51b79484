"""Traverse folders: ``traverse.json`` (or ``.yaml``/``.yml``) plus the files it names.

A traverse is a run of a vehicle over terrain: a list of frames, each with a time (s), the
vehicle pose in the world frame (m, rad) and a point cloud in the vehicle frame and/or a
stereo pair. The schema is :class:`rough_map.config.TraverseSpec` (published as
``data_schema/traverse.schema.json``). Paths in the file are relative to its folder and,
symbolic links followed, must stay inside it (or inside a folder given as ``allow_outside``,
the CLI's ``--allow-outside DIR``): :meth:`Traverse.resolve` checks every one.

>>> traverse = load_traverse("runs/field_a")          # doctest: +SKIP
>>> points = traverse.load_cloud(0, frame="world")     # doctest: +SKIP
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from rough_map._bounded import clip, short
from rough_map._files import PathLike, atomic_output
from rough_map.config import FrameSpec, TraverseSpec, load_model
from rough_map.errors import FileFormatError, SchemaError
from rough_map.geometry import pose_matrix, transform_points
from rough_map.io.pointcloud import read_cloud

log = logging.getLogger(__name__)

TRAVERSE_FILES = ("traverse.json", "traverse.yaml", "traverse.yml")
"""File names looked for in a traverse folder, in this order."""


@dataclass(frozen=True)
class Traverse:
    """A validated traverse and the folder its paths are relative to.

    Attributes
    ----------
    spec : TraverseSpec
        The content of the traverse file.
    root : Path
        Folder of the traverse file; relative paths are resolved against it.
    source : Path
        The traverse file (``root / "traverse.json"`` for one not yet saved); named in errors.
    allow_outside : tuple of Path
        Folders outside ``root`` whose files the traverse may name (see :meth:`resolve`);
        it travels with the object to worker processes.
    """

    spec: TraverseSpec
    root: Path
    source: Path
    allow_outside: tuple[Path, ...] = ()

    @classmethod
    def from_spec(
        cls, spec: TraverseSpec, root: PathLike, *, allow_outside: Iterable[PathLike] = ()
    ) -> Traverse:
        """Wrap an in-memory spec whose paths are relative to ``root`` (``allow_outside``
        as :func:`load_traverse`'s)."""
        root = Path(root)
        return cls(
            spec=spec,
            root=root,
            source=root / TRAVERSE_FILES[0],
            allow_outside=_allowed(allow_outside),
        )

    @property
    def name(self) -> str:
        """Name of the traverse."""
        return self.spec.name

    @property
    def frames(self) -> list[FrameSpec]:
        """The frames, in time order."""
        return self.spec.frames

    def __len__(self) -> int:
        return len(self.spec.frames)

    def times(self) -> np.ndarray:
        """Frame times, shape (N,), s."""
        return np.array([f.t for f in self.spec.frames])

    def poses(self) -> np.ndarray:
        """Vehicle poses, shape (N, 6): x, y, z in m, roll, pitch, yaw in rad."""
        return np.array(
            [[p.x, p.y, p.z, p.roll, p.pitch, p.yaw] for p in (f.pose for f in self.frames)]
        )

    def labels(self) -> list[str | None]:
        """Terrain class name of each frame (None where unlabelled)."""
        return [f.label for f in self.spec.frames]

    def resolve(self, relative: str, field: str = "path") -> Path:
        """Where a path written in the traverse file points: ``root / relative`` with its
        symbolic links followed.

        This is the one place that checks containment: every file a traverse names must
        resolve inside the traverse folder (itself resolved), or inside one of the folders
        of ``allow_outside`` (``rough-map ... --allow-outside DIR``).

        Parameters
        ----------
        relative : str
            The path as written in the traverse file.
        field : str
            Its field, named in errors (``frames[3].cloud``, ``height_field``).

        Returns
        -------
        Path
            The real path of the file (which may not exist).

        Raises
        ------
        SchemaError
            The path cannot be resolved (too long, a loop of links) or resolves outside the
            allowed folders; the message names the field.
        """
        return self.resolver()(relative, field)

    def resolver(self) -> Callable[[str, str], Path]:
        """:meth:`resolve`, for many paths: the real paths of the allowed folders and of
        the folders holding the files are found once (an hour of frames names 7,200
        clouds in one folder), then only a file that is itself a link is followed anew."""
        allowed: list[Path] | None = None
        folders: dict[Path, Path] = {}

        def real_path(path: Path) -> Path:
            if path.name in ("", ".", ".."):
                return path.resolve()
            folder = folders.get(path.parent)
            if folder is None:
                folder = folders[path.parent] = path.parent.resolve()
            file = folder / path.name
            return file.resolve() if os.path.islink(file) else file

        def resolve(relative: str, field: str = "path") -> Path:
            nonlocal allowed
            try:
                real = real_path(self.root / relative)
                if allowed is None:
                    allowed = [
                        self.root.resolve(),
                        *(Path(p).resolve() for p in self.allow_outside),
                    ]
            except (OSError, RuntimeError, ValueError) as err:
                reason = getattr(err, "strerror", None) or str(err)
                raise self._error(
                    field, f"{short(relative, 50)} cannot be resolved: {clip(reason, 50)}"
                ) from None
            if not any(real.is_relative_to(folder) for folder in allowed):
                raise self._error(
                    field,
                    f"{short(relative, 50)} resolves outside the traverse folder "
                    "(pass --allow-outside DIR to allow)",
                )
            return real

        return resolve

    def _is_file(self, path: Path, field: str, relative: str) -> bool:
        try:
            return path.is_file()
        except OSError as err:  # a name too long, no permission...
            reason = err.strerror or str(err)
            raise self._error(
                field, f"{short(relative, 50)} cannot be read: {clip(reason, 50)}"
            ) from None

    def pose_matrix(self, index: int) -> np.ndarray:
        """4x4 transform vehicle -> world of frame ``index`` (m)."""
        return pose_matrix(self._frame(index).pose)

    def cloud_path(self, index: int) -> Path:
        """Path of the point cloud of frame ``index``.

        Raises
        ------
        SchemaError
            The frame has no cloud, or the file does not exist.
        """
        frame = self._frame(index)
        if frame.cloud is None:
            raise self._error(f"frames[{index}].cloud", "this frame has no point cloud")
        where = f"frames[{index}].cloud"
        path = self.resolve(frame.cloud, where)
        if not self._is_file(path, where, frame.cloud):
            raise self._error(where, f"{clip(frame.cloud, 60)} does not exist")
        return path

    def load_cloud(self, index: int, frame: Literal["vehicle", "world"] = "vehicle") -> np.ndarray:
        """Read the point cloud of frame ``index``.

        Parameters
        ----------
        index : int
            Frame index (negative counts from the end).
        frame : {"vehicle", "world"}
            Return the points in the vehicle frame or in the world frame (moved with the
            frame's pose from the frame they are stored in, the traverse's ``cloud_frame``).

        Returns
        -------
        ndarray, shape (N, 3)
            x, y, z in m.

        Raises
        ------
        SchemaError
            The frame has no cloud or its file is missing.
        FileFormatError
            The cloud file cannot be read.
        """
        if frame not in ("vehicle", "world"):
            raise ValueError(f"frame must be 'vehicle' or 'world', got {frame!r}")
        points = read_cloud(self.cloud_path(index))
        if frame == self.spec.cloud_frame:
            return points
        transform = self.pose_matrix(index)
        if frame == "vehicle":  # stored in the world frame
            transform = np.linalg.inv(transform)
        return transform_points(points, transform[:3, :3], transform[:3, 3])

    def validate_files(self) -> None:
        """Check that every file the traverse names exists.

        Raises
        ------
        SchemaError
            Naming the first missing files by their field (``frames[3].cloud``) and path,
            or the first path that resolves outside the traverse folder (see
            :meth:`resolve`).
        """
        missing: list[tuple[str, str]] = []
        if self.spec.height_field is not None:
            missing += self._missing("height_field", self.spec.height_field)
        if self.spec.surface is not None:
            missing += self._missing("surface.path", self.spec.surface.path)
        for i, f in enumerate(self.spec.frames):
            for key in ("cloud", "left", "right"):
                relative = getattr(f, key)
                if relative is not None:
                    missing += self._missing(f"frames[{i}].{key}", relative)
        if missing:
            shown = "; ".join(
                f"{where}: {clip(rel, 40)} does not exist" for where, rel in missing[:2]
            )
            more = f" (and {len(missing) - 2} more missing files)" if len(missing) > 2 else ""
            error = SchemaError(self.source, shown + more)
            error.field = missing[0][0]
            raise error

    def _missing(self, where: str, relative: str) -> list[tuple[str, str]]:
        path = self.resolve(relative, where)
        return [] if self._is_file(path, where, relative) else [(where, relative)]

    def _frame(self, index: int) -> FrameSpec:
        try:
            return self.spec.frames[index]
        except IndexError:
            raise IndexError(
                f"frame {index} out of range: {self.source} has {len(self)} frames"
            ) from None

    def _error(self, where: str, message: str) -> SchemaError:
        error = SchemaError(self.source, f"{where}: {message}")
        error.field = where
        return error


def find_traverse_file(dir_or_file: PathLike) -> Path:
    """The traverse file of a folder, or ``dir_or_file`` itself if it is a file.

    Raises
    ------
    FileFormatError
        Nothing there, no traverse file in the folder, or more than one.
    """
    path = Path(dir_or_file)
    try:
        if path.is_file():
            return path
        if not path.exists():
            raise FileFormatError(path, "no such file or folder")
        found = [path / n for n in TRAVERSE_FILES if (path / n).is_file()]
    except OSError as err:  # a name too long, no permission
        raise FileFormatError(path, f"cannot read: {clip(str(err.strerror or err), 60)}") from None
    if not found:
        raise FileFormatError(path, f"not a traverse folder: none of {', '.join(TRAVERSE_FILES)}")
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise FileFormatError(path, f"ambiguous traverse folder: both {names}; keep one")
    return found[0]


def load_traverse(dir_or_file: PathLike, *, allow_outside: Iterable[PathLike] = ()) -> Traverse:
    """Load and validate a traverse.

    Only the traverse file is read; the files it names are checked when used, or all at
    once by :meth:`Traverse.validate_files`. Every one of them must resolve (symbolic links
    followed) inside the traverse folder, or inside a folder of ``allow_outside``: a
    traverse file cannot make rough_map read ``../../elsewhere`` unless the user allows it.

    Parameters
    ----------
    dir_or_file : str or PathLike
        A traverse folder (holding one of ``traverse.json``, ``traverse.yaml``,
        ``traverse.yml``) or the traverse file itself.
    allow_outside : iterable of str or PathLike
        Folders outside the traverse folder whose files the traverse may name (the CLI's
        ``--allow-outside DIR``); default none.

    Returns
    -------
    Traverse

    Raises
    ------
    FileFormatError
        No traverse file, or a JSON/YAML syntax error.
    SchemaError
        The content does not follow the schema. The message names the file, the frame and
        the field, e.g. ``runs/a/traverse.json: frames[3].pose.x: Field required``.
    """
    source = find_traverse_file(dir_or_file)
    spec = load_model(source, TraverseSpec)
    log.debug("loaded %s: %d frames", source, len(spec.frames))
    return Traverse(
        spec=spec, root=source.parent, source=source, allow_outside=_allowed(allow_outside)
    )


def _allowed(folders: Iterable[PathLike]) -> tuple[Path, ...]:
    if isinstance(folders, str | Path):
        folders = [folders]
    return tuple(Path(f) for f in folders)


def save_traverse(traverse: Traverse | TraverseSpec, out_dir: PathLike) -> Path:
    """Write ``traverse.json`` atomically into ``out_dir``.

    Paths inside are written as they are: they must be relative to ``out_dir``.

    Parameters
    ----------
    traverse : Traverse or TraverseSpec
        What to write.
    out_dir : str or PathLike
        The traverse folder (created if needed).

    Returns
    -------
    Path
        The file written.
    """
    spec = traverse.spec if isinstance(traverse, Traverse) else traverse
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / TRAVERSE_FILES[0]
    others = [n for n in TRAVERSE_FILES[1:] if (out_dir / n).exists()]
    if others:
        raise FileFormatError(
            out_dir, f"holds {others[0]}; writing {target.name} beside it would be ambiguous"
        )
    text = _dumps(spec.model_dump(mode="json", exclude_none=True))
    with atomic_output(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return target


def _dumps(data: dict[str, object]) -> str:
    """JSON with one frame per line: readable, and diffs show which frames changed."""
    frames = data.pop("frames")
    head = json.dumps(data, indent=2)[: -len("\n}")]
    rows = ",\n".join("    " + json.dumps(f) for f in frames)  # type: ignore[attr-defined]
    return f'{head},\n  "frames": [\n{rows}\n  ]\n}}\n'
