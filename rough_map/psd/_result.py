"""The estimator's result: :class:`PatchRoughness`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


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
        (dimensionless, :mod:`rough_map.psd._lateral`): 1 isotropic, 0 the same across
        the patch (swept or ridged ground), above 1 rougher across than along. Read from
        adjacent profiles of cell-mean grids (``unbiased``, one segment), where it
        corrects the fit; NaN where it is not read.
    omega_noise : float
        Highest wavenumber in rad/m up to which the terrain's power stays at least the
        noise floor's (``rough_map.psd._noise.noise_reach``): the band where the ground,
        not the sensor, dominates. Above it the ordinates still enter the fit with small
        weights. 0 where the noise dominates from the first ordinate of the fit on; NaN
        when no floor was subtracted.
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

    @property
    def sigma_lnR(self) -> float:
        """Standard deviation of ln R_i (dimensionless)."""
        return self.sigma_R / self.R if self.R > 0 else math.nan

    def as_dict(self) -> dict[str, float | int | str]:
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
        }
