"""The sensor-noise floor (see :mod:`rough_map.psd`, *Sensor noise*).

White measurement noise of variance ``s^2`` per cell adds a flat floor ``s^2 B / pi``
m^3/rad to every ordinate. Subtracting it from the patch-mean spectrum gives one log
correction per bin, shared by every profile of the patch; bins where the noise is more than
half the measured power leave the fit.
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.errors import InputError, PatchError

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


def floor_correction(
    mean_psd: np.ndarray, noise: float, base_mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-bin log correction and fit mask of each patch after subtracting the floor.

    Parameters
    ----------
    mean_psd : ndarray, shape (patches, bins)
        Patch-mean PSD in m^3/rad.
    noise : float
        The floor in m^3/rad.
    base_mask : ndarray of bool, shape (bins,)
        The ordinates the fit would use without noise.

    Returns
    -------
    shift : ndarray, shape (patches, bins)
        ``ln((P - noise) / P)``, added to every profile's log spectrum.
    mask : ndarray of bool, shape (patches, bins)
        ``base_mask`` without the bins where the noise is more than half the power.

    Raises
    ------
    PatchError
        Fewer than 3 bins are left in some patch.
    """
    ratio = np.clip((mean_psd - noise) / mean_psd, 1e-12, None)
    shift = np.log(ratio)  # per-bin log correction shared by all profiles of a patch
    mask = base_mask[None, :] & (ratio >= MIN_SIGNAL_FRACTION)
    if (mask.sum(axis=1) < MIN_BINS).any():
        raise PatchError(
            "fewer than 3 wavenumbers above the noise floor; the patch is too smooth "
            f"for this sensor (noise floor {noise:.3g} m^3/rad)"
        )
    return shift, mask
