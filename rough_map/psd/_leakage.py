"""Leakage tables: the expected log offset of detrended, windowed periodogram ordinates.

A power-law profile ``phi = R Omega^w`` seen through the linear detrend and the window has
expected periodogram ordinates ``phi(Omega_k) exp(d[w, k])``. The offset ``d`` depends on
the profile length ``n``, the window, the waviness ``w`` and the gridding, never on R or on
the spacing; it is tabulated on the waviness grid :data:`W_GRID`. The package ships the
Hann tables of common lengths (``rough_map/data/leakage_tables.npz``,
:func:`rough_map.psd.write_leakage_tables`); others are computed on first use (~50 ms) and
cached. Cached tables are read-only.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rough_map.errors import InputError
from rough_map.iso8608 import surface_constant
from rough_map.psd._cache import table_cache
from rough_map.psd._spectra import frozen, hann_plan

#: Waviness grid of the tables (dimensionless).
W_GRID = np.linspace(-4.5, -0.5, 81)
frozen(W_GRID)

#: The tables shipped with the package.
SHIPPED_TABLES = Path(__file__).resolve().parents[1] / "data" / "leakage_tables.npz"

#: How a height grid was sampled: surface values at the nodes, or means of many points.
GRIDDINGS = ("point", "cell_mean")

#: Ordinates computed exactly for long profiles (the rest only carry a smooth change).
_EXACT_BINS = 48


def check_gridding(gridding: str) -> None:
    """Raise :class:`InputError` unless ``gridding`` is one of :data:`GRIDDINGS`."""
    if not (isinstance(gridding, str) and gridding in GRIDDINGS):
        raise InputError(f"gridding must be one of {GRIDDINGS}, got {gridding!r:.40}")


@table_cache(32)
def leakage_table(n: int, window: str, gridding: str = "point") -> np.ndarray:
    """:func:`compute_leakage_table`, read from the shipped tables when they hold it.

    Returns a read-only array of shape ``(len(W_GRID), n // 2)`` (natural-log units).
    """
    table = shipped_array(f"{window}_{n}_{gridding}", (W_GRID.size, n // 2))
    if table is None:
        table = compute_leakage_table(n, window, gridding)
    frozen(table)
    return table


def shipped_array(key: str, shape: tuple[int, ...]) -> np.ndarray | None:
    """The array ``key`` of the shipped tables (:data:`SHIPPED_TABLES`) if they hold it
    with this shape, else None (the caller computes it)."""
    if not SHIPPED_TABLES.exists():
        return None
    with np.load(SHIPPED_TABLES) as data:
        if key in data.files and data[key].shape == shape:
            return np.asarray(data[key])
    return None


def _cell_mean_gain(nu: np.ndarray, waviness: np.ndarray, aliases: int = 4) -> np.ndarray:
    """Spectrum of a cell-averaged, sampled isotropic power-law surface over the true one.

    A grid whose cells hold the mean of many points is the surface filtered by a B x B box
    and then sampled every B: along a profile the box multiplies the spectrum by
    ``sinc^2(Omega B / 2)``, the lateral box averages the 2-D spectrum over ky, and the
    sampling folds wavenumbers above ``pi / B`` back into the band. For the isotropic field
    ``S(k) ~ |k|^(w - 1)`` whose profiles have PSD ``Omega^w`` this returns the ratio, with
    ``B = 1``, for every ``nu`` (rad per sample) and waviness: shape (len(nu), len(w)).
    """

    def sinc2(v: np.ndarray) -> np.ndarray:
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
        out[:, j] = total / (nu**wv * surface_constant(wv))
    return out


def _ordinate_gains(n: int, window: str, k: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """Expected one-sided ``|DFT_k|^2`` of each detrended, windowed unit sinusoid ``nu``.

    Shape (len(k), len(nu)); computed by FFT in chunks of 512 frequencies.
    """
    win, basis, _ = hann_plan(n, window)
    t = np.arange(n, dtype=float)
    gain = np.empty((k.size, nu.size))
    for j0 in range(0, nu.size, 512):
        phase = np.exp(1j * nu[j0 : j0 + 512, None] * t[None, :])
        resid = phase - (phase @ basis) @ basis.T  # detrend each unit sinusoid
        spec = np.fft.fft(resid * win[None, :], axis=1)
        f_pos = spec[:, k]
        f_neg = np.conj(spec[:, (n - k) % n])  # the spectrum of the conjugate sinusoid
        # Expectation over the phase; x2 for one-sided.
        gain[:, j0 : j0 + 512] = 0.5 * (np.abs(f_pos) ** 2 + np.abs(f_neg) ** 2).T
    return gain


def _cell_mean_spectrum(
    low: np.ndarray, step: float, nu: np.ndarray, omega_all: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The cell-mean gain on ``nu`` (len(nu), len(W_GRID)) and its log on ``omega_all``
    (len(W_GRID), len(omega_all)). The gain is smooth in nu and w: it is computed on a
    coarse grid and interpolated."""
    coarse_w = W_GRID[::4]
    coarse_nu = np.unique(np.concatenate([low, np.linspace(step / 2, math.pi, 160)]))
    g = _cell_mean_gain(coarse_nu, coarse_w)
    g_w = np.stack([np.interp(W_GRID, coarse_w, row) for row in g])  # (coarse nu, w)
    on_nu = np.stack([np.interp(nu, coarse_nu, col) for col in g_w.T], axis=1)
    local = np.log(np.stack([np.interp(omega_all, coarse_nu, col) for col in g_w.T]))
    return on_nu, local


def compute_leakage_table(n: int, window: str, gridding: str = "point") -> np.ndarray:
    """Expected log offset of detrended, windowed periodogram ordinates of a power law.

    For a band-limited power-law profile ``phi = R Omega^w`` (wavelengths from ~100 L down
    to 2 B), returns ``d[w_index, k - 1] = ln E[P_hat_k] - ln phi(Omega_k)`` for k = 1 ... n/2
    on the waviness grid :data:`W_GRID`. The offset comes from the detrending, which
    removes most of the power at k = 1, and from the window's main lobe, which mixes
    neighbouring ordinates of a steep spectrum; it does not depend on R or on the spacing.
    With ``gridding="cell_mean"`` the profile is a row of cell means of a dense cloud over
    an isotropic surface, and the offset also holds the box filter and the aliasing
    (:func:`_cell_mean_gain`).
    """
    check_gridding(gridding)
    _, _, wss = hann_plan(n, window)
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
    gain = _ordinate_gains(n, window, k, nu)
    scale = 1.0 / (math.pi * wss)  # (2 B / (2 pi sum w^2)) with B = 1
    if n % 2 == 0 and k.size == k_all.size:
        gain[-1] *= 0.5
    spectrum = nu[:, None] ** W_GRID[None, :]
    omega_all = 2 * math.pi * k_all / n
    local = np.zeros((W_GRID.size, k_all.size))  # smooth multiplicative spectrum change
    if gridding == "cell_mean":
        on_nu, local = _cell_mean_spectrum(low, step, nu, omega_all)
        spectrum *= on_nu
    expected = scale * (gain * dnu) @ spectrum  # (k, w grid)
    table = local.copy()
    table[:, : k.size] = np.log(expected.T) - W_GRID[:, None] * np.log(omega_all[: k.size])
    if n % 2 == 0 and k.size < k_all.size:
        table[:, -1] += math.log(0.5)  # the Nyquist ordinate carries half the density
    return table


def _grid_position(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each waviness falls on :data:`W_GRID` (clipped to it): the lower node, the
    fraction to the next, and which are NaN (overflowed spectra; they read as node 0)."""
    wv = np.asarray(w, dtype=float)
    bad = np.isnan(wv)
    pos = (np.clip(np.where(bad, W_GRID[0], wv), W_GRID[0], W_GRID[-1]) - W_GRID[0]) / (
        W_GRID[1] - W_GRID[0]
    )
    i = np.minimum(pos.astype(int), W_GRID.size - 2)
    return i, pos - i, bad


def interp_rows(w: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation on :data:`W_GRID` of one tabulated function per row (NaN where
    ``w`` is NaN)."""
    i, frac, bad = _grid_position(w)
    rows = np.arange(values.shape[0])
    out = (1 - frac) * values[rows, i] + frac * values[rows, i + 1]
    return np.where(bad, np.nan, out)


def leakage(n: int, window: str, waviness: np.ndarray, gridding: str = "point") -> np.ndarray:
    """Per-ordinate log offsets (see :func:`leakage_table`), one row per waviness (NaN rows
    where the waviness is NaN)."""
    table = leakage_table(n, window, gridding)
    i, frac, bad = _grid_position(waviness)
    out = (1 - frac[..., None]) * table[i] + frac[..., None] * table[i + 1]
    return np.where(bad[..., None], np.nan, out)
