"""The estimator's options, checked once (see :func:`rough_map.psd.patch_roughness`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from rough_map.errors import InputError
from rough_map.patch import METHODS
from rough_map.psd._leakage import check_gridding


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

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        check_gridding(self.gridding)
        w = self.waviness
        if w is not None and not (math.isfinite(w) and -6 < w < 0):
            raise InputError(f"waviness must be a negative number (about -2), got {w!r}")

    def check_omega0(self) -> None:
        """Raise :class:`InputError` unless ``omega0`` is a positive wavenumber."""
        if not (math.isfinite(self.omega0) and self.omega0 > 0):
            raise InputError(f"omega0 must be a positive wavenumber in rad/m, got {self.omega0!r}")

    def single_segment(self, n: int) -> bool:
        """Whether profiles of ``n`` samples take the one-segment fast path."""
        return self.nperseg is None or self.nperseg >= n
