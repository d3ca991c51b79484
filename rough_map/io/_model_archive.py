"""Bounds on a skops model archive, checked before skops parses anything.

A ``.skops`` file is a zip of ``schema.json`` and ``.npy`` arrays. :func:`check_archive`
refuses, with a one-line :class:`~rough_map.errors.ModelError`, an archive that is not a zip,
has too many members, declares more uncompressed bytes than ``LIMITS.model_uncompressed``
or a compression ratio above ``LIMITS.model_member_ratio`` (a zip bomb), a ``schema.json``
larger than ``LIMITS.model_schema`` or nested deeper than ``LIMITS.model_schema_depth``, or
an ``.npy`` member whose header declares more data than the member holds
(:data:`rough_map.limits.LIMITS`).
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import brief
from rough_map.errors import ModelError
from rough_map.limits import LIMITS

__all__ = [
    "check_archive",
]


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def json_depth(text: bytes) -> int:
    """Deepest nesting of objects and arrays in a JSON text (strings are skipped)."""
    bare = _STRING.sub(b'""', text)
    codes = np.frombuffer(bare, dtype=np.uint8)
    step = np.isin(codes, (ord("["), ord("{"))).astype(np.int64)
    step -= np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def _check_npy(zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: Path) -> None:
    """Refuse an ``.npy`` member whose header declares more data than it holds."""
    try:
        with zf.open(info) as fh:
            head = io.BytesIO(fh.read(65536 + 16))
        version = np.lib.format.read_magic(head)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(head)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(head)
        else:
            raise ValueError(f"npy version {version}")
    except Exception as err:  # any failure of a foreign header is a refusal
        raise ModelError(
            f"{where}: array {info.filename!r:.60} unreadable ({brief(err)})"
        ) from None
    if dtype.hasobject:
        raise ModelError(f"{where}: array {info.filename!r:.60} holds Python objects; refused")
    if any(int(n) < 0 for n in shape):
        raise ModelError(f"{where}: array {info.filename!r:.60} has a negative dimension")
    declared = math.prod(int(n) for n in shape) * dtype.itemsize
    if declared > info.file_size:
        raise ModelError(
            f"{where}: array {info.filename!r:.60} declares {declared} bytes of data but the "
            f"member holds {info.file_size}"
        )


def _referenced_bytes(schema: Any, members: dict[str, zipfile.ZipInfo]) -> int:
    """Sum of the sizes of the members the schema's nodes refer to (``"file"`` keys)."""
    total = 0
    stack = [schema]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            ref = node.get("file")
            if isinstance(ref, str) and ref in members:
                total += members[ref].file_size
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return total


def check_archive(data: bytes, where: Path) -> None:
    """Raise :class:`ModelError` unless ``data`` is a zip within the bounds of this module.

    Parameters
    ----------
    data : bytes
        The model file's content.
    where : Path
        The file, for messages.
    """
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except Exception as err:  # BadZipFile, ValueError, OverflowError, ...
        raise ModelError(f"{where}: not a skops model file (not a zip: {brief(err)})") from None
    with zf:
        members = zf.infolist()
        if len(members) > LIMITS.model_members:
            raise ModelError(
                f"{where}: {len(members)} archive members; at most {LIMITS.model_members}"
            )
        total = 0
        for info in members:
            total += info.file_size
            if info.file_size > 2**20 and info.file_size > LIMITS.model_member_ratio * max(
                info.compress_size, 1
            ):
                raise ModelError(
                    f"{where}: member {info.filename!r:.60} expands {info.compress_size} bytes "
                    f"to {info.file_size} (ratio above {LIMITS.model_member_ratio}): refused as a "
                    "zip bomb"
                )
        if total > LIMITS.model_uncompressed:
            raise ModelError(
                f"{where}: members declare {total} uncompressed bytes; at most "
                f"{LIMITS.model_uncompressed}"
            )
        names = {info.filename: info for info in members}
        schema = names.get("schema.json")
        if schema is None:
            raise ModelError(f"{where}: not a skops model file (no schema.json)")
        if schema.file_size > LIMITS.model_schema:
            raise ModelError(
                f"{where}: schema.json of {schema.file_size} bytes; at most {LIMITS.model_schema}"
            )
        try:
            text = zf.read(schema)
        except Exception as err:  # zlib.error, BadZipFile, EOFError, ...
            raise ModelError(f"{where}: schema.json unreadable ({brief(err)})") from None
        if len(text) > LIMITS.model_schema:  # a lying header
            raise ModelError(f"{where}: schema.json larger than {LIMITS.model_schema} bytes")
        depth = json_depth(text)
        if depth > LIMITS.model_schema_depth:
            raise ModelError(
                f"{where}: schema.json nested {depth} deep; at most {LIMITS.model_schema_depth}"
            )
        try:
            parsed: Any = json.loads(text)
        except Exception as err:  # JSONDecodeError, UnicodeDecodeError, ...
            raise ModelError(f"{where}: schema.json is not JSON ({brief(err)})") from None
        if not isinstance(parsed, dict):
            raise ModelError(f"{where}: schema.json is not a JSON object")
        referenced = _referenced_bytes(parsed, names)
        if referenced > LIMITS.model_uncompressed:
            raise ModelError(
                f"{where}: schema.json refers to {referenced} bytes of arrays; at most "
                f"{LIMITS.model_uncompressed}"
            )
        for info in members:
            if info.filename.endswith(".npy"):
                _check_npy(zf, info, where)
