"""ISO 8608 road classes, band rms, sensor sensitivity and random profile synthesis.

ISO 8608 describes a road profile by its displacement PSD ``Phi(Omega) = Phi(Omega0) *
(Omega / Omega0) ** w`` with ``Omega0 = 1 rad/m`` and ``w = -2`` for roads. Classes A to H
have geometric-mean ``Phi(Omega0)`` of 1, 4, 16, ..., 16384 x 1e-6 m^3/rad; their
boundaries are the geometric midpoints (2, 8, 32, ... x 1e-6). The older convention quotes
``Gd(n0)`` in m^3 (m^2 per cycle/m) at ``n0 = 0.1`` cycle/m; ``Phi(Omega) = Gd(n) / (2 pi)``
with ``Omega = 2 pi n``.

Paper references are to Reina et al., "Mind the ground" (section 5.2, Eqs. 9 and 10, Table 1).
"""

from __future__ import annotations

import math

import numpy as np

from rough_map.errors import InputError

#: Class letters, smoothest first.
CLASSES: tuple[str, ...] = ("A", "B", "C", "D", "E", "F", "G", "H")
#: Geometric-mean Phi(Omega0) per class, m^3/rad at Omega0 = 1 rad/m.
PHI0: dict[str, float] = {c: 1e-6 * 4.0**i for i, c in enumerate(CLASSES)}
#: Lower boundary of Phi(Omega0) per class (A has none), m^3/rad.
LOWER: dict[str, float] = {c: (PHI0[c] / 2.0 if i else 0.0) for i, c in enumerate(CLASSES)}
#: Reference wavenumber, rad/m.
OMEGA0 = 1.0
#: Reference spatial frequency of the Gd convention, cycles/m.
N0 = 0.1


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise InputError(f"{name} must be a positive finite number, got {value!r}")
    return value


def iso_class(R: float | np.ndarray, waviness: float = -2.0) -> str | np.ndarray:
    """ISO 8608 class letter of an overall energy.

    Parameters
    ----------
    R : float or array_like
        Phi(Omega0) in m^3/rad at Omega0 = 1 rad/m. NaN gives ``""``.
    waviness : float
        Ignored for the class (ISO classes are defined on Phi(Omega0) alone); kept so that
        callers document which waviness the class is quoted with.

    Returns
    -------
    str or ndarray of str
        ``"A"`` ... ``"H"``; values below the A/B boundary are ``"A"``, above G/H ``"H"``.
    """
    del waviness
    arr = np.asarray(R, dtype=float)
    edges = np.array([LOWER[c] for c in CLASSES[1:]])
    idx = np.searchsorted(edges, arr, side="right")
    letters = np.array(CLASSES)[np.clip(idx, 0, len(CLASSES) - 1)]
    letters = np.where(np.isfinite(arr) & (arr > 0), letters, "")
    return str(letters) if letters.ndim == 0 else letters


def class_fraction(R: float) -> float:
    """Continuous class position: 0 at A's centre, 1 at B's centre, ... (log4 scale)."""
    return math.log(_positive("R", R) / PHI0["A"], 4.0)


def gd_to_phi(gd_n0: float, n0: float = N0, waviness: float = -2.0) -> float:
    """Convert ``Gd(n0)`` (m^3, at n0 cycles/m) to ``Phi(Omega0 = 1 rad/m)`` (m^3/rad)."""
    gd_n0 = _positive("gd_n0", gd_n0)
    n_at_omega0 = OMEGA0 / (2 * math.pi)
    return gd_n0 * (n_at_omega0 / n0) ** waviness / (2 * math.pi)


def phi_to_gd(phi0: float, n0: float = N0, waviness: float = -2.0) -> float:
    """Convert ``Phi(Omega0 = 1 rad/m)`` (m^3/rad) to ``Gd(n0)`` (m^3, n0 in cycles/m)."""
    return _positive("phi0", phi0) / gd_to_phi(1.0, n0, waviness)


def waveband(length: float, spacing: float) -> tuple[float, float]:
    """The paper's waveband (Eq. 3): ``(2 pi / L, pi / B)`` in rad/m.

    Parameters
    ----------
    length : float
        Profile length L = n B in m.
    spacing : float
        Sample spacing B in m.
    """
    length = _positive("length", length)
    spacing = _positive("spacing", spacing)
    if length <= 2 * spacing:
        raise InputError(f"length ({length} m) must exceed twice the spacing ({spacing} m)")
    return 2 * math.pi / length, math.pi / spacing


def band_rms(
    phi0: float, length: float, spacing: float, waviness: float = -2.0, omega0: float = OMEGA0
) -> float:
    """Rms elevation in m of a power-law profile within the waveband (paper Eq. 9).

    ``rms^2 = integral from 2 pi / L to pi / B of phi0 (Omega / omega0)^w dOmega``.

    Parameters
    ----------
    phi0 : float
        Phi(omega0) in m^3/rad.
    length, spacing : float
        Profile length L and spacing B in m; the band is ``2 pi / L`` to ``pi / B`` rad/m.
    waviness : float
        Exponent w (dimensionless), -2 for ISO 8608 roads.
    omega0 : float
        Reference wavenumber in rad/m.

    Examples
    --------
    Table 1 of the paper (L = 0.896 m, B = 0.008 m), class C:

    >>> round(band_rms(16e-6, 0.896, 0.008) * 1e3, 2)
    1.5
    """
    phi0 = _positive("phi0", phi0)
    lo, hi = waveband(length, spacing)
    if abs(waviness + 1.0) < 1e-12:
        integral = omega0 * math.log(hi / lo)
    else:
        e = waviness + 1.0
        integral = (hi**e - lo**e) / (e * omega0**waviness)
    return math.sqrt(phi0 * integral)


def sensitivity(rms: float, length: float, spacing: float, omega0: float = OMEGA0) -> float:
    """Phi(omega0) in m^3/rad of a w = -2 profile with the given band rms (paper Eq. 10).

    Use it to turn a sensor's noise floor (rms of a scan of a flat reference) into the
    smallest overall energy the sensor can tell apart.

    Parameters
    ----------
    rms : float
        Rms elevation in m measured on a flat reference.
    length, spacing : float
        Profile length and spacing in m.
    omega0 : float
        Reference wavenumber in rad/m.

    Examples
    --------
    The paper's patio, 2.22 mm rms, sits between classes C and D:

    >>> round(sensitivity(2.22e-3, 0.896, 0.008) * 1e6)
    35
    """
    rms = _positive("rms", rms)
    lo, hi = waveband(length, spacing)
    return rms**2 / (1.0 / lo - 1.0 / hi) / omega0**2


def _resolve_phi0(phi0: float | str) -> float:
    if isinstance(phi0, str):
        key = phi0.strip().upper()
        if key not in PHI0:
            raise InputError(f"unknown ISO 8608 class {phi0!r}; expected one of A-H")
        return PHI0[key]
    return _positive("phi0", phi0)


def power_law(
    omega: np.ndarray, phi0: float, waviness: float, omega0: float = OMEGA0
) -> np.ndarray:
    """``phi0 * (omega / omega0) ** waviness`` in m^3/rad, with 0 at omega = 0."""
    omega = np.asarray(omega, dtype=float)
    with np.errstate(divide="ignore"):
        out = phi0 * (np.abs(omega) / omega0) ** waviness
    return np.where(omega == 0, 0.0, out)


def synthesize_profile(
    n: int,
    spacing: float,
    phi0: float | str = "C",
    waviness: float = -2.0,
    *,
    n_profiles: int | None = None,
    oversample: int = 8,
    seed: int | np.random.Generator | None = None,
) -> np.ndarray:
    """Random Gaussian profiles with the one-sided PSD ``phi0 (Omega / 1 rad/m)^w``.

    The profiles are cut from a periodic realisation ``oversample`` times longer, so they
    carry the long wavelengths (trend and curvature) that real profiles have.

    Parameters
    ----------
    n : int
        Samples per profile.
    spacing : float
        Sample spacing in m.
    phi0 : float or str
        Phi(1 rad/m) in m^3/rad, or an ISO class letter.
    waviness : float
        Exponent w.
    n_profiles : int, optional
        Number of independent profiles; ``None`` returns one 1-D profile.
    oversample : int
        Length of the underlying realisation in units of ``n``.
    seed : int or Generator, optional
        Seed for reproducibility.

    Returns
    -------
    ndarray
        Heights in m, shape ``(n,)`` or ``(n_profiles, n)``.
    """
    spacing = _positive("spacing", spacing)
    phi0 = _resolve_phi0(phi0)
    if n < 4:
        raise InputError(f"n must be at least 4 samples, got {n}")
    rng = np.random.default_rng(seed)
    m = 1 if n_profiles is None else int(n_profiles)
    big = n * max(1, int(oversample))
    omega = 2 * np.pi * np.fft.rfftfreq(big, d=spacing)
    d_omega = 2 * np.pi / (big * spacing)
    amp = np.sqrt(big * power_law(omega, phi0, waviness) * d_omega / 2.0)
    white = rng.standard_normal((m, big))
    prof = np.fft.irfft(np.fft.rfft(white, axis=1) * amp, n=big, axis=1)
    start = rng.integers(0, big - n + 1, size=m)
    out = prof[np.arange(m)[:, None], start[:, None] + np.arange(n)]
    return out[0] if n_profiles is None else out


def surface_constant(waviness: float) -> float:
    """Integral of ``(1 + u^2)^((w - 1) / 2)`` over the real line (for 2-D synthesis)."""
    if waviness >= 0:
        raise InputError(f"waviness must be negative for an isotropic surface, got {waviness}")
    return math.sqrt(math.pi) * math.gamma(-waviness / 2) / math.gamma((1 - waviness) / 2)


def synthesize_surface(
    shape: tuple[int, int],
    spacing: float,
    phi0: float | str = "C",
    waviness: float = -2.0,
    *,
    seed: int | np.random.Generator | None = None,
) -> np.ndarray:
    """A random isotropic Gaussian surface whose profiles have PSD ``phi0 Omega^w``.

    The 2-D two-sided spectrum is ``S(k) = C |k|^(w - 1)`` with
    ``C = phi0 / (2 * surface_constant(w))``, the isotropic field whose straight profiles have
    the one-sided PSD ``phi0 (Omega / 1 rad/m)^w`` in m^3/rad. Because the grid stops at
    ``pi / B`` in ky, each kx column is then rescaled so that profiles along x (the rows)
    have exactly that PSD up to Nyquist. The surface is periodic over its extent; cut a
    patch from a larger surface to get realistic long wavelengths.

    Parameters
    ----------
    shape : (int, int)
        ``(rows, cols)``.
    spacing : float
        Cell size in m.
    phi0 : float or str
        Phi(1 rad/m) in m^3/rad, or an ISO class letter.
    waviness : float
        Exponent w of the profile PSD, negative.
    seed : int or Generator, optional
        Seed for reproducibility.

    Returns
    -------
    ndarray, shape ``shape``
        Heights in m with zero mean.
    """
    spacing = _positive("spacing", spacing)
    phi0 = _resolve_phi0(phi0)
    ny, nx = (int(shape[0]), int(shape[1]))
    if ny < 2 or nx < 4:
        raise InputError(f"shape must be at least (2, 4), got {shape}")
    rng = np.random.default_rng(seed)
    const = phi0 / (2.0 * surface_constant(waviness))
    ky = 2 * np.pi * np.fft.fftfreq(ny, d=spacing)
    kx = 2 * np.pi * np.fft.rfftfreq(nx, d=spacing)
    k = np.hypot(ky[:, None], kx[None, :])
    with np.errstate(divide="ignore"):
        s2 = np.where(k > 0, const * k ** (waviness - 1.0), 0.0)
    # On a finite grid the profile spectrum is a sum over ky up to pi/B only, which misses
    # the tail of the integral near Nyquist: rescale every kx column so that profiles along
    # x have exactly the requested one-sided PSD.
    dky = 2 * np.pi / (ny * spacing)
    colsum = s2[:, 1:].sum(axis=0) * dky
    s2[:, 1:] *= (0.5 * power_law(kx[1:], phi0, waviness)) / colsum
    dk = (2 * np.pi / (nx * spacing)) * dky
    amp = np.sqrt(nx * ny * s2 * dk)
    white = rng.standard_normal((ny, nx))
    return np.fft.irfft2(np.fft.rfft2(white) * amp, s=(ny, nx))
