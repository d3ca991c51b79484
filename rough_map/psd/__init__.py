"""The roughness estimator of the paper's section 4: profile PSD, power-law fit, patch mean.

A patch is a height grid of ``m`` longitudinal profiles (rows) of ``n`` samples spaced ``B``
metres apart. For every profile the estimator

1. fills short gaps and drops profiles with long ones (see *Gap policy*),
2. removes a least-squares line (detrending, paper section 3.2),
3. computes the one-sided PSD ``phi(Omega_k)`` in m^3/rad on ``Omega_k = 2 pi k / (n B)``,
   ``k = 1 ... n/2`` (paper Eq. 2), scaled so that the sum of ``phi dOmega`` is the variance,
4. fits ``ln phi = ln R + w ln(Omega / Omega0)`` by least squares (Eqs. 4, 5),

and the patch values are ``R = exp(E[ln R_i])`` and ``w = E[w_i]`` (Eq. 7) with the
first-order uncertainties ``sigma_R = R * std(ln R_i)`` and ``sigma_w = std(w_i)`` (Eq. 8).

Bias of the log fit (``method``)
--------------------------------
A periodogram ordinate of a Gaussian profile is ``P * chi2_nu / nu`` with ``nu = 2`` for a
single segment, so ``E[ln P_hat] = ln P + psi(nu/2) - ln(nu/2)``, i.e. ``ln P - gamma`` (Euler's
gamma, 0.5772) for the default single Hann segment. A straight fit in log-log therefore
returns ``R`` about ``exp(-gamma) = 0.56`` times the truth (-44 %). ``method="unbiased"``
(the default) adds the exact offset back, computed from the equivalent degrees of freedom
of the window and segmenting; ``method="paper"`` keeps the paper's uncorrected fit, for
comparison with published numbers. The slope ``w`` is the same under both methods.

The Nyquist ordinate (``k = n/2``) is reported but left out of the fit: it is a one-degree-
of-freedom ordinate that carries half the one-sided density.

Sensor noise (``noise_psd``)
----------------------------
White measurement noise of variance ``s^2`` per grid cell adds a flat floor
``s^2 B / pi`` m^3/rad to every ordinate. It lifts the high-wavenumber end, which flattens
``w`` and lowers ``R``. Pass the floor (:func:`rough_map.patch.grid_points` estimates it from
the scatter of the points inside each cell) as ``noise_psd`` and set ``subtract_noise=True``
to remove it: the floor is subtracted from the patch-mean spectrum (smoothed over +-3
ordinates, so that one bin's scatter does not bias its own correction), every profile's log
spectrum is shifted by the same per-bin correction, and each ordinate weighs in the fit as
the inverse of the variance that the noise and its correction add to it (relative to the
same profiles read without noise; ``pi^2/6 / (pi^2/6 + 2 (pi^2/6 - Li2(1 / (1 + q))) +
q^2 / 4)`` for a noise-to-signal ratio ``q``), so that the band runs on into ordinates the
noise dominates, with small weights, up to where the signal is 1 % of the power. Cells the
gap policy filled hold their neighbours' mean: for a share ``f`` of filled cells the
terrain's power is multiplied by ``(1 + f (cos(Omega B) - 1))^2`` (1 - 4 f at ``pi / B``)
and the floor becomes that times ``N``, plus the white power of what interpolation misses
(``f (1 - f)`` times its mean square, measured on the patch, times ``B / pi``); both are
corrected (:func:`rough_map.psd._corrections.gap_filled_floor`). It matters when the floor
reaches a few per cent of the terrain's power at ``pi / B``: smooth surfaces (ISO A-C) seen
with stereo, or sparse clouds with only a few points per cell.

Gap policy
----------
NaN cells are missing data. Within each profile, gaps (runs of NaN) up to ``max_gap`` metres
long are filled by linear interpolation between their neighbours (or by the nearest value
at the ends of the profile). A profile is dropped if any gap is longer than ``max_gap`` or if
more than ``max_gap_fraction`` of its cells are missing. The number of dropped profiles is
``PatchRoughness.n_dropped``; fewer than ``min_profiles`` remaining raises
:class:`rough_map.errors.PatchError`.

Batches
-------
:func:`patch_roughness_batch` measures a stack of patches in one vectorised pass (raising
for the first patch it refuses); :func:`patch_roughness_each` does the same but returns a
patch's :class:`~rough_map.errors.PatchError` in its place and takes a noise floor per
patch. A patch's numbers do not depend on what it is stacked with, to the last bit: every
sum over a patch's bins or profiles is taken row by row, never through a matrix product
whose order of summation changes with the stack's size. So a traverse's frames, measured a
chunk at a time, read exactly as one frame measured alone (the online mapper).

Layout
------
:mod:`rough_map.psd.estimator` holds the public functions and :mod:`rough_map.psd.options`
their one :class:`Options`; the private modules hold the concepts: ``_spectra`` (input
checks, gap policy, periodogram, Welch, log bias, the table cache), ``_corrections`` (the
detrend/window/cell-mean leakage tables, the lateral scale of cell means, the noise floor,
the shipped tables), ``_fit`` (the line fit with the unbiased corrections, the checks of the
power law and :class:`PatchRoughness`) and ``_uncertainty`` (the standard errors ``se_lnR``,
``se_w``, with the correlation between profiles).
"""

from rough_map.errors import UnknownOptionError
from rough_map.patch import METHODS
from rough_map.psd._corrections import GRIDDINGS, grid_log_gain, write_leakage_tables
from rough_map.psd._fit import PatchRoughness
from rough_map.psd._spectra import fill_gaps, log_bias
from rough_map.psd.estimator import (
    patch_roughness,
    patch_roughness_batch,
    patch_roughness_each,
    profile_psd,
)
from rough_map.psd.options import Options

__all__ = [
    "GRIDDINGS",
    "METHODS",
    "Options",
    "PatchRoughness",
    "UnknownOptionError",
    "fill_gaps",
    "grid_log_gain",
    "log_bias",
    "patch_roughness",
    "patch_roughness_batch",
    "patch_roughness_each",
    "profile_psd",
    "write_leakage_tables",
]
