"""Standard errors of a patch's ln R and w that allow for the correlation between profiles.

The patch values are means over ``m`` profiles, ``ln R = mean(b_i)`` and ``w = mean(w_i)``,
but neighbouring profiles 8 mm apart share their long wavelengths, so the ``b_i`` and
``w_i`` are correlated across the profile index and ``std / sqrt(m)`` is 2-3 times too
small. The standard error here is

    se^2 = s^2 * (m - 1) / (m - d) * d / m,

with ``s`` the profile-to-profile standard deviation (``sigma_lnR``, ``sigma_w``: measured
on the patch) and ``d`` the design effect ``1 + 2 sum_{j<m} (1 - j/m) rho(j)`` of the
lag-``j`` correlation ``rho`` of the per-profile fits; ``(m - 1) / (m - d)`` undoes the
shrinking of ``s`` by the mean that the correlated profiles share. ``d >= 1``, so
``se >= s / sqrt(m)``.

The correlation ``rho(j)`` is not estimated from the patch (a lag-window estimate from 100
correlated profiles is biased low by ~20 % and so noisy that 95 % intervals cover ~84 %):
it is that of an isotropic Gaussian surface whose profiles have the patch's waviness,
sampled on square cells. For such a surface it depends on the waviness only, never on R
or the spacing:

* the windowed, detrended DFT ordinates ``X_ik`` of profiles ``j`` rows apart have the
  complex correlation ``E[X_ik X*_{i+j,k'}] / sqrt(...)``, an integral over the profile
  wavenumber ``nu`` of the two ordinates' kernels, the profile spectrum ``nu^w`` and the
  lateral coherence of the surface at lag ``j``, ``2^(1-mu) / Gamma(mu) t^mu K_mu(t)``
  with ``t = nu j`` and ``mu = -w / 2`` (the Fourier transform of ``(1 + u^2)^((w - 1) / 2)``,
  see :func:`rough_map.iso8608.surface_constant`); with ``gridding="cell_mean"`` the
  profile spectrum takes the cell-mean gain of :func:`rough_map.psd._leakage._cell_mean_gain`;
* the logs of two periodogram ordinates with correlation ``rho`` have the covariance
  ``Li2(|rho|^2)`` (``pi^2 / 6`` at ``rho = 1``); a Welch ordinate of ``2 a`` equivalent
  degrees of freedom has ``sum_n |rho|^(2n) Gamma(n) Gamma(a) / (n Gamma(a + n))``;
* ``b_i`` and ``w_i`` are linear in the log ordinates (:mod:`rough_map.psd._regression`),
  so their lag covariances are quadratic forms of those log covariances.

The tables (nine waviness nodes from -4.5 to -0.5, lags up to two profile lengths,
ordinates within ``_BAND`` of each other) are computed on first use for each profile
length, window and gridding (35 ms for 112 samples with one BLAS thread, 65 ms with cell
means) and cached; a patch then costs a table interpolation (well under 1 us in a batch).

On patches cut from continuous isotropic surfaces (``tests/surfaces.py``, w from -2 to
-2.8, ISO A-D) +-1 se covers the generating ln R and w 65-72 % of the time and +-1.96 se
93-97 % (``tests/test_uncertainty.py``).

Assumptions: profiles are adjacent rows of a square grid (the profiles kept after the
gap policy are treated as adjacent, which overstates their correlation: conservative), and
the ground is isotropic. On ground with features that run along the profiles (ruts, rows)
neighbouring profiles are more alike than the model says and the se is too small.
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.psd._cache import table_cache
from rough_map.psd._leakage import _cell_mean_gain
from rough_map.psd._options import Options
from rough_map.psd._regression import Projections
from rough_map.psd._spectra import frozen, hann_plan

#: Waviness nodes of the tables (dimensionless); the design effect is linear between them.
W_NODES = np.linspace(-4.5, -0.5, 9)
frozen(W_NODES)

#: Ordinates on either side whose log covariance is kept (the Hann window correlates
#: neighbours; beyond a few bins apart the log covariance is below 1e-3).
_BAND = 6
#: Wavenumber samples per ordinate spacing in the kernel integrals.
_PER_BIN = 4
#: Terms of the series of the log covariance of Welch ordinates.
_SERIES = 200


def lag_grid(seg_n: int) -> np.ndarray:
    """Profile lags of the tables: every lag up to 16, then coarser (the correlation is
    smooth there) up to two segment lengths."""
    top = 2 * seg_n
    parts = [np.arange(0, 17), np.arange(18, 33, 2), np.arange(36, 65, 4), np.arange(72, top, 8)]
    lags = np.concatenate([*parts, [top]])
    return np.unique(lags[lags <= top])


@table_cache(8)
def _kernels(seg_n: int, window: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wavenumbers ``nu`` (rad per sample), their weights and the complex response of each
    ordinate k = 1 ... seg_n/2 to a unit sinusoid of each ``nu`` and of ``-nu`` after the
    detrending and the window: shapes (N,), (N,), (2, N, K)."""
    win, basis, _ = hann_plan(seg_n, window)
    step = 2 * math.pi / seg_n
    low = np.exp(np.linspace(math.log(step / 100.0), math.log(step / 2), 40))
    high = np.arange(step / 2, math.pi + step / (2 * _PER_BIN), step / _PER_BIN)
    nu = np.concatenate([low[:-1], high[high <= math.pi]])
    dnu = np.gradient(nu)
    t = np.arange(seg_n, dtype=float)
    phase = np.exp(1j * nu[:, None] * t[None, :])
    resid = phase - (phase @ basis) @ basis.T
    spec = np.fft.fft(resid * win[None, :], axis=1)
    k = np.arange(1, seg_n // 2 + 1)
    resp = np.stack([spec[:, k], np.conj(spec[:, (seg_n - k) % seg_n])])
    frozen(nu, dnu, resp)
    return nu, dnu, resp


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


#: Gauss-Legendre nodes on [0, 1] and their weights times the triangle (1 - s).
_GL_S, _GL_W = np.polynomial.legendre.leggauss(10)
_TRI_S = np.concatenate([(_GL_S + 1) / 2, -(_GL_S + 1) / 2])
_TRI_W = np.concatenate([_GL_W / 2, _GL_W / 2]) * (1 - np.abs(_TRI_S))


def _lateral_coherence(nu: np.ndarray, lags: np.ndarray, w: float, gridding: str) -> np.ndarray:
    """Coherence (lags, N) of two rows ``lag`` cells apart at profile wavenumber ``nu``.

    Point samples: the Matern function of ``nu * lag``. Cell means: the rows are box
    averages across one cell, so their covariance is the point one averaged over the
    triangle ``1 - |s|``, ``s`` in [-1, 1] (Gauss-Legendre on each half).
    """
    if gridding != "cell_mean":
        return _matern(lags[:, None] * nu[None, :], w)
    arg = np.abs(lags[:, None, None] + _TRI_S[None, None, :]) * nu[None, :, None]
    num = _matern(arg, w) @ _TRI_W
    den = _matern(np.abs(_TRI_S)[None, :] * nu[:, None], w) @ _TRI_W
    return num / den[None, :]


def _cell_gain(nu: np.ndarray) -> np.ndarray:
    """:func:`rough_map.psd._leakage._cell_mean_gain` on ``nu`` at :data:`W_NODES`,
    computed on 48 wavenumbers and interpolated in log-log (it is smooth)."""
    coarse = np.geomspace(nu.min(), math.pi, 48)
    g = np.log(_cell_mean_gain(coarse, W_NODES))
    return np.exp(np.stack([np.interp(np.log(nu), np.log(coarse), col) for col in g.T], 1))


def _log_covariance(r2: np.ndarray, alpha: float) -> np.ndarray:
    """Covariance of the logs of two ordinates of ``2 alpha`` degrees of freedom whose
    correlation is ``r2`` (``|rho|^2``): ``Li2(r2)`` for one segment (``alpha = 1``)."""
    from scipy import special

    if alpha == 1.0:
        return special.spence(1.0 - r2)
    n = np.arange(1, _SERIES + 1, dtype=float)
    coef = np.exp(special.gammaln(n) + special.gammaln(alpha) - special.gammaln(alpha + n)) / n
    out = np.zeros_like(r2)
    power = np.ones_like(r2)
    for c in coef:
        power = power * r2
        out += c * power
    return np.where(r2 >= 1.0, special.polygamma(1, alpha), out)


@table_cache(8)
def log_covariances(seg_n: int, window: str, gridding: str, alpha: float) -> np.ndarray:
    """``Cov(ln P_{i,k}, ln P_{i+j,k+d})`` of an isotropic power-law surface.

    Shape ``(len(W_NODES), len(lag_grid(seg_n)), K, 2 * _BAND + 1)`` with ``K = seg_n // 2``
    ordinates, the lags ``j`` (in profiles) of :func:`lag_grid` and ``d = -_BAND ...
    _BAND`` (zero where ``k + d`` is outside the ordinates). Read-only.
    """
    nu, dnu, resp = _kernels(seg_n, window)
    n_k = resp.shape[2]
    lags = lag_grid(seg_n).astype(float)
    offsets = np.arange(-_BAND, _BAND + 1)
    # Cross products of each ordinate's response with its neighbours': (2, N, K, 2B + 1).
    idx = np.clip(np.arange(n_k)[:, None] + offsets[None, :], 0, n_k - 1)
    valid = (np.arange(n_k)[:, None] + offsets[None, :] >= 0) & (
        np.arange(n_k)[:, None] + offsets[None, :] < n_k
    )
    cross = (resp[:, :, :, None] * np.conj(resp[:, :, idx])).sum(axis=0) * 0.5
    gain = _cell_gain(nu) if gridding == "cell_mean" else None
    out = np.zeros((W_NODES.size, lags.size, n_k, offsets.size))
    for i, w in enumerate(W_NODES):
        weight = nu**w * dnu
        if gain is not None:
            weight = weight * gain[:, i]
        coh = _lateral_coherence(nu, lags, float(w), gridding) * weight[None, :]
        cov = (coh @ cross.reshape(nu.size, -1)).reshape(lags.size, n_k, offsets.size)
        var = cov[0, :, _BAND].real
        r2 = np.abs(cov) ** 2 / (var[:, None] * var[idx])
        r2 = np.where(valid, np.minimum(r2, 1.0), 0.0)
        out[i] = np.where(valid, _log_covariance(r2, alpha), 0.0)
    frozen(out)
    return out


@table_cache(256)
def _lag_correlations(
    seg_n: int, window: str, gridding: str, alpha: float, coef: bytes
) -> np.ndarray:
    """Lag correlation ``rho[node, j]``, j = 0 ... 2 seg_n, of the linear statistic
    ``sum_k v_k ln P_ik`` whose weights ``v`` (float64, K) are in ``coef`` (0 for v = 0).

    The direct form of what :func:`_effect_tables` contracts (a test checks they agree).
    """
    v = np.frombuffer(coef, dtype=float)
    cov = log_covariances(seg_n, window, gridding, alpha)
    n_k = v.size
    pos = np.arange(n_k)[:, None] + np.arange(-_BAND, _BAND + 1)[None, :]
    vv = v[:, None] * np.where((pos >= 0) & (pos < n_k), v[np.clip(pos, 0, n_k - 1)], 0.0)
    q = np.einsum("ajkd,kd->aj", cov, vv)
    rho = np.divide(q, q[:, :1], out=np.zeros_like(q), where=q[:, :1] > 0)
    lags = lag_grid(seg_n)
    rho = np.stack([np.interp(np.arange(lags[-1] + 1), lags, row) for row in rho])
    frozen(rho)
    return rho


def design_effect(rho: np.ndarray, m: int) -> np.ndarray:
    """``1 + 2 sum_{j=1}^{m-1} (1 - j / m) rho[:, j]`` per node, at least 1."""
    top = min(m - 1, rho.shape[1] - 1)
    j = np.arange(1, top + 1)
    d = 1.0 + 2.0 * ((1.0 - j / m) * rho[:, 1 : top + 1]).sum(axis=1)
    return np.maximum(d, 1.0)


def equivalent_alpha(bias: float) -> float:
    """Half the equivalent degrees of freedom of an ordinate whose log has the mean offset
    ``bias = psi(alpha) - ln(alpha)`` (``-gamma`` for one segment: ``alpha = 1``)."""
    if abs(bias + float(np.euler_gamma)) < 1e-9:
        return 1.0
    from scipy import special

    lo, hi = math.log(0.05), math.log(1e4)  # psi(a) - ln(a) increases with a
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if special.digamma(math.exp(mid)) - mid < bias:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def standard_errors(
    b: np.ndarray,
    wv: np.ndarray,
    wm: np.ndarray,
    pr: Projections,
    opt: Options,
    *,
    seg_n: int,
    bias: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of the patch means of ``b`` (ln R) and ``wv`` (w).

    Parameters
    ----------
    b, wv : ndarray, shape (patches, profiles)
        Per-profile intercepts (ln of m^3/rad) and slopes.
    wm : ndarray, shape (patches,)
        The patches' waviness, where the tables are read.
    pr : Projections
        The fit's regressors (``xc``, ``avg``, ``xm``, ``sxx``).
    opt : Options
        The estimator's options (window, gridding, a fixed waviness: then ``b`` is the mean
        log ordinate and se_w is 0).
    seg_n : int
        Samples per spectral segment.
    bias : float
        Log bias of an ordinate, which gives the Welch degrees of freedom.

    Returns
    -------
    se_lnR, se_w : ndarray, shape (patches,)
        NaN for a single profile.
    """
    fixed = opt.waviness is not None
    xc, avg, xm, sxx = pr.xc, pr.avg, pr.xm, pr.sxx
    n_patch, m = b.shape
    if m < 2:
        nan = np.full(n_patch, np.nan)
        return nan, (np.zeros(n_patch) if fixed else nan)
    alpha = equivalent_alpha(bias)
    t0, tw = _effect_tables(seg_n, opt.window, opt.gridding, alpha, m)
    c = xc / sxx[:, None]  # weights of w on the log ordinates: (patches or 1, K)
    a = avg if fixed else avg - xm[:, None] * c
    d_b = _interp_nodes(_design_effects(a, t0, tw), wm)
    d_w = _interp_nodes(_design_effects(c, t0, tw), wm)
    se_b = np.sqrt(b.var(axis=1, ddof=1) * _inflation(d_b, m))
    se_w = np.zeros(n_patch) if fixed else np.sqrt(wv.var(axis=1, ddof=1) * _inflation(d_w, m))
    return se_b, se_w


@table_cache(64)
def _effect_tables(
    seg_n: int, window: str, gridding: str, alpha: float, m: int
) -> tuple[np.ndarray, np.ndarray]:
    """The log covariances at lag 0 and their sum over the lags weighted as the design
    effect of ``m`` profiles weights them, each of shape ``(len(W_NODES), K, 2 _BAND + 1)``.

    The design effect ``1 + 2 sum_j (1 - j/m) rho_j`` is linear in the lag covariances of the
    statistic (``rho_j = q_j / q_0``, interpolated between the tabulated lags), so a
    statistic's effect at every node is two contractions of its weights with these tables.
    """
    cov = log_covariances(seg_n, window, gridding, alpha)
    lags = lag_grid(seg_n)
    n_int = int(lags[-1]) + 1
    top = min(m - 1, n_int - 1)
    per_lag = np.zeros(n_int)
    per_lag[1 : top + 1] = 1.0 - np.arange(1, top + 1) / m
    # Linear interpolation from the tabulated lags to every lag, as a matrix.
    interp = np.stack(
        [np.interp(np.arange(n_int), lags, np.eye(lags.size)[i]) for i in range(lags.size)],
        axis=1,
    )
    weights = per_lag @ interp  # (L,)
    tw = np.tensordot(weights, cov, axes=(0, 1))
    t0 = np.ascontiguousarray(cov[:, 0])
    frozen(t0, tw)
    return t0, tw


def _design_effects(v: np.ndarray, t0: np.ndarray, tw: np.ndarray) -> np.ndarray:
    """Design effect at every node of the linear statistics ``sum_k v_k ln P_ik``, one per
    row of ``v`` (rows, K): shape (rows, len(W_NODES)), at least 1."""
    n_k = v.shape[1]
    pos = np.arange(n_k)[:, None] + np.arange(-_BAND, _BAND + 1)[None, :]
    inside = (pos >= 0) & (pos < n_k)
    vv = v[:, :, None] * np.where(inside, v[:, np.clip(pos, 0, n_k - 1)], 0.0)
    flat = vv.reshape(vv.shape[0], -1)
    # dot products one at a time, as rough_map.psd._regression._row_dot does: the same
    # numbers whatever the number of patches in the batch
    q0 = np.multiply(flat[:, None, :], t0.reshape(t0.shape[0], -1), order="C").sum(axis=-1)
    qw = np.multiply(flat[:, None, :], tw.reshape(tw.shape[0], -1), order="C").sum(axis=-1)
    d = 1.0 + 2.0 * np.divide(qw, q0, out=np.zeros_like(qw), where=q0 > 0)
    return np.maximum(d, 1.0)


def _interp_nodes(d: np.ndarray, wm: np.ndarray) -> np.ndarray:
    """The design effects ``d`` (rows, nodes) linearly interpolated at each patch's
    waviness (clipped to the nodes); one row is shared by every patch."""
    pos = (np.clip(wm, W_NODES[0], W_NODES[-1]) - W_NODES[0]) / (W_NODES[1] - W_NODES[0])
    i = np.minimum(pos.astype(int), W_NODES.size - 2)
    frac = pos - i
    rows = np.arange(wm.size) if d.shape[0] > 1 else np.zeros(wm.size, dtype=int)
    return (1 - frac) * d[rows, i] + frac * d[rows, i + 1]


def _inflation(d: np.ndarray, m: int) -> np.ndarray:
    """``(m - 1) / (m - d) * d / m``: the variance of the mean over ``s^2``."""
    return (m - 1) / np.maximum(m - d, 0.1) * d / m
