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
#: The models rough_map ships. Any other file in ``models/`` is a user's (``train --out
#: models/mine`` in a checkout): it is not listed as shipped, and the wheel leaves it out.
SHIPPED_MODELS = ("default",)


def _folder(name: str) -> Path:
    # A package installed from a wheel or a checkout lives on the file system, so the
    # Traversable is a real path (zip imports are not supported by rough_map).
    return Path(str(resources.files("rough_map").joinpath(name)))


def shipped_models() -> list[str]:
    """Names of the models shipped with rough_map (:data:`SHIPPED_MODELS` that are there)."""
    folder = _folder("models")
    return [n for n in SHIPPED_MODELS if (folder / (n + _MODEL_SUFFIX)).is_file()]


def model_base(name: str = DEFAULT_MODEL) -> Path:
    """The shipped model ``name``: its path without suffix (``.../models/default``).

    Raises
    ------
    InputError
        No model of that name is shipped.
    """
    base = _folder("models") / name
    if name not in SHIPPED_MODELS or not base.with_name(name + _MODEL_SUFFIX).is_file():
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
