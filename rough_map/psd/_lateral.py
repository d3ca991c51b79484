"""How alike neighbouring profiles are, and what the cell means' lateral box does to them.

A grid of cell means is the ground averaged over square cells, so each profile is the
ground averaged across one cell as well as along it. Along the profile the box is the
``sinc^2`` of the cell-mean tables (:mod:`rough_map.psd._leakage`); across it, the average
takes the power of everything that changes within a cell's width. How much depends on the
ground, not only on its profile spectrum: an isotropic surface loses a share that grows
with the wavenumber, a surface that is the same across the patch (a rut, a road
texture scanned along one line and swept across) loses none, and one whose neighbouring
rows are unrelated loses most.

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
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.psd._cache import table_cache
from rough_map.psd._leakage import leakage, shipped_array
from rough_map.psd._spectra import frozen
from rough_map.psd._uncertainty import _TRI_S, _TRI_W, A_NODES, W_NODES, _matern

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
    cells' box filter with its folding (:mod:`rough_map.psd._leakage`) at each frame's
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
