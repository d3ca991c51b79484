"""The power-law fit of a stack of spectra, with the corrections of ``method="unbiased"``.

Every profile's log spectrum is fitted by a line in ``ln(Omega / omega0)``
(:mod:`rough_map.psd._regression`). The unbiased method corrects it for

* the log-periodogram bias ``E[ln P_hat] - ln P`` (``-gamma`` for one segment,
  :func:`rough_map.psd._spectra.log_bias` for Welch), the same for every ordinate;
* the leakage of the detrend and the window (and the box filter of cell means), which
  depends on the waviness: it is interpolated in the tables of
  :mod:`rough_map.psd._leakage` at the patch's waviness, iterated three times;

and, with ``subtract_noise``, every fit takes the noise-floor correction of
:mod:`rough_map.psd._noise`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from rough_map import iso8608
from rough_map.errors import PatchError
from rough_map.psd._lateral import lateral_log_gain, lateral_scale, lateral_scale_value
from rough_map.psd._leakage import interp_rows, leakage, leakage_table
from rough_map.psd._noise import floor_correction, gap_filled_floor, noise_reach
from rough_map.psd._options import Options
from rough_map.psd._regression import Projections, fit_plan, project, project_masked
from rough_map.psd._result import PatchRoughness
from rough_map.psd._shape import shape_statistics
from rough_map.psd._uncertainty import standard_errors


class Spectra(NamedTuple):
    """Spectra of a stack of patches, the input of :func:`fit`.

    Attributes
    ----------
    omega : ndarray, shape (bins,)
        Wavenumbers in rad/m.
    p : ndarray, shape (patches, profiles, bins)
        One-sided PSD in m^3/rad.
    bias : float
        ``E[ln(P_hat / P)]`` of an ordinate.
    rms : ndarray, shape (patches,)
        Rms of the detrended profiles in m.
    cross : ndarray, shape (patches, bins), or None
        Mean cross-spectrum of adjacent profiles in m^3/rad, for the lateral correction
        of cell means (:mod:`rough_map.psd._lateral`); None: the ground is taken as
        isotropic.
    """

    omega: np.ndarray
    p: np.ndarray
    bias: float
    rms: np.ndarray
    cross: np.ndarray | None = None


def _leakage_offsets(
    pr: Projections, sx: np.ndarray, waviness: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Projections on (xc, avg) of the leakage offset at each patch's waviness."""
    n_patch = pr.yx.shape[0]
    if waviness is not None:
        w_patch = np.full(n_patch, float(waviness))
    else:
        # The window/detrend offset depends (weakly) on the waviness: iterated three times.
        ym = pr.yx.mean(axis=1) + sx
        lx = np.zeros(n_patch)
        for _ in range(2):
            lx = interp_rows((ym - lx) / pr.sxx, pr.leak_x)
        w_patch = (ym - lx) / pr.sxx
    lx = interp_rows(w_patch, pr.leak_x)
    la = interp_rows(w_patch, pr.leak_a)
    return lx, la


def _lateral_correction(
    spectra: Spectra,
    mean_psd: np.ndarray,
    floor: np.ndarray,
    pr: Projections,
    sx: np.ndarray,
    opt: Options,
    seg_n: int,
    spacing: float,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """Per-bin log gain (patches, bins) of each patch's lateral scale over the isotropic
    one that the cell-mean tables assume (:mod:`rough_map.psd._lateral`), at the
    waviness the fit finds without it, the lateral scale ``a`` of each patch, and the
    scale its rows show (a fractional index into ``A_NODES``, for the standard errors).

    Only ``unbiased`` fits of cell means with the cross-spectrum of one segment are
    corrected; the others get None and scales of NaN (not read)."""
    cross = spectra.cross
    if opt.method != "unbiased" or opt.gridding != "cell_mean" or cross is None:
        nan = np.full(mean_psd.shape[0], math.nan)
        return None, nan, nan
    if opt.waviness is not None:
        w = np.full(mean_psd.shape[0], float(opt.waviness))
    else:  # one step of the leakage iteration of _leakage_offsets is close enough here
        ym = pr.yx.mean(axis=1) + sx
        w = (ym - interp_rows(ym / pr.sxx, pr.leak_x)) / pr.sxx
    usable = np.broadcast_to(pr.mask, mean_psd.shape)
    position = lateral_scale(cross, mean_psd, floor, w, usable, seg_n)
    gain = lateral_log_gain(position, w, seg_n)[:, : mean_psd.shape[1]]
    # Rows wider and further apart than the step along them show the ground's lateral
    # scale times their ratio (the family is stretched across): the gain is read at what
    # the rows show, the scale is reported per step along the profiles.
    ratio = 1.0 if opt.row_spacing is None else opt.row_spacing / spacing
    return gain, lateral_scale_value(position) / ratio, position


def fit(
    spectra: Spectra,
    opt: Options,
    floors: np.ndarray | None,
    *,
    spacing: float,
    n: int,
    seg_n: int,
    n_dropped: int,
    filled: np.ndarray | None = None,
) -> list[PatchRoughness | PatchError]:
    """Vectorised log-log fit of ``spectra.p`` (patches, profiles, bins).

    ``floors`` is each patch's noise floor in m^3/rad (None: none known), subtracted when
    ``opt`` says so, with what the gap filling did to it and to the terrain's power
    (``filled``: rows of :func:`rough_map.psd._noise.gap_statistics`, None for no gaps,
    see :func:`rough_map.psd._noise.gap_filled_floor`); ``n`` is the profile length and
    ``seg_n`` the samples per spectral segment. The per-bin corrections (bias, leakage,
    noise) are the same for every profile of a patch, so the line fits are computed once
    on the raw log spectra and the corrections enter through their projections on the
    fit's two regressors. A patch with too few wavenumbers above its floor gets a
    :class:`PatchError` in its place.
    """
    p, bias = spectra.p, spectra.bias
    n_bins = p.shape[2]
    unbiased = opt.method == "unbiased"
    plan = fit_plan(n_bins, seg_n, opt.method, spacing, opt.omega0, opt.window, opt.gridding)
    mean_psd = p.mean(axis=1, dtype=np.float64)
    noise = np.full(p.shape[0], math.nan) if floors is None else floors
    shift: np.ndarray
    floor_or_zero: np.ndarray = np.zeros((1, n_bins))
    log_gain: np.ndarray | float = 0.0  # of the terrain's power through the gap filling
    reach = np.full(p.shape[0], math.nan)  # omega_noise of each patch
    if opt.subtract_noise:
        floor, gain = gap_filled_floor(noise, filled, n_bins, seg_n, spacing)
        floor_or_zero = floor
        log_gain = np.log(gain)
        shift, weights, short = floor_correction(mean_psd, floor, plan.mask)
        reach = noise_reach(shift, plan.mask, spectra.omega)
        shift = shift - np.log(gain)
        if short.any():
            return _without(short, spectra, opt, noise, spacing, n, seg_n, n_dropped, filled)
    logp = np.log(np.maximum(p, np.float32(1e-38)))
    if opt.subtract_noise:
        table = leakage_table(seg_n, opt.window, opt.gridding)[:, :n_bins]
        pr = project_masked(logp, plan.x, weights, table)
    else:
        shift = np.zeros((1, n_bins))
        pr = project(logp, plan)
    # Projections of the per-bin corrections on (centred x, mean).
    sx = (shift * pr.xc).sum(axis=1)
    lateral, scale, rows_scale = _lateral_correction(
        spectra, mean_psd, floor_or_zero, pr, sx, opt, seg_n, spacing
    )
    if lateral is not None:
        shift = shift - lateral
        sx = (shift * pr.xc).sum(axis=1)
    sa = (shift * pr.avg).sum(axis=1)
    if unbiased:
        # E[ln P_hat] = ln P + bias: the bias projects to 0 on xc and to `bias` on the mean.
        sa = sa - bias
        lx, la = _leakage_offsets(pr, sx, opt.waviness)
        sx = sx - lx
        sa = sa - la
    if opt.waviness is None:
        wv = (pr.yx + sx[:, None]) / pr.sxx[:, None]
    else:
        wv = np.full_like(pr.yx, float(opt.waviness))
    b = pr.ym + sa[:, None] - wv * pr.xm[:, None]
    wm = wv.mean(axis=1)
    bm = b.mean(axis=1)
    adj = shift - bias if unbiased else shift
    leak: np.ndarray | float = 0.0
    if unbiased:
        leak = leakage(seg_n, opt.window, wm, opt.gridding)[:, :n_bins]
        adj = adj - leak
    # Residual of the patch-mean log spectrum about the patch line (shape of the spectrum).
    mean_log = logp.mean(axis=1, dtype=np.float64) + adj
    resid = np.where(pr.mask, mean_log - bm[:, None] - wm[:, None] * plan.x[None, :], 0.0)
    fit_res = np.sqrt((resid * resid).sum(axis=1) / pr.mask.sum(axis=1))
    # The band's own power (arithmetic over the profiles) with the same corrections.
    correction = log_gain + leak + (0.0 if lateral is None else lateral)
    power = np.maximum(mean_psd - floor_or_zero, 0.0) * np.exp(-correction)
    shape = shape_statistics(mean_log, pr.mask, plan.x, (bm, wm), power, spectra.omega, opt.omega0)
    # Standard errors of the patch means, with the correlation between profiles.
    se = standard_errors(b, wv, wm, pr, opt, seg_n=seg_n, bias=bias, scale=rows_scale)
    read = (scale, reach, shape)
    return list(
        _results(
            spectra, opt, b, wv, mean_psd, pr.mask, fit_res, noise, spacing, n, n_dropped, se, read
        )
    )


def _without(
    short: np.ndarray,
    spectra: Spectra,
    opt: Options,
    noise: np.ndarray,
    spacing: float,
    n: int,
    seg_n: int,
    n_dropped: int,
    filled: np.ndarray | None,
) -> list[PatchRoughness | PatchError]:
    """The fit of the patches that keep enough wavenumbers above their floor, and a
    :class:`PatchError` for the ``short`` ones, in order."""
    keep = ~short
    cross = None if spectra.cross is None else spectra.cross[keep]
    kept = Spectra(spectra.omega, spectra.p[keep], spectra.bias, spectra.rms[keep], cross)
    part = None if filled is None else filled[keep]
    fitted = iter(
        fit(
            kept,
            opt,
            noise[keep],
            spacing=spacing,
            n=n,
            seg_n=seg_n,
            n_dropped=n_dropped,
            filled=part,
        )
        if keep.any()
        else []
    )
    return [
        PatchError(
            "fewer than 3 wavenumbers above the noise floor; the patch is too smooth "
            f"for this sensor (noise floor {noise[i]:.3g} m^3/rad)"
        )
        if short[i]
        else next(fitted)
        for i in range(short.size)
    ]


def _results(
    spectra: Spectra,
    opt: Options,
    b: np.ndarray,
    wv: np.ndarray,
    mean_psd: np.ndarray,
    mask: np.ndarray,
    fit_res: np.ndarray,
    noise: np.ndarray,
    spacing: float,
    n: int,
    n_dropped: int,
    se: tuple[np.ndarray, np.ndarray],
    read: tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]],
) -> list[PatchRoughness]:
    """One :class:`PatchRoughness` per patch from the per-profile intercepts ``b`` and
    slopes ``wv`` (patches, profiles), the standard errors ``se`` of their means, and
    ``read``: the lateral scale (NaN: not read), ``omega_noise`` in rad/m (NaN: no floor
    subtracted) and the band statistics (:func:`rough_map.psd._shape.shape_statistics`)
    of each patch."""
    scale, reach, shape = read
    n_patch, m = b.shape
    wm = wv.mean(axis=1)
    bm = b.mean(axis=1)
    R = np.exp(bm)
    sb = b.std(axis=1, ddof=1) if m > 1 else np.full(n_patch, np.nan)
    sw = wv.std(axis=1, ddof=1) if m > 1 else np.full(n_patch, np.nan)
    letters = np.asarray(iso8608.iso_class(R)).tolist()
    # Python floats up front (tolist): one conversion per array, not per element.
    per_patch = {
        "R": R.tolist(),
        "w": wm.tolist(),
        "sigma_R": (R * sb).tolist(),
        "sigma_w": sw.tolist(),
        "se_lnR": se[0].tolist(),
        "se_w": se[1].tolist(),
        "rms": np.asarray(spectra.rms, dtype=float).tolist(),
        "iso_class": [str(c) for c in letters],
        "psd": list(mean_psd),
        "profile_R": list(np.exp(b)),
        "profile_w": list(wv),
        "fit_mask": list(mask),
        "fit_residual": fit_res.tolist(),
        "noise_psd": noise.tolist(),
        "lateral_scale": scale.tolist(),
        "omega_noise": reach.tolist(),
        **{k: np.asarray(v, dtype=float).tolist() for k, v in shape.items()},
    }
    common = {
        "omega": spectra.omega,
        "n_profiles": m,
        "n_dropped": n_dropped,
        "spacing": spacing,
        "length": n * spacing,
        "noise_subtracted": bool(opt.subtract_noise),
        "method": opt.method,
        "omega0": opt.omega0,
    }
    columns = list(per_patch.items())
    return [
        PatchRoughness.from_fields({**common, **{k: v[i] for k, v in columns}})
        for i in range(n_patch)
    ]
