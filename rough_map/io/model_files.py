"""Where a terrain model's files are, and its card: read without loading the model.

A model ``models/NAME`` is two files, ``NAME.skops`` (the model,
:mod:`rough_map.classify.persistence` reads and writes it) and ``NAME.card.json`` (its card:
classes, feature extraction, training data, metrics, the model file's sha256). This module
needs neither scikit-learn nor skops, so a command can learn from the card how the model
reads a cloud (:func:`card_extraction`) and start on the frames while the model loads.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from rough_map import _files
from rough_map._bounded import brief
from rough_map.errors import FileFormatError, ModelError
from rough_map.io._model_archive import json_depth
from rough_map.limits import LIMITS
from rough_map.resources import model_base, shipped_models, user_models_dir

__all__ = [
    "CARD_FORMAT",
    "CARD_SUFFIX",
    "MODEL_SUFFIX",
    "card_extraction",
    "model_paths",
    "read_card",
    "resolve_model",
    "resolve_pending",
    "sha256_file",
]

MODEL_SUFFIX = ".skops"
CARD_SUFFIX = ".card.json"
CARD_FORMAT = "rough_map model card 1"


def model_paths(name: str | Path) -> tuple[Path, Path]:
    """The model file and the card of a model name.

    Parameters
    ----------
    name : str or Path
        ``models/NAME``, ``models/NAME.skops`` or ``models/NAME.card.json``.

    Returns
    -------
    (Path, Path)
        ``models/NAME.skops`` and ``models/NAME.card.json``.
    """
    if not isinstance(name, str | os.PathLike) or "\0" in os.fspath(name):
        raise ModelError(f"a model name must be a path (str or Path); got {name!r:.60}")
    path = Path(name)
    text = path.name
    if text in ("", ".", "..") or text in (CARD_SUFFIX, MODEL_SUFFIX):
        raise ModelError(f"{str(name)!r:.80}: not a model name (models/NAME)")
    for suffix in (CARD_SUFFIX, MODEL_SUFFIX):
        if text.endswith(suffix):
            text = text[: -len(suffix)]
            break
    base = path.with_name(text)
    return base.with_name(text + MODEL_SUFFIX), base.with_name(text + CARD_SUFFIX)


def resolve_pending(model_file: Path, card_file: Path) -> None:
    """Finish or discard an interrupted save of a model and its card (one set of files,
    :func:`rough_map._files.resolve_pending`), as a ModelError when it cannot."""
    try:
        _files.resolve_pending([model_file, card_file])
    except FileFormatError as err:
        raise ModelError(str(err)) from None


def resolve_model(name: str | Path) -> tuple[Path, Path]:
    """Model and card files of a path, of a shipped model's bare name (``default``), or of
    a model in the user models folder (:func:`rough_map.resources.user_models_dir`) by its
    bare name.

    Raises
    ------
    ModelError
        No such model file, no shipped model and no user model of that name.
    """
    model_file, card_file = model_paths(name)
    if model_file.is_file():
        return model_file, card_file
    bare = Path(name).name == str(name) and not str(name).endswith(MODEL_SUFFIX)
    if bare and str(name) in shipped_models():
        return model_paths(model_base(str(name)))
    if bare:
        mine = model_paths(user_models_dir() / str(name))
        if mine[0].is_file():
            return mine
    shipped = ", ".join(shipped_models()) or "none"
    raise ModelError(
        f"{model_file}: no such model file (shipped with rough_map: {shipped}; "
        f"yours, by name: in {user_models_dir()})"
    )


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    except (OSError, ValueError, TypeError) as err:
        raise ModelError(f"{str(path)!r:.80}: cannot read ({brief(err)})") from None
    return digest.hexdigest()


def read_card(name: str | Path) -> dict[str, Any]:
    """Read a model card.

    Parameters
    ----------
    name : str or Path
        The model name, its file or its card.

    Raises
    ------
    ModelError
        Missing or unreadable card.
    """
    model_file, card_file = model_paths(name)
    resolve_pending(model_file, card_file)
    try:
        if card_file.stat().st_size > LIMITS.model_card:
            raise ModelError(f"{card_file}: model card larger than {LIMITS.model_card} bytes")
        text = card_file.read_bytes()
        if json_depth(text) > LIMITS.model_schema_depth:
            raise ModelError(
                f"{card_file}: model card nested deeper than {LIMITS.model_schema_depth}"
            )
        card = json.loads(text.decode("utf-8"))
    except FileNotFoundError:
        raise ModelError(f"{card_file}: no model card") from None
    except ModelError:
        raise
    except Exception as err:  # OSError, UnicodeDecodeError, JSONDecodeError, ...
        raise ModelError(f"{card_file}: unreadable model card ({brief(err)})") from None
    if not isinstance(card, dict) or card.get("format") != CARD_FORMAT:
        raise ModelError(f"{card_file}: not a rough_map model card")
    if not isinstance(card.get("sha256"), str):
        raise ModelError(f"{card_file}: the model card has no sha256 string")
    return card


def card_extraction(name: str | Path) -> dict[str, Any] | None:
    """The feature extraction a model's card records (what the model's ``extraction_``
    holds), or None when there is no readable card or it records none. Only a hint: the
    card is not covered by the model file's sha256, so whoever uses it checks it against
    the loaded model."""
    try:
        card = read_card(resolve_model(name)[1])
    except ModelError:
        return None
    extraction = card.get("feature_extraction")
    return extraction if isinstance(extraction, dict) else None
