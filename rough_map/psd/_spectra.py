"""Profile spectra in m^3/rad: the input checks and gap policy of the estimator (see
:mod:`rough_map.psd`, *Gap policy*), then the detrended, windowed spectra (the
single-segment fast path and Welch).

The plans (window, detrend basis, density scale) are cached per profile length, as are the
estimator's other tables (projections, leakage, the standard-error kernels), with
:func:`table_cache`; the cached arrays are read-only, so that no caller can change what the
next call gets. Several tables are built with matrix products, and OpenBLAS splits a
product's sums by its number of threads: a table built on two threads differs in the last
bit from one built on one. A worker (BLAS pinned to one thread) and a main process that
built its tables earlier on two would then read the same patch differently. So the tables
are built with BLAS on one thread, whatever the caller's setting.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache, wraps
from numbers import Real
from typing import Any, TypeVar

import numpy as np
import scipy.fft

from rough_map._blas import one_blas_thread
from rough_map.errors import InputError
from rough_map.limits import LIMITS
from rough_map.patch._params import check_bool, check_int, check_real

F = TypeVar("F", bound=Callable[..., Any])


def table_cache(maxsize: int) -> Callable[[F], F]:
    """:func:`functools.lru_cache` of a function computed with BLAS on one thread."""

    def decorate(fn: F) -> F:
        @wraps(fn)
        def one_thread(*args: Any, **kwargs: Any) -> Any:
            with one_blas_thread():
                return fn(*args, **kwargs)

        return lru_cache(maxsize=maxsize)(one_thread)  # type: ignore[return-value]

    return decorate


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


def check_spacing(spacing: Any) -> float:
    """The sample spacing as a positive float in m, or :class:`InputError`."""
    ok = isinstance(spacing, Real) and not isinstance(spacing, bool | np.bool_)
    value = float(spacing) if ok else math.nan
    if not (math.isfinite(value) and 0 < value <= 1e3):
        shown = repr(spacing) if len(repr(spacing)) <= 40 else repr(spacing)[:37] + "..."
        raise InputError(f"spacing must be a positive length in m (at most 1000); got {shown}")
    return value


def check_heights(heights: Any, min_samples: int = 8) -> np.ndarray:
    """A height grid (profiles, samples) in m; a 1-D profile becomes one row.

    Raises :class:`InputError` for non-numeric, empty, short or infinite input (NaN is
    missing data and passes).
    """
    h = as_heights(heights)
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
    if h.size > LIMITS.grid_cells:
        raise InputError(
            f"heights has {h.size} cells (shape {h.shape}); at most {LIMITS.grid_cells}"
        )
    # two passes (fmax and fmin skip NaN; all NaN gives NaN), where isinf, isnan, abs and
    # nanmax took four
    flat = h.reshape(-1)
    hi, lo = float(np.fmax.reduce(flat)), float(np.fmin.reduce(flat))
    if math.isinf(hi) or math.isinf(lo):
        raise InputError("heights contain infinite values; use NaN for missing cells")
    top = max(hi, -lo) if not math.isnan(hi) else 0.0
    if top > MAX_HEIGHT:
        raise InputError(
            f"heights reach {top:.3g} m, beyond {MAX_HEIGHT:.0e} m: wrong units? (elevations in m)"
        )
    return h


MAX_HEIGHT = 1e6
"""Largest |height| accepted, m: far beyond any relief, so only wrong units or garbage reach it
(and the spectra of larger values can overflow)."""


def as_heights(heights: Any) -> np.ndarray:
    """``heights`` as a float array, or :class:`InputError` for non-numeric input."""
    try:
        raw = np.asarray(heights)
        if raw.dtype.kind not in "biuf":
            raise TypeError(raw.dtype)
        return np.asarray(raw, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError("heights must be a real numeric array of elevations in m") from None


def fill_gaps(
    heights: np.ndarray,
    spacing: float,
    *,
    max_gap: float = 0.05,
    max_gap_fraction: float = 0.2,
    copy: bool = True,
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
    copy : bool
        Fill a copy (the default); False fills ``heights`` itself when it is a float64
        array, which the caller then gives up.

    Returns
    -------
    filled : ndarray, shape (m, n)
        Heights in m with short gaps filled; dropped rows are left as they were.
    keep : ndarray of bool, shape (m,)
        Profiles that pass the policy.
    """
    h = as_heights(heights)
    if h.ndim != 2 or h.size == 0:
        raise InputError(
            f"heights must be a non-empty 2-D grid (profiles x samples), got {h.shape}"
        )
    if h.size > LIMITS.grid_cells:
        raise InputError(
            f"heights has {h.size} cells (shape {h.shape}); at most {LIMITS.grid_cells}"
        )
    spacing = check_spacing(spacing)
    check_real("max_gap", max_gap, "m", low=0.0, high=1e6)
    check_real("max_gap_fraction", max_gap_fraction, "", low=0.0, high=1.0)
    check_bool("copy", copy)
    missing = np.isnan(h)
    if not missing.any():
        return h, np.ones(h.shape[0], dtype=bool)
    m, n = h.shape
    # The runs of missing cells, found on the rows padded with a valid cell at each end
    # (so no run crosses a row): start and end (exclusive) in padded coordinates.
    padded = np.zeros((m, n + 2), dtype=np.int8)
    padded[:, 1:-1] = missing
    step = np.diff(padded.ravel())
    starts = np.flatnonzero(step == 1) + 1
    ends = np.flatnonzero(step == -1) + 1
    row = starts // (n + 2)
    first = starts - row * (n + 2) - 1  # first missing column of each run
    length = ends - starts  # a gap touching an end counts its full length from that end
    longest = np.zeros(m, dtype=np.intp)
    np.maximum.at(longest, row, length)
    n_missing = missing.sum(axis=1)
    max_cells = int(math.floor(max_gap / spacing + 1e-9))
    keep = (longest <= max_cells) & (n_missing / n <= max_gap_fraction)
    keep &= n - n_missing >= 2
    filled = h.copy() if copy else h
    fill = keep[row]
    if not fill.any():
        return filled, keep
    row, first, length = row[fill], first[fill], length[fill]
    # Each missing cell of a kept row: the valid samples before and after its run
    # (-1 and n past the ends), interpolated linearly; a run touching an end takes the
    # valid sample at its other side.
    size = int(length.sum())
    run = np.repeat(np.arange(row.size), length)
    col = first[run] + (np.arange(size) - np.repeat(np.cumsum(length) - length, length))
    r = row[run]
    prev = first[run] - 1
    nxt = first[run] + length[run]
    hp = h[r, np.clip(prev, 0, n - 1)]
    hq = h[r, np.clip(nxt, 0, n - 1)]
    hp = np.where(prev < 0, hq, hp)
    hq = np.where(nxt >= n, hp, hq)
    inside = (nxt < n) & (prev >= 0)
    span = np.where(inside, (nxt - prev).astype(float), 1.0)
    frac = np.where(inside, (col - prev) / span, 0.0)
    filled[r, col] = hp + frac * (hq - hp)
    return filled, keep
