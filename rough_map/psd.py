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
to remove it: the floor is subtracted from the patch-mean spectrum, every profile's log
spectrum is shifted by the same per-bin correction, and bins where the noise is more than
half the measured power are left out of the fit. It matters when the floor reaches a few
per cent of the terrain's power at ``pi / B``: smooth surfaces (ISO A-C) seen with stereo,
or sparse clouds with only a few points per cell.

Gap policy
----------
NaN cells are missing data. Within each profile, gaps (runs of NaN) up to ``max_gap`` metres
long are filled by linear interpolation between their neighbours (or by the nearest value
at the ends of the profile). A profile is dropped if any gap is longer than ``max_gap`` or if
more than ``max_gap_fraction`` of its cells are missing. The number of dropped profiles is
``PatchRoughness.n_dropped``; fewer than ``min_profiles`` remaining raises
:class:`rough_map.errors.PatchError`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.fft
from scipy import signal, special

from rough_map import iso8608
from rough_map.errors import InputError, PatchError

log = logging.getLogger(__name__)

METHODS = ("unbiased", "paper")


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
    """

    R: float
    w: float
    sigma_R: float
    sigma_w: float
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
            "rms": self.rms,
            "iso_class": self.iso_class,
            "n_profiles": self.n_profiles,
            "n_dropped": self.n_dropped,
            "fit_residual": self.fit_residual,
            "noise_psd": self.noise_psd,
            "method": self.method,
        }


# --------------------------------------------------------------------------- validation


def _check_spacing(spacing: float) -> float:
    try:
        spacing = float(spacing)
    except (TypeError, ValueError):
        raise InputError(f"spacing must be a number in m, got {spacing!r}") from None
    if not math.isfinite(spacing) or spacing <= 0:
        raise InputError(f"spacing must be a positive length in m, got {spacing!r}")
    return spacing


def _check_heights(heights: np.ndarray, min_samples: int = 8) -> np.ndarray:
    try:
        h = np.asarray(heights, dtype=float)
    except (TypeError, ValueError):
        raise InputError("heights must be a numeric array of elevations in m") from None
    if h.ndim == 1:
        h = h[None, :]
    if h.ndim != 2:
        raise InputError(
            f"heights must be a 2-D grid (profiles x samples), got shape {np.shape(heights)}"
        )
    if h.size == 0:
        raise InputError(f"heights is empty (shape {h.shape})")
    if h.shape[1] < min_samples:
        raise InputError(
            f"profiles need at least {min_samples} samples, got {h.shape[1]} (shape {h.shape})"
        )
    if np.isinf(h).any():
        raise InputError("heights contain infinite values; use NaN for missing cells")
    return h


# --------------------------------------------------------------------------- gaps


def fill_gaps(
    heights: np.ndarray,
    spacing: float,
    *,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the gap policy to the rows of a height grid.

    Parameters
    ----------
    heights : ndarray, shape (m, n)
        Elevations in m, NaN for missing cells.
    spacing : float
        Sample spacing in m.
    max_gap : float
        Longest gap in m that is filled by interpolation.
    max_gap_fraction : float
        Largest fraction of missing cells a kept profile may have.

    Returns
    -------
    filled : ndarray, shape (m, n)
        Heights with short gaps filled; dropped rows are left as they were.
    keep : ndarray of bool, shape (m,)
        Profiles that pass the policy.
    """
    h = np.asarray(heights, dtype=float)
    missing = np.isnan(h)
    if not missing.any():
        return h, np.ones(h.shape[0], dtype=bool)
    m, n = h.shape
    cols = np.arange(n)
    valid = ~missing
    # Index of the previous and next valid sample for every cell (vectorised over rows).
    prev = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(valid, cols, n)[:, ::-1], axis=1)[:, ::-1]
    gap_len = np.where(missing, np.minimum(nxt, n) - np.maximum(prev, -1) - 1, 0)
    # A gap touching an end counts its full length from that end.
    max_cells = int(math.floor(max_gap / spacing + 1e-9))
    keep = (gap_len.max(axis=1) <= max_cells) & (missing.mean(axis=1) <= max_gap_fraction)
    keep &= valid.sum(axis=1) >= 2
    p = np.clip(prev, 0, n - 1)
    q = np.clip(nxt, 0, n - 1)
    rows = np.arange(m)[:, None]
    hp = h[rows, p]
    hq = h[rows, q]
    hp = np.where(prev < 0, hq, hp)
    hq = np.where(nxt >= n, hp, hq)
    span = np.where((nxt < n) & (prev >= 0), (nxt - prev).astype(float), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where((nxt < n) & (prev >= 0), (cols - prev) / span, 0.0)
    filled = np.where(missing & keep[:, None], hp + frac * (hq - hp), h)
    return filled, keep


# --------------------------------------------------------------------------- spectra


@lru_cache(maxsize=32)
def _hann_plan(n: int, window: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Window, detrend basis and density scale for a single-segment periodogram."""
    win = signal.get_window(window, n)
    t = np.arange(n, dtype=float)
    basis, _ = np.linalg.qr(np.column_stack([np.ones(n), t - t.mean()]))
    return win, np.ascontiguousarray(basis), float(np.sum(win**2))


@lru_cache(maxsize=64)
def log_bias(window: str, nperseg: int, noverlap: int, n: int) -> float:
    """``E[ln(P_hat / P)]`` of a (Welch) PSD ordinate of a Gaussian process.

    Uses the equivalent degrees of freedom ``nu`` of Welch averaging with the given window
    and overlap (Percival and Walden, Eq. 292b); the ordinate is ``P chi2_nu / nu`` and its
    log has mean ``psi(nu / 2) - ln(nu / 2)``: ``-gamma`` for one segment.
    """
    step = nperseg - noverlap
    k = 1 + (n - nperseg) // step
    if k <= 1:
        return -float(np.euler_gamma)
    win = signal.get_window(window, nperseg)
    denom = np.sum(win**2) ** 2
    corr = 0.0
    for j in range(1, k):
        shift = j * step
        if shift >= nperseg:
            break
        rho = np.sum(win[: nperseg - shift] * win[shift:]) ** 2 / denom
        corr += (1 - j / k) * rho
    nu = 2 * k / (1 + 2 * corr)
    return float(special.digamma(nu / 2) - math.log(nu / 2))


_W_GRID = np.linspace(-4.5, -0.5, 81)


_SHIPPED_TABLES = Path(__file__).parent / "data" / "leakage_tables.npz"


GRIDDINGS = ("point", "cell_mean")
_EXACT_BINS = 48


@lru_cache(maxsize=32)
def _leakage_table(n: int, window: str, gridding: str = "point") -> np.ndarray:
    """:func:`_compute_leakage_table`, read from the shipped tables when they hold it."""
    key = f"{window}_{n}_{gridding}"
    if _SHIPPED_TABLES.exists():
        with np.load(_SHIPPED_TABLES) as data:
            if key in data.files and data[key].shape == (_W_GRID.size, n // 2):
                return data[key]
    return _compute_leakage_table(n, window, gridding)


def _cell_mean_gain(nu: np.ndarray, waviness: np.ndarray, aliases: int = 4) -> np.ndarray:
    """Spectrum of a cell-averaged, sampled isotropic power-law surface over the true one.

    A grid whose cells hold the mean of many points is the surface filtered by a B x B box
    and then sampled every B: along a profile the box multiplies the spectrum by
    ``sinc^2(Omega B / 2)``, the lateral box averages the 2-D spectrum over ky, and the
    sampling folds wavenumbers above ``pi / B`` back into the band. For the isotropic field
    ``S(k) ~ |k|^(w - 1)`` whose profiles have PSD ``Omega^w`` this returns the ratio, with
    ``B = 1``, for every ``nu`` (rad per sample) and waviness: shape (len(nu), len(w)).
    """

    def sinc2(v):
        return np.sinc(v / (2 * np.pi)) ** 2

    ky = np.exp(np.linspace(math.log(1e-4), math.log(2e3), 500))
    dky = np.gradient(ky)
    wy = 2 * sinc2(ky) * dky  # both signs of ky
    out = np.empty((nu.size, waviness.size))
    for j, wv in enumerate(waviness):
        total = np.zeros(nu.size)
        for a in range(-aliases, aliases + 1):
            na = np.abs(nu + 2 * np.pi * a)
            k2 = na[:, None] ** 2 + ky[None, :] ** 2
            total += sinc2(na) * ((k2 ** ((wv - 1) / 2)) @ wy)
        from rough_map.iso8608 import surface_constant

        out[:, j] = total / (nu**wv * surface_constant(wv))
    return out


def _compute_leakage_table(n: int, window: str, gridding: str = "point") -> np.ndarray:
    """Expected log offset of detrended, windowed periodogram ordinates of a power law.

    For a band-limited power-law profile ``phi = R Omega^w`` (wavelengths from ~100 L down
    to 2 B), returns ``d[w_index, k - 1] = ln E[P_hat_k] - ln phi(Omega_k)`` for k = 1 ... n/2
    on the waviness grid ``_W_GRID``. The offset comes from the detrending, which removes
    most of the power at k = 1, and from the window's main lobe, which mixes neighbouring
    ordinates of a steep spectrum; it does not depend on R or on the spacing. With
    ``gridding="cell_mean"`` the profile is a row of cell means of a dense cloud over an
    isotropic surface, and the offset also holds the box filter and the aliasing
    (:func:`_cell_mean_gain`).
    """
    if gridding not in GRIDDINGS:
        raise InputError(f"gridding must be one of {GRIDDINGS}, got {gridding!r}")
    win, basis, wss = _hann_plan(n, window)
    t = np.arange(n, dtype=float)
    k_all = np.arange(1, n // 2 + 1)
    # Far from k = 1 the window only mixes neighbours of a smooth spectrum (< 0.1 % beyond
    # k = 48): for long profiles compute the exact expectation of the first ordinates only.
    k = k_all[:_EXACT_BINS] if n // 2 > 128 else k_all
    # Normalised angular frequency per sample (Omega * B): log-spaced below the first
    # ordinate (where the detrending acts), then 8 points per ordinate up to a few
    # ordinates past the last exact one (band-limited at pi).
    step = 2 * math.pi / n
    low = np.exp(np.linspace(math.log(step / 100.0), math.log(step / 2), 120))
    top = min(math.pi, (k[-1] + 8) * step)
    high = np.arange(step / 2, top + step / 16, step / 8)
    nu = np.concatenate([low[:-1], high])
    dnu = np.gradient(nu)
    # |DFT|^2 at the ordinates of each detrended, windowed unit sinusoid, by FFT, in chunks.
    gain = np.empty((k.size, nu.size))
    for j0 in range(0, nu.size, 512):
        phase = np.exp(1j * nu[j0 : j0 + 512, None] * t[None, :])
        resid = phase - (phase @ basis) @ basis.T  # detrend each unit sinusoid
        spec = np.fft.fft(resid * win[None, :], axis=1)
        f_pos = spec[:, k]
        f_neg = np.conj(spec[:, (n - k) % n])  # the spectrum of the conjugate sinusoid
        # Expectation over the phase; x2 for one-sided.
        gain[:, j0 : j0 + 512] = 0.5 * (np.abs(f_pos) ** 2 + np.abs(f_neg) ** 2).T
    scale = 1.0 / (math.pi * wss)  # (2 B / (2 pi sum w^2)) with B = 1
    if n % 2 == 0 and k.size == k_all.size:
        gain[-1] *= 0.5
    spectrum = nu[:, None] ** _W_GRID[None, :]
    omega_all = 2 * math.pi * k_all / n
    local = np.zeros((_W_GRID.size, k_all.size))  # smooth multiplicative spectrum change
    if gridding == "cell_mean":
        # The gain is smooth in nu and w: compute it on a coarse grid, interpolate.
        coarse_w = _W_GRID[::4]
        coarse_nu = np.unique(np.concatenate([low, np.linspace(step / 2, math.pi, 160)]))
        g = _cell_mean_gain(coarse_nu, coarse_w)
        g_w = np.stack([np.interp(_W_GRID, coarse_w, row) for row in g])  # (coarse nu, w)
        spectrum *= np.stack([np.interp(nu, coarse_nu, col) for col in g_w.T], axis=1)
        local = np.log(np.stack([np.interp(omega_all, coarse_nu, col) for col in g_w.T]))
    expected = scale * (gain * dnu) @ spectrum  # (k, w grid)
    table = local.copy()
    table[:, : k.size] = np.log(expected.T) - _W_GRID[:, None] * np.log(omega_all[: k.size])
    if n % 2 == 0 and k.size < k_all.size:
        table[:, -1] += math.log(0.5)  # the Nyquist ordinate carries half the density
    return table


def write_leakage_tables(path: Path = _SHIPPED_TABLES, sizes=(56, 64, 100, 112, 128, 225)):
    """Precompute the leakage tables of the Hann window for common profile lengths.

    The package ships them (``rough_map/data/leakage_tables.npz``) so that a one-shot
    command does not spend ~50 ms building one; a test checks they are up to date.
    """
    from rough_map._files import atomic_output

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            **{
                f"hann_{n}_{g}": _compute_leakage_table(n, "hann", g)
                for n in sizes
                for g in GRIDDINGS
            },
        )


def _interp_rows(w: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation on ``_W_GRID`` of one tabulated function per row."""
    pos = np.clip((w - _W_GRID[0]) / (_W_GRID[1] - _W_GRID[0]), 0, _W_GRID.size - 1.000001)
    i = pos.astype(int)
    frac = pos - i
    rows = np.arange(values.shape[0])
    return (1 - frac) * values[rows, i] + frac * values[rows, i + 1]


def _leakage(n: int, window: str, waviness: np.ndarray, gridding: str = "point") -> np.ndarray:
    """Per-ordinate log offsets (see :func:`_leakage_table`), one row per waviness."""
    table = _leakage_table(n, window, gridding)
    wv = np.clip(np.asarray(waviness, dtype=float), _W_GRID[0], _W_GRID[-1])
    pos = (wv - _W_GRID[0]) / (_W_GRID[1] - _W_GRID[0])
    i = np.minimum(pos.astype(int), _W_GRID.size - 2)
    frac = (pos - i)[..., None]
    return (1 - frac) * table[i] + frac * table[i + 1]


def _detrend(h: np.ndarray, basis: np.ndarray) -> np.ndarray:
    return h - (h @ basis) @ basis.T


@lru_cache(maxsize=32)
def _fast_plan(n: int, window: str):
    """float32 window, detrend basis, spectrum of the windowed basis, and density scale."""
    win, basis, wss = _hann_plan(n, window)
    basis_fft = np.fft.rfft(basis.T * win, axis=-1)[:, 1:]
    return (
        win.astype(np.float32),
        basis.astype(np.float32),
        basis_fft.astype(np.complex64),
        1.0 / (math.pi * wss),
    )


def _periodogram(
    h: np.ndarray, spacing: float, window: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detrended single-segment periodogram of finite profiles (rows), in m^3/rad.

    Detrending is linear, so the spectrum of the detrended, windowed profile is the spectrum
    of the windowed profile minus the spectra of the windowed trend basis (precomputed).
    Computed in float32 after removing one reference height per patch, which keeps about
    1e-6 relative accuracy. Also returns the detrended sum of squares per profile (m^2).
    """
    shape = h.shape
    n = shape[-1]
    win, basis, basis_fft, scale = _fast_plan(n, window)
    # Non-finite cells are allowed through here: the caller finds them in ``ss``.
    with np.errstate(invalid="ignore", over="ignore"):
        ref = h[..., :1, :].mean(axis=-1, keepdims=True) if h.ndim > 1 else h[:1].mean()
        x = np.empty(shape, dtype=np.float32)
        np.subtract(h, ref, out=x, casting="same_kind")
        x = x.reshape(-1, n)
        coef = x @ basis
        ss = np.einsum("ij,ij->i", x, x) - np.einsum("ij,ij->i", coef, coef)
        # Fold the density scale into the window (one pass less): |c X|^2 = c^2 |X|^2.
        c = np.float32(math.sqrt(scale * spacing))
        x *= win * c
        spec = scipy.fft.rfft(x, axis=-1)[:, 1:]
        spec -= coef @ (basis_fft * c)
        p = spec.real * spec.real
        p += spec.imag * spec.imag
        if n % 2 == 0:
            p[:, -1] *= 0.5
    omega = 2.0 * np.pi * np.arange(1, n // 2 + 1) / (n * spacing)
    return omega, p.reshape(*shape[:-1], p.shape[-1]), ss.reshape(shape[:-1])


def _spectrum(
    h: np.ndarray, spacing: float, window: str, nperseg: int | None, noverlap: int | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """PSD of finite profiles: (omega rad/m, psd m^3/rad, log bias)."""
    n = h.shape[-1]
    if nperseg is None or nperseg >= n:
        omega, p, _ = _periodogram(h, spacing, window)
        return omega, p, -float(np.euler_gamma)
    if nperseg < 8:
        raise InputError(f"nperseg must be at least 8 samples, got {nperseg}")
    if noverlap is None:
        noverlap = nperseg // 2
    if not 0 <= noverlap < nperseg:
        raise InputError(f"noverlap must be in [0, nperseg), got {noverlap} for {nperseg}")
    _, basis, _ = _hann_plan(n, window)
    f, p = signal.welch(
        _detrend(h, basis),
        fs=1.0 / spacing,
        window=window,
        nperseg=nperseg,
        noverlap=noverlap,
        detrend="linear",
        axis=-1,
    )
    return 2 * np.pi * f[1:], p[..., 1:] / (2 * np.pi), log_bias(window, nperseg, noverlap, n)


def profile_psd(
    heights: np.ndarray,
    spacing: float,
    *,
    window: str = "hann",
    nperseg: int | None = None,
    noverlap: int | None = None,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """One-sided PSD of every longitudinal profile of a height grid.

    Parameters
    ----------
    heights : ndarray, shape (n,) or (m, n)
        Elevation profiles in m along the rows, NaN for missing cells.
    spacing : float
        Sample spacing B in m.
    window : str
        Window name understood by :func:`scipy.signal.get_window`; default Hann.
    nperseg, noverlap : int, optional
        Welch segment length and overlap in samples; default one segment over the profile.
    max_gap, max_gap_fraction : float
        Gap policy (see module docstring); max_gap in m.

    Returns
    -------
    omega : ndarray
        Wavenumbers in rad/m, ``2 pi k / (nperseg B)`` for k = 1 ... nperseg/2.
    psd : ndarray
        PSD in m^3/rad, shape ``(len(omega),)`` for a 1-D input, else ``(m, len(omega))``;
        rows of dropped profiles are NaN. The sum of ``psd * dOmega`` is the variance of
        the detrended profile (Parseval).
    """
    spacing = _check_spacing(spacing)
    one = np.ndim(heights) == 1
    h = _check_heights(heights)
    filled, keep = fill_gaps(h, spacing, max_gap=max_gap, max_gap_fraction=max_gap_fraction)
    safe = np.where(keep[:, None], filled, 0.0)
    omega, p, _ = _spectrum(safe, spacing, window, nperseg, noverlap)
    p = p.astype(float)
    p[~keep] = np.nan
    return omega, (p[0] if one else p)


# --------------------------------------------------------------------------- the estimator


def patch_roughness(
    heights: np.ndarray,
    spacing: float,
    *,
    window: str = "hann",
    method: str = "unbiased",
    nperseg: int | None = None,
    noverlap: int | None = None,
    omega0: float = 1.0,
    noise_psd: float | None = None,
    subtract_noise: bool = False,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
    min_profiles: int = 3,
    gridding: str = "point",
    waviness: float | None = None,
) -> PatchRoughness | list[PatchRoughness]:
    """Roughness parameters (R, w) of a patch, with their first-order uncertainty.

    Parameters
    ----------
    heights : ndarray, shape (m, n) or (p, m, n)
        Height grid in m: ``m`` longitudinal profiles (rows, along the direction of travel)
        of ``n`` samples, NaN for missing cells. A 3-D stack is ``p`` patches analysed in
        one vectorised pass (returns a list).
    spacing : float
        Sample spacing B in m (8 mm in the paper).
    window : str
        Spectral window, default ``"hann"`` (a rectangular window leaks badly on spectra as
        steep as Omega^-2.5).
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
        the unbiased method corrects for it.

    waviness : float, optional
        Fix the waviness instead of fitting it (ISO 8608 classifies roads with w = -2);
        then only R is estimated and ``sigma_w`` is 0.

    Returns
    -------
    PatchRoughness or list of PatchRoughness

    Raises
    ------
    InputError
        Bad shape, spacing, method or non-finite values other than NaN.
    PatchError
        Too few usable profiles.
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    if gridding not in GRIDDINGS:
        raise InputError(f"gridding must be one of {GRIDDINGS}, got {gridding!r}")
    if waviness is not None and not (math.isfinite(waviness) and -6 < waviness < 0):
        raise InputError(f"waviness must be a negative number (about -2), got {waviness!r}")
    spacing = _check_spacing(spacing)
    if not (math.isfinite(omega0) and omega0 > 0):
        raise InputError(f"omega0 must be a positive wavenumber in rad/m, got {omega0!r}")
    try:
        arr = np.asarray(heights, dtype=float)
    except (TypeError, ValueError):
        raise InputError("heights must be a numeric array of elevations in m") from None
    if arr.size == 0 and arr.ndim != 3:
        raise InputError(f"heights is empty (shape {arr.shape})")
    single = arr.ndim != 3
    if single:
        if arr.ndim == 1:
            arr = arr[None, :]
        arr = arr[None]
    elif arr.shape[0] == 0:
        return []
    if arr.ndim != 3 or arr.size == 0 or arr.shape[-1] < 8:
        _check_heights(arr.reshape(-1, arr.shape[-1]) if arr.ndim == 3 else arr)
    if arr.shape[1] < min_profiles:
        raise PatchError(f"the patch has {arr.shape[1]} profiles, need at least {min_profiles}")
    options = {
        "window": window,
        "method": method,
        "nperseg": nperseg,
        "noverlap": noverlap,
        "omega0": omega0,
        "noise_psd": noise_psd,
        "subtract_noise": subtract_noise,
        "max_gap": max_gap,
        "max_gap_fraction": max_gap_fraction,
        "min_profiles": min_profiles,
        "gridding": gridding,
        "waviness": waviness,
    }
    out = _estimate(arr, spacing, options)
    return out[0] if single else out


def _estimate(
    arr: np.ndarray, spacing: float, opt: dict, n_dropped: int = 0, check: bool = True
) -> list[PatchRoughness]:
    """Estimates for a stack (patches, profiles, samples) of heights, in cache-sized chunks.

    With ``check``, patches with non-finite cells go through :func:`_with_gaps`. The
    single-segment path finds them in its own output (per-profile sums of squares), which
    saves a pass over the input; the Welch path checks up front.
    """
    n_patch, m, n = arr.shape
    nperseg = opt["nperseg"]
    fast = nperseg is None or nperseg >= n
    if check and not fast:
        finite = np.isfinite(arr).all(axis=(1, 2))
        if not finite.all():
            return _merge(
                finite,
                _estimate(arr[finite], spacing, opt, check=False),
                _with_gaps(arr[~finite], spacing, opt),
            )
    seg_n = n if fast else min(nperseg, n)
    out: list[PatchRoughness] = []
    chunk = max(1, _CHUNK_CELLS // (m * n))  # keep chunks in cache
    for start in range(0, n_patch, chunk):
        part = arr[start : start + chunk]
        if fast:
            omega, p, ss = _periodogram(part, spacing, opt["window"])
            if check:
                finite = np.isfinite(ss).all(axis=1)
                if not finite.all():
                    out += _merge(
                        finite,
                        _estimate(part[finite], spacing, opt, n_dropped, False),
                        _with_gaps(part[~finite], spacing, opt),
                    )
                    continue
            bias = -float(np.euler_gamma)
            rms = np.sqrt(np.maximum(ss.sum(axis=1), 0.0) / (m * n))
        else:
            omega, p, bias = _spectrum(part, spacing, opt["window"], nperseg, opt["noverlap"])
            rms = _rms(part)
        out += _fit(
            omega,
            p,
            bias,
            spacing,
            n,
            seg_n,
            opt["window"],
            opt["method"],
            opt["omega0"],
            opt["noise_psd"],
            opt["subtract_noise"],
            n_dropped,
            rms,
            opt["gridding"],
            opt["waviness"],
        )
    return out


def _merge(mask: np.ndarray, where_true: list, where_false: list) -> list:
    """Interleave two result lists back into the order given by ``mask``."""
    t, f = iter(where_true), iter(where_false)
    return [next(t) if k else next(f) for k in mask]


def _with_gaps(arr: np.ndarray, spacing: float, opt: dict) -> list[PatchRoughness]:
    """Patches with missing cells: the gap policy, one patch at a time."""
    out = []
    for patch in arr:
        h = _check_heights(patch)  # refuses infinities; NaN is missing data
        m = h.shape[0]
        filled, keep = fill_gaps(
            h, spacing, max_gap=opt["max_gap"], max_gap_fraction=opt["max_gap_fraction"]
        )
        n_used = int(keep.sum())
        if n_used < opt["min_profiles"]:
            raise PatchError(
                f"only {n_used} of {m} profiles are usable (need {opt['min_profiles']}); "
                f"{m - n_used} dropped for gaps longer than {opt['max_gap']} m or more than "
                f"{opt['max_gap_fraction']:.0%} missing"
            )
        if n_used < m:
            log.debug("dropped %d of %d profiles for gaps", m - n_used, m)
        out += _estimate(filled[keep][None], spacing, opt, m - n_used, check=False)
    return out


_CHUNK_CELLS = 400_000


def _rms(h: np.ndarray) -> np.ndarray:
    """Rms in m of the linearly detrended profiles, per patch (first axis)."""
    _, basis, _ = _hann_plan(h.shape[-1], "hann")
    x = h - h.mean(axis=-1, keepdims=True)
    c = x @ basis
    ss = np.einsum("pmn,pmn->p", x, x) - np.einsum("pmk,pmk->p", c, c)
    return np.sqrt(np.maximum(ss, 0.0) / (h.shape[1] * h.shape[2]))


@lru_cache(maxsize=64)
def _fit_plan(
    n_bins: int, seg_n: int, method: str, spacing: float, omega0: float, window: str, gridding: str
):
    """Everything of the line fit that depends only on the geometry (cached)."""
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
    proj = np.stack([xc, avg], axis=1).astype(np.float32)
    table = _leakage_table(seg_n, window, gridding)[:, :n_bins]
    return mask, x, xm, xc, sxx, avg, proj, table @ xc, table @ avg


def _fit(
    omega,
    p,
    bias,
    spacing,
    n,
    seg_n,
    window,
    method,
    omega0,
    noise_psd,
    subtract_noise,
    n_dropped,
    rms,
    gridding,
    waviness=None,
) -> list[PatchRoughness]:
    """Vectorised log-log fit of ``p`` (patches, profiles, bins).

    ``n`` is the profile length and ``seg_n`` the samples per spectral segment. The
    per-bin corrections (bias, leakage, noise) are the same for every profile of a patch,
    so the line fits are computed once on the raw log spectra (one matrix product) and the
    corrections enter through their projections on the fit's two regressors.
    """
    n_patch, m, n_bins = p.shape
    base, x, xm0, xc0, sxx0, avg0, proj, leak_x, leak_a = _fit_plan(
        n_bins, seg_n, method, spacing, omega0, window, gridding
    )
    logp = np.log(np.maximum(p, np.float32(1e-38)))
    mean_psd = p.mean(axis=1, dtype=np.float64)
    noise = math.nan if noise_psd is None else float(noise_psd)
    if subtract_noise:
        if noise_psd is None or not math.isfinite(noise) or noise < 0:
            raise InputError("subtract_noise=True needs a finite noise_psd >= 0 in m^3/rad")
        ratio = np.clip((mean_psd - noise) / mean_psd, 1e-12, None)
        shift = np.log(ratio)  # per-bin log correction shared by all profiles of a patch
        mask = base[None, :] & (ratio >= 0.5)
        if (mask.sum(axis=1) < 3).any():
            raise PatchError(
                "fewer than 3 wavenumbers above the noise floor; the patch is too smooth "
                f"for this sensor (noise floor {noise:.3g} m^3/rad)"
            )
        wts = mask.astype(float)
        cnt = wts.sum(axis=1)
        xm = (wts @ x) / cnt
        xc = (x[None, :] - xm[:, None]) * wts
        sxx = (xc * xc).sum(axis=1)
        avg = wts / cnt[:, None]
        yx = np.einsum("pmk,pk->pm", logp, xc.astype(np.float32)).astype(float)
        ym = np.einsum("pmk,pk->pm", logp, avg.astype(np.float32)).astype(float)
        table = _leakage_table(seg_n, window, gridding)[:, :n_bins]
        leak_xp, leak_ap = xc @ table.T, avg @ table.T  # (patches, w grid)
    else:
        mask = np.broadcast_to(base, (n_patch, n_bins))
        shift = np.zeros((1, n_bins))
        xm, xc, sxx, avg = (
            np.full(n_patch, xm0),
            xc0[None, :],
            np.full(n_patch, sxx0),
            avg0[None, :],
        )
        proj_all = (logp.reshape(-1, n_bins) @ proj).astype(float)
        yx = proj_all[:, 0].reshape(n_patch, m)
        ym = proj_all[:, 1].reshape(n_patch, m)
        leak_xp = np.broadcast_to(leak_x, (n_patch, leak_x.size))
        leak_ap = np.broadcast_to(leak_a, (n_patch, leak_a.size))
    # Projections of the per-bin corrections on (centred x, mean).
    sx = (shift * xc).sum(axis=1)
    sa = (shift * avg).sum(axis=1)
    if method == "unbiased":
        # E[ln P_hat] = ln P + bias: the bias projects to 0 on xc and to `bias` on the mean.
        sa = sa - bias
        lx = np.zeros(n_patch)
        la = np.zeros(n_patch)
        for _ in range(1 if waviness is not None else 3):
            # The window/detrend offset depends (weakly) on the waviness.
            w_patch = (
                np.full(n_patch, float(waviness))
                if waviness is not None
                else (yx.mean(axis=1) + sx - lx) / sxx
            )
            lx = _interp_rows(w_patch, leak_xp)
            la = _interp_rows(w_patch, leak_ap)
        sx = sx - lx
        sa = sa - la
    if waviness is None:
        wv = (yx + sx[:, None]) / sxx[:, None]
    else:
        wv = np.full_like(yx, float(waviness))
    b = ym + sa[:, None] - wv * xm[:, None]
    wm = wv.mean(axis=1)
    bm = b.mean(axis=1)
    adj = shift - bias if method == "unbiased" else shift
    if method == "unbiased":
        adj = adj - _leakage(seg_n, window, wm, gridding)[:, :n_bins]
    # Residual of the patch-mean log spectrum about the patch line (shape of the spectrum).
    mean_log = logp.mean(axis=1, dtype=np.float64) + adj
    resid = np.where(mask, mean_log - bm[:, None] - wm[:, None] * x[None, :], 0.0)
    fit_res = np.sqrt((resid * resid).sum(axis=1) / mask.sum(axis=1))
    R = np.exp(bm)
    sb = b.std(axis=1, ddof=1) if m > 1 else np.full(n_patch, np.nan)
    sw = wv.std(axis=1, ddof=1) if m > 1 else np.full(n_patch, np.nan)
    letters = iso8608.iso_class(R)
    return [
        PatchRoughness(
            R=float(R[i]),
            w=float(wm[i]),
            sigma_R=float(R[i] * sb[i]),
            sigma_w=float(sw[i]),
            rms=float(rms[i]),
            iso_class=str(letters[i]),
            omega=omega,
            psd=mean_psd[i],
            profile_R=np.exp(b[i]),
            profile_w=wv[i],
            n_profiles=m,
            n_dropped=n_dropped,
            spacing=spacing,
            length=n * spacing,
            fit_mask=mask[i],
            fit_residual=float(fit_res[i]),
            noise_psd=noise,
            noise_subtracted=bool(subtract_noise),
            method=method,
            omega0=omega0,
        )
        for i in range(n_patch)
    ]
