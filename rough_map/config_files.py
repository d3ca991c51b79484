"""Loading JSON/YAML files into the pydantic models of :mod:`rough_map.config`.

:func:`load_mapping` reads a file within the limits of :mod:`rough_map._bounded` (size,
nesting, number size, YAML aliases); :func:`load_model` validates it against a model and
:func:`schema_error` turns pydantic's errors into a one-line
:class:`~rough_map.errors.SchemaError` naming the file and the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from rough_map._bounded import clip, parse_document, short
from rough_map.errors import FileFormatError, SchemaError

__all__ = ["format_location", "load_mapping", "load_model", "schema_error"]


def load_mapping(path: str | Path) -> dict[str, Any]:
    """Read a JSON or YAML file whose top level is a mapping.

    YAML is read with PyYAML's ``SafeLoader``: tags that would build Python objects are
    refused. Both syntaxes are parsed within the limits of :mod:`rough_map._bounded` (64 MB,
    nesting 64 deep, integers of 30 digits, finite floats, bounded alias expansion).

    Parameters
    ----------
    path : str or Path
        A ``.json``, ``.yaml`` or ``.yml`` file.

    Returns
    -------
    dict
        The parsed mapping.

    Raises
    ------
    FileFormatError
        Missing or unreadable file, unknown suffix, a JSON/YAML syntax error (with its
        line and column), or a document over a limit.
    SchemaError
        The top level is not a mapping.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".yaml", ".yml"):
        raise FileFormatError(path, f"expected .json, .yaml or .yml, got {short(suffix)}", "suffix")
    data = parse_document(path, kind="json" if suffix == ".json" else "yaml")
    if not isinstance(data, dict):
        raise SchemaError(path, f"expected a mapping at the top level, got {type(data).__name__}")
    return data


def format_location(loc: tuple[int | str, ...] | list[int | str]) -> str:
    """``("frames", 3, "pose", "yaw")`` -> ``"frames[3].pose.yaw"``."""
    out = ""
    for part in loc:
        name = str(part) if isinstance(part, int) else clip(str(part), 30)
        out += f"[{name}]" if isinstance(part, int) else f".{name}" if out else name
    return clip(out, 80) if out else "(top level)"


_MAX_SCHEMA_TEXT = 120
"""Longest list of problems in a SchemaError's message (characters, before the path)."""


def schema_error(path: str | Path, err: ValidationError, max_shown: int = 3) -> SchemaError:
    """Turn a pydantic ValidationError into a one-line :class:`SchemaError`.

    The message reads ``<path>: frames[3].pose.x: Field required; ...``: the location of each
    problem in the file, then pydantic's explanation. ``SchemaError.field`` is the location
    of the first problem.

    Parameters
    ----------
    path : str or Path
        The file that was validated.
    err : pydantic.ValidationError
        The validation error.
    max_shown : int
        How many problems to spell out; the rest are counted.
    """
    problems: list[tuple[str, str]] = []
    for item in err.errors(include_url=False):
        loc = list(item["loc"])
        ctx = item.get("ctx") or {}
        if item["type"] == "time_order":
            loc += [ctx["frame_index"], "t"]
        elif item["type"] == "frame_data":
            loc += [ctx["frame_index"]]
        message = clip(item["msg"].removeprefix("Value error, "), 100)
        if item["type"] == "extra_forbidden":
            message = "unknown field (a typo?)"
        problems.append((format_location(loc), message))
    text, shown = "", 0
    for where, what in problems[:max_shown]:
        part = clip(f"{where}: {what}", _MAX_SCHEMA_TEXT)
        if shown and len(text) + len(part) > _MAX_SCHEMA_TEXT:
            break
        text, shown = (f"{text}; {part}" if text else part), shown + 1
    if len(problems) > shown:
        text += f" (and {len(problems) - shown} more problems)"
    error = SchemaError(path, text)
    error.field = problems[0][0] if problems else None
    return error


def load_model(path: str | Path, model: type[BaseModel]) -> Any:
    """Load a JSON/YAML file and validate it against ``model``.

    Raises
    ------
    FileFormatError
        The file cannot be read or parsed (see :func:`load_mapping`).
    SchemaError
        The content does not follow the model; the message names the field.
    """
    data = load_mapping(path)
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise schema_error(path, err) from err
