"""Bounded parsing of the JSON and YAML documents rough_map reads.

Every JSON/YAML file (traverses, calibrations, configs, sidecars) goes through
:func:`parse_document`, so every reader has the same limits:

* the file is at most ``LIMITS.document`` (64 MB);
* lists and mappings nest at most ``LIMITS.document_depth`` (64) levels;
* integers have at most ``LIMITS.int_digits`` (30) digits and numbers at most 400
  characters (NaN and infinities pass: the models refuse them, naming the field);
* YAML is read with PyYAML's ``SafeLoader`` (tags that build Python objects are refused),
  its nesting is checked while the node tree is composed (no deep recursion), and anchors
  and aliases may not expand to more than ``LIMITS.yaml_alias_values`` nodes (no "billion
  laughs") or refer to themselves.

The values are those of :data:`rough_map.limits.LIMITS`.

A document over a limit is a :class:`~rough_map.errors.FileFormatError` naming the file and
the place (line, or the path of keys) -- never a RecursionError, ValueError or a hang.
"""

from __future__ import annotations

import json
import os
import reprlib
from pathlib import Path
from typing import Any

import yaml

from rough_map.errors import FileFormatError
from rough_map.limits import LIMITS

__all__ = [
    "brief",
    "check_tree",
    "clip",
    "parse_document",
    "parse_json",
    "parse_yaml",
    "read_document_text",
    "short",
    "shorten",
]


class _Limit(Exception):
    """A document over a limit (turned into a FileFormatError by the caller)."""


def short(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters: safe to quote in a one-line message (a
    long string is cut before its repr is taken, a large container shown a few items and
    levels deep, however large it is)."""
    if isinstance(value, str | bytes) and len(value) > limit:
        value = value[: limit + 1]
    big = isinstance(value, list | tuple | dict | set | frozenset) and len(value) > 8
    return clip(reprlib.repr(value) if big else repr(value), limit)


def brief(err: BaseException, limit: int = 80) -> str:
    """``Type: 'message'`` of an exception, the message quoted and cut (never raw bytes)."""
    text = repr(str(err))
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{type(err).__name__}: {text}"


def shorten(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters with "…" in the middle (head two thirds), so
    that a message keeps both its start and the file or field it ends on."""
    if len(text) <= limit:
        return text
    head = (limit - 1) * 2 // 3
    tail = limit - 1 - head
    return text[:head] + "…" + (text[-tail:] if tail else "")


def clip(text: object, limit: int = 100) -> str:
    """``text`` on one printable line (control characters escaped), cut to ``limit``."""
    text = " ".join(str(text).split())
    if not text.isprintable():
        text = text.encode("unicode_escape", "backslashreplace").decode("ascii")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _read_chunks(stream: Any, max_bytes: int) -> bytes:
    chunks, total = [], 0
    while total <= max_bytes:
        chunk = stream.read(1 << 16)
        if not chunk:
            break
        chunks.append(chunk)
        total += len(chunk)
    return b"".join(chunks)


def read_document_text(path: Path, max_bytes: int | None = None) -> str:
    """The UTF-8 text of ``path``, refused beyond ``max_bytes`` (default
    ``LIMITS.document``).

    Raises
    ------
    FileFormatError
        Missing, unreadable, too large, or not UTF-8.
    """
    max_bytes = LIMITS.document if max_bytes is None else max_bytes
    try:
        with path.open("rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            if size > max_bytes:
                raise FileFormatError(
                    path, f"larger than {max_bytes // 2**20} MB: not a config file"
                )
            # a regular file: read what it holds (no buffer of max_bytes); else in chunks
            data = stream.read(size + 1) if size else _read_chunks(stream, max_bytes)
    except OSError as err:
        raise FileFormatError(path, f"cannot read: {clip(str(err.strerror or err), 80)}") from None
    if len(data) > max_bytes:
        raise FileFormatError(path, f"larger than {max_bytes // 2**20} MB: not a config file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise FileFormatError(path, f"not UTF-8 text (byte {err.start})") from None


# --------------------------------------------------------------------------------------------
# JSON


def _json_int(text: str) -> int:
    if len(text.lstrip("-")) > LIMITS.int_digits:
        raise _Limit(f"an integer of {len(text.lstrip('-'))} digits (most {LIMITS.int_digits})")
    return int(text)


def _json_float(text: str) -> float:
    if len(text) > 400:
        raise _Limit(f"a number of {len(text)} characters")
    return float(text)


def parse_json(text: str, path: Path) -> Any:
    """Parse JSON text within the limits of this module.

    Raises
    ------
    FileFormatError
        A syntax error (with its line and column) or a document over a limit.
    """
    try:
        data = json.loads(text, parse_int=_json_int, parse_float=_json_float)
    except json.JSONDecodeError as err:
        raise FileFormatError(
            path, f"invalid JSON at line {err.lineno}, column {err.colno}: {err.msg}"
        ) from None
    except _Limit as err:
        raise FileFormatError(path, str(err)) from None
    except RecursionError:
        raise FileFormatError(path, f"nested deeper than {LIMITS.document_depth} levels") from None
    check_tree(data, path)
    return data


def check_tree(data: Any, path: Path, max_depth: int | None = None) -> None:
    """Check the nesting of parsed JSON-like data (lists and dicts) without recursion.

    Raises
    ------
    FileFormatError
        Nested deeper than ``max_depth`` (default ``LIMITS.document_depth``).
    """
    max_depth = LIMITS.document_depth if max_depth is None else max_depth
    stack: list[tuple[Any, int]] = [(data, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict | list):
            if depth > max_depth:
                raise FileFormatError(path, f"nested deeper than {max_depth} levels")
            children = value.values() if isinstance(value, dict) else value
            stack.extend((child, depth + 1) for child in children)


# --------------------------------------------------------------------------------------------
# YAML


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader that refuses deep nesting while composing and huge integers/non-finite
    floats while constructing."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > LIMITS.document_depth:
                mark = self.peek_event().start_mark
                raise _Limit(
                    f"nested deeper than {LIMITS.document_depth} levels (line {mark.line + 1})"
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _yaml_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int:
    digits = str(node.value).replace("_", "").lstrip("+-")
    if len(digits) > LIMITS.int_digits:
        raise _Limit(
            f"an integer of {len(digits)} digits at line {node.start_mark.line + 1} "
            f"(most {LIMITS.int_digits})"
        )
    return int(yaml.SafeLoader.construct_yaml_int(loader, node))


def _yaml_float(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> float:
    if len(str(node.value)) > 400:
        line = node.start_mark.line + 1
        raise _Limit(f"a number of {len(str(node.value))} characters at line {line}")
    return float(yaml.SafeLoader.construct_yaml_float(loader, node))


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _yaml_int)
_BoundedLoader.add_constructor("tag:yaml.org,2002:float", _yaml_float)


class _OpenCVLoader(_BoundedLoader):
    """The bounded loader plus OpenCV ``FileStorage``'s ``!!opencv-matrix`` tags (read as
    plain mappings ``{rows, cols, dt, data}``)."""


def _opencv_mapping(loader: yaml.SafeLoader, node: yaml.Node) -> dict[Any, Any]:
    if not isinstance(node, yaml.MappingNode):
        raise _Limit(f"an OpenCV matrix that is not a mapping (line {node.start_mark.line + 1})")
    return loader.construct_mapping(node, deep=True)


for _tag in ("opencv-matrix", "opencv-nd-matrix"):
    _OpenCVLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _opencv_mapping)


def _check_nodes(root: yaml.Node) -> None:
    """Refuse node graphs (aliases shared) that expand beyond ``LIMITS.yaml_alias_values``
    values or ``LIMITS.document_depth`` levels, or that contain themselves. Iterative,
    memoised per node: linear in the graph's size."""
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        if done:
            active.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in children)
            depth[key] = 1 + max((depth[id(c)] for c in children), default=0)
            if size[key] > LIMITS.yaml_alias_values + len(size) * 4:
                raise _Limit(f"aliases expand to more than {LIMITS.yaml_alias_values} values")
            if depth[key] > LIMITS.document_depth:
                raise _Limit(f"aliases nest deeper than {LIMITS.document_depth} levels")
            continue
        if key in size:
            continue
        if key in active:
            raise _Limit(f"an alias refers to itself (line {node.start_mark.line + 1})")
        active.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in children if id(c) not in size)


def _yaml_message(err: yaml.YAMLError) -> str:
    """``invalid YAML: <problem> (line L, column C)``, short."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or str(err)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return f"invalid YAML: {clip(problem, 100)}{where}"


def parse_yaml(text: str, path: Path, *, opencv: bool = False) -> Any:
    """Parse YAML text (one document) within the limits of this module; with ``opencv``
    an OpenCV ``FileStorage`` file (its ``%YAML:1.0`` line dropped, ``!!opencv-matrix``
    read as a mapping).

    Raises
    ------
    FileFormatError
        A syntax error, a tag that is not plain data, or a document over a limit.
    """
    if len(text) > LIMITS.yaml_document:
        raise FileFormatError(
            path, f"a YAML file of {len(text)} characters; at most {LIMITS.yaml_document} are read"
        )
    if opencv and text.lstrip().startswith("%YAML"):
        text = text.lstrip().split("\n", 1)[1] if "\n" in text.lstrip() else ""
    try:
        loader = (_OpenCVLoader if opencv else _BoundedLoader)(text)
    except yaml.YAMLError as err:  # the reader refuses control characters at once
        raise FileFormatError(path, _yaml_message(err)) from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_nodes(node)
        return loader.construct_document(node)
    except _Limit as err:
        raise FileFormatError(path, str(err)) from None
    except yaml.YAMLError as err:
        raise FileFormatError(path, _yaml_message(err)) from None
    except (ValueError, TypeError, OverflowError, RecursionError) as err:
        # values PyYAML cannot build (a bad date, base64, a key that cannot be hashed)
        raise FileFormatError(path, "invalid YAML value: " + clip(str(err), 100)) from None
    finally:
        loader.dispose()


def parse_document(path: str | Path, *, kind: str | None = None) -> Any:
    """Read and parse a JSON or YAML file within the limits of this module.

    Parameters
    ----------
    path : str or Path
        The file.
    kind : {"json", "yaml"}, optional
        The syntax; default from the suffix (``.json``: JSON, anything else YAML).

    Raises
    ------
    FileFormatError
        Unreadable, too large, not UTF-8, a syntax error or a document over a limit.
    """
    path = Path(path)
    text = read_document_text(path)
    if kind is None:
        kind = "json" if path.suffix.lower() == ".json" else "yaml"
    return parse_json(text, path) if kind == "json" else parse_yaml(text, path)
