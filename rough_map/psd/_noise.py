"""The sensor-noise floor (see :mod:`rough_map.psd`, *Sensor noise*).

White measurement noise of variance ``s^2`` per cell adds a flat floor ``s^2 B / pi``
m^3/rad to every ordinate (less flat where the gap policy filled cells:
:func:`gap_filled_floor`). Subtracting it from the patch-mean spectrum gives one log
correction per bin, shared by every profile of the patch. Each ordinate then weighs in the
fit as the inverse of its variance about the same profiles read without noise
(:func:`floor_correction`): ordinates where the noise dominates keep a small weight, as
the patch mean averages the noise of ~100 profiles that are nearly independent at those
wavenumbers, and the fit ends only where the noise takes practically all the power.
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.errors import InputError

#: The band ends at the first bin whose noise-free power is below this fraction of the
#: measured power (its weight would be below 1e-4 anyway).
MIN_SIGNAL_FRACTION = 0.01
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


def _smooth_bins(psd: np.ndarray, valid: np.ndarray, half: int = SMOOTH_BINS) -> np.ndarray:
    """Running mean over ``2 half + 1`` bins of each row (shorter windows at the ends), of
    the ``valid`` bins only.

    The floor correction of a bin is a non-linear function of the patch-mean power there;
    computed from one bin's scatter it would be biased (Jensen, and the selection of the
    mask). Smoothing over neighbouring ordinates, where the spectrum changes by a few per
    cent per bin, removes most of the scatter and little of the shape. Bins outside the
    fit do not enter the means: the first ordinate has lost most of its power to the
    detrending, and the Nyquist ordinate carries half the density, so either would pull
    its neighbours' power down and their floor correction up.
    """
    n = psd.shape[-1]
    ok = np.asarray(valid, dtype=float)
    zero = np.zeros(psd.shape[:-1] + (1,))
    c = np.cumsum(np.concatenate([zero, psd * ok], axis=-1), axis=-1)
    cn = np.cumsum(np.concatenate([[0.0], ok]))
    k = np.arange(n)
    lo = np.maximum(k - half, 0)
    hi = np.minimum(k + half + 1, n)
    count = cn[hi] - cn[lo]
    # C order (fancy indexing gives F order): row sums must not depend on the stack's size
    out = np.ascontiguousarray((c[..., hi] - c[..., lo]) / np.maximum(count, 1.0))
    return np.where(count > 0, out, psd)


#: Variance of the log of a periodogram ordinate of a Gaussian profile (one segment).
LOG_VAR = math.pi**2 / 6
#: Independent ordinates in the running mean of ``2 SMOOTH_BINS + 1`` Hann-windowed
#: ordinates: neighbours are correlated (their squared coherence is 4/9), so seven
#: ordinates weigh as 7 / (1 + 2 * 4/9 * 6/7), about 4.
SMOOTH_DOF = 4.0


def _dilog(z: np.ndarray) -> np.ndarray:
    """Li2(z) for z in [0, 1] (scipy's spence(1 - z))."""
    from scipy.special import spence

    return spence(1.0 - z)


def excess_log_variance(q: np.ndarray) -> np.ndarray:
    """Variance of ``ln|X + E|^2 - ln|X|^2`` for a complex Gaussian ordinate ``X`` and
    independent noise ``E`` with ``q`` times its power: ``2 (pi^2/6 - Li2(1 / (1 + q)))``
    (the covariance of the logs of two exponential variables of squared correlation
    ``rho^2`` is ``Li2(rho^2)``). 0 without noise, ``pi^2/3`` when noise dominates."""
    q = np.asarray(q, dtype=float)
    return 2.0 * (LOG_VAR - _dilog(1.0 / (1.0 + q)))


def gap_statistics(grid: np.ndarray, missing: np.ndarray) -> tuple[float, float]:
    """What the gap policy did to one patch, for :func:`gap_filled_floor`.

    Parameters
    ----------
    grid : ndarray, shape (profiles, samples)
        The kept profiles in m, gaps filled.
    missing : ndarray of bool, same shape
        The cells that were filled.

    Returns
    -------
    share : float
        Fraction of the cells that were filled.
    residual : float
        Mean square in m^2 of what linear interpolation misses on measured cells,
        ``(y[j-1] + y[j+1]) / 2 - y[j]``, over the cells measured with both neighbours
        measured, in every 4th profile (a patch-wide mean: ~3,000 cells are plenty; 0 when
        nothing was filled).
    """
    share = float(missing.mean())
    if share == 0.0:
        return 0.0, 0.0
    grid, missing = grid[::4], missing[::4]
    ok = ~(missing[:, :-2] | missing[:, 1:-1] | missing[:, 2:])
    miss = 0.5 * (grid[:, :-2] + grid[:, 2:]) - grid[:, 1:-1]
    return share, float(np.mean(miss[ok] ** 2)) if ok.any() else 0.0


def gap_filled_floor(
    noise: np.ndarray, gaps: np.ndarray | None, n_bins: int, seg_n: int, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each ordinate's floor in m^3/rad, and the gain of the terrain's power, after the
    gap policy filled cells by linear interpolation; both of shape (patches, bins).

    ``gaps`` holds a row ``(f, v)`` of :func:`gap_statistics` per patch (None: nothing
    filled). A share ``f`` of isolated cells replaced by the mean of their neighbours is
    the profile ``y + m (A y)``, with ``(A y)[j] = (y[j-1] + y[j+1]) / 2 - y[j]`` and ``m``
    the indicator of the filled cells. Its expected spectrum is that of ``y`` times
    ``g = (1 + f (cos(Omega B) - 1))^2`` (the terrain loses up to 4 f of its power at the
    Nyquist wavenumber, where a few per cent are a large share of what a steep spectrum has
    left above the noise), plus the white ``f (1 - f) E[(A y)^2] B / pi`` of the cells that
    were filled and not measured. ``y`` holds the terrain and the noise, so the floor is
    ``N g + f (1 - f) v B / pi``, and the terrain's power is the rest divided by ``g``.
    """
    floor = np.asarray(noise, dtype=float)[:, None]
    if gaps is None:
        ones = np.ones((floor.shape[0], n_bins))
        return floor * ones, ones
    nu = 2.0 * np.pi * np.arange(1, n_bins + 1) / seg_n
    stats = np.asarray(gaps, dtype=float)
    share, resid = stats[:, :1], stats[:, 1:]
    gain = (1.0 + share * (np.cos(nu)[None, :] - 1.0)) ** 2
    return floor * gain + share * (1.0 - share) * resid * spacing / np.pi, gain


def floor_correction(
    mean_psd: np.ndarray, noise: np.ndarray, base_mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin log correction and fit weights of each patch after subtracting its floor.

    Parameters
    ----------
    mean_psd : ndarray, shape (patches, bins)
        Patch-mean PSD in m^3/rad.
    noise : ndarray, shape (patches,) or (patches, bins)
        Each patch's floor in m^3/rad (or each ordinate's: :func:`gap_filled_floor`).
    base_mask : ndarray of bool, shape (bins,)
        The ordinates the fit would use without noise.

    Returns
    -------
    shift : ndarray, shape (patches, bins)
        ``ln((P - noise) / P)``, added to every profile's log spectrum (``P`` smoothed over
        neighbouring ordinates).
    weights : ndarray, shape (patches, bins)
        Fit weight of each ordinate: the variance of a clean log ordinate over that of
        the corrected one, which has noise ``q = noise / (P - noise)`` times its signal
        (:func:`excess_log_variance`, and the share ``q^2 / SMOOTH_DOF`` of the shift's
        own scatter). The same profiles read without noise have weight 1 everywhere, so
        the fit stays as close to theirs as the noise allows. 0 outside ``base_mask`` and
        from the first bin where the signal is less than :data:`MIN_SIGNAL_FRACTION` of
        the measured power.
    short : ndarray of bool, shape (patches,)
        Patches left with fewer than 3 bins: too smooth for their sensor, no fit.
    """
    smooth = _smooth_bins(mean_psd, base_mask)
    floor = np.asarray(noise, dtype=float)
    floor = floor[:, None] if floor.ndim == 1 else floor
    ratio = np.clip((smooth - floor) / smooth, 1e-12, None)
    shift = np.log(ratio)  # per-bin log correction shared by all profiles of a patch
    q = np.minimum(1.0 / ratio - 1.0, 1e12)
    var = LOG_VAR + excess_log_variance(q) + q * q / SMOOTH_DOF
    # The band ends where the noise takes practically all the power: a mask that kept later
    # bins wherever the spectrum happens to be high would keep only upward fluctuations.
    above = ratio > MIN_SIGNAL_FRACTION
    mask = base_mask[None, :] & (np.cumprod(above | ~base_mask[None, :], axis=1) > 0)
    short = mask.sum(axis=1) < MIN_BINS
    return shift, np.where(mask, LOG_VAR / var, 0.0), short


def noise_reach(shift: np.ndarray, base_mask: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """The highest wavenumber in rad/m, counted on from the fit's first ordinate, up to
    which each patch's terrain keeps at least as much power as its floor (the smoothed
    patch-mean power at least twice the floor); 0 where the first is already below. Above
    it the noise dominates and the ordinates weigh little in the fit.

    ``shift`` (patches, bins) is :func:`floor_correction`'s ``ln((P - floor) / P)``, which
    is at least ``ln(1/2)`` exactly there; ``base_mask`` and ``omega`` (rad/m) have shape
    (bins,).
    """
    above = (shift >= math.log(0.5)) | ~base_mask[None, :]
    run = (np.cumprod(above, axis=1) > 0) & base_mask[None, :]
    last = np.where(run, np.arange(shift.shape[1])[None, :], -1).max(axis=1)
    return np.where(last >= 0, omega[np.maximum(last, 0)], 0.0)
