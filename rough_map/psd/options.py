"""The estimator's options: one typed object, documented and checked once.

:func:`~rough_map.psd.patch_roughness`, :func:`~rough_map.psd.patch_roughness_batch`,
:func:`~rough_map.psd.patch_roughness_each` and :func:`~rough_map.psd.profile_psd` take the
same :class:`Options`, given whole (``options=Options(method="paper")``), as keyword
changes of the defaults (``method="paper"``), or both (the keywords change the object).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Real
from typing import Any

from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch import METHODS
from rough_map.patch._params import check_bool, check_choice, check_int, check_real, options_of
from rough_map.psd._corrections import GRIDDINGS
from rough_map.psd._spectra import check_window


@dataclass(frozen=True)
class Options:
    """Options of the roughness estimator, checked when made (:class:`InputError`).

    Attributes
    ----------
    window : str
        Spectral window, default ``"hann"`` (a rectangular window leaks badly on spectra as
        steep as Omega^-2.5); any of :data:`rough_map.psd._spectra.WINDOWS`.
    method : {"unbiased", "paper"}
        ``"unbiased"`` corrects the -gamma bias of the log periodogram; ``"paper"`` is the
        paper's plain log-log fit (R about 44 % low).
    nperseg, noverlap : int, optional
        Welch segmenting in samples; default one segment over the whole profile.
    omega0 : float
        Reference wavenumber of R in rad/m.
    noise_psd : float, optional
        Measurement-noise floor in m^3/rad (see :func:`rough_map.patch.grid_points`).
    subtract_noise : bool
        Subtract ``noise_psd`` before the fit.
    max_gap : float
        Longest gap in m filled by interpolation.
    max_gap_fraction : float
        Largest fraction of missing cells in a kept profile.
    min_profiles : int
        Fewest usable profiles; fewer raise :class:`~rough_map.errors.PatchError`.
    gridding : {"point", "cell_mean"}
        How the heights were sampled. ``"point"``: samples of the surface at the grid
        nodes (synthetic grids, interpolated surfaces). ``"cell_mean"``: means of many points
        per cell (a dense cloud gridded by :func:`rough_map.patch.grid_points`); the box
        filter of the averaging steepens w by about 0.25 and raises R about 2.5 times, and
        the unbiased method corrects for it, for the lateral scale of the ground that the
        coherence of adjacent rows shows (:mod:`rough_map.psd._corrections`; the rows must
        be adjacent rows of the grid; with Welch segments the ground is taken as isotropic).
    waviness : float, optional
        Fix the waviness (dimensionless) instead of fitting it (ISO 8608 classifies roads
        with w = -2); then only R is estimated and ``sigma_w`` is 0.
    row_spacing : float, optional
        Distance in m between neighbouring profiles (the rows of a grid of cells wider
        across than along, :attr:`rough_map.patch.PatchSpec.row_spacing`); default the
        sample spacing. It sets the unit of the lateral scale the cell-mean fit reports
        (the correction itself reads the rows as they are).
    """

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

    def single_segment(self, n: int) -> bool:
        """Whether profiles of ``n`` samples take the one-segment fast path."""
        return self.nperseg is None or self.nperseg >= n

    @classmethod
    def of(cls, options: Options | None, changes: dict[str, Any], caller: str) -> Options:
        """``options`` (default: the defaults) with the keyword ``changes`` of ``caller``
        (:func:`~rough_map.patch._params.options_of`); an unknown keyword raises
        :class:`UnknownOptionError`."""
        return options_of(cls, options, changes, caller)
