"""Clouds on a regular lattice: a height map exported as points, read on its own grid.

A height grid (a DEM, a photogrammetric surface, a simulator's terrain) written out as
points puts one point on every node of a regular lattice. Re-binned onto the patch's 8 mm
cells, a 1 cm lattice leaves one cell in five empty in a fixed pattern and the others
holding one point off their centre, so the estimator's model of cell means (many points at
random places in a cell) does not hold. :func:`find_lattice` recognises such a cloud from
the points over the patch, and :func:`lattice_patch` places the patch on the lattice: its
step is the lattice's and its cells are centred on the nodes, so each cell holds its node's
height, a point sample of the surface (``gridding="point"``), with NaN where a node is
missing.

Only square lattices aligned with the vehicle frame's x and y are recognised (a grid
exported in the frame it is read in); a rotated or rectangular lattice reads as a cloud.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rough_map.patch.spec import PatchSpec, _as_cloud, _check_spec

log = logging.getLogger(__name__)

__all__ = ["Lattice", "find_lattice", "lattice_patch"]

#: Points over the patch that :func:`find_lattice` looks at (of 8 times as many spread over
#: the cloud): a lattice shows in a few hundred, and a cloud costs a fraction of a ms.
_SAMPLE = 2000
#: A coordinate takes at most this share of distinct values among the sampled points for
#: the cloud to be a lattice (a random cloud has as many values as points).
_DISTINCT = 0.25
#: Nodes within this fraction of a step of where the lattice puts them.
_TOLERANCE = 0.02
#: The lattice's step must lie between these multiples of the patch's step.
_STEP_RANGE = (0.5, 8.0)


@dataclass(frozen=True)
class Lattice:
    """A regular lattice of points aligned with x and y.

    Attributes
    ----------
    step_x, step_y : float
        Distance in m between neighbouring nodes along x and along y.
    origin_x, origin_y : float
        x and y in m of one node.
    """

    step_x: float
    step_y: float
    origin_x: float
    origin_y: float


def _axis(values: np.ndarray) -> tuple[float, float] | None:
    """The step and one node in m of the regular set that ``values`` (m) lie on, or
    None."""
    v = np.sort(values)
    if v.size < 16:
        return None
    span = float(v[-1] - v[0])
    if not span > 0:
        return None
    jumps = np.flatnonzero(np.diff(v) > 1e-6 * max(span, 1e-3))
    if jumps.size + 1 > _DISTINCT * v.size or jumps.size < 3:
        return None
    starts = np.concatenate([[0], jumps + 1])
    centres = np.add.reduceat(v, starts) / np.diff(np.concatenate([starts, [v.size]]))
    gaps = np.diff(centres)
    step = float(np.median(gaps))
    if not step > 0:
        return None
    multiple = gaps / step
    if np.abs(multiple - np.rint(multiple)).max() > _TOLERANCE or np.rint(multiple).min() < 1:
        return None
    k = np.rint((centres - centres[0]) / step)
    # refine the step and the origin by least squares over every node seen
    slope, origin = np.polyfit(k, centres, 1)
    step, origin = float(slope), float(origin)
    if np.abs(centres - (origin + k * step)).max() > _TOLERANCE * step:
        return None
    return step, origin


def _spread(size: int, count: int) -> np.ndarray:
    """``count`` distinct indices below ``size`` spread over it in no regular order (all of
    them, in order, if there are not more): multiplication by a prime modulo ``size``."""
    if size <= count:
        return np.arange(size)
    return (np.arange(count, dtype=np.int64) * 2_654_435_761) % size


def find_lattice(points: np.ndarray, spec: PatchSpec) -> Lattice | None:
    """The lattice the cloud's points over the patch lie on, or None for a cloud.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in the vehicle frame (finite rows).
    spec : PatchSpec
        The patch; only the points over its square are looked at, and a lattice whose step
        is not within 0.5 to 8 times ``spec.spacing`` is not taken as one.

    Returns
    -------
    Lattice or None
    """
    spec = _check_spec(spec)
    if not (isinstance(points, np.ndarray) and points.dtype.kind == "f"):
        points = _as_cloud(points)  # checks, and a float copy (a float cloud needs neither)
    elif points.ndim != 2 or points.shape[1] != 3:
        _as_cloud(points)  # raises: not N x 3
    half_x, half_y = 0.5 * spec.n * spec.spacing, 0.5 * spec.rows * spec.row_step
    # A spread subsample: every k-th point would alias with the lattice's rows.
    pick = _spread(len(points), 8 * _SAMPLE)
    xs, ys = points[pick, 0].astype(float), points[pick, 1].astype(float)
    inside = np.flatnonzero(
        (np.abs(xs - spec.ahead) < half_x) & (np.abs(ys - spec.lateral) < half_y)
    )
    inside = inside[:_SAMPLE]
    found_x = _axis(xs[inside])
    found_y = _axis(ys[inside]) if found_x is not None else None
    if found_x is None or found_y is None:
        return None
    (sx, ox), (sy, oy) = found_x, found_y
    low, high = (f * spec.spacing for f in _STEP_RANGE)
    if not (low <= sx <= high and math.isclose(sx, sy, rel_tol=_TOLERANCE)):
        log.debug("a lattice of %.4g x %.4g m: not square, or outside the patch's steps", sx, sy)
        return None
    return Lattice(sx, sy, ox, oy)


def _aligned(centre: float, cells: int, step: float, origin: float) -> float:
    """The centre in m nearest ``centre`` of ``cells`` cells of ``step`` m whose centres
    fall on the nodes ``origin + k * step``."""
    first = centre - 0.5 * cells * step + 0.5 * step  # the first cell's centre
    first = origin + step * round((first - origin) / step)
    return first - 0.5 * step + 0.5 * cells * step


def lattice_patch(spec: PatchSpec, lattice: Lattice) -> PatchSpec:
    """The patch ``spec`` on ``lattice``: its step the lattice's, the same size to the
    nearest whole node, and its centre moved (by at most half a step) so that every cell is
    centred on a node."""
    spec = _check_spec(spec)
    step = lattice.step_x
    n = max(8, round(spec.size / step))
    ahead = _aligned(spec.ahead, n, step, lattice.origin_x)
    lateral = _aligned(spec.lateral, n, step, lattice.origin_y)
    return PatchSpec(ahead=ahead, size=n * step, spacing=step, lateral=lateral)
