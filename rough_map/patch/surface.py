"""The patch of interest cut from a height raster at a vehicle's pose (a route over a survey).

A surveyed surface (:class:`~rough_map.io.raster.HeightRaster`) is already a grid: the patch
ahead of a vehicle standing at ``(x, y, yaw)`` on it is read off that grid, not turned into
points and gridded again. :func:`surface_patch_spec` gives the patch its geometry on the
raster's own cells (their step, and the window a survey of that raster measures:
:func:`window_size`), so a frame placed where a survey window is reads what that window
reads. :func:`cut_patch` samples the raster at the patch's nodes:

* heading along the raster's rows or columns (a multiple of 90 degrees): each node takes the
  cell it falls in, so the heights are the raster's own (the patch moves by at most half a
  cell to sit on them);
* any other heading: the raster is resampled at the turned nodes by Fourier interpolation
  (three shears, :func:`_interpolated`), which keeps the profiles' spectrum up to the
  grid's Nyquist wavenumber; a node next to a missing cell is missing. Spline or bilinear
  weights would not do: on isotropic power-law ground, cubic splines at 17 degrees read w
  0.2 steeper and R 2.3-2.4 times higher than the same places along the rows; Fourier
  interpolation reads within the ground's own spread between directions (0.03-0.13 in
  median ln R at 17, 45 and 115 degrees, ``tests/test_route.py``). That holds for ground
  the raster's step resolves. Real texture finer than two cells (the CAPTIF chipseal laid
  out as 8 mm cell means) is aliased in the raster, and no resampling recovers it: turned
  patches there read -0.6 to +0.7 in median ln R from the same ground sampled exactly at
  the turned nodes (cubic splines +0.4 to +0.5, the unturned patch -0.7 to -0.9). Prefer
  routes along the raster's axes on such ground, or a raster at a finer step.

The profiles run along the vehicle's heading, as a traverse's do.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from rough_map.errors import InputError
from rough_map.patch.grid import GriddedPatch
from rough_map.patch.spec import DEFAULT_SIZE, DEFAULT_SPACING, PatchSpec

if TYPE_CHECKING:
    from rough_map.io.raster import HeightRaster

__all__ = ["AUTO_CELLS", "cut_patch", "surface_max_gap", "surface_patch_spec", "window_size"]

#: Cells a side of the default window on a raster coarser than the paper's grid.
AUTO_CELLS = 32
#: Longest gap in m filled at the paper's grid step (:class:`rough_map.psd.Options`).
_MAX_GAP = 0.05
#: Headings within this many radians of a multiple of 90 degrees read the cells as they are.
_AXIS_TOLERANCE = 1e-9


def window_size(spacing: float, asked: float | None = None) -> float:
    """The side in m of the patch (or survey window) on cells of ``spacing`` m: ``asked``,
    or the paper's 0.896 m patch, or :data:`AUTO_CELLS` cells of a coarser raster."""
    if asked is not None:
        return asked
    return max(DEFAULT_SIZE, AUTO_CELLS * spacing)


def surface_max_gap(spacing: float) -> float:
    """The longest gap in m that the estimator fills on cells of ``spacing`` m: as many
    cells as the paper's 5 cm are at its 8 mm, and never less than 5 cm."""
    return max(_MAX_GAP, _MAX_GAP * spacing / DEFAULT_SPACING)


def surface_patch_spec(raster: HeightRaster, asked: PatchSpec) -> PatchSpec:
    """``asked`` (where the patch is) on ``raster``'s cells: their step, and the window a
    survey of the raster takes (``asked``'s size when it is larger).

    Raises
    ------
    InputError
        A raster not in metres (a route's poses are in m), or too coarse for a patch.
    """
    if raster.unit_m != 1.0:
        raise InputError(
            f"{raster.path.name}: a route needs a raster in metres, not in units of "
            f"{raster.unit_m:g} m; reproject it (gdalwarp -t_srs) to a metric CRS"
        )
    size = max(asked.size, window_size(raster.spacing))
    return PatchSpec(ahead=asked.ahead, size=size, spacing=raster.spacing, lateral=asked.lateral)


def cut_patch(
    raster: HeightRaster, pose: tuple[float, float, float], spec: PatchSpec
) -> tuple[GriddedPatch, NDArray[np.float64]]:
    """The patch ``spec`` (on ``raster``'s cells: :func:`surface_patch_spec`) ahead of a
    vehicle at ``pose`` = ``(x, y, yaw)`` (m in the raster's CRS, rad anticlockwise from
    +x), and its nodes as points in the vehicle frame (x, y, world height; m), for the
    frame's height sample.

    Raises
    ------
    FileFormatError
        The raster cannot give the cells.
    """
    x, y, yaw = pose
    n, step = spec.n, spec.spacing
    along = spec.x0 + (np.arange(n) + 0.5) * step
    across = spec.y0 + (np.arange(spec.rows) + 0.5) * spec.row_step
    vx, vy = np.meshgrid(along, across)  # rows: profiles along x, row 0 the rightmost
    c, s = math.cos(yaw), math.sin(yaw)
    wx, wy = x + c * vx - s * vy, y + s * vx + c * vy
    # fractional raster indices of the nodes, 0 at the centre of cell [0, 0]
    cols = (wx - raster.origin[0]) / raster.cell - 0.5
    rows = (raster.origin[1] - wy) / raster.cell - 0.5
    quarter = yaw / (math.pi / 2)
    on_axes = abs(quarter - round(quarter)) * math.pi / 2 <= _AXIS_TOLERANCE
    if on_axes:
        # the first node's cell, and the others whole cells from it
        ri = round(rows[0, 0]) + np.rint(rows - rows[0, 0]).astype(np.int64)
        ci = round(cols[0, 0]) + np.rint(cols - cols[0, 0]).astype(np.int64)
        r0, c0 = int(ri.min()), int(ci.min())
        block = raster.window(r0, c0, int(ri.max()) - r0 + 1, int(ci.max()) - c0 + 1)
        heights = block[ri - r0, ci - c0]
    else:
        heights = _interpolated(raster, rows, cols, yaw)
    filled = np.isfinite(heights)
    grid = GriddedPatch(
        heights=heights,
        counts=filled.astype(np.int64),
        spec=spec,
        n_points=int(filled.sum()),
        point_noise=math.nan,
        noise_psd=math.nan,
        gridding=raster.gridding,
        max_gap=surface_max_gap(step),
    )
    nodes = np.column_stack([vx[filled], vy[filled], heights[filled]])
    return grid, nodes


def _interpolated(
    raster: HeightRaster, rows: NDArray[np.float64], cols: NDArray[np.float64], yaw: float
) -> NDArray[np.float64]:
    """The raster's heights at the nodes of a patch turned ``yaw`` rad from its columns,
    given as fractional cell indices ``rows``, ``cols`` (node ``[i, j]`` at ``j`` steps
    along the heading and ``i`` to its left of node ``[0, 0]``), by Fourier interpolation:
    NaN next to a missing cell or off the raster.

    The block of raster around the patch is turned by a multiple of 90 degrees (exactly),
    moved by the nodes' sub-cell offset and turned by the remaining angle (at most 45
    degrees) with three shears, each a shift of every line by a Fourier phase ramp
    (Unser's decomposition): for a surface sampled finely enough to hold its band, the
    profiles keep their spectrum up to the grid's Nyquist wavenumber. Each line is shifted
    less its straight trend, so that its ends meet.
    """
    n_rows, n_cols = rows.shape
    quarter = round(yaw / (math.pi / 2))
    theta = yaw - quarter * math.pi / 2  # within +-45 degrees
    centre = (int(round(float(rows.mean()))), int(round(float(cols.mean()))))
    half = max(n_rows, n_cols) + 24  # holds the turned patch, with room for the shears
    block = raster.window(centre[0] - half, centre[1] - half, 2 * half + 1, 2 * half + 1)
    local = block[::-1]  # [y, x], y up (north), centred on the centre cell
    missing = ~np.isfinite(local)
    if missing.all():
        return np.full(rows.shape, np.nan)
    level = float(np.mean(local[~missing]))
    f = np.where(missing, 0.0, local - level)
    # the first node, in cells from the centre, in the frame turned by quarter * 90 deg
    q = np.array([cols[0, 0] - centre[1], centre[0] - rows[0, 0]])
    f = _quarter_turn(f, quarter)
    q = _quarter_turn_vector(q, -quarter)
    c, s = math.cos(theta), math.sin(theta)
    d = np.array([c * q[0] + s * q[1], -s * q[0] + c * q[1]])  # R(-theta) q
    whole = np.rint(d)
    frac = d - whole
    pre = (c * frac[0] - s * frac[1], s * frac[0] + c * frac[1])  # R(theta) frac
    f = _shift_lines(
        _shift_lines(f, np.full(f.shape[0], pre[0]), 1), np.full(f.shape[1], pre[1]), 0
    )
    alpha, beta = -math.tan(theta / 2), math.sin(theta)
    offsets = np.arange(f.shape[0]) - half
    f = _shift_lines(f, alpha * offsets, 1)
    f = _shift_lines(f, beta * offsets, 0)
    f = _shift_lines(f, alpha * offsets, 1)
    i0, j0 = int(whole[1]) + half, int(whole[0]) + half
    heights = f[i0 : i0 + n_rows, j0 : j0 + n_cols] + level
    # a node next to a missing cell (of the raster as it was) is missing
    from scipy.ndimage import map_coordinates

    where = [rows - centre[0] + half, cols - centre[1] + half]
    near = map_coordinates((~np.isfinite(block)).astype(np.float64), where, order=1, cval=1.0)
    heights[near > 0] = np.nan
    return np.asarray(heights, dtype=np.float64)


def _quarter_turn(a: NDArray[Any], quarter: int) -> NDArray[Any]:
    """``a`` (indexed ``[y, x]``, y up, square) with ``out(u) = a(R(quarter * 90) u)``."""
    k = quarter % 4
    if k == 0:
        return a
    if k == 1:  # out[y, x] = a at (-y, x)
        return a[:, ::-1].T
    if k == 2:
        return a[::-1, ::-1]
    return a[::-1].T  # out[y, x] = a at (y, -x)


def _quarter_turn_vector(v: NDArray[np.float64], quarter: int) -> NDArray[np.float64]:
    """``R(quarter * 90) v`` for ``v = (x, y)``, exactly."""
    x, y = float(v[0]), float(v[1])
    for _ in range(quarter % 4):
        x, y = -y, x
    return np.array([x, y])


def _shift_lines(
    a: NDArray[np.float64], shifts: NDArray[np.float64], axis: int
) -> NDArray[np.float64]:
    """Each line of ``a`` along ``axis`` moved by its ``shifts`` (cells):
    ``out[k] = a[k + shift]``, by a Fourier phase ramp, less the line's straight trend
    (which moves exactly)."""
    lines = np.moveaxis(a, axis, -1)
    n = lines.shape[-1]
    k = np.arange(n)
    first = lines[..., :1]
    slope = (lines[..., -1:] - first) / (n - 1)
    spectrum = np.fft.rfft(lines - first - slope * k, axis=-1)
    shift = np.asarray(shifts, dtype=np.float64)[..., None]
    spectrum *= np.exp(2j * np.pi * np.fft.rfftfreq(n) * shift)
    out = np.fft.irfft(spectrum, n, axis=-1) + first + slope * (k + shift)
    return np.moveaxis(out, -1, axis)
