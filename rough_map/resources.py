"""Files that travel inside the package: the shipped terrain models and configs.

The top-level ``models/`` and ``configs/`` of a checkout are where people look at and edit
them; ``rough_map/models`` and ``rough_map/configs`` link to them, so a wheel carries them
as package data and :mod:`importlib.resources` finds them in a checkout, an editable install
and an installed wheel alike.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from rough_map.errors import InputError

__all__ = ["DEFAULT_MODEL", "config_file", "model_base", "shipped_models"]

#: Name of the terrain model used when none is given.
DEFAULT_MODEL = "default"

_MODEL_SUFFIX = ".skops"


def _folder(name: str) -> Path:
    # A package installed from a wheel or a checkout lives on the file system, so the
    # Traversable is a real path (zip imports are not supported by rough_map).
    return Path(str(resources.files("rough_map").joinpath(name)))


def shipped_models() -> list[str]:
    """Names of the models shipped with rough_map (``default``, ...)."""
    folder = _folder("models")
    if not folder.is_dir():
        return []
    return sorted(p.name[: -len(_MODEL_SUFFIX)] for p in folder.glob("*" + _MODEL_SUFFIX))


def model_base(name: str = DEFAULT_MODEL) -> Path:
    """The shipped model ``name``: its path without suffix (``.../models/default``).

    Raises
    ------
    InputError
        No model of that name is shipped.
    """
    base = _folder("models") / name
    if not base.with_name(name + _MODEL_SUFFIX).is_file():
        known = ", ".join(shipped_models()) or "none"
        raise InputError(f"no shipped model named {name!r} (shipped: {known})")
    return base


def config_file(name: str) -> Path:
    """A shipped config file, e.g. ``config_file("roughness_levels.yaml")``.

    Raises
    ------
    InputError
        No such file in the shipped configs (a broken installation).
    """
    path = _folder("configs") / name
    if not path.is_file():
        raise InputError(f"{path}: shipped config file missing; reinstall rough_map")
    return path
