"""Discrete roughness levels from the overall energy R (paper section 5.5)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from rough_map.config import load_model
from rough_map.iso8608 import CLASSES, LOWER
from rough_map.resources import config_file

__all__ = ["RoughnessLevels", "load_roughness_levels", "roughness_level"]


def _iso_boundary(value: float | str) -> float:
    """A threshold in m^3/rad: a number, or an ISO 8608 boundary written ``"C/D"``."""
    if isinstance(value, str):
        parts = value.replace(" ", "").upper().split("/")
        if len(parts) != 2 or any(p not in CLASSES for p in parts):
            raise ValueError(
                f"{value!r} is not an ISO 8608 boundary such as 'C/D' (classes {CLASSES})"
            )
        lo, hi = CLASSES.index(parts[0]), CLASSES.index(parts[1])
        if hi != lo + 1:
            raise ValueError(f"{value!r}: an ISO boundary joins two adjacent classes, e.g. 'C/D'")
        return LOWER[parts[1]]
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"a threshold must be a positive R in m^3/rad; got {value!r}")
    return v


class RoughnessLevels(BaseModel):
    """Discrete roughness levels from the overall energy R (paper section 5.5).

    A frame is in the first level whose upper threshold its R is below, and in the last
    level when R is at or above every threshold. The defaults are those of
    ``configs/roughness_levels.yaml``: low (ISO A-C), medium (ISO D-E), high (ISO F and up).

    Attributes
    ----------
    levels : tuple of str
        Level names, smoothest first.
    thresholds : tuple of float or str
        ``len(levels) - 1`` increasing upper bounds on R: numbers in m^3/rad, or ISO 8608
        class boundaries written ``"C/D"`` (geometric midpoint of the two classes' centres).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    levels: tuple[str, ...] = Field(("low", "medium", "high"), min_length=2)
    thresholds: tuple[float | str, ...] = ("C/D", "E/F")

    @model_validator(mode="after")
    def _check(self) -> RoughnessLevels:
        if any(not name.strip() for name in self.levels) or len(set(self.levels)) != len(
            self.levels
        ):
            raise ValueError(f"levels must be distinct non-empty names; got {self.levels}")
        if len(self.thresholds) != len(self.levels) - 1:
            raise ValueError(
                f"{len(self.levels)} levels need {len(self.levels) - 1} thresholds; got "
                f"{len(self.thresholds)}"
            )
        values = [_iso_boundary(t) for t in self.thresholds]
        if any(b <= a for a, b in itertools.pairwise(values)):
            raise ValueError(f"thresholds must increase; got {values} m^3/rad")
        return self

    def values(self) -> NDArray[np.float64]:
        """The thresholds in m^3/rad."""
        return np.array([_iso_boundary(t) for t in self.thresholds])


def load_roughness_levels(path: str | Path | None = None) -> RoughnessLevels:
    """Read roughness levels from YAML/JSON (safe loading).

    Parameters
    ----------
    path : str or Path, optional
        A file like ``configs/roughness_levels.yaml``; None reads the one shipped with
        rough_map (:func:`rough_map.resources.config_file`).

    Returns
    -------
    RoughnessLevels

    Raises
    ------
    FileFormatError, SchemaError
        Unreadable file, or content that does not follow :class:`RoughnessLevels`.
    """
    if path is None:
        path = config_file("roughness_levels.yaml")
    return load_model(path, RoughnessLevels)


def roughness_level(
    R: ArrayLike, names: tuple[str, ...] | list[str], thresholds: ArrayLike
) -> NDArray[np.object_]:
    """Level name per frame from its R.

    Parameters
    ----------
    R : array_like
        Overall energy Phi(1 rad/m) in m^3/rad; NaN for frames without a valid patch.
    names : sequence of str
        Level names, smoothest first.
    thresholds : array_like
        ``len(names) - 1`` increasing upper bounds in m^3/rad.

    Returns
    -------
    ndarray of str
        The level of each frame; ``""`` where R is NaN or not positive.
    """
    r = np.asarray(R, dtype=float)
    idx = np.searchsorted(np.asarray(thresholds, dtype=float), r, side="right")
    out = np.asarray(names, dtype=object)[np.clip(idx, 0, len(names) - 1)]
    return np.where(np.isfinite(r) & (r > 0), out, "").astype(object)
