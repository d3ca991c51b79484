"""Seeded synthetic terrain: the paper's surfaces as height fields.

Each surface is a random isotropic Gaussian field with a power-law profile PSD
``R (Omega / 1 rad/m)^w`` (see :func:`rough_map.iso8608.synthesize_surface`), plus the
structure that makes it what it is:

========== ================ ===== =============================================
name       R (m^3/rad)      w     extra
========== ================ ===== =============================================
concrete   16e-6 (ISO C)    -2.0  none (:func:`joints` adds expansion joints)
dirt_road  64e-6 (ISO D)    -2.2  shallow wheel ruts
gravel     256e-6 (ISO E)   -2.4  pebbles (5-25 mm) scattered on the surface
compact    393e-6           -2.40 none (paper section 5.1, olive grove)
ploughed   1734e-6          -2.59 furrows and ridges across the direction of travel
========== ================ ===== =============================================

Isolated defects (paper section 5.1, Fig. 13) are added with :func:`add_manhole`,
:func:`add_pit` and :func:`add_rock`. Everything is deterministic for a given seed.
Heights are in m, grids are ``[row = y, col = x]`` with the direction of travel along x.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rough_map.errors import InputError
from rough_map.iso8608 import PHI0, synthesize_surface


@dataclass(frozen=True)
class SurfaceSpec:
    """Spectral parameters of a named surface.

    Attributes
    ----------
    name : str
        Terrain class name.
    R : float
        Phi(1 rad/m) of the random part, m^3/rad.
    w : float
        Waviness of the random part.
    description : str
        What it stands for.
    """

    name: str
    R: float
    w: float
    description: str
    base_scale: float = 1.0  # R of the random part relative to R (the extras add the rest)
    base_w: float | None = None  # waviness of the random part, if the extras shift w


SURFACES: dict[str, SurfaceSpec] = {
    "concrete": SurfaceSpec("concrete", PHI0["C"], -2.0, "smooth concrete pathway, ISO C"),
    "dirt_road": SurfaceSpec("dirt_road", PHI0["D"], -2.2, "well-beaten dirt road, ISO D"),
    "gravel": SurfaceSpec(
        "gravel",
        PHI0["E"],
        -2.4,
        "gravel-like surface with pebbles, ISO E",
        base_scale=0.75,
        base_w=-2.58,
    ),
    "compact_soil": SurfaceSpec("compact_soil", 393e-6, -2.40, "compact agricultural soil"),
    "ploughed_soil": SurfaceSpec(
        "ploughed_soil", 1734e-6, -2.59, "ploughed vineyard soil", base_scale=0.75, base_w=-2.55
    ),
}

ALIASES = {"compact": "compact_soil", "ploughed": "ploughed_soil", "dirt": "dirt_road"}


def surface_spec(name: str) -> SurfaceSpec:
    """The :class:`SurfaceSpec` of a surface name (aliases: compact, ploughed, dirt)."""
    key = ALIASES.get(name, name)
    if key not in SURFACES:
        raise InputError(f"unknown surface {name!r}; expected one of {sorted(SURFACES)}")
    return SURFACES[key]


def _rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    return np.random.default_rng(seed)


def generate(
    name: str,
    shape: tuple[int, int],
    spacing: float = 0.008,
    *,
    seed: int | np.random.Generator | None = None,
    roughness_scale: float = 1.0,
    extras: bool = True,
) -> np.ndarray:
    """A height field of a named surface.

    Parameters
    ----------
    name : str
        One of :data:`SURFACES` (or an alias).
    shape : (int, int)
        ``(rows, cols)``; rows along y, columns along x (the direction of travel).
    spacing : float
        Cell size in m.
    seed : int or Generator, optional
        Seed for reproducibility.
    roughness_scale : float
        Multiplies R (so heights by its square root); used to vary a stretch along a course.
    extras : bool
        Add the surface's structure (pebbles, furrows, ruts, joints).

    Returns
    -------
    ndarray
        Heights in m.
    """
    spec = surface_spec(name)
    rng = _rng(seed)
    if not (math.isfinite(roughness_scale) and roughness_scale > 0):
        raise InputError(f"roughness_scale must be positive, got {roughness_scale!r}")
    w_base = spec.w if spec.base_w is None else spec.base_w
    h = synthesize_surface(
        shape, spacing, spec.R * spec.base_scale * roughness_scale, w_base, seed=rng
    )
    if extras and spec.name in _EXTRAS:
        h = h + math.sqrt(roughness_scale) * _EXTRAS[spec.name](shape, spacing, rng)
    return h


# --------------------------------------------------------------------------- structure


def _grid(shape: tuple[int, int], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    ny, nx = shape
    return np.arange(nx) * spacing, np.arange(ny) * spacing


def pebbles(
    shape: tuple[int, int],
    spacing: float,
    rng: np.random.Generator,
    *,
    density: float = 40.0,
    radius: tuple[float, float] = (0.005, 0.025),
) -> np.ndarray:
    """Rounded pebbles: ``density`` per m^2, radii uniform in ``radius`` (m)."""
    ny, nx = shape
    area = nx * ny * spacing**2
    count = rng.poisson(density * area)
    out = np.zeros(shape)
    if count == 0:
        return out
    r = rng.uniform(*radius, size=count)
    cx = rng.uniform(0, nx * spacing, size=count)
    cy = rng.uniform(0, ny * spacing, size=count)
    height = r * rng.uniform(0.4, 0.8, size=count)
    for ri, xi, yi, hi in zip(r, cx, cy, height, strict=True):
        j0, j1 = max(int((xi - ri) / spacing), 0), min(int((xi + ri) / spacing) + 2, nx)
        i0, i1 = max(int((yi - ri) / spacing), 0), min(int((yi + ri) / spacing) + 2, ny)
        if j0 >= j1 or i0 >= i1:
            continue
        xx = np.arange(j0, j1) * spacing - xi
        yy = np.arange(i0, i1) * spacing - yi
        d2 = (xx[None, :] ** 2 + yy[:, None] ** 2) / ri**2
        bump = hi * np.sqrt(np.clip(1 - d2, 0, None))  # half-ellipsoid
        np.maximum(out[i0:i1, j0:j1], bump, out=out[i0:i1, j0:j1])
    return out - out.mean()


def furrows(
    shape: tuple[int, int],
    spacing: float,
    rng: np.random.Generator,
    *,
    period: tuple[float, float] = (0.28, 0.40),
    amplitude: tuple[float, float] = (0.002, 0.004),
    angle_deg: tuple[float, float] = (70.0, 110.0),
) -> np.ndarray:
    """Ploughing furrows and ridges: a skewed periodic ridge pattern, wobbling slightly.

    ``angle_deg`` is the angle between the furrows and the direction of travel (x).
    """
    x, y = _grid(shape, spacing)
    per = rng.uniform(*period)
    amp = rng.uniform(*amplitude)
    ang = math.radians(rng.uniform(*angle_deg))
    # Coordinate across the furrows, with a slow wobble so the ridges are not ruler-straight.
    s = x[None, :] * math.sin(ang) - y[:, None] * math.cos(ang)
    along = x[None, :] * math.cos(ang) + y[:, None] * math.sin(ang)
    wobble = 0.03 * np.sin(2 * np.pi * along / rng.uniform(1.5, 3.0) + rng.uniform(0, 6.3))
    phase = 2 * np.pi * (s + wobble) / per + rng.uniform(0, 2 * np.pi)
    # Sharp ridges, broad furrows.
    return amp * (np.abs(np.cos(0.5 * phase)) ** 0.5 * 2 - 1.2)


def ruts(shape: tuple[int, int], spacing: float, rng: np.random.Generator) -> np.ndarray:
    """Two shallow wheel ruts along x, 1.8-2.0 m apart about the middle, 5-15 mm deep."""
    x, y = _grid(shape, spacing)
    gauge = rng.uniform(1.8, 2.0)
    depth = rng.uniform(0.005, 0.015)
    centre = y.mean() + rng.uniform(-0.05, 0.05)
    drift = 0.1 * np.sin(2 * np.pi * x / rng.uniform(8, 20) + rng.uniform(0, 6.3))
    out = np.zeros(shape)
    for side in (-0.5, 0.5):
        c = centre + side * gauge + drift[None, :]
        out -= depth * np.exp(-(((y[:, None] - c) / 0.12) ** 2))
    return out


def joints(
    shape: tuple[int, int], spacing: float, rng: np.random.Generator, every: float = 3.0
) -> np.ndarray:
    """Concrete expansion joints across x: 10 mm wide, 3-6 mm deep, every ``every`` m."""
    x, _ = _grid(shape, spacing)
    out = np.zeros(shape)
    start = rng.uniform(0, every)
    for xj in np.arange(start, x[-1] + spacing, every):
        out[:, np.abs(x - xj) < 0.005] -= rng.uniform(0.003, 0.006)
    return out


_EXTRAS: dict[str, Callable[[tuple[int, int], float, np.random.Generator], np.ndarray]] = {
    "gravel": pebbles,
    "ploughed_soil": furrows,
    "dirt_road": ruts,
}


# --------------------------------------------------------------------------- defects


def _disc(
    h: np.ndarray, spacing: float, centre: tuple[float, float], radius: float
) -> tuple[np.ndarray, float]:
    ny, nx = h.shape
    x = np.arange(nx) * spacing - centre[0]
    y = np.arange(ny) * spacing - centre[1]
    return np.hypot(x[None, :], y[:, None]), radius


def add_manhole(
    h: np.ndarray,
    spacing: float,
    centre: tuple[float, float],
    *,
    radius: float = 0.3,
    depth: float = 0.02,
    rim: float = 0.03,
) -> np.ndarray:
    """A manhole: a cover sunk ``depth`` m inside a ``rim`` m wide gap, at grid (x, y) m.

    Returns a new array; the cover itself is flat (it replaces the surface).
    """
    r, radius = _disc(h, spacing, centre, radius)
    out = h.copy()
    inside = r < radius
    if inside.any():
        out[inside] = np.median(h[inside]) - depth
    ring = (r >= radius) & (r < radius + rim)
    out[ring] -= 3 * depth
    return out


def add_pit(
    h: np.ndarray,
    spacing: float,
    centre: tuple[float, float],
    *,
    radius: float = 0.15,
    depth: float = 0.06,
) -> np.ndarray:
    """A bowl-shaped pit ``depth`` m deep at grid (x, y) m; returns a new array."""
    r, radius = _disc(h, spacing, centre, radius)
    return h - depth * np.clip(1 - (r / radius) ** 2, 0, None)


def add_rock(
    h: np.ndarray,
    spacing: float,
    centre: tuple[float, float],
    *,
    radius: float = 0.12,
    height: float = 0.08,
) -> np.ndarray:
    """A rock (half-ellipsoid) ``height`` m high at grid (x, y) m; returns a new array."""
    r, radius = _disc(h, spacing, centre, radius)
    return np.maximum(h, h + height * np.sqrt(np.clip(1 - (r / radius) ** 2, 0, None)))


#: Defect name -> ``add(h, spacing, centre, **size)`` returning a new height grid (m).
DEFECTS: dict[str, Callable[..., np.ndarray]] = {
    "manhole": add_manhole,
    "pit": add_pit,
    "rock": add_rock,
}
