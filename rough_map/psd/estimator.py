"""The public estimator: :func:`patch_roughness`, :func:`patch_roughness_batch`,
:func:`profile_psd` (the method is described in :mod:`rough_map.psd`).

These are thin wrappers in the manner of :func:`scipy.signal.welch`, taking one
:class:`~rough_map.psd.Options`: they check the input, apply the gap policy and compute the
spectra (:mod:`rough_map.psd._spectra`) and fit them (:mod:`rough_map.psd._fit`).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from rough_map.errors import InputError, PatchError
from rough_map.limits import LIMITS
from rough_map.psd._corrections import check_floor, gap_statistics
from rough_map.psd._fit import PatchRoughness, Spectra, fit
from rough_map.psd._spectra import (
    adjacent_cross,
    as_heights,
    check_heights,
    check_spacing,
    detrended_dft,
    detrended_rms,
    fill_gaps,
    power,
    spectrum,
)
from rough_map.psd.options import Options

log = logging.getLogger(__name__)

#: Heights per chunk of a batch (patches x profiles x samples), to stay in cache.
_CHUNK_CELLS = 800_000


def patch_roughness(
    heights: np.ndarray, spacing: float, options: Options | None = None, **changes: Any
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
    options : Options, optional
        The estimator's options (:class:`~rough_map.psd.Options`, where each is described
        with its unit); default ``Options()``.
    **changes
        Fields of ``options`` changed by keyword (``method="paper"``).

    Returns
    -------
    PatchRoughness

    Raises
    ------
    InputError
        Bad shape, spacing, options or non-finite values other than NaN.
    PatchError
        Too few usable profiles.
    """
    opt = Options.of(options, changes, "patch_roughness")
    spacing = check_spacing(spacing)
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
    stack = _checked_stack(arr.reshape(1, -1, arr.shape[-1]), opt)
    return _raised(_estimate(stack, spacing, opt, _floors(opt, 1)))[0]


def patch_roughness_batch(
    heights: np.ndarray, spacing: float, options: Options | None = None, **changes: Any
) -> list[PatchRoughness]:
    """:func:`patch_roughness` of a stack of patches, in one vectorised pass.

    Parameters
    ----------
    heights : ndarray, shape (p, m, n)
        ``p`` height grids in m of ``m`` profiles of ``n`` samples, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    options, **changes
        The estimator's options, as for :func:`patch_roughness`.

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
    opt = Options.of(options, changes, "patch_roughness_batch")
    spacing = check_spacing(spacing)
    return _raised(_batch(_as_float(heights), spacing, opt, None))


def patch_roughness_each(
    heights: np.ndarray, spacing: float, options: Options | None = None, **changes: Any
) -> list[PatchRoughness | PatchError]:
    """:func:`patch_roughness_batch`, but a patch the estimator refuses (too few usable
    profiles, too few wavenumbers above its noise floor) gets its
    :class:`~rough_map.errors.PatchError` in its place instead of stopping the batch, and
    each patch may have its own noise floor.

    A patch's estimate does not depend on the patches stacked with it (the same numbers,
    to the last bit, as :func:`patch_roughness` of that patch alone), so frames can be
    measured in batches and one at a time alike.

    Parameters
    ----------
    heights : ndarray, shape (p, m, n)
        ``p`` height grids in m, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    options, **changes
        The estimator's options, as for :func:`patch_roughness`; here ``noise_psd`` may
        also be an array of shape (p,): the noise floor of each patch in m^3/rad.

    Returns
    -------
    list of PatchRoughness or PatchError
        One per patch, in order.

    Raises
    ------
    InputError
        What :func:`patch_roughness_batch` raises for the whole stack (shape, spacing,
        options, infinite values).
    """
    arr = _as_float(heights)
    floors: np.ndarray | None = None
    if changes.get("noise_psd") is not None and np.ndim(changes["noise_psd"]) > 0:
        floors = np.asarray(changes.pop("noise_psd"), dtype=float)
        if arr.ndim != 3 or floors.shape != (arr.shape[0],):
            raise InputError(
                f"noise_psd has shape {floors.shape}; give one floor (m^3/rad) or one per "
                f"patch of the stack of shape {arr.shape}"
            )
        if not (np.isfinite(floors).all() and (floors >= 0).all() and (floors <= 1e6).all()):
            raise InputError("noise_psd must be finite floors in [0, 1e6] m^3/rad")
    opt = Options.of(options, changes, "patch_roughness_each")
    spacing = check_spacing(spacing)
    return _batch(arr, spacing, opt, floors)


def _as_float(heights: Any) -> np.ndarray:
    return as_heights(heights)


#: What the estimator gives for one patch: its estimate, or why it refused it.
Outcome = PatchRoughness | PatchError


def _batch(
    arr: np.ndarray, spacing: float, opt: Options, floors: np.ndarray | None
) -> list[Outcome]:
    if arr.ndim != 3:
        raise InputError(
            f"heights must be a stack (patches, profiles, samples), got shape {arr.shape}"
        )
    if arr.shape[0] == 0:
        return []
    stack = _checked_stack(arr, opt)
    return _estimate(stack, spacing, opt, _floors(opt, arr.shape[0]) if floors is None else floors)


def _floors(opt: Options, n_patch: int) -> np.ndarray | None:
    """``opt``'s noise floor (m^3/rad) for each patch, checked when it is subtracted; None
    without one."""
    if opt.subtract_noise:
        return np.full(n_patch, check_floor(opt.noise_psd))
    return None if opt.noise_psd is None else np.full(n_patch, float(opt.noise_psd))


def _raised(outcomes: list[Outcome]) -> list[PatchRoughness]:
    """The estimates, or the first patch's refusal raised."""
    for r in outcomes:
        if isinstance(r, PatchError):
            raise r
    return outcomes  # type: ignore[return-value]  # no PatchError left


def _checked_stack(arr: np.ndarray, opt: Options) -> np.ndarray:
    """``arr`` (patches, profiles, samples) after the shape checks; NaN passes."""
    if arr.size == 0:
        raise InputError(f"heights is empty (shape {arr.shape})")
    if arr.shape[-1] < 8:
        check_heights(arr.reshape(-1, arr.shape[-1]))  # raises: too few samples
    n = arr.shape[-1]
    if n > LIMITS.profile_samples:
        raise InputError(
            f"heights has {n} samples per profile; the estimator takes at most "
            f"{LIMITS.profile_samples}: use a coarser spacing (m)"
        )
    seg = n if opt.nperseg is None else min(opt.nperseg, n)
    if arr.shape[1] > 1 and seg > LIMITS.patch_samples:
        raise InputError(
            f"heights has {n} samples per profile (segment) and {arr.shape[1]} profiles; the "
            f"estimator takes at most {LIMITS.patch_samples} per segment when it correlates "
            "profiles (its tables grow as the square): use a coarser spacing (m) or nperseg"
        )
    if arr[0].size > LIMITS.grid_cells:
        raise InputError(
            f"a patch of {arr[0].size} cells (shape {arr.shape}); at most {LIMITS.grid_cells}"
        )
    if arr.shape[1] < opt.min_profiles:
        raise PatchError(f"the patch has {arr.shape[1]} profiles, need at least {opt.min_profiles}")
    return arr


def _estimate(
    arr: np.ndarray,
    spacing: float,
    opt: Options,
    floors: np.ndarray | None,
    n_dropped: int = 0,
    check: bool = True,
    filled: np.ndarray | None = None,
) -> list[Outcome]:
    """Estimates for a stack (patches, profiles, samples) of heights, in cache-sized chunks;
    ``floors`` is each patch's noise floor in m^3/rad (None: none known), subtracted when
    ``opt`` says so; ``filled`` what the gap policy did to each patch (rows of
    :func:`rough_map.psd._corrections.gap_statistics`; None: nothing).

    With ``check``, patches with non-finite cells go through :func:`_with_gaps`: found up
    front from the stack's sum (one cheap pass), and for the rare patch whose values only
    overflow later, by the single-segment path in its own output (per-profile sums of
    squares).
    """
    n_patch, m, n = arr.shape
    fast = opt.single_segment(n)
    # A sum is cheaper than a periodogram: patches whose sum is not finite have gaps (or
    # overflow, which the gap path also takes) and skip the periodogram of the fast path.
    with np.errstate(over="ignore", invalid="ignore"):
        gaps = check and (not fast or not np.isfinite(arr.sum()))
    if gaps:
        finite = np.isfinite(arr).all(axis=(1, 2))
        if not finite.all():
            return _split(finite, arr, floors, spacing, opt, n_dropped)
    seg_n = n if fast or opt.nperseg is None else min(opt.nperseg, n)
    out: list[Outcome] = []
    chunk = max(1, _CHUNK_CELLS // (m * n))  # keep chunks in cache
    for start in range(0, n_patch, chunk):
        part = arr[start : start + chunk]
        noise = None if floors is None else floors[start : start + chunk]
        gaps_filled = None if filled is None else filled[start : start + chunk]
        cross = None
        if fast:
            omega, dft, ss = detrended_dft(part, spacing, opt.window)
            if opt.gridding == "cell_mean":
                cross = adjacent_cross(dft, n)
            p = power(dft, n, overwrite=True)
            if check:
                finite = np.isfinite(ss).all(axis=1)
                if not finite.all():
                    out += _split(finite, part, noise, spacing, opt, n_dropped)
                    continue
            spectra = Spectra(
                omega,
                p,
                -float(np.euler_gamma),
                np.sqrt(np.maximum(ss.sum(axis=1), 0.0) / (m * n)),
                cross,
            )
        else:
            omega, p, bias = spectrum(part, spacing, opt.window, opt.nperseg, opt.noverlap)
            spectra = Spectra(omega, p, bias, detrended_rms(part))
        out += fit(
            spectra,
            opt,
            noise,
            spacing=spacing,
            n=n,
            seg_n=seg_n,
            n_dropped=n_dropped,
            filled=gaps_filled,
        )
    return out


def _split(
    finite: np.ndarray,
    arr: np.ndarray,
    floors: np.ndarray | None,
    spacing: float,
    opt: Options,
    n_dropped: int,
) -> list[Outcome]:
    """The finite patches estimated as they are, the others through the gap policy, back
    in order."""

    def sub(mask: np.ndarray) -> np.ndarray | None:
        return None if floors is None else floors[mask]

    clean = _estimate(arr[finite], spacing, opt, sub(finite), n_dropped, check=False)
    gapped = _with_gaps(arr[~finite], spacing, opt, sub(~finite))
    t, f = iter(clean), iter(gapped)
    return [next(t) if k else next(f) for k in finite]


def _with_gaps(
    arr: np.ndarray, spacing: float, opt: Options, floors: np.ndarray | None
) -> list[Outcome]:
    """Patches with missing cells: the gap policy, patch by patch (filling ``arr``, a
    stack of the caller's that it gives up, in place); then the patches that keep the same
    number of profiles are estimated together."""
    n_patch, m, n = arr.shape
    out: list[Outcome | None] = [None] * n_patch
    kept: dict[int, np.ndarray] = {}
    gaps: dict[int, tuple[float, float]] = {}  # what the gap policy did (gap_statistics)
    chunk = max(1, _CHUNK_CELLS // (m * n))
    for start in range(0, n_patch, chunk):
        # the gap policy works profile by profile: on all the chunk's profiles at once
        rows = check_heights(arr[start : start + chunk].reshape(-1, n))  # NaN passes, inf not
        missing = np.isnan(rows).reshape(-1, m, n)  # before the filling, which is in place
        filled, keep = fill_gaps(
            rows,
            spacing,
            max_gap=opt.max_gap,
            max_gap_fraction=opt.max_gap_fraction,
            copy=False,
        )
        grids, uses = filled.reshape(-1, m, n), keep.reshape(-1, m)
        for j, (grid, used) in enumerate(zip(grids, uses, strict=True)):
            i, n_used = start + j, int(used.sum())
            if n_used < opt.min_profiles:
                out[i] = PatchError(
                    f"only {n_used} of {m} profiles are usable (need {opt.min_profiles}); "
                    f"{m - n_used} dropped for gaps longer than {opt.max_gap} m or more than "
                    f"{opt.max_gap_fraction:.0%} missing"
                )
                continue
            if n_used < m:
                log.debug("dropped %d of %d profiles for gaps", m - n_used, m)
            kept[i] = grid[used]
            gaps[i] = gap_statistics(kept[i], missing[j][used])
    for n_used in sorted({k.shape[0] for k in kept.values()}):
        group = [i for i, k in kept.items() if k.shape[0] == n_used]
        stack = np.stack([kept[i] for i in group])
        noise = None if floors is None else floors[group]
        part = np.array([gaps[i] for i in group])
        results = _estimate(stack, spacing, opt, noise, m - n_used, check=False, filled=part)
        for i, result in zip(group, results, strict=True):
            out[i] = result
    return [r for r in out if r is not None]


def profile_psd(
    heights: np.ndarray, spacing: float, options: Options | None = None, **changes: Any
) -> tuple[np.ndarray, np.ndarray]:
    """One-sided PSD of every longitudinal profile of a height grid.

    Parameters
    ----------
    heights : ndarray, shape (n,) or (m, n)
        Elevation profiles in m along the rows, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    options, **changes
        The estimator's options, as for :func:`patch_roughness`; the spectra use
        ``window``, ``nperseg``, ``noverlap`` and the gap policy (``max_gap`` in m,
        ``max_gap_fraction``).

    Returns
    -------
    omega : ndarray
        Wavenumbers in rad/m, ``2 pi k / (nperseg B)`` for k = 1 ... nperseg/2.
    psd : ndarray
        PSD in m^3/rad, shape ``(len(omega),)`` for a 1-D input, else ``(m, len(omega))``;
        rows of dropped profiles are NaN. The sum of ``psd * dOmega`` is the variance of
        the detrended profile (Parseval).
    """
    opt = Options.of(options, changes, "profile_psd")
    spacing = check_spacing(spacing)
    h = check_heights(heights)
    one = h.shape[0] == 1 and np.ndim(heights) == 1
    filled, keep = fill_gaps(h, spacing, max_gap=opt.max_gap, max_gap_fraction=opt.max_gap_fraction)
    safe = np.where(keep[:, None], filled, 0.0)
    omega, p, _ = spectrum(safe, spacing, opt.window, opt.nperseg, opt.noverlap)
    p = p.astype(float)
    p[~keep] = np.nan
    return omega, (p[0] if one else p)
