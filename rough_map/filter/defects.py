"""Isolated defects along the path: a short spike of R, such as a manhole.

:func:`isolated_spikes` flags the frames; :class:`IsolatedSpikes` holds its settings, the
defect detector a :class:`~rough_map.classify.TerrainModel` takes as its ``defects``
component (the filter gives those frames a predict step only).
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Real

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map import errors
from rough_map._numeric import median

__all__ = ["IsolatedSpikes", "isolated_spikes"]


def isolated_spikes(
    values: ArrayLike,
    distance: ArrayLike,
    *,
    ratio: float = 8.0,
    window: float = 3.0,
    max_length: float = 1.5,
    margin: float = 0.5,
) -> NDArray[np.bool_]:
    """Frames that see an isolated defect: a short spike of R along the path.

    A manhole, a pothole or a rock in otherwise uniform ground lifts the overall energy R of
    the few patches that contain it by an order of magnitude, and R falls back once they
    have passed (paper section 5.1, Fig. 13). Those frames say little about what the ground
    around the defect is made of, and a classifier reads them as rougher terrain. A frame is
    *above* when its value exceeds ``ratio`` times the median over the frames within
    ``window`` m along the path; a run of frames above that spans at most ``max_length`` m
    is a spike, and the frames within ``margin`` m of it (which see the defect only in
    part) are flagged with it. A longer run is a change of terrain and is not flagged.

    The test looks ahead of each frame as well as behind it, so it suits recorded traverses
    (the smoother and Viterbi), not the online filter.

    Parameters
    ----------
    values : array_like, shape (n,)
        Per-frame R in m^3/rad (any positive quantity that scales like it); NaN or <= 0 for
        frames without one (never above; inside a run, or within ``margin`` of one, they
        are flagged with it).
    distance : array_like, shape (n,)
        Distance travelled along the path in m, non-decreasing.
    ratio : float
        How many times the local median a frame must exceed (> 1).
    window : float
        Half-width in m of the neighbourhood of the local median.
    max_length : float
        Longest run in m that still counts as one isolated defect.
    margin : float
        Distance in m around a spike within which frames are flagged with it.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    v = np.asarray(values, dtype=float)
    s = np.asarray(distance, dtype=float)
    if v.ndim != 1 or s.shape != v.shape:
        raise errors.InputError(
            f"values and distance must be 1-D of the same length; got {v.shape} and {s.shape}"
        )
    if not np.all(np.isfinite(s)) or np.any(np.diff(s) < 0):
        raise errors.InputError("distance must be finite and non-decreasing (m)")
    _check_settings(ratio, window, max_length, margin)
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_v = np.where(np.isfinite(v) & (v > 0), np.log(v), np.nan)
    known = np.isfinite(ln_v)
    n = len(v)
    flagged = np.zeros(n, dtype=bool)
    if known.sum() < 3:
        return flagged
    lo = np.searchsorted(s, s - window, side="left")
    hi = np.searchsorted(s, s + window, side="right")
    above = np.zeros(n, dtype=bool)
    ln_ratio = np.log(ratio)
    for k in np.flatnonzero(known):
        local = ln_v[lo[k] : hi[k]]
        above[k] = ln_v[k] - median(local[np.isfinite(local)]) > ln_ratio
    # runs of frames above, bridging frames without a value
    i = 0
    while i < n:
        if not above[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and (above[j + 1] or not known[j + 1]):
            j += 1
        last = j
        while not above[last]:  # the run ends at its last frame above
            last -= 1
        if s[last] - s[i] <= max_length:
            flagged |= (s >= s[i] - margin) & (s <= s[last] + margin)
        i = j + 1
    return flagged


def _check_settings(ratio: float, window: float, max_length: float, margin: float) -> None:
    """Raise InputError unless the settings of :func:`isolated_spikes` are valid."""
    for name, value, low in (
        ("ratio", ratio, 1.0),
        ("window", window, 0.0),
        ("max_length", max_length, 0.0),
        ("margin", margin, -np.inf),
    ):
        if not (isinstance(value, Real) and np.isfinite(value) and value > low):
            raise errors.InputError(f"{name} must be a finite number > {low:g}; got {value!r}")
    if margin < 0:
        raise errors.InputError(f"margin must be >= 0 (m); got {margin!r}")


@dataclass(frozen=True)
class IsolatedSpikes:
    """The settings of :func:`isolated_spikes`, as a defect detector: ``detector(R, distance)``.

    A :class:`~rough_map.classify.TerrainModel` calls its ``defects`` component this way on
    the R of the valid frames of a recorded traverse. The settings are checked when the
    detector is made.

    Parameters
    ----------
    ratio : float, default 8.0
        How many times the local median R a frame must exceed (> 1).
    window : float, default 3.0
        Half-width in m of the neighbourhood of the local median.
    max_length : float, default 1.5
        Longest run in m that still counts as one isolated defect.
    margin : float, default 0.5
        Distance in m around a spike within which frames are flagged with it.
    """

    ratio: float = 8.0
    window: float = 3.0
    max_length: float = 1.5
    margin: float = 0.5

    def __post_init__(self) -> None:
        _check_settings(self.ratio, self.window, self.max_length, self.margin)

    def __call__(self, values: ArrayLike, distance: ArrayLike) -> NDArray[np.bool_]:
        """Frames that see an isolated defect (see :func:`isolated_spikes`).

        Parameters
        ----------
        values : array_like, shape (n,)
            Per-frame R in m^3/rad; NaN for frames without one.
        distance : array_like, shape (n,)
            Distance travelled along the path in m, non-decreasing.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        return isolated_spikes(
            values,
            distance,
            ratio=self.ratio,
            window=self.window,
            max_length=self.max_length,
            margin=self.margin,
        )
