"""Detrended, windowed profile spectra in m^3/rad: the single-segment fast path and Welch.

The plans (window, detrend basis, density scale) are cached per profile length; the cached
arrays are read-only, so that no caller can change what the next call gets.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch._params import check_int
from rough_map.psd._cache import table_cache

#: Windows the estimator is known to work with (any scipy window name that needs no
#: parameter is accepted).
WINDOWS = ("hann", "hamming", "blackman", "boxcar", "bartlett", "flattop", "nuttall")


def check_window(window: object) -> str:
    """``window`` if :func:`scipy.signal.get_window` knows it without parameters, else
    :class:`InputError` listing the usual names."""
    if window in WINDOWS:  # without importing scipy.signal (a worker never needs it)
        return str(window)
    if isinstance(window, str) and window.strip():
        from scipy.signal import get_window

        try:
            get_window(window, 16)
            return window
        except (ValueError, TypeError, KeyError):
            pass
    shown = repr(window)
    shown = shown if len(shown) <= 40 else shown[:37] + "..."
    raise InputError(
        f"window must be a scipy window name such as {', '.join(WINDOWS)}; got {shown}"
    )


def frozen(*arrays: np.ndarray) -> None:
    """Make cached arrays read-only (in place)."""
    for a in arrays:
        a.setflags(write=False)


def get_window(window: str, n: int) -> np.ndarray:
    """:func:`scipy.signal.get_window` (periodic), with the Hann window computed here as
    scipy does it, bit for bit: importing scipy.signal costs a worker process 50 MB and
    half a second."""
    if window in ("hann", "hanning", "han"):
        fac = np.linspace(-np.pi, np.pi, n + 1)  # scipy: n + 1 symmetric points, truncated
        w = np.zeros(n + 1)
        w += 0.5 * np.cos(0 * fac)
        w += 0.5 * np.cos(1 * fac)
        return w[:-1]
    from scipy import signal

    return np.asarray(signal.get_window(window, n), dtype=float)


@table_cache(32)
def hann_plan(n: int, window: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Window, orthonormal detrend basis (n, 2) and ``sum(window^2)`` for ``n`` samples."""
    win = get_window(window, n)
    t = np.arange(n, dtype=float)
    basis, _ = np.linalg.qr(np.column_stack([np.ones(n), t - t.mean()]))
    basis = np.ascontiguousarray(basis)
    frozen(win, basis)
    return win, basis, float(np.sum(win**2))


def log_bias(window: str, nperseg: int, noverlap: int, n: int) -> float:
    """``E[ln(P_hat / P)]`` of a (Welch) PSD ordinate of a Gaussian process.

    Uses the equivalent degrees of freedom ``nu`` of Welch averaging with the given window
    and overlap (Percival and Walden, Eq. 292b); the ordinate is ``P chi2_nu / nu`` and its
    log has mean ``psi(nu / 2) - ln(nu / 2)``: ``-gamma`` for one segment.

    Parameters
    ----------
    window : str
        Window name (:func:`scipy.signal.get_window`).
    nperseg, noverlap : int
        Segment length and overlap in samples.
    n : int
        Profile length in samples.

    Raises
    ------
    InputError
        An unknown window, or segment sizes that are not integers with
        ``8 <= nperseg <= n`` and ``0 <= noverlap < nperseg``.
    """
    check_window(window)
    check_int("n", n, low=8, high=LIMITS.grid_cells, unit="samples")
    check_int("nperseg", nperseg, low=8, high=int(n), unit="samples")
    check_int("noverlap", noverlap, low=0, high=int(nperseg) - 1, unit="samples")
    return _log_bias(window, int(nperseg), int(noverlap), int(n))


@table_cache(64)
def _log_bias(window: str, nperseg: int, noverlap: int, n: int) -> float:
    """:func:`log_bias` of checked arguments (cached)."""
    step = nperseg - noverlap
    k = 1 + (n - nperseg) // step
    if k <= 1:
        return -float(np.euler_gamma)
    from scipy import special

    win = get_window(window, nperseg)
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


@table_cache(32)
def _fast_plan(n: int, window: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """float32 mean weights ``1 / n``, unit linear trend (orthogonal to the mean), window,
    and density scale: contiguous vectors, which einsum's row loop reads three times
    faster than the columns of the (n, 2) basis."""
    win, basis, wss = hann_plan(n, window)
    mean32 = np.full(n, 1.0 / n, dtype=np.float32)
    slope32 = np.ascontiguousarray(basis[:, 1], dtype=np.float32)
    win32 = win.astype(np.float32)
    frozen(mean32, slope32, win32)
    return mean32, slope32, win32, 1.0 / (math.pi * wss)


def detrended_dft(
    h: np.ndarray, spacing: float, window: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Density-scaled DFT of the detrended, windowed finite profiles (rows).

    Each profile is detrended (its mean, then its projection on the unit linear trend,
    which is orthogonal to the mean), then windowed. Computed in float32 after removing
    one reference height per patch, which keeps about 1e-6 relative accuracy. Returns
    (omega in rad/m, the ordinates k = 1 ... n // 2 of the DFT scaled so that their
    squared modulus is the one-sided PSD in m^3/rad (but for the halving of an even
    length's last ordinate), shape ``h.shape[:-1] + (n // 2,)``, and the detrended sum of
    squares per profile in m^2).
    """
    shape = h.shape
    n = shape[-1]
    mean_w, slope, win, scale = _fast_plan(n, window)
    # Non-finite cells are allowed through here: the caller finds them in ``ss``.
    with np.errstate(invalid="ignore", over="ignore"):
        ref = h[..., :1, :].mean(axis=-1, keepdims=True) if h.ndim > 1 else h[:1].mean()
        x: np.ndarray = np.empty(shape, dtype=np.float32)
        np.subtract(h, ref, out=x, casting="same_kind")
        x = x.reshape(-1, n)
        # Row by row (einsum's own loop along each row), never a matrix product, whose
        # order of summation depends on how many rows are stacked: a profile's spectrum
        # must not depend on the batch it came in.
        x -= np.einsum("ij,j->i", x, mean_w)[:, None]  # a broadcast pass, no temporary
        x -= np.einsum("ij,j->i", x, slope)[:, None] * slope
        # The sum of squares of the detrended profile itself: no cancellation.
        ss = np.einsum("ij,ij->i", x, x)
        # Fold the density scale into the window (one pass less): |c X|^2 = c^2 |X|^2.
        x *= win * np.float32(math.sqrt(scale * spacing))
        spec = scipy.fft.rfft(x, axis=-1)[:, 1:]
    omega = 2.0 * np.pi * np.arange(1, n // 2 + 1) / (n * spacing)
    return omega, spec.reshape(*shape[:-1], spec.shape[-1]), ss.reshape(shape[:-1])


def power(spec: np.ndarray, n: int, overwrite: bool = False) -> np.ndarray:
    """One-sided PSD in m^3/rad of the ordinates of :func:`detrended_dft` (profile length
    ``n``); with ``overwrite``, ``spec`` is used as scratch (and no longer holds the
    ordinates)."""
    # Squares of the float view (one contiguous pass), then re^2 + im^2.
    v = spec.view(spec.real.dtype)
    with np.errstate(invalid="ignore", over="ignore"):
        sq = np.square(v, out=v if overwrite else None)
        p = sq[..., 0::2] + sq[..., 1::2]
    if n % 2 == 0:
        p[..., -1] *= 0.5
    return p


def adjacent_cross(spec: np.ndarray, n: int) -> np.ndarray:
    """Mean cross-spectrum in m^3/rad of adjacent rows, ``Re(X_i conj(X_(i+1)))``, of the
    ordinates of :func:`detrended_dft` of a stack (patches, rows, bins): (patches, bins).
    NaN for patches of one row."""
    if spec.shape[1] < 2:
        return np.full((spec.shape[0], spec.shape[2]), np.nan)
    # Re(a conj(b)) = a.re b.re + a.im b.im: the sum over the rows of the products of the
    # float views, one pass (no matrix product: the sum runs row by row for every patch).
    v = np.ascontiguousarray(spec).view(spec.real.dtype)
    with np.errstate(invalid="ignore", over="ignore"):
        s = np.einsum("prk,prk->pk", v[:, :-1], v[:, 1:])
        out = (s[:, 0::2] + s[:, 1::2]).astype(np.float64) / (spec.shape[1] - 1)
    if n % 2 == 0:
        out[:, -1] *= 0.5
    return out


def periodogram(
    h: np.ndarray, spacing: float, window: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detrended single-segment periodogram of finite profiles (rows), in m^3/rad.

    Returns (omega in rad/m, psd, detrended sum of squares per profile in m^2); see
    :func:`detrended_dft`.
    """
    omega, spec, ss = detrended_dft(h, spacing, window)
    return omega, power(spec, h.shape[-1], overwrite=True), ss


def spectrum(
    h: np.ndarray, spacing: float, window: str, nperseg: int | None, noverlap: int | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """PSD of finite profiles: (omega rad/m, psd m^3/rad, log bias)."""
    n = h.shape[-1]
    if nperseg is None or nperseg >= n:
        omega, p, _ = periodogram(h, spacing, window)
        return omega, p, -float(np.euler_gamma)
    if nperseg < 8:
        raise InputError(f"nperseg must be at least 8 samples, got {nperseg}")
    if noverlap is None:
        noverlap = nperseg // 2
    if not 0 <= noverlap < nperseg:
        raise InputError(f"noverlap must be in [0, nperseg), got {noverlap} for {nperseg}")
    from scipy import signal

    _, basis, _ = hann_plan(n, window)
    f, p = signal.welch(
        h - (h @ basis) @ basis.T,
        fs=1.0 / spacing,
        window=window,
        nperseg=nperseg,
        noverlap=noverlap,
        detrend="linear",
        axis=-1,
    )
    return 2 * np.pi * f[1:], p[..., 1:] / (2 * np.pi), _log_bias(window, nperseg, noverlap, n)


def detrended_rms(h: np.ndarray) -> np.ndarray:
    """Rms in m of the linearly detrended profiles, per patch (first axis of (p, m, n))."""
    _, basis, _ = hann_plan(h.shape[-1], "hann")
    x = h - h.mean(axis=-1, keepdims=True)
    c = x @ basis
    ss = np.einsum("pmn,pmn->p", x, x) - np.einsum("pmk,pmk->p", c, c)
    return np.sqrt(np.maximum(ss, 0.0) / (h.shape[1] * h.shape[2]))
