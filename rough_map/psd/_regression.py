"""The log-log line fit as projections on its two regressors (centred ln Omega, mean).

A line fit ``ln P_k = b + w x_k`` over the ordinates in the fit mask is linear in the log
spectrum: ``w = sum(xc_k ln P_k) / sum(xc_k^2)`` and ``b = sum(avg_k ln P_k) - w xm``. The
fits of all profiles are one matrix product with the two regressors, and any per-bin
correction of the log spectrum (bias, leakage, noise floor) enters through its own
projection on them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rough_map.psd._cache import table_cache
from rough_map.psd._leakage import leakage_table
from rough_map.psd._spectra import frozen


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
