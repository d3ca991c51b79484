"""Does the patch follow its power law? The band's own roughness and the fit's checks.

R is ``Phi(omega0)``, at 1 rad/m, extrapolated from a band of about 7-400 rad/m: on ground
whose log spectrum curves over the band, it depends on how the band is weighed (three fits
of one paving patch spread 10x). Beside R and w a reading therefore gives

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

import numpy as np

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
