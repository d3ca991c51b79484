"""Files that travel inside the package: the shipped terrain models and configs.

The top-level ``models/`` and ``configs/`` of a checkout are where people look at and edit
them; ``rough_map/models`` and ``rough_map/configs`` link to them, so a wheel carries them
as package data and :mod:`importlib.resources` finds them in a checkout, an editable install
and an installed wheel alike.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from rough_map.errors import InputError

__all__ = [
    "DEFAULT_MODEL",
    "USER_MODELS_ENV",
    "config_file",
    "in_package_models",
    "model_base",
    "shipped_models",
    "user_models_dir",
]

#: Name of the terrain model used when none is given.
DEFAULT_MODEL = "default"

_MODEL_SUFFIX = ".skops"
#: The models rough_map ships. A user's own models live in the user models folder
#: (:func:`user_models_dir`), never in the package: ``train`` refuses to write any other
#: name into ``models/``, and the wheel packs only these.
SHIPPED_MODELS = ("default",)
#: Environment variable naming the user models folder.
USER_MODELS_ENV = "ROUGH_MAP_MODELS"


def _folder(name: str) -> Path:
    # A package installed from a wheel or a checkout lives on the file system, so the
    # Traversable is a real path (zip imports are not supported by rough_map).
    return Path(str(resources.files("rough_map").joinpath(name)))


def shipped_models() -> list[str]:
    """Names of the models shipped with rough_map (:data:`SHIPPED_MODELS` that are there)."""
    folder = _folder("models")
    return [n for n in SHIPPED_MODELS if (folder / (n + _MODEL_SUFFIX)).is_file()]


def user_models_dir() -> Path:
    """The folder of the user's own models: ``$ROUGH_MAP_MODELS``, else
    ``$XDG_DATA_HOME/rough_map/models`` (``~/.local/share/rough_map/models``). Not created
    here: ``train`` creates it when it writes a model there."""
    given = os.environ.get(USER_MODELS_ENV, "").strip()
    if given:
        return Path(given).expanduser()
    data = os.environ.get("XDG_DATA_HOME", "").strip() or str(Path("~/.local/share").expanduser())
    return Path(data) / "rough_map" / "models"


def in_package_models(path: Path) -> bool:
    """Whether ``path`` (a model name as a path) lies in the package's ``models/`` folder
    (or the checkout's top-level ``models/``, which it links to)."""
    folder = _folder("models").resolve()
    return Path(os.path.abspath(path)).parent.resolve() == folder


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
