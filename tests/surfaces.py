"""Continuous random surfaces for tests: an isotropic Gaussian field with a power-law spectrum.

:func:`power_law_field` synthesises, by FFT, a periodic Gaussian height field over a domain
much larger than a patch (say 8-16 m square), so that the long wavelengths that real ground
has (trends, curvature, lateral correlation between neighbouring profiles) are there when a
0.9 m patch is cut from it. It is written independently of :mod:`rough_map.psd`: the
truth is the generating spectrum, not anything the estimator assumes.

The field is the isotropic one whose straight profiles have the one-sided PSD
``R (Omega / 1 rad/m)^w`` in m^3/rad: the two-sided 2-D spectral density is
``S(k) = C |k|^(w - 1)`` with ``C = R / (2 I(w))`` and ``I(w) = integral over the real line
of (1 + u^2)^((w - 1) / 2) du`` (:func:`rough_map.iso8608.surface_constant`), because a
profile's PSD is the integral of ``S`` over the lateral wavenumber.

Sampling. The grid rows (along x, the profiles) are band-limited at ``pi / spacing``: the
field holds no wavenumber above the rows' Nyquist along x, so every row has exactly the PSD
``R Omega^w`` up to ``pi / spacing`` and nothing aliases along the profile (the model of
``gridding="point"``). Across the rows (along y) the field is the full continuous one
sampled every ``spacing``: the lateral wavenumbers above ``pi / spacing`` are folded into
the band (aliased) exactly as point samples of the continuous surface would fold them, so the
covariance between rows j apart is that of the continuous field at lag ``j * spacing``, and
the integral over ky of every column is the full integral. To get true point samples of a
surface that is not band-limited along x either, synthesise at a finer spacing and take
every q-th sample (:meth:`Field.sample` interpolates between the nodes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from rough_map.iso8608 import surface_constant

#: Folds of the lateral wavenumber summed explicitly on each side; the rest is an integral.
_FOLDS = 6


@dataclass(frozen=True)
class Field:
    """A periodic height field on a square grid.

    Attributes
    ----------
    heights : ndarray, shape (ny, nx)
        Heights in m; rows are profiles along x, row ``i`` is at ``y = i * spacing``.
        Read-only (fields are cached).
    spacing : float
        Grid spacing in m.
    R : float
        Profile PSD at 1 rad/m, m^3/rad (the truth for the estimator).
    w : float
        Waviness (slope of the profile PSD in log-log), dimensionless.
    """

    heights: np.ndarray
    spacing: float
    R: float
    w: float

    @property
    def size(self) -> tuple[float, float]:
        """``(ly, lx)`` extent of the periodic domain in m."""
        ny, nx = self.heights.shape
        return ny * self.spacing, nx * self.spacing

    def patches(self, n: int = 112, step: int | None = None) -> np.ndarray:
        """Square ``n x n`` patches cut on a regular grid, ``step`` cells apart (default
        ``n``: adjacent, not overlapping). Shape ``(count, n, n)``, a copy."""
        step = n if step is None else int(step)
        ny, nx = self.heights.shape
        rows = range(0, ny - n + 1, step)
        cols = range(0, nx - n + 1, step)
        return np.stack([self.heights[r : r + n, c : c + n] for r in rows for c in cols])

    def sample(self, x: np.ndarray, y: np.ndarray, order: int = 3) -> np.ndarray:
        """Heights in m at points ``(x, y)`` in m, by spline interpolation of the grid
        (cubic by default), wrapping around the periodic domain."""
        coords = np.stack([np.asarray(y, float), np.asarray(x, float)]) / self.spacing
        if order == 3:
            return sample_spline(self.coefficients, coords)
        return ndimage.map_coordinates(self.heights, coords, order=order, mode="grid-wrap")

    @cached_property
    def coefficients(self) -> np.ndarray:
        """Cubic spline coefficients of the periodic grid (:func:`spline_coefficients`),
        computed once per field: a cloud's sample then costs its points, not the field."""
        return spline_coefficients(self.heights)


def spline_coefficients(heights: np.ndarray) -> np.ndarray:
    """Cubic spline coefficients of a periodic grid, read-only: what
    ``ndimage.map_coordinates(order=3, mode="grid-wrap")`` computes on every call (about
    0.2 s for 2048 x 2048), for :func:`sample_spline`."""
    coeffs = ndimage.spline_filter(heights, order=3, mode="grid-wrap")
    coeffs.setflags(write=False)
    return coeffs


def sample_spline(coefficients: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Cubic interpolation at ``coords`` (rows, columns; in cells) of the periodic grid whose
    :func:`spline_coefficients` are given: the same numbers as ``map_coordinates`` on the
    grid itself."""
    return ndimage.map_coordinates(coefficients, coords, order=3, mode="grid-wrap", prefilter=False)


def fold_spectrum(kx: np.ndarray, ky: np.ndarray, spacing: float, w: float) -> np.ndarray:
    """``sum over a of |k + (0, 2 pi a / spacing)|^(w - 1)`` on the grid ``kx`` x ``ky``
    (rad/m, ky within the band): the lateral folding of the unit-constant spectrum.

    ``_FOLDS`` folds on each side are summed; the remaining tails are their integrals
    (Euler-Maclaurin, with the first-order term in ``kx^2``), a few 1e-5 of the total.
    """
    period = 2 * math.pi / spacing
    kx2 = (kx * kx)[None, :]
    p = (w - 1.0) / 2.0
    total = np.zeros((ky.size, kx.size))
    for a in range(-_FOLDS, _FOLDS + 1):
        k2 = kx2 + ((ky + a * period) ** 2)[:, None]
        with np.errstate(divide="ignore"):
            total += np.where(k2 > 0, k2, np.inf) ** p
    for sign in (1.0, -1.0):
        # sum over a > _FOLDS of f(ky + sign a P) ~ (1/P) integral from Y of f, Y as below.
        y0 = ((_FOLDS + 0.5) * period + sign * ky)[:, None]
        tail = y0**w / -w + p * kx2 * y0 ** (w - 2.0) / (2.0 - w)
        total += tail / period
    return total


@lru_cache(maxsize=4)
def power_law_field(n: int, spacing: float, R: float, w: float, seed: int) -> Field:
    """A periodic ``n x n`` isotropic Gaussian field whose profiles have PSD ``R Omega^w``.

    Parameters
    ----------
    n : int
        Cells per side (even); the domain is ``n * spacing`` m square.
    spacing : float
        Grid spacing in m.
    R : float
        One-sided profile PSD at 1 rad/m, m^3/rad (ISO 8608 class A to D: about 2.5e-7
        to 1.3e-4).
    w : float
        Waviness, negative (-2 for ISO roads; -2 to -3 for natural ground).
    seed : int
        Seed of the white noise.

    Returns
    -------
    Field
        Cached and read-only: the same arguments give the same array.

    Notes
    -----
    Every row is a stationary Gaussian profile whose expected periodogram over the full
    domain is ``R kx^w`` at each ``kx = 2 pi j / (n spacing)`` up to ``pi / spacing``
    (the domain's discrete ky sum equals the integral up to ``exp(-kx * n * spacing)``).
    The kx = 0 column (constant along a row) is kept: each row has its own mean.
    """
    if n % 2 or n < 8:
        raise ValueError(f"n must be an even number of at least 8, got {n}")
    if not (w < -1.0):
        raise ValueError(f"w must be below -1 for the lateral sum to converge, got {w}")
    const = R / (2.0 * surface_constant(w))
    kx = 2 * np.pi * np.fft.rfftfreq(n, d=spacing)
    ky = 2 * np.pi * np.fft.fftfreq(n, d=spacing)
    s2 = const * fold_spectrum(kx, ky, spacing, w)
    s2[0, 0] = 0.0
    dk = (2 * np.pi / (n * spacing)) ** 2
    amp = np.sqrt(s2 * dk * n * n)
    white = np.random.default_rng(seed).standard_normal((n, n))
    heights = np.fft.irfft2(np.fft.rfft2(white) * amp, s=(n, n))
    heights.setflags(write=False)
    return Field(heights, spacing, float(R), float(w))


# ------------------------------------------------------- ground that is not a power law
#: Spacing in m of the height grids below: a photogrammetric or DEM-like 1 cm grid.
GRID_STEP = 0.01


@lru_cache(maxsize=8)
def real_like_surface(kind: str, seed: int, n: int = 300) -> np.ndarray:
    """A 1 cm height grid (``n`` x ``n``, read-only) of ground outside the Gaussian
    power-law family, as users bring it; read between the nodes bilinearly
    (:func:`bilinear`), as a height map exported or gridded from a survey is.

    ``kind``:

    * ``"blocks"``: paving, rounded stones of about 9 cm on a jittered lattice, each at
      its own height (4 mm rms), with joints between them: a characteristic scale.
    * ``"boulders"``: a gravel bed with boulders 3-20 cm across and half as high, with
      steep sides: heavy tails, slopes near vertical.
    * ``"smooth"``: an isotropic power law (w -2.4, 4 mm rms) smoothed over 4 mm, as a
      stereo reconstruction is: no power below a few millimetres.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] * GRID_STEP
    if kind == "blocks":
        stone = 0.09
        k = int(n * GRID_STEP / stone) + 2
        cy, cx = np.mgrid[0:k, 0:k] * stone
        centres = np.column_stack([cx.ravel(), cy.ravel()])
        centres += rng.uniform(-0.3, 0.3, centres.shape) * stone
        from scipy.spatial import cKDTree

        d, i = cKDTree(centres).query(np.column_stack([x.ravel(), y.ravel()]), k=2)
        edge = np.clip((d[:, 1] - d[:, 0]) / (0.5 * stone), 0.0, 1.0)
        z = rng.normal(0.0, 0.004, len(centres))[i[:, 0]] + 0.012 * np.sqrt(edge)
        z = z.reshape(n, n)
    elif kind == "boulders":
        z = ndimage.gaussian_filter(rng.normal(0.0, 0.01, (n, n)), 1.0)
        side = n * GRID_STEP
        for _ in range(int(12 * side * side)):
            r = rng.uniform(0.03, 0.2)
            h = rng.uniform(0.3, 0.8) * r
            x0, y0 = rng.uniform(0.0, side, 2)
            rr = np.hypot(x - x0, y - y0) / r
            z = np.maximum(z, h * np.sqrt(np.clip(1.0 - rr**4, 0.0, None)))
    elif kind == "smooth":
        fine = 4
        m = n * fine
        step = GRID_STEP / fine
        k1 = 2 * np.pi * np.fft.fftfreq(m, step)
        kk = np.hypot(*np.meshgrid(k1, k1))
        kk[0, 0] = 1.0
        amp = kk ** ((-2.4 - 1.0) / 2.0)
        amp[0, 0] = 0.0
        noise = rng.normal(size=(m, m)) + 1j * rng.normal(size=(m, m))
        f = ndimage.gaussian_filter(np.fft.ifft2(amp * noise).real, 0.004 / step)
        z = (f * (0.004 / f.std()))[::fine, ::fine]
    else:
        raise ValueError(f"unknown surface kind {kind!r}")
    z = np.ascontiguousarray(z, dtype=float)
    z.setflags(write=False)
    return z


def bilinear(grid: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Heights in m at ``(x, y)`` in m (from node (0, 0)) of a 1 cm grid
    (:data:`GRID_STEP`), by bilinear interpolation between its nodes."""
    coords = np.stack([np.asarray(y, float), np.asarray(x, float)]) / GRID_STEP
    return ndimage.map_coordinates(grid, coords, order=1, mode="nearest")


def write_height_geotiff(
    path: Path, z: np.ndarray, crs: str | None, transform: Any, dtype: str = "float32"
) -> Path:
    """``z`` (m, NaN missing) as a one-band GeoTIFF of ``dtype`` with nodata -9999, in
    ``crs`` (None: none) at ``transform`` (an affine.Affine): any raster a test needs,
    rotated, in degrees or in feet included."""
    import rasterio

    nodata = -9999.0
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=z.shape[1],
        height=z.shape[0],
        count=1,
        dtype=dtype,
        crs=crs,
        transform=transform,
        nodata=nodata,
    ) as ds:
        ds.write(np.where(np.isfinite(z), z, nodata).astype(dtype), 1)
    return path
