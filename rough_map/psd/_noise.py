"""The sensor-noise floor (see :mod:`rough_map.psd`, *Sensor noise*).

White measurement noise of variance ``s^2`` per cell adds a flat floor ``s^2 B / pi``
m^3/rad to every ordinate. Subtracting it from the patch-mean spectrum gives one log
correction per bin, shared by every profile of the patch; bins where the noise is more than
half the measured power leave the fit.
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.errors import InputError

#: Bins whose noise-free power is below this fraction of the measured power leave the fit.
MIN_SIGNAL_FRACTION = 0.5
#: Fewest bins left for a fit.
MIN_BINS = 3


def check_floor(noise_psd: float | None) -> float:
    """The floor in m^3/rad to subtract; :class:`InputError` unless finite and >= 0."""
    noise = math.nan if noise_psd is None else float(noise_psd)
    if noise_psd is None or not math.isfinite(noise) or noise < 0:
        raise InputError("subtract_noise=True needs a finite noise_psd >= 0 in m^3/rad")
    return noise


#: Half-width in bins of the running mean that smooths the patch-mean PSD before the floor
#: is subtracted.
SMOOTH_BINS = 3


def _smooth_bins(psd: np.ndarray, half: int = SMOOTH_BINS) -> np.ndarray:
    """Running mean over ``2 half + 1`` bins of each row (shorter windows at the ends).

    The floor correction of a bin is a non-linear function of the patch-mean power there;
    computed from one bin's scatter it would be biased (Jensen, and the selection of the
    mask). Smoothing over neighbouring ordinates, where the spectrum changes by a few per
    cent per bin, removes most of the scatter and little of the shape.
    """
    n = psd.shape[-1]
    c = np.cumsum(np.concatenate([np.zeros(psd.shape[:-1] + (1,)), psd], axis=-1), axis=-1)
    k = np.arange(n)
    lo = np.maximum(k - half, 0)
    hi = np.minimum(k + half + 1, n)
    # C order (fancy indexing gives F order): row sums must not depend on the stack's size
    return np.ascontiguousarray((c[..., hi] - c[..., lo]) / (hi - lo))


def floor_correction(
    mean_psd: np.ndarray, noise: np.ndarray, base_mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin log correction and fit weights of each patch after subtracting its floor.

    Parameters
    ----------
    mean_psd : ndarray, shape (patches, bins)
        Patch-mean PSD in m^3/rad.
    noise : ndarray, shape (patches,)
        Each patch's floor in m^3/rad.
    base_mask : ndarray of bool, shape (bins,)
        The ordinates the fit would use without noise.

    Returns
    -------
    shift : ndarray, shape (patches, bins)
        ``ln((P - noise) / P)``, added to every profile's log spectrum (``P`` smoothed over
        neighbouring ordinates).
    weights : ndarray, shape (patches, bins)
        Fit weight of each ordinate, ``((P - noise) / P)^2``: a log ordinate corrected for
        a floor that takes a share ``1 - r`` of its power has ``1 / r^2`` times the variance
        of a clean one. 0 outside ``base_mask`` and from the first bin where the noise
        takes more than half the power.
    short : ndarray of bool, shape (patches,)
        Patches left with fewer than 3 bins: too smooth for their sensor, no fit.
    """
    smooth = _smooth_bins(mean_psd)
    floor = np.asarray(noise, dtype=float)[:, None]
    ratio = np.clip((smooth - floor) / smooth, 1e-12, None)
    shift = np.log(ratio)  # per-bin log correction shared by all profiles of a patch
    # The band ends at the first wavenumber where the noise takes half the power: a mask
    # that kept later bins wherever the spectrum happens to be high would keep only upward
    # fluctuations there, which flattens w and lowers R.
    above = ratio >= MIN_SIGNAL_FRACTION
    mask = base_mask[None, :] & (np.cumprod(above | ~base_mask[None, :], axis=1) > 0)
    short = mask.sum(axis=1) < MIN_BINS
    return shift, np.where(mask, ratio * ratio, 0.0), short
