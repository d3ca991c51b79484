"""The corrections of ``method="unbiased"``: what the detrend, the window, the cells and
the sensor noise do to a power-law spectrum, in tables the package ships.

**Leakage.** A power-law profile ``phi = R Omega^w`` seen through the linear detrend and the
window has expected periodogram ordinates ``phi(Omega_k) exp(d[w, k])``. The offset ``d``
depends on the profile length ``n``, the window, the waviness ``w`` and the gridding, never
on R or on the spacing; it is tabulated on the waviness grid :data:`W_GRID`. The package
ships the Hann tables of common lengths (``rough_map/data/leakage_tables.npz``,
:func:`rough_map.psd.write_leakage_tables`); others are computed on first use (~50 ms) and
cached. Cached tables are read-only.

**The lateral box of cell means.** How alike neighbouring profiles are, and what the cell
means' lateral box does to them. A grid of cell means is the ground averaged over square
cells, so each profile is the ground averaged across one cell as well as along it. Along the
profile the box is the ``sinc^2`` of the cell-mean leakage tables; across it, the average
takes the power of everything that changes within a cell's width. How much depends on the
ground, not only on its profile spectrum: an isotropic surface loses a share that grows with
the wavenumber, a surface that is the same across the patch (a rut, a road texture scanned
along one line and swept across) loses none, and one whose neighbouring rows are unrelated
loses most.

The tables assume an isotropic surface. Here the ground's lateral scale is measured on
the patch and the tables are corrected for it:

* the family of surfaces is the isotropic one stretched across the profiles: the 2-D
  spectrum ``S(kx, ky / a)``, whose profiles keep the PSD ``Omega^w`` for every ``a``.
  ``a = 1`` is isotropic, ``a = 0`` the same across the patch, ``a > 1`` rougher across
  than along. The lateral average then takes what the isotropic one takes at ``a Omega``;
* ``a`` is read from the coherence of adjacent rows, the mean cross-spectrum of rows ``i``
  and ``i + 1`` over the mean spectrum less the noise floor (the noise of two rows is
  independent, so it adds to the spectrum and not to the cross-spectrum). For the family
  it is the triangle-averaged Matern coherence at ``a Omega`` (see
  :mod:`rough_map.psd._uncertainty`), with the folded wavenumbers weighted as the
  sampling folds them;
* the fit then takes ``ln G(a) - ln G(1)`` off every ordinate, ``G`` being the cell-mean
  gain of the family (box, lateral average and folding) on the ordinate.

The tables are (``a`` nodes x waviness nodes x ordinates), shipped with the leakage tables
for common profile lengths, computed on first use for others (about 50 ms for 112
samples) and cached; a patch costs a few interpolations on its ordinates. Welch spectra
(``nperseg``) carry no cross-spectrum: their ground is taken as isotropic.

**The sensor-noise floor** (see :mod:`rough_map.psd`, *Sensor noise*). White measurement
noise of variance ``s^2`` per cell adds a flat floor ``s^2 B / pi`` m^3/rad to every
ordinate (less flat where the gap policy filled cells: :func:`gap_filled_floor`).
Subtracting it from the patch-mean spectrum gives one log correction per bin, shared by
every profile of the patch. Each ordinate then weighs in the fit as the inverse of its
variance about the same profiles read without noise (:func:`floor_correction`): ordinates
where the noise dominates keep a small weight, as the patch mean averages the noise of ~100
profiles that are nearly independent at those wavenumbers, and the fit ends only where the
noise takes practically all the power.

The tables the package ships, ``rough_map/data/leakage_tables.npz``, hold the leakage
tables and the lateral tables of cell means of common profile lengths
(:func:`write_leakage_tables` writes them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output
from rough_map.errors import InputError
from rough_map.iso8608 import surface_constant
from rough_map.limits import LIMITS
from rough_map.patch._params import check_int
from rough_map.psd._spectra import frozen, hann_plan, table_cache

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


#: Waviness nodes of the tables (dimensionless); the design effect is linear between them.
W_NODES = np.linspace(-4.5, -0.5, 9)
frozen(W_NODES)
#: Lateral scales of the lateral tables and of :mod:`rough_map.psd._uncertainty`: ``a = 0`` is
#: ground that is the same across the patch, ``a = 1`` isotropic ground.
A_NODES = np.array([0.0, 0.1, 0.2, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 3.0, 5.0])
frozen(A_NODES)

#: Gauss-Legendre nodes on [0, 1] and their weights times the triangle (1 - s).
_GL_S, _GL_W = np.polynomial.legendre.leggauss(10)
_TRI_S = np.concatenate([(_GL_S + 1) / 2, -(_GL_S + 1) / 2])
_TRI_W = np.concatenate([_GL_W / 2, _GL_W / 2]) * (1 - np.abs(_TRI_S))


def _matern(t: np.ndarray, w: float) -> np.ndarray:
    """Lateral coherence ``2^(1-mu) / Gamma(mu) t^mu K_mu(t)``, ``mu = -w / 2``, of the
    isotropic surface whose profiles have PSD ``Omega^w`` (``t`` = wavenumber x lag, >= 0),
    interpolated in a table (log-spaced in t, relative error ~1e-5)."""
    from scipy import special  # imported on first use: it costs a worker 70 ms

    mu = -w / 2.0
    grid = np.concatenate([[0.0], np.geomspace(1e-7, max(float(t.max()), 1.0) * 1.01, 3000)])
    table = np.ones_like(grid)
    table[1:] = 2.0 ** (1.0 - mu) / math.gamma(mu) * grid[1:] ** mu * special.kv(mu, grid[1:])
    return np.interp(t, grid, np.nan_to_num(table))


_ISOTROPIC = int(np.flatnonzero(A_NODES == 1.0)[0])
#: Folded wavenumbers on either side of the band taken into the gain.
_ALIASES = 2
#: Ordinates whose coherence is read: the terrain must be at least this share of the power.
MIN_SIGNAL_SHARE = 0.5


@table_cache(8)
def lateral_tables(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ln G(a) - ln G(1), coherence)`` of the ordinates ``k = 1 ... n // 2`` of rows of
    ``n`` cell means; each of shape ``(len(A_NODES), len(W_NODES), n // 2)``, read-only.
    Read from the shipped tables when they hold them (``rough_map/data/leakage_tables.npz``,
    :func:`rough_map.psd.write_leakage_tables`), else computed."""
    shape = (A_NODES.size, W_NODES.size, n // 2)
    ratio = shipped_array(f"lateral_ratio_{n}", shape)
    coherence = shipped_array(f"lateral_coherence_{n}", shape)
    if ratio is None or coherence is None:
        ratio, coherence = compute_lateral_tables(n)
    frozen(ratio, coherence)
    return ratio, coherence


def compute_lateral_tables(n: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lateral_tables` computed (about 50 ms for 112 samples)."""
    nu = 2 * math.pi * np.arange(1, n // 2 + 1) / n
    folded = np.abs(nu[None, :] + 2 * math.pi * np.arange(-_ALIASES, _ALIASES + 1)[:, None])
    box = np.sinc(folded / (2 * math.pi)) ** 2  # the box along the profile
    t = A_NODES[:, None, None] * folded[None]  # (a, aliases, ordinates)
    gain = np.empty((A_NODES.size, W_NODES.size, nu.size))
    cross = np.empty_like(gain)
    for j, w in enumerate(W_NODES):
        power = box * folded**w
        within = _matern(np.abs(_TRI_S) * t[..., None], w) @ _TRI_W  # lateral box average
        across = _matern(np.abs(1 + _TRI_S) * t[..., None], w) @ _TRI_W  # next row
        gain[:, j] = (power * within).sum(axis=1)
        cross[:, j] = (power * across).sum(axis=1)
    coherence = cross / gain
    ratio = np.log(gain / gain[_ISOTROPIC])
    return ratio, coherence


@table_cache(8)
def _by_waviness(n: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lateral_tables` with the waviness first: (W_NODES, a, k) each, read-only."""
    out = tuple(np.ascontiguousarray(np.moveaxis(t, 1, 0)) for t in lateral_tables(n))
    frozen(*out)
    return out[0], out[1]


def _at_waviness(table: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``table`` (W_NODES, a, k) interpolated at each patch's waviness: (patches, a, k)."""
    pos = np.clip((w - W_NODES[0]) / (W_NODES[1] - W_NODES[0]), 0, W_NODES.size - 1 - 1e-9)
    pos = np.where(np.isfinite(pos), pos, _ISOTROPIC)
    i = pos.astype(int)
    f = (pos - i)[:, None, None]
    return table[i] + f * (table[i + 1] - table[i])


def lateral_scale(
    cross: np.ndarray,
    psd: np.ndarray,
    floor: np.ndarray,
    w: np.ndarray,
    usable: np.ndarray,
    n: int,
) -> np.ndarray:
    """Each patch's lateral scale, as a fractional index into :data:`A_NODES`.

    ``cross`` and ``psd`` (patches, bins) are the mean cross-spectrum of adjacent rows and
    the mean spectrum, ``floor`` the noise floor (patches, bins), ``w`` each patch's
    waviness, ``usable`` (patches, bins) the ordinates of its fit and ``n`` the profile
    length in samples. The scale is the
    node whose coherence is nearest, in least squares, to the measured one over the
    usable ordinates where the terrain is at least :data:`MIN_SIGNAL_SHARE` of the
    power, refined by a parabola through its neighbours; patches without such ordinates
    get the isotropic node.
    """
    _, coherence = _by_waviness(n)
    model = _at_waviness(coherence, w)  # (patches, a, k)
    signal = psd - floor
    ok = usable & (signal > MIN_SIGNAL_SHARE * psd) & np.isfinite(cross)
    ok[:, 0] = False  # the detrend takes most of the first ordinate
    with np.errstate(divide="ignore", invalid="ignore"):
        measured = np.where(ok, cross / np.where(ok, signal, 1.0), 0.0)
    resid = (model - measured[:, None, :]) * ok[:, None, :]
    sse = (resid * resid).sum(axis=2)  # (patches, a)
    best = np.argmin(sse, axis=1)
    mid = np.clip(best, 1, A_NODES.size - 2)
    rows = np.arange(best.size)
    lo, c, hi = sse[rows, mid - 1], sse[rows, mid], sse[rows, mid + 1]
    curve = lo - 2 * c + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.where(curve > 0, 0.5 * (lo - hi) / curve, 0.0)
    pos = np.where(best == mid, mid + np.clip(step, -0.5, 0.5), best)
    return np.where(ok.sum(axis=1) >= 2, pos, float(_ISOTROPIC))


def lateral_log_gain(position: np.ndarray, w: np.ndarray, n: int) -> np.ndarray:
    """``ln G(a) - ln G(1)`` (patches, n // 2) at each patch's lateral scale (a fractional
    index into :data:`A_NODES`, :func:`lateral_scale`) and waviness, for profiles of ``n``
    samples."""
    ratio, _ = _by_waviness(n)
    table = _at_waviness(ratio, w)  # (patches, a, k)
    i = np.clip(position.astype(int), 0, A_NODES.size - 2)
    f = (position - i)[:, None]
    rows = np.arange(position.size)
    return (1 - f) * table[rows, i] + f * table[rows, i + 1]


def lateral_scale_value(position: np.ndarray) -> np.ndarray:
    """The lateral scale ``a`` of a fractional index into :data:`A_NODES`."""
    return np.interp(position, np.arange(A_NODES.size), A_NODES)


def grid_log_gain(
    n: int, waviness: np.ndarray, lateral_scale: np.ndarray, window: str = "hann"
) -> np.ndarray:
    """What a cell-mean grid of ``n`` samples along the profiles measures of a power-law
    ground's profile spectrum, over the truth, at its ordinates ``k = 1 ... n // 2``:
    natural log, shape (frames, n // 2).

    It is the estimator's own model of its grid: the window and detrend leakage and the
    cells' box filter with its folding (:mod:`rough_map.psd._corrections`) at each frame's
    waviness, and the lateral box at its lateral scale (NaN: isotropic). The same ground
    gridded at two steps over the same patch has the same wavenumbers at the same ``k``;
    the difference of the two gains maps one grid's spectrum onto the other's.

    Parameters
    ----------
    n : int
        Samples per profile (the patch side over the step).
    waviness, lateral_scale : ndarray, shape (frames,)
        Each frame's w (dimensionless; NaN rows give NaN) and lateral scale ``a``.
    window : str
        The estimator's window.
    """
    w = np.asarray(waviness, dtype=float)
    a = np.asarray(lateral_scale, dtype=float)
    position = np.interp(np.where(np.isfinite(a), a, 1.0), A_NODES, np.arange(A_NODES.size))
    gain = leakage(n, window, w, "cell_mean")[:, : n // 2]
    return gain + lateral_log_gain(position, np.where(np.isfinite(w), w, -2.5), n)[:, : n // 2]


#: The band ends at the first bin whose noise-free power is below this fraction of the
#: measured power (its weight would be below 1e-4 anyway).
MIN_SIGNAL_FRACTION = 0.01
#: Fewest bins left for a fit.
MIN_BINS = 3


def check_floor(noise_psd: float | None) -> float:
    """The floor in m^3/rad to subtract; :class:`InputError` unless finite and >= 0."""
    noise = math.nan if noise_psd is None else float(noise_psd)
    if noise_psd is None or not math.isfinite(noise) or noise < 0:
        raise InputError("subtract_noise=True needs a finite noise_psd >= 0 in m^3/rad")
    return noise


#: Half-width in bins of the running mean that smooths the patch-mean PSD before the floor
#: is subtracted.
SMOOTH_BINS = 3


def _smooth_bins(psd: np.ndarray, valid: np.ndarray, half: int = SMOOTH_BINS) -> np.ndarray:
    """Running mean over ``2 half + 1`` bins of each row (shorter windows at the ends), of
    the ``valid`` bins only.

    The floor correction of a bin is a non-linear function of the patch-mean power there;
    computed from one bin's scatter it would be biased (Jensen, and the selection of the
    mask). Smoothing over neighbouring ordinates, where the spectrum changes by a few per
    cent per bin, removes most of the scatter and little of the shape. Bins outside the
    fit do not enter the means: the first ordinate has lost most of its power to the
    detrending, and the Nyquist ordinate carries half the density, so either would pull
    its neighbours' power down and their floor correction up.
    """
    n = psd.shape[-1]
    ok = np.asarray(valid, dtype=float)
    zero = np.zeros(psd.shape[:-1] + (1,))
    c = np.cumsum(np.concatenate([zero, psd * ok], axis=-1), axis=-1)
    cn = np.cumsum(np.concatenate([[0.0], ok]))
    k = np.arange(n)
    lo = np.maximum(k - half, 0)
    hi = np.minimum(k + half + 1, n)
    count = cn[hi] - cn[lo]
    # C order (fancy indexing gives F order): row sums must not depend on the stack's size
    out = np.ascontiguousarray((c[..., hi] - c[..., lo]) / np.maximum(count, 1.0))
    return np.where(count > 0, out, psd)


#: Variance of the log of a periodogram ordinate of a Gaussian profile (one segment).
LOG_VAR = math.pi**2 / 6
#: Independent ordinates in the running mean of ``2 SMOOTH_BINS + 1`` Hann-windowed
#: ordinates: neighbours are correlated (their squared coherence is 4/9), so seven
#: ordinates weigh as 7 / (1 + 2 * 4/9 * 6/7), about 4.
SMOOTH_DOF = 4.0


def _dilog(z: np.ndarray) -> np.ndarray:
    """Li2(z) for z in [0, 1] (scipy's spence(1 - z))."""
    from scipy.special import spence

    return spence(1.0 - z)


def excess_log_variance(q: np.ndarray) -> np.ndarray:
    """Variance of ``ln|X + E|^2 - ln|X|^2`` for a complex Gaussian ordinate ``X`` and
    independent noise ``E`` with ``q`` times its power: ``2 (pi^2/6 - Li2(1 / (1 + q)))``
    (the covariance of the logs of two exponential variables of squared correlation
    ``rho^2`` is ``Li2(rho^2)``). 0 without noise, ``pi^2/3`` when noise dominates."""
    q = np.asarray(q, dtype=float)
    return 2.0 * (LOG_VAR - _dilog(1.0 / (1.0 + q)))


def gap_statistics(grid: np.ndarray, missing: np.ndarray) -> tuple[float, float]:
    """What the gap policy did to one patch, for :func:`gap_filled_floor`.

    Parameters
    ----------
    grid : ndarray, shape (profiles, samples)
        The kept profiles in m, gaps filled.
    missing : ndarray of bool, same shape
        The cells that were filled.

    Returns
    -------
    share : float
        Fraction of the cells that were filled.
    residual : float
        Mean square in m^2 of what linear interpolation misses on measured cells,
        ``(y[j-1] + y[j+1]) / 2 - y[j]``, over the cells measured with both neighbours
        measured, in every 4th profile (a patch-wide mean: ~3,000 cells are plenty; 0 when
        nothing was filled).
    """
    share = float(missing.mean())
    if share == 0.0:
        return 0.0, 0.0
    grid, missing = grid[::4], missing[::4]
    ok = ~(missing[:, :-2] | missing[:, 1:-1] | missing[:, 2:])
    miss = 0.5 * (grid[:, :-2] + grid[:, 2:]) - grid[:, 1:-1]
    return share, float(np.mean(miss[ok] ** 2)) if ok.any() else 0.0


def gap_filled_floor(
    noise: np.ndarray, gaps: np.ndarray | None, n_bins: int, seg_n: int, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each ordinate's floor in m^3/rad, and the gain of the terrain's power, after the
    gap policy filled cells by linear interpolation; both of shape (patches, bins).

    ``gaps`` holds a row ``(f, v)`` of :func:`gap_statistics` per patch (None: nothing
    filled). A share ``f`` of isolated cells replaced by the mean of their neighbours is
    the profile ``y + m (A y)``, with ``(A y)[j] = (y[j-1] + y[j+1]) / 2 - y[j]`` and ``m``
    the indicator of the filled cells. Its expected spectrum is that of ``y`` times
    ``g = (1 + f (cos(Omega B) - 1))^2`` (the terrain loses up to 4 f of its power at the
    Nyquist wavenumber, where a few per cent are a large share of what a steep spectrum has
    left above the noise), plus the white ``f (1 - f) E[(A y)^2] B / pi`` of the cells that
    were filled and not measured. ``y`` holds the terrain and the noise, so the floor is
    ``N g + f (1 - f) v B / pi``, and the terrain's power is the rest divided by ``g``.
    """
    floor = np.asarray(noise, dtype=float)[:, None]
    if gaps is None:
        ones = np.ones((floor.shape[0], n_bins))
        return floor * ones, ones
    nu = 2.0 * np.pi * np.arange(1, n_bins + 1) / seg_n
    stats = np.asarray(gaps, dtype=float)
    share, resid = stats[:, :1], stats[:, 1:]
    gain = (1.0 + share * (np.cos(nu)[None, :] - 1.0)) ** 2
    return floor * gain + share * (1.0 - share) * resid * spacing / np.pi, gain


def floor_correction(
    mean_psd: np.ndarray, noise: np.ndarray, base_mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin log correction and fit weights of each patch after subtracting its floor.

    Parameters
    ----------
    mean_psd : ndarray, shape (patches, bins)
        Patch-mean PSD in m^3/rad.
    noise : ndarray, shape (patches,) or (patches, bins)
        Each patch's floor in m^3/rad (or each ordinate's: :func:`gap_filled_floor`).
    base_mask : ndarray of bool, shape (bins,)
        The ordinates the fit would use without noise.

    Returns
    -------
    shift : ndarray, shape (patches, bins)
        ``ln((P - noise) / P)``, added to every profile's log spectrum (``P`` smoothed over
        neighbouring ordinates).
    weights : ndarray, shape (patches, bins)
        Fit weight of each ordinate: the variance of a clean log ordinate over that of
        the corrected one, which has noise ``q = noise / (P - noise)`` times its signal
        (:func:`excess_log_variance`, and the share ``q^2 / SMOOTH_DOF`` of the shift's
        own scatter). The same profiles read without noise have weight 1 everywhere, so
        the fit stays as close to theirs as the noise allows. 0 outside ``base_mask`` and
        from the first bin where the signal is less than :data:`MIN_SIGNAL_FRACTION` of
        the measured power.
    short : ndarray of bool, shape (patches,)
        Patches left with fewer than 3 bins: too smooth for their sensor, no fit.
    """
    smooth = _smooth_bins(mean_psd, base_mask)
    floor = np.asarray(noise, dtype=float)
    floor = floor[:, None] if floor.ndim == 1 else floor
    ratio = np.clip((smooth - floor) / smooth, 1e-12, None)
    shift = np.log(ratio)  # per-bin log correction shared by all profiles of a patch
    q = np.minimum(1.0 / ratio - 1.0, 1e12)
    var = LOG_VAR + excess_log_variance(q) + q * q / SMOOTH_DOF
    # The band ends where the noise takes practically all the power: a mask that kept later
    # bins wherever the spectrum happens to be high would keep only upward fluctuations.
    above = ratio > MIN_SIGNAL_FRACTION
    mask = base_mask[None, :] & (np.cumprod(above | ~base_mask[None, :], axis=1) > 0)
    short = mask.sum(axis=1) < MIN_BINS
    return shift, np.where(mask, LOG_VAR / var, 0.0), short


def noise_reach(shift: np.ndarray, base_mask: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """The highest wavenumber in rad/m, counted on from the fit's first ordinate, up to
    which each patch's terrain keeps at least as much power as its floor (the smoothed
    patch-mean power at least twice the floor); 0 where the first is already below. Above
    it the noise dominates and the ordinates weigh little in the fit.

    ``shift`` (patches, bins) is :func:`floor_correction`'s ``ln((P - floor) / P)``, which
    is at least ``ln(1/2)`` exactly there; ``base_mask`` and ``omega`` (rad/m) have shape
    (bins,).
    """
    above = (shift >= math.log(0.5)) | ~base_mask[None, :]
    run = (np.cumprod(above, axis=1) > 0) & base_mask[None, :]
    last = np.where(run, np.arange(shift.shape[1])[None, :], -1).max(axis=1)
    return np.where(last >= 0, omega[np.maximum(last, 0)], 0.0)


def write_leakage_tables(
    path: Path = SHIPPED_TABLES, sizes: Sequence[int] = (40, 56, 64, 80, 100, 112, 128, 225)
) -> None:
    """Precompute the leakage tables of the Hann window for common profile lengths, and
    the lateral tables of cell means (:mod:`rough_map.psd._corrections`).

    The package ships them (``rough_map/data/leakage_tables.npz``) so that a one-shot
    command does not spend ~50 ms building one; a test checks they are up to date.

    Parameters
    ----------
    path : Path
        The ``.npz`` to write.
    sizes : sequence of int
        Profile lengths in samples.
    """
    if not isinstance(path, str | Path):
        raise InputError(f"path must be a file path; got {type(path).__name__}")
    path = Path(path)
    if isinstance(sizes, str | bytes) or not isinstance(sizes, Sequence) or len(sizes) > 64:
        raise InputError("sizes must be a sequence of at most 64 profile lengths (samples)")
    for n in sizes:
        check_int("sizes[i]", n, low=8, high=LIMITS.patch_samples, unit="samples")
    sizes = [int(n) for n in sizes]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{path.parent}: cannot create the folder ({err.strerror})") from None
    tables: dict[str, Any] = {
        f"hann_{n}_{g}": compute_leakage_table(n, "hann", g) for n in sizes for g in GRIDDINGS
    }
    for n in sizes:
        tables[f"lateral_ratio_{n}"], tables[f"lateral_coherence_{n}"] = compute_lateral_tables(n)
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **tables)
