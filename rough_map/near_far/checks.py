"""Checks of :class:`~rough_map.near_far.NearToFar`'s parameters and near labels."""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.near_far.cells import NearField

__all__ = ["check_numbers", "class_weights"]


def check_numbers(model: Any, near: NearField) -> None:
    """Check the numeric parameters of a NearToFar ``model`` whose near field is ``near``.

    Raises
    ------
    InputError
        A parameter out of range, naming it.
    """

    def integer(value: Any, low: int) -> bool:
        return (
            isinstance(value, int | np.integer)
            and not isinstance(value, bool)
            and bool(value >= low)
        )

    def positive(value: Any) -> bool:
        number = isinstance(value, int | float | np.number) and not isinstance(value, bool)
        return number and bool(value > 0)

    if not integer(model.tile_px, 4):
        raise InputError(f"tile_px must be an integer >= 4 px, got {model.tile_px!r}")
    if not (positive(model.max_range) and model.max_range > near.ahead[1]):
        raise InputError(
            f"max_range ({model.max_range!r} m) must exceed the end of the near field "
            f"({near.ahead[1]:g} m)"
        )
    if not positive(model.ground_step):
        raise InputError(f"ground_step must be positive (m), got {model.ground_step!r}")
    if not integer(model.min_near_tiles, 1):
        raise InputError(f"min_near_tiles must be an integer >= 1, got {model.min_near_tiles!r}")
    if not integer(model.memory_cells, 0):
        raise InputError(f"memory_cells must be an integer >= 0, got {model.memory_cells!r}")
    if not isinstance(model.recall, bool | np.bool_):
        raise InputError(f"recall must be true or false, got {model.recall!r}")
    for name in ("min_confidence", "recall_min_confidence"):
        value = getattr(model, name)
        if not (isinstance(value, Real) and 0.0 <= float(value) <= 1.0):
            raise InputError(f"{name} must be in [0, 1], got {value!r}")


def class_weights(classes: Sequence[str], near_label: str | int | ArrayLike) -> NDArray[np.float64]:
    """Class weights (K,) of a near label: a class name, an index or a probability vector.

    Raises
    ------
    InputError
        An unknown name or index, or a bad probability vector.
    """
    k = len(classes)
    if isinstance(near_label, str):
        if near_label not in classes:
            raise InputError(f"unknown class label {near_label!r}; expected one of {classes}")
        return np.eye(k)[list(classes).index(near_label)]
    arr = np.asarray(near_label)
    if arr.ndim == 0:
        if not np.issubdtype(arr.dtype, np.integer) or not 0 <= int(arr) < k:
            raise InputError(
                f"unknown class label {near_label!r}; expected a class name or an index 0..{k - 1}"
            )
        return np.eye(k)[int(arr)]
    try:
        p = arr.astype(float)
    except (TypeError, ValueError):
        p = np.full(0, np.nan)
    if p.shape != (k,) or not np.all(np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
        raise InputError(
            f"near probabilities must be {k} non-negative finite numbers (one per class "
            f"{classes}), got {arr!r}"
        )
    return np.asarray(p / p.sum())
