"""The estimator's options, checked once (see :func:`rough_map.psd.patch_roughness`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Real

from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch import METHODS
from rough_map.patch._params import check_bool, check_choice, check_int, check_real
from rough_map.psd._leakage import GRIDDINGS
from rough_map.psd._spectra import check_window


@dataclass(frozen=True)
class Options:
    """Keyword options of :func:`rough_map.psd.patch_roughness` (units there)."""

    window: str = "hann"
    method: str = "unbiased"
    nperseg: int | None = None
    noverlap: int | None = None
    omega0: float = 1.0
    noise_psd: float | None = None
    subtract_noise: bool = False
    max_gap: float = 0.05
    max_gap_fraction: float = 0.2
    min_profiles: int = 3
    gridding: str = "point"
    waviness: float | None = None
    row_spacing: float | None = None

    def __post_init__(self) -> None:
        check_window(self.window)
        check_choice("method", self.method, METHODS)
        check_choice("gridding", self.gridding, GRIDDINGS)
        check_int("nperseg", self.nperseg, low=8, high=LIMITS.grid_cells, unit="samples", none=True)
        check_int(
            "noverlap", self.noverlap, low=0, high=LIMITS.grid_cells, unit="samples", none=True
        )
        if self.nperseg is not None and self.noverlap is not None:
            if self.noverlap >= self.nperseg:
                raise InputError(
                    f"noverlap must be in [0, nperseg), got {self.noverlap} for {self.nperseg}"
                )
        check_real("omega0", self.omega0, "rad/m", low=1e-6, high=1e6)
        check_real("noise_psd", self.noise_psd, "m^3/rad", low=0.0, high=1e6, none=True)
        check_bool("subtract_noise", self.subtract_noise)
        check_real("max_gap", self.max_gap, "m", low=0.0, high=1e6)
        check_real("max_gap_fraction", self.max_gap_fraction, "", low=0.0, high=1.0)
        check_real(
            "row_spacing", self.row_spacing, "m", low=0.0, high=1e3, low_open=True, none=True
        )
        check_int("min_profiles", self.min_profiles, low=1, high=LIMITS.grid_cells, unit="profiles")
        w = self.waviness
        if w is not None and not (
            isinstance(w, Real) and not isinstance(w, bool) and math.isfinite(w) and -6 < w < 0
        ):
            raise InputError(
                f"waviness must be a negative number in (-6, 0) (about -2, dimensionless) or "
                f"None; got {w!r:.40}"
            )

    def check_omega0(self) -> None:
        """Raise :class:`InputError` unless ``omega0`` is a positive wavenumber."""
        if not (math.isfinite(self.omega0) and self.omega0 > 0):
            raise InputError(f"omega0 must be a positive wavenumber in rad/m, got {self.omega0!r}")

    def single_segment(self, n: int) -> bool:
        """Whether profiles of ``n`` samples take the one-segment fast path."""
        return self.nperseg is None or self.nperseg >= n
