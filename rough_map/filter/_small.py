"""2 x 2 linear algebra written out, for the roughness smoother's per-frame loops: at this
size LAPACK's calls (and numpy's error-state context) cost several times the arithmetic."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["inv2", "quad2"]


def quad2(C: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
    """``d_k' C_k^-1 d_k`` for a stack of 2 x 2 matrices ``C`` (k, 2, 2) and vectors ``d``
    (k, 2), written out (the jump test's statistic, per frame); a singular ``C_k`` gives
    -inf, no change of ground."""
    a, b, c, e = C[:, 0, 0], C[:, 0, 1], C[:, 1, 0], C[:, 1, 1]
    d0, d1 = d[:, 0], d[:, 1]
    det = a * e - b * c
    num = d0 * (e * d0 - b * d1) + d1 * (a * d1 - c * d0)
    if det.all():  # (np.errstate costs more than the arithmetic here)
        return num / det
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = num / det
    return np.where(det != 0, stat, -np.inf)


def inv2(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The inverse of a 2 x 2 matrix, written out: the filter inverts two a frame, and
    LAPACK's call costs several times the arithmetic at this size."""
    (a, b), (c, d) = m.tolist()
    det = a * d - b * c
    if det == 0.0 or not math.isfinite(det):
        return np.asarray(np.linalg.inv(m), dtype=float)  # a singular one raises, as before
    return np.array([[d / det, -b / det], [-c / det, a / det]])
