"""Procedural ground textures: albedo as a function of world (x, y) and terrain class.

Stereo matching needs texture, and the two views of a rig must see the same texture, so the
albedo is a pure function of the world position of a surface point (never of the pixel):
multi-octave value noise around a class colour, plus pebbles for the stony classes.

Value noise of lattice step ``s`` (m) is a smooth interpolation of independent uniform values
at the lattice nodes; the lattice values come from an integer hash of the node and of a salt,
so the texture is defined everywhere without storing anything and never repeats. Octaves
finer than the pixel footprint would alias (and alias differently in the two views), so each
octave is faded out where the footprint of a pixel on the ground exceeds half its step
(:meth:`TextureSet.albedo`'s ``footprint``), the usual frequency clamping of procedural
textures.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

#: Weights of the B, G, R channels in the gray level (ITU-R BT.601, as OpenCV).
GRAY_WEIGHTS = np.array([0.114, 0.587, 0.299])


def _mix(h: np.ndarray) -> np.ndarray:
    """Finalise 32-bit hashes (lowbias32) into uniform float32 in [0, 1); consumes ``h``."""
    tmp = np.empty_like(h)
    for shift, factor in ((16, 0x7FEB352D), (15, 0x846CA68B)):
        np.right_shift(h, np.uint32(shift), out=tmp)
        np.bitwise_xor(h, tmp, out=h)
        np.multiply(h, np.uint32(factor), out=h)
    np.right_shift(h, np.uint32(16), out=tmp)
    np.bitwise_xor(h, tmp, out=h)
    out = h.astype(np.float32)
    out *= np.float32(2.0**-32)
    return out


def _lattice(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice node (as wrapping uint32) and fractional part (float32) of ``g``.

    Nodes must fit in int32: 3000 km at a 1.5 mm step.
    """
    node = np.floor(g)
    return node.astype(np.int32).view(np.uint32), (g - node).astype(np.float32)


_KX, _KY = np.uint32(0x8DA6B343), np.uint32(0xD8163841)


def _hash01(ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """Uniform float32 in [0, 1) per integer lattice node (uint32 arrays) and salt."""
    return _mix((ix * _KX) ^ (iy * _KY) ^ np.uint32(salt & 0xFFFFFFFF))


def value_noise(x: np.ndarray, y: np.ndarray, step: float, salt: int = 0) -> np.ndarray:
    """Smooth value noise in [-1, 1) at world points.

    Parameters
    ----------
    x, y : ndarray
        World coordinates, m (same shape).
    step : float
        Lattice step, m: features are about ``2 * step`` across.
    salt : int
        Selects an independent noise field.

    Returns
    -------
    ndarray of float32
        Noise of the shape of ``x``, zero mean, standard deviation about 0.4.
    """
    ix, tx = _lattice(np.asarray(x, dtype=np.float64) / step)
    iy, ty = _lattice(np.asarray(y, dtype=np.float64) / step)
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    # (i + 1) * K = i * K + K modulo 2**32: four corners from two products.
    key = np.uint32(salt & 0xFFFFFFFF)
    hx0 = ix * _KX
    hx1 = hx0 + _KX
    hy0 = iy * _KY
    hy1 = (hy0 + _KY) ^ key
    hy0 ^= key
    v00, v10 = _mix(hx0 ^ hy0), _mix(hx1 ^ hy0)
    v01, v11 = _mix(hx0 ^ hy1), _mix(hx1 ^ hy1)
    top = v00 + tx * (v10 - v00)
    bottom = v01 + tx * (v11 - v01)
    return 2.0 * (top + ty * (bottom - top)) - 1.0


@dataclass(frozen=True)
class ClassTexture:
    """The look of one terrain class.

    Attributes
    ----------
    color : (float, float, float)
        Mean albedo, B, G, R in [0, 1].
    octaves : tuple of (float, float)
        ``(step, amplitude)`` pairs: lattice step in m and relative albedo amplitude of a value
        noise octave; albedo = ``color * (1 + sum(amplitude * noise))``.
    pebbles : (float, float, float) or None
        ``(step, fraction, amplitude)``: a lattice of step m where a ``fraction`` of the cells
        hold a round pebble up to ``0.45 * step`` in radius, lighter or darker by up to
        ``amplitude`` (relative).
    """

    color: tuple[float, float, float]
    octaves: tuple[tuple[float, float], ...]
    pebbles: tuple[float, float, float] | None = None


def _salt(seed: int, name: str, index: int) -> int:
    return zlib.crc32(f"{seed}:{name}:{index}".encode())


#: Default looks of the simulator's classes (colours are B, G, R).
DEFAULT_TEXTURES: dict[str, ClassTexture] = {
    "concrete": ClassTexture(
        color=(0.56, 0.57, 0.58),
        octaves=((0.0015, 0.14), (0.003, 0.12), (0.008, 0.06), (0.04, 0.05), (0.3, 0.05)),
        pebbles=(0.006, 0.15, 0.25),
    ),
    "dirt_road": ClassTexture(
        color=(0.42, 0.56, 0.68),
        octaves=((0.002, 0.14), (0.005, 0.14), (0.015, 0.10), (0.06, 0.08), (0.4, 0.08)),
        pebbles=(0.010, 0.08, 0.35),
    ),
    "gravel": ClassTexture(
        color=(0.60, 0.61, 0.63),
        octaves=((0.002, 0.10), (0.006, 0.08), (0.05, 0.06), (0.4, 0.05)),
        pebbles=(0.014, 0.75, 0.45),
    ),
    "compact_soil": ClassTexture(
        color=(0.24, 0.36, 0.48),
        octaves=((0.002, 0.14), (0.006, 0.14), (0.02, 0.10), (0.1, 0.10), (0.5, 0.06)),
        pebbles=(0.012, 0.04, 0.30),
    ),
    "ploughed_soil": ClassTexture(
        color=(0.13, 0.20, 0.30),
        octaves=((0.003, 0.16), (0.008, 0.20), (0.025, 0.20), (0.08, 0.15), (0.4, 0.06)),
        pebbles=(0.030, 0.10, 0.30),
    ),
}

#: Look of cells with no class (-1) or a class without a texture.
FALLBACK_TEXTURE = ClassTexture(
    color=(0.45, 0.47, 0.50),
    octaves=((0.002, 0.14), (0.006, 0.12), (0.02, 0.10), (0.1, 0.08)),
)


@dataclass(frozen=True)
class TextureSet:
    """Textures per class name, with the seed of the texture fields.

    The seed fixes the world's appearance: keep it for all frames of one world, so that the
    ground looks the same from frame to frame (sensor noise is seeded separately).

    Attributes
    ----------
    textures : mapping of str to ClassTexture
        Look per class name.
    fallback : ClassTexture
        Look of unclassified cells and of classes not in ``textures``.
    seed : int
        Seed of the noise fields.
    """

    textures: Mapping[str, ClassTexture] = field(default_factory=lambda: dict(DEFAULT_TEXTURES))
    fallback: ClassTexture = FALLBACK_TEXTURE
    seed: int = 0

    def albedo(
        self,
        class_names: Sequence[str],
        classes: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        footprint: np.ndarray | None = None,
        *,
        color: bool = False,
    ) -> np.ndarray:
        """Albedo of surface points.

        Parameters
        ----------
        class_names : sequence of str
            Names of the class indices.
        classes : ndarray of int, shape (N,)
            Class index per point; -1 for none.
        x, y : ndarray, shape (N,)
            World coordinates, m.
        footprint : ndarray, shape (N,), optional
            Size of a pixel on the ground at each point, m; octaves with a step below twice
            the footprint fade out (anti-aliasing). None keeps every octave.
        color : bool
            Return B, G, R instead of gray.

        Returns
        -------
        ndarray of float32, shape (N,) or (N, 3)
            Albedo in [0, 1] (gray, or BGR if ``color``).
        """
        classes = np.asarray(classes)
        out = np.empty((classes.size, 3) if color else classes.size, dtype=np.float32)
        for value in np.unique(classes):
            name = class_names[value] if 0 <= value < len(class_names) else ""
            texture = self.textures.get(name, self.fallback)
            sel = np.flatnonzero(classes == value)
            fp = None if footprint is None else footprint[sel]
            modulation = self._modulation(texture, name, x[sel], y[sel], fp)
            base = np.asarray(texture.color, dtype=np.float32)
            if color:
                out[sel] = base[None, :] * modulation[:, None]
            else:
                out[sel] = np.float32(base @ GRAY_WEIGHTS) * modulation
        return np.clip(out, 0.0, 1.0)

    def _modulation(
        self,
        texture: ClassTexture,
        name: str,
        x: np.ndarray,
        y: np.ndarray,
        footprint: np.ndarray | None,
    ) -> np.ndarray:
        total = np.ones(x.shape, dtype=np.float32)
        for i, (step, amplitude) in enumerate(texture.octaves):
            salt = _salt(self.seed, name, i)
            if footprint is None:
                total += np.float32(amplitude) * value_noise(x, y, step, salt)
                continue
            weight = np.clip(step / footprint - 1.0, 0.0, 1.0).astype(np.float32)
            sel = np.flatnonzero(weight)  # fine octaves only reach the nearest pixels
            if sel.size:
                total[sel] += (
                    np.float32(amplitude) * weight[sel] * value_noise(x[sel], y[sel], step, salt)
                )
        if texture.pebbles is not None:
            reach: np.floating | np.ndarray = (
                np.float32(1.0)
                if footprint is None
                else np.clip(texture.pebbles[0] / footprint - 1.0, 0.0, 1.0).astype(np.float32)
            )
            total *= 1.0 + reach * self._pebbles(texture.pebbles, name, x, y)
        return total

    def _pebbles(
        self, pebbles: tuple[float, float, float], name: str, x: np.ndarray, y: np.ndarray
    ) -> np.ndarray:
        step, fraction, amplitude = pebbles
        salt = _salt(self.seed, name, 1000)
        ix, fx = _lattice(np.asarray(x, dtype=np.float64) / step)
        iy, fy = _lattice(np.asarray(y, dtype=np.float64) / step)
        # Per cell: is there a pebble, its centre (jittered), radius and brightness.
        present = _hash01(ix, iy, salt) < fraction
        radius = 0.25 + 0.2 * _hash01(ix, iy, salt + 1)
        cx = 0.5 + (0.5 - radius) * (2.0 * _hash01(ix, iy, salt + 2) - 1.0)
        cy = 0.5 + (0.5 - radius) * (2.0 * _hash01(ix, iy, salt + 3) - 1.0)
        tone = amplitude * (2.0 * _hash01(ix, iy, salt + 4) - 1.0)
        r2 = (fx - cx) ** 2 + (fy - cy) ** 2
        # Soft edge over ~10 % of the radius, and a little shading towards the rim.
        inside = np.clip((radius - np.sqrt(r2)) / (0.1 * radius), 0.0, 1.0)
        rim = 1.0 - 0.5 * r2 / radius**2
        return (present * inside * tone * rim).astype(np.float32)
