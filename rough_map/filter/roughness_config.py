"""``configs/roughness_smoothing.yaml``: the noise model of the roughness smoother.

:class:`RoughnessSmoothingConfig` is the file's schema (pydantic, unknown keys refused);
:func:`rough_map.filter.load_roughness_smoother` reads it into a fitted
:class:`~rough_map.filter.RoughnessSmoother`, and
:meth:`~rough_map.filter.RoughnessSmoother.to_config` writes one back.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["CONFIG_FILE", "RoughnessSmoothingConfig"]

#: The shipped noise model, found by :func:`rough_map.resources.config_file`.
CONFIG_FILE = "roughness_smoothing.yaml"


#: Bounds of the noise model's values (their squares and products stay finite and
#: covariances invertible).
_SMALL, _BIG = 1e-9, 1e6


class _Rates(BaseModel):
    """Process noise of ln R and w, 1/m."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    lnR: float = Field(gt=0, le=_BIG, allow_inf_nan=False)
    w: float = Field(gt=0, le=_BIG, allow_inf_nan=False)


class _Lengths(BaseModel):
    """Error lengths in m of the PSD level at the pivot and of w."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    level: float = Field(gt=0, le=_BIG, allow_inf_nan=False)
    w: float = Field(gt=0, le=_BIG, allow_inf_nan=False)


class _Spread(BaseModel):
    """Standard deviations of ln R and w and their correlation."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    sd_lnR: float = Field(ge=_SMALL, le=_BIG, allow_inf_nan=False)
    sd_w: float = Field(ge=_SMALL, le=_BIG, allow_inf_nan=False)
    corr: float = Field(gt=-1, lt=1)

    def cov(self) -> NDArray[np.float64]:
        """The 2 x 2 covariance of (ln R, w)."""
        c = self.corr * self.sd_lnR * self.sd_w
        return np.array([[self.sd_lnR**2, c], [c, self.sd_w**2]])

    @classmethod
    def of(cls, cov: NDArray[np.float64]) -> dict[str, float]:
        """The mapping of a 2 x 2 covariance."""
        sd = np.sqrt(np.diag(cov))
        return {
            "sd_lnR": float(sd[0]),
            "sd_w": float(sd[1]),
            "corr": float(cov[0, 1] / (sd[0] * sd[1])),
        }


class RoughnessSmoothingConfig(BaseModel):
    """The file ``configs/roughness_smoothing.yaml``: a fitted roughness smoother.

    R is in m³/rad; ln R and w are dimensionless.

    Attributes
    ----------
    process_noise : {lnR, w}
        ``q``: variance of ln R, resp. w, added per metre travelled, 1/m.
    measurement : {sd_lnR, sd_w, corr}
        One frame's error about its ground (frames far apart): standard deviations of ln R
        and w and their correlation.
    error_length : {level, w}
        Distance in m over which frames share their error, for the two uncorrelated parts
        of it: the log PSD level at the fit's pivot (``ln R + kappa w``, ``kappa`` from
        ``measurement``) and w.
    jump : {sd_lnR, sd_w, corr}
        Size of a change of ground: standard deviations of the change of ln R and of w,
        and their correlation.
    alpha : float
        False-alarm probability of the jump test of one onset, in (0, 1).
    window : float
        How far back in m the jump test looks for the onset of a change.
    min_process_noise : float
        Lower bound on ``q`` when it is learnt, 1/m.
    training : dict
        Where the numbers come from (traverses, counts); not used.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    process_noise: _Rates
    measurement: _Spread
    error_length: _Lengths
    jump: _Spread
    alpha: float = Field(0.01, gt=0, lt=1)
    window: float = Field(5.0, gt=0, le=_BIG, allow_inf_nan=False)
    min_process_noise: float = Field(1e-5, gt=0, le=_BIG, allow_inf_nan=False)
    training: dict[str, Any] = Field(default_factory=dict)


def spread(cov: NDArray[np.float64]) -> dict[str, float]:
    """``{sd_lnR, sd_w, corr}`` of a 2 x 2 covariance of (ln R, w)."""
    return _Spread.of(cov)
