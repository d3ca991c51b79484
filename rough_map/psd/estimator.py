"""The public estimator: :func:`patch_roughness`, :func:`patch_roughness_batch`,
:func:`profile_psd` (the method is described in :mod:`rough_map.psd`).

These are thin wrappers in the manner of :func:`scipy.signal.welch`: they check the input,
apply the gap policy (:mod:`rough_map.psd._gaps`), compute the spectra
(:mod:`rough_map.psd._spectra`) and fit them (:mod:`rough_map.psd._fit`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from rough_map.errors import InputError, PatchError
from rough_map.patch._params import MAX_CELLS, MAX_PROFILE, MAX_SAMPLES, check_int
from rough_map.psd._fit import Spectra, fit
from rough_map.psd._gaps import as_heights, check_heights, check_spacing, fill_gaps
from rough_map.psd._options import Options, check_window
from rough_map.psd._result import PatchRoughness
from rough_map.psd._spectra import detrended_rms, periodogram, spectrum

log = logging.getLogger(__name__)

#: Heights per chunk of a batch (patches x profiles x samples), to stay in cache.
_CHUNK_CELLS = 400_000


def patch_roughness(
    heights: np.ndarray,
    spacing: float,
    *,
    window: str = "hann",
    method: str = "unbiased",
    nperseg: int | None = None,
    noverlap: int | None = None,
    omega0: float = 1.0,
    noise_psd: float | None = None,
    subtract_noise: bool = False,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
    min_profiles: int = 3,
    gridding: str = "point",
    waviness: float | None = None,
) -> PatchRoughness:
    """Roughness parameters (R, w) of one patch, with their first-order uncertainty.

    Parameters
    ----------
    heights : ndarray, shape (m, n)
        Height grid in m: ``m`` longitudinal profiles (rows, along the direction of travel)
        of ``n`` samples, NaN for missing cells. A stack of patches goes to
        :func:`patch_roughness_batch`.
    spacing : float
        Sample spacing B in m (8 mm in the paper).
    window : str
        Spectral window, default ``"hann"`` (a rectangular window leaks badly on spectra as
        steep as Omega^-2.5).
    method : {"unbiased", "paper"}
        ``"unbiased"`` corrects the -gamma bias of the log periodogram; ``"paper"`` is the
        paper's plain log-log fit (R about 44 % low).
    nperseg, noverlap : int, optional
        Welch segmenting in samples; default one segment over the whole profile.
    omega0 : float
        Reference wavenumber of R in rad/m.
    noise_psd : float, optional
        Measurement-noise floor in m^3/rad (see :func:`rough_map.patch.grid_points`).
    subtract_noise : bool
        Subtract ``noise_psd`` before the fit.
    max_gap : float
        Longest gap in m filled by interpolation.
    max_gap_fraction : float
        Largest fraction of missing cells in a kept profile.
    min_profiles : int
        Fewest usable profiles; fewer raise :class:`~rough_map.errors.PatchError`.
    gridding : {"point", "cell_mean"}
        How the heights were sampled. ``"point"``: samples of the surface at the grid
        nodes (synthetic grids, interpolated surfaces). ``"cell_mean"``: means of many points
        per cell (a dense cloud gridded by :func:`rough_map.patch.grid_points`); the box
        filter of the averaging steepens w by about 0.25 and raises R about 2.5 times, and
        the unbiased method corrects for it.
    waviness : float, optional
        Fix the waviness (dimensionless) instead of fitting it (ISO 8608 classifies roads
        with w = -2); then only R is estimated and ``sigma_w`` is 0.

    Returns
    -------
    PatchRoughness

    Raises
    ------
    InputError
        Bad shape, spacing, method or non-finite values other than NaN.
    PatchError
        Too few usable profiles.
    """
    opt = Options(
        window=window,
        method=method,
        nperseg=nperseg,
        noverlap=noverlap,
        omega0=omega0,
        noise_psd=noise_psd,
        subtract_noise=subtract_noise,
        max_gap=max_gap,
        max_gap_fraction=max_gap_fraction,
        min_profiles=min_profiles,
        gridding=gridding,
        waviness=waviness,
    )
    spacing = check_spacing(spacing)
    opt.check_omega0()
    arr = _as_float(heights)
    if arr.ndim == 3:
        raise InputError(
            f"heights has shape {arr.shape}: patch_roughness takes one patch (profiles, "
            "samples); use patch_roughness_batch for a stack (patches, profiles, samples)"
        )
    if arr.ndim not in (1, 2):
        check_heights(arr)  # raises: not a 2-D grid
    if arr.size == 0:
        raise InputError(f"heights is empty (shape {arr.shape})")
    return _estimate(_checked_stack(arr.reshape(1, -1, arr.shape[-1]), opt), spacing, opt)[0]


def patch_roughness_batch(
    heights: np.ndarray, spacing: float, **options: Any
) -> list[PatchRoughness]:
    """:func:`patch_roughness` of a stack of patches, in one vectorised pass.

    Parameters
    ----------
    heights : ndarray, shape (p, m, n)
        ``p`` height grids in m of ``m`` profiles of ``n`` samples, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    **options
        The keyword options of :func:`patch_roughness` (``window``, ``method``, ``nperseg``,
        ``noverlap``, ``omega0`` in rad/m, ``noise_psd`` in m^3/rad, ``subtract_noise``,
        ``max_gap`` in m, ``max_gap_fraction``, ``min_profiles``, ``gridding``,
        ``waviness``).

    Returns
    -------
    list of PatchRoughness
        One per patch, in order (empty for an empty stack).

    Raises
    ------
    InputError
        Not a 3-D stack, bad spacing or options, non-finite values other than NaN.
    PatchError
        Too few usable profiles in some patch.
    """
    unknown = sorted(set(options) - {f.name for f in dataclasses.fields(Options)})
    if unknown:
        raise UnknownOptionError(
            f"patch_roughness_batch() got unexpected keyword arguments {unknown[:5]}"
        )
    opt = Options(**options)
    spacing = check_spacing(spacing)
    opt.check_omega0()
    return _batch(_as_float(heights), spacing, opt)


class UnknownOptionError(InputError, TypeError):
    """An unknown keyword option (a TypeError too, as Python raises for a bad keyword)."""


def _as_float(heights: Any) -> np.ndarray:
    return as_heights(heights)


def _batch(arr: np.ndarray, spacing: float, opt: Options) -> list[PatchRoughness]:
    if arr.ndim != 3:
        raise InputError(
            f"heights must be a stack (patches, profiles, samples), got shape {arr.shape}"
        )
    if arr.shape[0] == 0:
        return []
    return _estimate(_checked_stack(arr, opt), spacing, opt)


def _checked_stack(arr: np.ndarray, opt: Options) -> np.ndarray:
    """``arr`` (patches, profiles, samples) after the shape checks; NaN passes."""
    if arr.size == 0:
        raise InputError(f"heights is empty (shape {arr.shape})")
    if arr.shape[-1] < 8:
        check_heights(arr.reshape(-1, arr.shape[-1]))  # raises: too few samples
    n = arr.shape[-1]
    if n > MAX_PROFILE:
        raise InputError(
            f"heights has {n} samples per profile; the estimator takes at most {MAX_PROFILE}: "
            "use a coarser spacing (m)"
        )
    seg = n if opt.nperseg is None else min(opt.nperseg, n)
    if arr.shape[1] > 1 and seg > MAX_SAMPLES:
        raise InputError(
            f"heights has {n} samples per profile (segment) and {arr.shape[1]} profiles; the "
            f"estimator takes at most {MAX_SAMPLES} per segment when it correlates profiles "
            "(its tables grow as the square): use a coarser spacing (m) or nperseg"
        )
    if arr[0].size > MAX_CELLS:
        raise InputError(f"a patch of {arr[0].size} cells (shape {arr.shape}); at most {MAX_CELLS}")
    if arr.shape[1] < opt.min_profiles:
        raise PatchError(f"the patch has {arr.shape[1]} profiles, need at least {opt.min_profiles}")
    return arr


def _estimate(
    arr: np.ndarray, spacing: float, opt: Options, n_dropped: int = 0, check: bool = True
) -> list[PatchRoughness]:
    """Estimates for a stack (patches, profiles, samples) of heights, in cache-sized chunks.

    With ``check``, patches with non-finite cells go through :func:`_with_gaps`. The
    single-segment path finds them in its own output (per-profile sums of squares), which
    saves a pass over the input; the Welch path checks up front.
    """
    n_patch, m, n = arr.shape
    fast = opt.single_segment(n)
    if check and not fast:
        finite = np.isfinite(arr).all(axis=(1, 2))
        if not finite.all():
            return _merge(
                finite,
                _estimate(arr[finite], spacing, opt, check=False),
                _with_gaps(arr[~finite], spacing, opt),
            )
    seg_n = n if fast or opt.nperseg is None else min(opt.nperseg, n)
    out: list[PatchRoughness] = []
    chunk = max(1, _CHUNK_CELLS // (m * n))  # keep chunks in cache
    for start in range(0, n_patch, chunk):
        part = arr[start : start + chunk]
        if fast:
            omega, p, ss = periodogram(part, spacing, opt.window)
            if check:
                finite = np.isfinite(ss).all(axis=1)
                if not finite.all():
                    out += _merge(
                        finite,
                        _estimate(part[finite], spacing, opt, n_dropped, False),
                        _with_gaps(part[~finite], spacing, opt),
                    )
                    continue
            spectra = Spectra(
                omega, p, -float(np.euler_gamma), np.sqrt(np.maximum(ss.sum(axis=1), 0.0) / (m * n))
            )
        else:
            omega, p, bias = spectrum(part, spacing, opt.window, opt.nperseg, opt.noverlap)
            spectra = Spectra(omega, p, bias, detrended_rms(part))
        out += fit(spectra, opt, spacing=spacing, n=n, seg_n=seg_n, n_dropped=n_dropped)
    return out


def _merge(mask: np.ndarray, where_true: list, where_false: list) -> list:
    """Interleave two result lists back into the order given by ``mask``."""
    t, f = iter(where_true), iter(where_false)
    return [next(t) if k else next(f) for k in mask]


def _with_gaps(arr: np.ndarray, spacing: float, opt: Options) -> list[PatchRoughness]:
    """Patches with missing cells: the gap policy, one patch at a time."""
    out = []
    for patch in arr:
        h = check_heights(patch)  # refuses infinities; NaN is missing data
        m = h.shape[0]
        filled, keep = fill_gaps(
            h, spacing, max_gap=opt.max_gap, max_gap_fraction=opt.max_gap_fraction
        )
        n_used = int(keep.sum())
        if n_used < opt.min_profiles:
            raise PatchError(
                f"only {n_used} of {m} profiles are usable (need {opt.min_profiles}); "
                f"{m - n_used} dropped for gaps longer than {opt.max_gap} m or more than "
                f"{opt.max_gap_fraction:.0%} missing"
            )
        if n_used < m:
            log.debug("dropped %d of %d profiles for gaps", m - n_used, m)
        out += _estimate(filled[keep][None], spacing, opt, m - n_used, check=False)
    return out


def profile_psd(
    heights: np.ndarray,
    spacing: float,
    *,
    window: str = "hann",
    nperseg: int | None = None,
    noverlap: int | None = None,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """One-sided PSD of every longitudinal profile of a height grid.

    Parameters
    ----------
    heights : ndarray, shape (n,) or (m, n)
        Elevation profiles in m along the rows, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    window : str
        Window name understood by :func:`scipy.signal.get_window`; default Hann.
    nperseg, noverlap : int, optional
        Welch segment length and overlap in samples; default one segment over the profile.
    max_gap, max_gap_fraction : float
        Gap policy (see :mod:`rough_map.psd`); max_gap in m.

    Returns
    -------
    omega : ndarray
        Wavenumbers in rad/m, ``2 pi k / (nperseg B)`` for k = 1 ... nperseg/2.
    psd : ndarray
        PSD in m^3/rad, shape ``(len(omega),)`` for a 1-D input, else ``(m, len(omega))``;
        rows of dropped profiles are NaN. The sum of ``psd * dOmega`` is the variance of
        the detrended profile (Parseval).
    """
    spacing = check_spacing(spacing)
    check_window(window)
    check_int("nperseg", nperseg, low=8, high=MAX_CELLS, unit="samples", none=True)
    check_int("noverlap", noverlap, low=0, high=MAX_CELLS, unit="samples", none=True)
    h = check_heights(heights)
    one = h.shape[0] == 1 and np.ndim(heights) == 1
    filled, keep = fill_gaps(h, spacing, max_gap=max_gap, max_gap_fraction=max_gap_fraction)
    safe = np.where(keep[:, None], filled, 0.0)
    omega, p, _ = spectrum(safe, spacing, window, nperseg, noverlap)
    p = p.astype(float)
    p[~keep] = np.nan
    return omega, (p[0] if one else p)
