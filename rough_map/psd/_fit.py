"""The power-law fit of a stack of spectra, with the corrections of ``method="unbiased"``,
the checks of the fit and the result, :class:`PatchRoughness`.

Every profile's log spectrum is fitted by a line ``ln P_k = b + w x_k`` in
``x = ln(Omega / omega0)``. The fit is linear in the log spectrum: ``w = sum(xc_k ln P_k) /
sum(xc_k^2)`` and ``b = sum(avg_k ln P_k) - w xm`` over the ordinates in the fit mask, so the
fits of all profiles are one matrix product with the two regressors (centred ln Omega,
mean), and any per-bin correction of the log spectrum enters through its own projection on
them (:class:`FitPlan`, :func:`project`). The unbiased method corrects the fit for

* the log-periodogram bias ``E[ln P_hat] - ln P`` (``-gamma`` for one segment,
  :func:`rough_map.psd._spectra.log_bias` for Welch), the same for every ordinate;
* the leakage of the detrend and the window (and the box filter of cell means), which
  depends on the waviness: it is interpolated in the tables of
  :mod:`rough_map.psd._corrections` at the patch's waviness, iterated three times;

and, with ``subtract_noise``, every fit takes the noise-floor correction of
:mod:`rough_map.psd._corrections`.

Does the patch follow its power law? R is ``Phi(omega0)``, at 1 rad/m, extrapolated from a
band of about 7-400 rad/m: on ground whose log spectrum curves over the band, it depends on
how the band is weighed (three fits of one paving patch spread 10x). Beside R and w a
reading therefore gives

* ``centre_psd``, the fitted PSD at the band's log centre ``omega_centre`` (the geometric
  mean of its first and last ordinate fitted, about 74 rad/m for the paper's patch): no
  extrapolation, and near where the line is least uncertain;
* ``band_rms``, the rms height in m over the ordinates fitted, from the patch-mean
  spectrum (the power of the profiles, arithmetic over them) less the noise floor and
  corrected for what the detrend, the window and the cells do to it (the leakage table at
  the patch's waviness);
* ``rms_ratio``, the rms that the fitted ``R Omega^w`` gives over the same ordinates over
  ``band_rms``: near 1 when the fit describes the patch's power; far from 1 when it does
  not (a patch dominated by a few profiles over boulders, whose geometric mean, the
  paper's ``exp(E[ln R_i])``, sits far below their power, or a fit that the noise floor
  or a curved spectrum pulled away);
* ``curvature`` (per (ln rad/m)^2) and ``curvature_z``: the quadratic term of the
  patch-mean log spectrum in ln Omega over the band, and how many of its own standard
  errors (from the scatter of the ordinates about the quadratic) it is from 0. Beyond
  :data:`CURVED_Z` the log spectrum is not a line over the band, and R is a property of
  the fit as much as of the ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from rough_map import iso8608
from rough_map.errors import PatchError
from rough_map.psd._corrections import (
    floor_correction,
    gap_filled_floor,
    interp_rows,
    lateral_log_gain,
    lateral_scale,
    lateral_scale_value,
    leakage,
    leakage_table,
    noise_reach,
)
from rough_map.psd._spectra import frozen, table_cache
from rough_map.psd._uncertainty import standard_errors
from rough_map.psd.options import Options


@dataclass(frozen=True)
class FitPlan:
    """Everything of the line fit that depends only on the geometry (cached, read-only).

    Attributes
    ----------
    mask : ndarray of bool, shape (bins,)
        Ordinates in the fit.
    x : ndarray
        ``ln(Omega / omega0)`` per ordinate.
    xm, sxx : float
        Mean of ``x`` over the mask and ``sum(xc^2)``.
    xc, avg : ndarray
        Centred ``x`` and the averaging weights (0 outside the mask).
    proj : ndarray, shape (2, bins), float32
        ``xc`` and ``avg`` as contiguous rows, for einsum's row loop on float32 log
        spectra.
    leak_x, leak_a : ndarray, shape (len(W_GRID),)
        Projections of the leakage table on ``xc`` and ``avg``.
    """

    mask: np.ndarray
    x: np.ndarray
    xm: float
    xc: np.ndarray
    sxx: float
    avg: np.ndarray
    proj: np.ndarray
    leak_x: np.ndarray
    leak_a: np.ndarray


@table_cache(64)
def fit_plan(
    n_bins: int, seg_n: int, method: str, spacing: float, omega0: float, window: str, gridding: str
) -> FitPlan:
    """The :class:`FitPlan` of ``n_bins`` ordinates of ``seg_n``-sample segments."""
    omega = 2.0 * np.pi * np.arange(1, n_bins + 1) / (seg_n * spacing)
    mask = np.ones(n_bins, dtype=bool)
    if method == "unbiased":
        mask[0] = False  # k = 1 is mostly removed by the detrending
        if seg_n % 2 == 0 and n_bins == seg_n // 2:
            mask[-1] = False  # Nyquist ordinate: one degree of freedom, half density
    x = np.log(omega / omega0)
    wts = mask.astype(float)
    cnt = wts.sum()
    xm = float(wts @ x) / cnt
    xc = (x - xm) * wts
    sxx = float(xc @ xc)
    avg = wts / cnt
    proj = np.stack([xc, avg]).astype(np.float32)
    table = leakage_table(seg_n, window, gridding)[:, :n_bins]
    leak_x, leak_a = table @ xc, table @ avg
    frozen(mask, x, xc, avg, proj, leak_x, leak_a)
    return FitPlan(mask, x, xm, xc, sxx, avg, proj, leak_x, leak_a)


@dataclass(frozen=True)
class Projections:
    """The log spectra of a stack projected on the fit's regressors.

    Attributes
    ----------
    mask : ndarray of bool, shape (patches, bins)
        Ordinates in each patch's fit.
    xm, sxx : ndarray, shape (patches,)
        Per patch: weighted mean of ``x`` over its mask, ``sum(wt (x - xm)^2)``.
    xc, avg : ndarray, shape (patches or 1, bins)
        Per patch: weighted centred ``x`` (``wt (x - xm)``) and averaging weights
        (``wt / sum(wt)``); the weights ``wt`` are 0 or 1 unless a noise floor was
        subtracted.
    yx, ym : ndarray, shape (patches, profiles)
        Projections of each profile's log spectrum on ``xc`` and ``avg``.
    leak_x, leak_a : ndarray, shape (patches, len(W_GRID))
        Projections of the leakage table on ``xc`` and ``avg``.
    """

    mask: np.ndarray
    xm: np.ndarray
    sxx: np.ndarray
    xc: np.ndarray
    avg: np.ndarray
    yx: np.ndarray
    ym: np.ndarray
    leak_x: np.ndarray
    leak_a: np.ndarray


def project(logp: np.ndarray, plan: FitPlan) -> Projections:
    """Projections with the plan's mask for every patch (float32 dot products)."""
    n_patch, m, n_bins = logp.shape
    rows = logp.reshape(-1, n_bins)
    # einsum's loop along each row (as in _row_dot, the sum does not depend on the stack).
    yx, ym = (np.einsum("ij,j->i", rows, v).astype(float) for v in plan.proj)
    return Projections(
        mask=np.broadcast_to(plan.mask, (n_patch, n_bins)),
        xm=np.full(n_patch, plan.xm),
        sxx=np.full(n_patch, plan.sxx),
        xc=plan.xc[None, :],
        avg=plan.avg[None, :],
        yx=yx.reshape(n_patch, m),
        ym=ym.reshape(n_patch, m),
        leak_x=np.broadcast_to(plan.leak_x, (n_patch, plan.leak_x.size)),
        leak_a=np.broadcast_to(plan.leak_a, (n_patch, plan.leak_a.size)),
    )


def project_masked(
    logp: np.ndarray, x: np.ndarray, weights: np.ndarray, table: np.ndarray
) -> Projections:
    """Projections of a weighted fit, with weights per patch and bin, shape (patches, bins)
    (0: the bin is out of the fit; a boolean mask gives the plain fit); ``table`` is the
    leakage table cut to the bins."""
    wts = np.ascontiguousarray(weights, dtype=float)  # row sums in one order
    mask = wts > 0
    cnt = wts.sum(axis=1)
    xm = _row_dot(wts, x) / cnt
    dev = x[None, :] - xm[:, None]
    xc = dev * wts
    sxx = (xc * dev).sum(axis=1)  # sum of w (x - xm)^2
    avg = wts / cnt[:, None]
    return Projections(
        mask=mask,
        xm=xm,
        sxx=sxx,
        xc=xc,
        avg=avg,
        yx=_row_dot(logp, xc.astype(np.float32)[:, None, :]).astype(float),
        ym=_row_dot(logp, avg.astype(np.float32)[:, None, :]).astype(float),
        leak_x=_row_dot(xc[:, None, :], table),
        leak_a=_row_dot(avg[:, None, :], table),
    )


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a * b).sum(axis=-1)``, broadcast: the dot products along the last axis, each
    computed alone. A matrix product or einsum would sum in an order that depends on how
    many patches are stacked, so a patch's estimate would change (in its last bits) with
    the batch it came in; a frame measured alone, as the online mapper does, must give
    the same numbers as in a traverse's chunk."""
    return np.multiply(a, b, order="C").sum(axis=-1)


#: |curvature_z| beyond which the log spectrum is taken as curved over the band.
CURVED_Z = 5.0
#: A reading whose fitted power over the band is more than this factor from the patch's
#: measured band power (in rms) contradicts its patch.
RMS_FACTOR = 2.0
#: The ordinates of one Hann periodogram are correlated with their neighbours: the
#: standard error of the quadratic term from independent residuals is this much too small
#: (measured on isotropic power-law patches: the z of their curvature then has unit spread).
_NEIGHBOURS = 2.4


def shape_statistics(
    mean_log: np.ndarray,
    mask: np.ndarray,
    x: np.ndarray,
    line: tuple[np.ndarray, np.ndarray],
    power: np.ndarray,
    omega: np.ndarray,
    omega0: float,
) -> dict[str, np.ndarray]:
    """The band's statistics of each patch (see the module's text).

    ``mean_log`` (patches, bins) is the corrected patch-mean log spectrum, ``mask``
    (patches, bins) the ordinates fitted, ``x`` their ``ln(Omega / omega0)``, ``line`` the
    patches' ``ln R`` and waviness, ``power`` (patches, bins) the patch-mean PSD in
    m^3/rad less its floor and corrected for leakage, ``omega`` the ordinates in rad/m.
    """
    b, w = line
    d_omega = float(omega[1] - omega[0]) if omega.size > 1 else 1.0
    wts = mask.astype(float)
    cnt = np.maximum(wts.sum(axis=1), 1.0)
    xm = (wts * x).sum(axis=1) / cnt
    xc = (x[None, :] - xm[:, None]) * wts
    sxx = np.maximum((xc * xc).sum(axis=1), 1e-300)
    q = xc * xc
    q -= ((q * wts).sum(axis=1) / cnt)[:, None] * wts  # orthogonal to the mean
    q -= ((q * xc).sum(axis=1) / sxx)[:, None] * xc  # and to the slope
    qq = np.maximum((q * q).sum(axis=1), 1e-300)
    r = np.where(mask, mean_log - (b[:, None] + w[:, None] * x[None, :]), 0.0)
    curvature = (q * r).sum(axis=1) / qq
    e = np.where(mask, r - curvature[:, None] * q, 0.0)
    dof = np.maximum(cnt - 3.0, 1.0)
    se = _NEIGHBOURS * np.sqrt((e * e).sum(axis=1) / dof / qq)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(se > 0, curvature / se, 0.0)
    model = np.exp(np.clip(b[:, None] + w[:, None] * x[None, :], -700.0, 700.0))
    fitted = np.sqrt((model * wts).sum(axis=1) * d_omega)
    band = np.sqrt(np.maximum(np.where(mask, power, 0.0).sum(axis=1), 0.0) * d_omega)
    # the band's log centre: halfway in ln Omega between its first and last ordinate
    lo = np.where(mask, x[None, :], np.inf).min(axis=1)
    hi = np.where(mask, x[None, :], -np.inf).max(axis=1)
    xmid = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), xm)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = np.where(band > 0, fitted / band, math.inf)
        centre = np.exp(b + w * xmid)
    return {
        "band_rms": band,
        "rms_ratio": ratio,
        "centre_psd": centre,
        "omega_centre": omega0 * np.exp(xmid),
        "curvature": curvature,
        "curvature_z": z,
    }


@dataclass(frozen=True, eq=False)
class PatchRoughness:
    """Roughness parameters of one patch.

    Attributes
    ----------
    R : float
        Overall energy, Phi(omega0) in m^3/rad (``exp(E[ln R_i])``).
    w : float
        Waviness (dimensionless slope of the log-log fit, ``E[w_i]``).
    sigma_R : float
        First-order standard deviation of R in m^3/rad (paper Eq. 8).
    sigma_w : float
        Standard deviation of the profile waviness.
    se_lnR : float
        Standard error of ``ln R`` (natural-log units): the uncertainty of the patch value
        itself, allowing for the correlation between neighbouring profiles
        (:mod:`rough_map.psd._uncertainty`); ``R * exp(+-1.96 se_lnR)`` is a 95 % interval.
        At least ``sigma_lnR / sqrt(n_profiles)``; NaN for a single profile.
    se_w : float
        Standard error of ``w`` (the same way); 0 when the waviness was fixed.
    rms : float
        Rms of the detrended profiles in m.
    iso_class : str
        ISO 8608 class letter of ``R``.
    omega : ndarray
        Wavenumbers ``Omega_k`` in rad/m, k = 1 ... n/2.
    psd : ndarray
        Patch-mean one-sided PSD in m^3/rad on ``omega`` (arithmetic mean over profiles).
    profile_R, profile_w : ndarray
        Per-profile fits (m^3/rad and dimensionless) of the profiles used.
    n_profiles : int
        Profiles used.
    n_dropped : int
        Profiles dropped by the gap policy.
    spacing : float
        Sample spacing B in m.
    length : float
        Profile length L = n B in m.
    fit_mask : ndarray of bool
        Which ordinates of ``omega`` entered the fit.
    fit_residual : float
        Rms residual of the per-profile log-log fits (natural-log units).
    noise_psd : float
        Noise floor in m^3/rad that was given (NaN if none).
    noise_subtracted : bool
        Whether the floor was subtracted before the fit.
    method : str
        ``"unbiased"`` or ``"paper"``.
    omega0 : float
        Reference wavenumber of R in rad/m.
    lateral_scale : float
        How fast the ground decorrelates across the profiles relative to along them
        (dimensionless, :mod:`rough_map.psd._corrections`): 1 isotropic, 0 the same across
        the patch (swept or ridged ground), above 1 rougher across than along. Read from
        adjacent profiles of cell-mean grids (``unbiased``, one segment), where it
        corrects the fit; NaN where it is not read.
    omega_noise : float
        Highest wavenumber in rad/m up to which the terrain's power stays at least the
        noise floor's (``rough_map.psd._corrections.noise_reach``): the band where the ground,
        not the sensor, dominates. Above it the ordinates still enter the fit with small
        weights. 0 where the noise dominates from the first ordinate of the fit on; NaN
        when no floor was subtracted.
    band_rms : float
        Rms height in m over the ordinates fitted, from the patch-mean spectrum less the
        noise floor, corrected for the detrend, the window and the cells: a roughness that
        needs no extrapolation (:mod:`rough_map.psd._fit`).
    rms_ratio : float
        The rms that the fitted ``R Omega^w`` gives over the same ordinates, over
        ``band_rms``: within 1/2 to 2 (:attr:`consistent`) when the fit describes the
        patch's power.
    centre_psd : float
        The fitted PSD in m^3/rad at ``omega_centre``: R without the extrapolation.
    omega_centre : float
        The band's log centre in rad/m: the geometric mean of its first and last ordinate
        fitted.
    curvature : float
        Quadratic term of the patch-mean log spectrum in ln Omega over the band, per
        (ln rad/m)^2: negative where the spectrum falls ever faster (smooth ground, a block
        scale), positive where it flattens (a noise floor left in).
    curvature_z : float
        ``curvature`` over its standard error from the ordinates' scatter: beyond
        +-:data:`rough_map.psd._fit.CURVED_Z` the log spectrum is not a line over the
        band (:attr:`power_law` is False) and R at ``omega0`` depends on the fit.
    """

    R: float
    w: float
    sigma_R: float
    sigma_w: float
    se_lnR: float
    se_w: float
    rms: float
    iso_class: str
    omega: np.ndarray
    psd: np.ndarray
    profile_R: np.ndarray
    profile_w: np.ndarray
    n_profiles: int
    n_dropped: int
    spacing: float
    length: float
    fit_mask: np.ndarray
    fit_residual: float
    noise_psd: float
    noise_subtracted: bool
    method: str
    omega0: float
    lateral_scale: float = math.nan
    omega_noise: float = math.nan
    band_rms: float = math.nan
    rms_ratio: float = math.nan
    centre_psd: float = math.nan
    omega_centre: float = math.nan
    curvature: float = math.nan
    curvature_z: float = math.nan

    @classmethod
    def from_fields(cls, values: dict[str, Any]) -> PatchRoughness:
        """``PatchRoughness(**values)`` for a dict that names every field, built in a tenth
        of the time: a frozen dataclass sets each of its 30 fields through
        ``object.__setattr__``, which is what the batched estimator would spend most of
        its per-patch time on. :class:`TypeError` for a missing or unknown field, as the
        constructor would refuse it."""
        if values.keys() != _FIELDS:
            missing, extra = _FIELDS - values.keys(), values.keys() - _FIELDS
            raise TypeError(
                f"PatchRoughness fields: missing {sorted(missing)}, unknown {sorted(extra)}"
            )
        out = object.__new__(cls)
        out.__dict__.update(values)
        return out

    @property
    def consistent(self) -> bool:
        """The fit reproduces the patch's band rms within a factor of
        :data:`~rough_map.psd._fit.RMS_FACTOR` (2)."""
        return bool(1.0 / RMS_FACTOR <= self.rms_ratio <= RMS_FACTOR)

    @property
    def power_law(self) -> bool:
        """The log spectrum is a line over the band, within
        :data:`~rough_map.psd._fit.CURVED_Z` standard errors of its curvature."""
        return bool(abs(self.curvature_z) <= CURVED_Z)

    @property
    def sigma_lnR(self) -> float:
        """Standard deviation of ln R_i (dimensionless)."""
        return self.sigma_R / self.R if self.R > 0 else math.nan

    def as_dict(self) -> dict[str, float | int | str | bool]:
        """Scalar fields, for tables and JSON."""
        return {
            "R": self.R,
            "w": self.w,
            "sigma_R": self.sigma_R,
            "sigma_w": self.sigma_w,
            "se_lnR": self.se_lnR,
            "se_w": self.se_w,
            "rms": self.rms,
            "iso_class": self.iso_class,
            "n_profiles": self.n_profiles,
            "n_dropped": self.n_dropped,
            "fit_residual": self.fit_residual,
            "noise_psd": self.noise_psd,
            "method": self.method,
            "lateral_scale": self.lateral_scale,
            "omega_noise": self.omega_noise,
            "band_rms": self.band_rms,
            "rms_ratio": self.rms_ratio,
            "consistent": self.consistent,
            "centre_psd": self.centre_psd,
            "omega_centre": self.omega_centre,
            "curvature": self.curvature,
            "curvature_z": self.curvature_z,
            "power_law": self.power_law,
        }


_FIELDS = frozenset(f.name for f in fields(PatchRoughness))


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
        of cell means (:mod:`rough_map.psd._corrections`); None: the ground is taken as
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
    one that the cell-mean tables assume (:mod:`rough_map.psd._corrections`), at the
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
    (``filled``: rows of :func:`rough_map.psd._corrections.gap_statistics`, None for no gaps,
    see :func:`rough_map.psd._corrections.gap_filled_floor`); ``n`` is the profile length and
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
    subtracted) and the band statistics (:func:`rough_map.psd._fit.shape_statistics`)
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
