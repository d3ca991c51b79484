"""The estimator's result: :class:`PatchRoughness`."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from rough_map.psd._shape import CURVED_Z, RMS_FACTOR


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
    band_rms : float
        Rms height in m over the ordinates fitted, from the patch-mean spectrum less the
        noise floor, corrected for the detrend, the window and the cells: a roughness that
        needs no extrapolation (:mod:`rough_map.psd._shape`).
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
        +-:data:`rough_map.psd._shape.CURVED_Z` the log spectrum is not a line over the
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
        :data:`~rough_map.psd._shape.RMS_FACTOR` (2)."""
        return bool(1.0 / RMS_FACTOR <= self.rms_ratio <= RMS_FACTOR)

    @property
    def power_law(self) -> bool:
        """The log spectrum is a line over the band, within
        :data:`~rough_map.psd._shape.CURVED_Z` standard errors of its curvature."""
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
