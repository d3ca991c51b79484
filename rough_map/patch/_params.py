"""Up-front checks of public parameters, shared by :mod:`rough_map.patch` and
:mod:`rough_map.psd`: every bad value is an :class:`~rough_map.errors.InputError` with a
one-line message naming the parameter and its unit.

Budgets: the estimator's correlation between profiles costs memory and time growing as the
square of the samples per segment (about 200 MB and several seconds at 512), so
:func:`rough_map.psd.patch_roughness` takes at most ``LIMITS.patch_samples`` samples per
segment when a patch has several profiles, at most ``LIMITS.profile_samples`` per profile, and
a patch has at most ``LIMITS.patch_samples`` samples per side; a plain spectrum
(:func:`rough_map.psd.profile_psd`) takes at most ``LIMITS.grid_cells`` cells
(:data:`rough_map.limits.LIMITS`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from numbers import Integral, Real
from typing import Any, TypeVar

import numpy as np

from rough_map.errors import InputError, UnknownOptionError

__all__ = [
    "check_bool",
    "check_choice",
    "check_int",
    "check_real",
    "options_of",
]

T = TypeVar("T")


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_real(
    name: str,
    value: Any,
    unit: str,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
    none: bool = False,
) -> float | None:
    """``value`` as a float in the range, or :class:`InputError` naming ``name`` and ``unit``.

    ``none`` lets None through. Booleans, strings and sequences are refused.
    """
    if value is None and none:
        return None
    ok = isinstance(value, Real | np.floating | np.integer) and not isinstance(
        value, bool | np.bool_
    )
    try:
        v = float(value) if ok else math.nan
    except OverflowError:  # an int beyond any float
        v = math.inf
    if ok and math.isfinite(v):
        ok = (v > low if low_open else v >= low) and (v < high if high_open else v <= high)
    else:
        ok = False
    if not ok:
        lo = ("(" if low_open else "[") + (f"{low:g}" if math.isfinite(low) else "-inf")
        hi = (f"{high:g}" if math.isfinite(high) else "inf") + (")" if high_open else "]")
        unit_text = f" in {unit}" if unit else ""
        also = " or None" if none else ""
        raise InputError(
            f"{name} must be a finite number{unit_text} in {lo}, {hi}{also}; got {_show(value)}"
        )
    return v


def check_int(
    name: str, value: Any, *, low: int, high: int, unit: str = "", none: bool = False
) -> int | None:
    """``value`` as an int in ``[low, high]`` (None if ``none``), or :class:`InputError`."""
    if value is None and none:
        return None
    if (
        isinstance(value, Integral | np.integer)
        and not isinstance(value, bool | np.bool_)
        and low <= int(value) <= high
    ):
        return int(value)
    unit_text = f" ({unit})" if unit else ""
    also = " or None" if none else ""
    raise InputError(
        f"{name} must be an integer{unit_text} in [{low}, {high}]{also}; got {_show(value)}"
    )


def check_bool(name: str, value: Any) -> bool:
    """``value`` as a bool (numpy's included), or :class:`InputError`."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    raise InputError(f"{name} must be true or false; got {_show(value)}")


def check_choice(name: str, value: Any, choices: Sequence[str]) -> str:
    """``value`` if it is one of the strings ``choices``, else :class:`InputError` listing them."""
    if isinstance(value, str) and value in choices:
        return value
    raise InputError(f"{name} must be one of {', '.join(choices)}; got {_show(value)}")


def options_of(cls: type[T], options: T | None, changes: dict[str, Any], caller: str) -> T:
    """The options object (a frozen dataclass ``cls``) that ``caller`` was given: ``options``
    whole (None: the defaults) with its keyword ``changes``, checked once, as
    :class:`rough_map.psd.Options` and :class:`rough_map.workflow.AnalysisOptions` are taken.

    Raises
    ------
    InputError
        ``options`` is not a ``cls``, or a change is a bad value (the dataclass's checks).
    UnknownOptionError
        A keyword that is not a field of ``cls``.
    """
    if options is not None and not isinstance(options, cls):
        raise InputError(f"{caller}() options must be a {_public_name(cls)}")
    unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(cls)})  # type: ignore[arg-type]
    if unknown:
        raise UnknownOptionError(f"{caller}() got unexpected keyword arguments {unknown[:5]}")
    return dataclasses.replace(options or cls(), **changes)  # type: ignore[type-var]


def _public_name(cls: type) -> str:
    """``rough_map.psd.Options`` for a class exported by its package, else its module path."""
    package = cls.__module__.rsplit(".", 1)[0] if cls.__module__.count(".") > 1 else None
    return f"{package or cls.__module__}.{cls.__qualname__}"
