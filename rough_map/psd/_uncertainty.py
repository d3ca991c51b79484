"""Standard errors of a patch's ln R and w that allow for the correlation between profiles.

The patch values are means over ``m`` profiles, ``ln R = mean(b_i)`` and ``w = mean(w_i)``,
but neighbouring profiles 8 mm apart share their long wavelengths, so the ``b_i`` and
``w_i`` are correlated across the profile index and ``std / sqrt(m)`` is 2-3 times too
small. The standard error here is

    se^2 = v1 * d / m,   v1 = (n1 * s^2 (m - 1) / (m - d) + k * q0) / (n1 + k),

at least ``s^2 / m``, with ``s`` the profile-to-profile standard deviation (``sigma_lnR``,
``sigma_w``: measured on the patch), ``d`` the design effect ``1 + 2 sum_{j<m} (1 - j/m)
rho(j)`` of the lag-``j`` correlation ``rho`` of the per-profile fits, and ``v1`` the
variance of one profile's fit: ``s^2 (m - 1) / (m - d)`` undoes the shrinking of ``s`` by
the mean that the correlated profiles share, and has ``n1 = m / d - 1`` degrees of
freedom; ``q0`` is the model's variance of one profile's fit, pooled in with the weight of
``k = 2`` profiles (:data:`PRIOR_PROFILES`). On isotropic ground (``d`` about 4-9 of 112)
the measured spread decides; on ground the same across the track (``d`` near ``m``: every
row the same profile) it says nothing and the model decides.

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
  profile spectrum takes the cell-mean gain of :func:`rough_map.psd._corrections._cell_mean_gain`;
* the logs of two periodogram ordinates with correlation ``rho`` have the covariance
  ``Li2(|rho|^2)`` (``pi^2 / 6`` at ``rho = 1``); a Welch ordinate of ``2 a`` equivalent
  degrees of freedom has ``sum_n |rho|^(2n) Gamma(n) Gamma(a) / (n Gamma(a + n))``;
* ``b_i`` and ``w_i`` are linear in the log ordinates (:mod:`rough_map.psd._fit`),
  so their lag covariances are quadratic forms of those log covariances.

The tables (nine waviness nodes from -4.5 to -0.5, lags up to two profile lengths,
ordinates within ``_BAND`` of each other) are computed on first use for each profile
length, window and gridding (35 ms for 112 samples with one BLAS thread, 65 ms with cell
means) and cached; a patch then costs a table interpolation (well under 1 us in a batch).

On patches cut from continuous isotropic surfaces (``tests/surfaces.py``, w from -2 to
-2.8, ISO A-D) +-1 se covers the generating ln R and w 65-72 % of the time and +-1.96 se
93-97 % (``tests/test_uncertainty.py``).

The ground's lateral scale ``a`` (:mod:`rough_map.psd._corrections`: the isotropic surface
stretched across the profiles, ``a = 0`` the same at every row) enters the lateral
coherence as ``t = nu j a``; the tables are computed at the scale nodes ``A_NODES`` that
the patches need and the design effect is linear between them. Patches whose scale is
not read (point samples, Welch segments, the paper's method) are taken as isotropic. On
stretched (``a = 0.3``) and swept (``a = 0``) clouds, and on sparse swept clouds read in
pooled rows, +-1 se covers the truth 68-74 % of the time and +-1.96 se 93-96 %
(``tests/test_lateral.py``).

Assumptions: profiles are adjacent rows of the grid (the profiles kept after the gap
policy are treated as adjacent, which overstates their correlation: conservative), and
the ground belongs to the stretched family. Features that run along the profiles without
being the same across (a few ruts in otherwise isotropic ground) are not of it.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from rough_map.psd._corrections import _TRI_S, _TRI_W, A_NODES, W_NODES, _cell_mean_gain, _matern
from rough_map.psd._spectra import frozen, hann_plan, table_cache

if TYPE_CHECKING:
    from rough_map.psd._fit import Projections
    from rough_map.psd.options import Options


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


def _lateral_coherence(
    nu: np.ndarray, lags: np.ndarray, w: float, gridding: str, scale: float = 1.0
) -> np.ndarray:
    """Coherence (lags, N) of two rows ``lag`` cells apart at profile wavenumber ``nu``.

    Point samples: the Matern function of ``nu * lag``. Cell means: the rows are box
    averages across one cell, so their covariance is the point one averaged over the
    triangle ``1 - |s|``, ``s`` in [-1, 1] (Gauss-Legendre on each half). ``scale`` is the
    rows' lateral scale ``a`` (:mod:`rough_map.psd._corrections`): the isotropic surface
    stretched across the profiles, whose rows ``lag`` apart are ``a * lag`` apart on it.
    """
    nu_across = nu if scale == 1.0 else nu * scale
    if gridding != "cell_mean":
        return _matern(lags[:, None] * nu_across[None, :], w)
    arg = np.abs(lags[:, None, None] + _TRI_S[None, None, :]) * nu_across[None, :, None]
    num = _matern(arg, w) @ _TRI_W
    return num / _lateral_box(nu_across, w)[None, :]


def _lateral_box(nu: np.ndarray, w: float) -> np.ndarray:
    """The share of a row's power that its cells' average across one cell keeps at the
    (lateral) wavenumber ``nu``: the Matern function averaged over the triangle."""
    return _matern(np.abs(_TRI_S)[None, :] * nu[:, None], w) @ _TRI_W


def _cell_gain(nu: np.ndarray) -> np.ndarray:
    """:func:`rough_map.psd._corrections._cell_mean_gain` on ``nu`` at :data:`W_NODES`,
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
def log_covariances(
    seg_n: int, window: str, gridding: str, alpha: float, scale: float = 1.0
) -> np.ndarray:
    """``Cov(ln P_{i,k}, ln P_{i+j,k+d})`` of a power-law surface, isotropic or (``scale``,
    one of :data:`A_NODES`) stretched across the profiles.

    Shape ``(len(W_NODES), len(lag_grid(seg_n)), K, 2 * _BAND + 1)`` with ``K = seg_n // 2``
    ordinates, the lags ``j`` (in profiles) of :func:`lag_grid` and ``d = -_BAND ...
    _BAND`` (zero where ``k + d`` is outside the ordinates). Read-only; each waviness node
    is :func:`_log_covariances_at`.
    """
    out = np.stack(
        [_log_covariances_at(seg_n, window, gridding, alpha, scale, i) for i in range(W_NODES.size)]
    )
    frozen(out)
    return out


@table_cache(8)
def _covariance_plan(
    seg_n: int, window: str, gridding: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """What every node of :func:`log_covariances` shares: the kernels' wavenumbers and
    weights, the cross products of each ordinate's response with its neighbours' (N, K,
    2B + 1), their indices and validity (K, 2B + 1) and the cell-mean gain (or None)."""
    nu, dnu, resp = _kernels(seg_n, window)
    n_k = resp.shape[2]
    offsets = np.arange(-_BAND, _BAND + 1)
    idx = np.clip(np.arange(n_k)[:, None] + offsets[None, :], 0, n_k - 1)
    valid = (np.arange(n_k)[:, None] + offsets[None, :] >= 0) & (
        np.arange(n_k)[:, None] + offsets[None, :] < n_k
    )
    cross = (resp[:, :, :, None] * np.conj(resp[:, :, idx])).sum(axis=0) * 0.5
    gain = _cell_gain(nu) if gridding == "cell_mean" else None
    frozen(cross, idx, valid)
    return nu, dnu, cross, idx, valid, gain


@table_cache(128)
def _log_covariances_at(
    seg_n: int, window: str, gridding: str, alpha: float, scale: float, node: int
) -> np.ndarray:
    """:func:`log_covariances` at the waviness node ``W_NODES[node]`` alone: a patch needs
    two of the nine (about 15 ms each for 112 samples)."""
    nu, dnu, cross, idx, valid, gain = _covariance_plan(seg_n, window, gridding)
    lags = lag_grid(seg_n).astype(float)
    n_k, n_off = idx.shape
    w = float(W_NODES[node])
    weight = nu**w * dnu
    if gain is not None:
        weight = weight * gain[:, node]
        if scale != 1.0:  # the lateral box keeps more of a row stretched across
            weight = weight * _lateral_box(nu * scale, w) / _lateral_box(nu, w)
    coh = _lateral_coherence(nu, lags, w, gridding, scale) * weight[None, :]
    cov = (coh @ cross.reshape(nu.size, -1)).reshape(lags.size, n_k, n_off)
    var = cov[0, :, _BAND].real
    r2 = np.abs(cov) ** 2 / (var[:, None] * var[idx])
    r2 = np.where(valid, np.minimum(r2, 1.0), 0.0)
    out = np.where(valid, _log_covariance(r2, alpha), 0.0)
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
    scale: np.ndarray | None = None,
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
    scale : ndarray, shape (patches,), optional
        Each patch's lateral scale as its rows show it, a fractional index into
        :data:`A_NODES` (:func:`rough_map.psd._corrections.lateral_scale`);
        None or NaN: isotropic.

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
    tables = functools.partial(_effect_tables_at, seg_n, opt.window, opt.gridding, alpha, m)
    at = _scale_weights(n_patch, scale)
    if xc.shape[0] == 1 and (sxx == sxx[0]).all() and (xm == xm[0]).all():
        xm, sxx = xm[:1], sxx[:1]  # one fit for all patches: one row of weights
    c = xc / sxx[:, None]  # weights of w on the log ordinates: (patches or 1, K)
    a = avg if fixed else avg - xm[:, None] * c
    se_b = np.sqrt(_variance(b.var(axis=1, ddof=1), *_effects(a, wm, at, tables), m))
    if fixed:
        return se_b, np.zeros(n_patch)
    return se_b, np.sqrt(_variance(wv.var(axis=1, ddof=1), *_effects(c, wm, at, tables), m))


#: Profiles' worth of weight that the model's variance of one profile's statistic gets
#: against the measured one (:func:`_variance`).
PRIOR_PROFILES = 2.0


def _scale_weights(n_patch: int, scale: np.ndarray | None) -> dict[int, np.ndarray]:
    """Weights (patches,) of each lateral-scale node a patch's tables are read at: the two
    nodes around its scale (a fractional index), linearly; node ``a = 1`` for None/NaN."""
    iso = float(np.flatnonzero(A_NODES == 1.0)[0])
    pos = np.full(n_patch, iso) if scale is None else np.asarray(scale, dtype=float)
    pos = np.clip(np.where(np.isfinite(pos), pos, iso), 0.0, A_NODES.size - 1.0)
    lo = np.floor(pos).astype(int)
    frac = pos - lo
    out: dict[int, np.ndarray] = {}
    for node in np.unique(np.concatenate([lo, np.minimum(lo + 1, A_NODES.size - 1)])):
        weight = np.where(lo == node, 1.0 - frac, 0.0) + np.where(lo + 1 == node, frac, 0.0)
        if weight.any():
            out[int(node)] = weight
    return out


def _effects(
    v: np.ndarray,
    wm: np.ndarray,
    at: dict[int, np.ndarray],
    tables: functools.partial[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """The design effect ``d`` and the model's variance ``q0`` of one profile's statistic
    ``sum_k v_k ln P_ik`` (``v``: one row per patch, or one for all), each (patches,), at
    each patch's waviness and lateral scale: linear between the two waviness nodes around
    ``wm`` and between the scale nodes of ``at``, contracted only at those. ``tables`` is
    :func:`_effect_tables_at` with its geometry bound."""
    shared = v.shape[0] == 1  # one row of weights for all patches
    flat = None if shared else _pair_products(v)
    key = np.ascontiguousarray(v, dtype=float).tobytes() if shared else b""
    pos = (np.clip(wm, W_NODES[0], W_NODES[-1]) - W_NODES[0]) / (W_NODES[1] - W_NODES[0])
    i = np.minimum(pos.astype(int), W_NODES.size - 2)
    frac = pos - i
    need = np.unique(np.concatenate([i, i + 1]))
    lo_at, hi_at = np.searchsorted(need, i), np.searchsorted(need, i + 1)
    d = q = 0.0
    for node, weight in at.items():
        scale = float(A_NODES[node])
        if flat is None:  # the shared row's numbers at each node, computed once a process
            dq = np.array([_shared_effect(key, tables.args, scale, int(j)) for j in need])
            d_at, q_at = dq[:, 0], dq[:, 1]
            lo, q_lo, hi, q_hi = d_at[lo_at], q_at[lo_at], d_at[hi_at], q_at[hi_at]
        else:
            pairs = [tables(scale, int(j)) for j in need]
            t0 = np.stack([t for t, _ in pairs])
            tw = np.stack([t for _, t in pairs])
            lo, q_lo = _contract(flat, t0[lo_at], tw[lo_at])
            hi, q_hi = _contract(flat, t0[hi_at], tw[hi_at])
        d_node, q_node = (1 - frac) * lo + frac * hi, (1 - frac) * q_lo + frac * q_hi
        if len(at) == 1:  # one node for all patches: its numbers, with no arithmetic
            return d_node, q_node
        d = d + weight * d_node
        q = q + weight * q_node
    return np.asarray(d), np.asarray(q)


@table_cache(4096)
def _shared_effect(
    key: bytes, geometry: tuple[Any, ...], scale: float, node: int
) -> tuple[float, float]:
    """:func:`_contract` of the one row of weights whose float64 bytes are ``key`` at one
    node of the tables (``geometry``: the leading arguments of :func:`_effect_tables_at`)."""
    v = np.frombuffer(key)[None, :]
    seg_n, window, gridding, alpha, m = geometry
    t0, tw = _effect_tables_at(seg_n, window, gridding, alpha, m, scale, node)
    d, q0 = _contract(_pair_products(v), t0[None, :], tw[None, :])
    return float(d[0]), float(q0[0])


def _pair_products(v: np.ndarray) -> np.ndarray:
    """``v_k v_{k+d}`` for ``d = -_BAND ... _BAND`` (0 outside the ordinates), flattened:
    shape (rows, K * (2 _BAND + 1)), to contract with the log covariance tables."""
    n_k = v.shape[1]
    pos = np.arange(n_k)[:, None] + np.arange(-_BAND, _BAND + 1)[None, :]
    inside = (pos >= 0) & (pos < n_k)
    vv = v[:, :, None] * np.where(inside, v[:, np.clip(pos, 0, n_k - 1)], 0.0)
    return vv.reshape(vv.shape[0], -1)


def _contract(flat: np.ndarray, t0: np.ndarray, tw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Design effect (at least 1) and variance of one profile's statistic from its pair
    products ``flat`` and the tables ``t0``, ``tw`` (flattened alike; one row per row of
    ``flat``, or one node for all). The dot products are taken one row at a time, as
    ``rough_map.psd._fit._row_dot`` does: the same numbers in any batch."""
    q0 = np.multiply(flat, t0, order="C").sum(axis=-1)
    qw = np.multiply(flat, tw, order="C").sum(axis=-1)
    d = 1.0 + 2.0 * np.divide(qw, q0, out=np.zeros_like(qw), where=q0 > 0)
    return np.maximum(d, 1.0), q0


def _variance(s2: np.ndarray, d: np.ndarray, q0: np.ndarray, m: int) -> np.ndarray:
    """Variance of the mean of ``m`` profiles' statistics whose sample variance is ``s2``,
    whose design effect is ``d`` and whose variance for one profile the model puts at
    ``q0`` (``d`` and ``q0`` as :func:`_effects` gives them).

    ``s2`` is shrunk by the profiles' shared mean: ``E[s2] = v1 (m - d) / (m - 1)`` for one
    profile's variance ``v1``, with ``m / d - 1`` degrees of freedom. Where the profiles
    are many and nearly independent that estimate is good; where they are nearly alike
    (ground the same across the track: ``d`` near ``m``) it says nothing, and the model's
    ``q0`` takes over. The two are pooled with :data:`PRIOR_PROFILES` profiles' weight on
    the model: then ``v1 d / m``, and never below ``s2 / m``.
    """
    dof = np.maximum(m / d - 1.0, 0.0)
    measured = s2 * (m - 1) / np.maximum(m - d, 1e-9)
    v1 = (dof * measured + PRIOR_PROFILES * q0) / (dof + PRIOR_PROFILES)
    return np.maximum(v1 * d / m, s2 / m)


def _effect_tables(
    seg_n: int, window: str, gridding: str, alpha: float, m: int, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """The log covariances at lag 0 and their sum over the lags weighted as the design
    effect of ``m`` profiles weights them, each of shape ``(len(W_NODES), K, 2 _BAND + 1)``.

    The design effect ``1 + 2 sum_j (1 - j/m) rho_j`` is linear in the lag covariances of the
    statistic (``rho_j = q_j / q_0``, interpolated between the tabulated lags), so a
    statistic's effect at every node is two contractions of its weights with these tables.
    Each node is :func:`_effect_tables_at`.
    """
    n_k = seg_n // 2
    nodes = [
        _effect_tables_at(seg_n, window, gridding, alpha, m, scale, i) for i in range(W_NODES.size)
    ]
    t0 = np.stack([t.reshape(n_k, -1) for t, _ in nodes])
    tw = np.stack([t.reshape(n_k, -1) for _, t in nodes])
    return t0, tw


@table_cache(2048)
def _effect_tables_at(
    seg_n: int, window: str, gridding: str, alpha: float, m: int, scale: float, node: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_effect_tables` at one waviness node, flattened: shapes ``(K (2 _BAND + 1),)``."""
    cov = _log_covariances_at(seg_n, window, gridding, alpha, scale, node)
    lags = lag_grid(seg_n)
    n_int = int(lags[-1]) + 1
    top = min(m - 1, n_int - 1)
    per_lag = np.zeros(n_int)
    per_lag[1 : top + 1] = 1.0 - np.arange(1, top + 1) / m
    weights = per_lag @ _lag_interpolation(seg_n)  # (L,)
    tw = np.tensordot(weights, cov, axes=(0, 0)).ravel()
    t0 = np.ascontiguousarray(cov[0]).ravel()
    frozen(t0, tw)
    return t0, tw


@table_cache(8)
def _lag_interpolation(seg_n: int) -> np.ndarray:
    """Linear interpolation from the tabulated lags (:func:`lag_grid`) to every lag, as a
    matrix (every lag, tabulated lags)."""
    lags = lag_grid(seg_n)
    n_int = int(lags[-1]) + 1
    out = np.stack(
        [np.interp(np.arange(n_int), lags, np.eye(lags.size)[i]) for i in range(lags.size)],
        axis=1,
    )
    frozen(out)
    return out


def _design_effects(v: np.ndarray, t0: np.ndarray, tw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Design effect at every waviness node of the linear statistics ``sum_k v_k ln P_ik``,
    one per row of ``v`` (rows, K), at least 1, and the statistic's variance for one
    profile: shapes (rows, len(W_NODES)). :func:`_effects` contracts only the nodes it
    needs, with the same numbers."""
    flat = _pair_products(v)[:, None, :]
    return _contract(flat, t0.reshape(t0.shape[0], -1), tw.reshape(tw.shape[0], -1))
