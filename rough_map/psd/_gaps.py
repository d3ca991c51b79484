"""Input checks and the gap policy of the estimator (see :mod:`rough_map.psd`, *Gap policy*)."""

from __future__ import annotations

import math
from numbers import Real
from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch._params import check_bool, check_real


def check_spacing(spacing: Any) -> float:
    """The sample spacing as a positive float in m, or :class:`InputError`."""
    ok = isinstance(spacing, Real) and not isinstance(spacing, bool | np.bool_)
    value = float(spacing) if ok else math.nan
    if not (math.isfinite(value) and 0 < value <= 1e3):
        shown = repr(spacing) if len(repr(spacing)) <= 40 else repr(spacing)[:37] + "..."
        raise InputError(f"spacing must be a positive length in m (at most 1000); got {shown}")
    return value


def check_heights(heights: Any, min_samples: int = 8) -> np.ndarray:
    """A height grid (profiles, samples) in m; a 1-D profile becomes one row.

    Raises :class:`InputError` for non-numeric, empty, short or infinite input (NaN is
    missing data and passes).
    """
    h = as_heights(heights)
    if h.ndim == 1:
        h = h[None, :]
    if h.ndim != 2:
        raise InputError(
            f"heights must be a 2-D grid (profiles x samples), got shape {np.shape(heights)}"
        )
    if h.size == 0:
        raise InputError(f"heights is empty (shape {h.shape})")
    if h.shape[1] < min_samples:
        raise InputError(
            f"profiles need at least {min_samples} samples, got {h.shape[1]} (shape {h.shape})"
        )
    if h.size > LIMITS.grid_cells:
        raise InputError(
            f"heights has {h.size} cells (shape {h.shape}); at most {LIMITS.grid_cells}"
        )
    # two passes (fmax and fmin skip NaN; all NaN gives NaN), where isinf, isnan, abs and
    # nanmax took four
    flat = h.reshape(-1)
    hi, lo = float(np.fmax.reduce(flat)), float(np.fmin.reduce(flat))
    if math.isinf(hi) or math.isinf(lo):
        raise InputError("heights contain infinite values; use NaN for missing cells")
    top = max(hi, -lo) if not math.isnan(hi) else 0.0
    if top > MAX_HEIGHT:
        raise InputError(
            f"heights reach {top:.3g} m, beyond {MAX_HEIGHT:.0e} m: wrong units? (elevations in m)"
        )
    return h


MAX_HEIGHT = 1e6
"""Largest |height| accepted, m: far beyond any relief, so only wrong units or garbage reach it
(and the spectra of larger values can overflow)."""


def as_heights(heights: Any) -> np.ndarray:
    """``heights`` as a float array, or :class:`InputError` for non-numeric input."""
    try:
        raw = np.asarray(heights)
        if raw.dtype.kind not in "biuf":
            raise TypeError(raw.dtype)
        return np.asarray(raw, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError("heights must be a real numeric array of elevations in m") from None


def fill_gaps(
    heights: np.ndarray,
    spacing: float,
    *,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
    copy: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the gap policy to the rows of a height grid.

    Parameters
    ----------
    heights : ndarray, shape (m, n)
        Elevations in m, NaN for missing cells.
    spacing : float
        Sample spacing in m.
    max_gap : float
        Longest gap in m that is filled by interpolation.
    max_gap_fraction : float
        Largest fraction of missing cells a kept profile may have.
    copy : bool
        Fill a copy (the default); False fills ``heights`` itself when it is a float64
        array, which the caller then gives up.

    Returns
    -------
    filled : ndarray, shape (m, n)
        Heights in m with short gaps filled; dropped rows are left as they were.
    keep : ndarray of bool, shape (m,)
        Profiles that pass the policy.
    """
    h = as_heights(heights)
    if h.ndim != 2 or h.size == 0:
        raise InputError(
            f"heights must be a non-empty 2-D grid (profiles x samples), got {h.shape}"
        )
    if h.size > LIMITS.grid_cells:
        raise InputError(
            f"heights has {h.size} cells (shape {h.shape}); at most {LIMITS.grid_cells}"
        )
    spacing = check_spacing(spacing)
    check_real("max_gap", max_gap, "m", low=0.0, high=1e6)
    check_real("max_gap_fraction", max_gap_fraction, "", low=0.0, high=1.0)
    check_bool("copy", copy)
    missing = np.isnan(h)
    if not missing.any():
        return h, np.ones(h.shape[0], dtype=bool)
    m, n = h.shape
    # The runs of missing cells, found on the rows padded with a valid cell at each end
    # (so no run crosses a row): start and end (exclusive) in padded coordinates.
    padded = np.zeros((m, n + 2), dtype=np.int8)
    padded[:, 1:-1] = missing
    step = np.diff(padded.ravel())
    starts = np.flatnonzero(step == 1) + 1
    ends = np.flatnonzero(step == -1) + 1
    row = starts // (n + 2)
    first = starts - row * (n + 2) - 1  # first missing column of each run
    length = ends - starts  # a gap touching an end counts its full length from that end
    longest = np.zeros(m, dtype=np.intp)
    np.maximum.at(longest, row, length)
    n_missing = missing.sum(axis=1)
    max_cells = int(math.floor(max_gap / spacing + 1e-9))
    keep = (longest <= max_cells) & (n_missing / n <= max_gap_fraction)
    keep &= n - n_missing >= 2
    filled = h.copy() if copy else h
    fill = keep[row]
    if not fill.any():
        return filled, keep
    row, first, length = row[fill], first[fill], length[fill]
    # Each missing cell of a kept row: the valid samples before and after its run
    # (-1 and n past the ends), interpolated linearly; a run touching an end takes the
    # valid sample at its other side.
    size = int(length.sum())
    run = np.repeat(np.arange(row.size), length)
    col = first[run] + (np.arange(size) - np.repeat(np.cumsum(length) - length, length))
    r = row[run]
    prev = first[run] - 1
    nxt = first[run] + length[run]
    hp = h[r, np.clip(prev, 0, n - 1)]
    hq = h[r, np.clip(nxt, 0, n - 1)]
    hp = np.where(prev < 0, hq, hp)
    hq = np.where(nxt >= n, hp, hq)
    inside = (nxt < n) & (prev >= 0)
    span = np.where(inside, (nxt - prev).astype(float), 1.0)
    frac = np.where(inside, (col - prev) / span, 0.0)
    filled[r, col] = hp + frac * (hq - hp)
    return filled, keep
