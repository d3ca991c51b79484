"""Gridding a cloud into the patch's height grid: :func:`grid_points`, :class:`GriddedPatch`."""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from dataclasses import dataclass

import numpy as np

from rough_map._numeric import median
from rough_map.errors import InputError, PatchError
from rough_map.geometry import check_angle, levelling_rotation, rotation_matrix, transform_columns
from rough_map.patch._params import check_bool, check_int, check_real
from rough_map.patch.lattice import Lattice, lattice_patch
from rough_map.patch.spec import PatchSpec, _as_cloud, _check_spec

log = logging.getLogger(__name__)

_CHUNK = 65536  # points per pass: keeps the temporaries in cache
#: The noise floor pools the cells of every 4th row, of every 8th in a dense cloud (at
#: least _DENSE points per cell of the patch's grid on average: 12,000 degrees of freedom
#: or more, so the floor is still known within about 1 %).
_NOISE_STRIDE, _DENSE_STRIDE, _DENSE = 4, 8, 8.0


@dataclass(frozen=True, eq=False)
class GriddedPatch:
    """Height grid of a patch, with what the gridding learned about the points.

    Attributes
    ----------
    heights : ndarray, shape (rows, n)
        Mean z in m per cell; NaN where no point fell. Rows are longitudinal profiles
        (``spec.rows`` of them, ``spec.row_step`` apart; ``spec.n`` samples each).
    counts : ndarray of int, shape (rows, n)
        Points per cell.
    spec : PatchSpec
        The patch geometry.
    n_points : int
        Points inside the patch.
    point_noise : float
        Estimated standard deviation in m of a single point about the plane the gridding
        refers its cell to (the cell mean and the local gradient of the centroid
        correction): sensor noise, and the surface's departure from that plane inside the
        cell. Pooled over the cells with 3 or more points in every 4th row of the grid
        (the 4th, 8th, ...; 3,136 of the 12,544 cells at n = 112), every 8th in clouds of 8
        or more points per cell; NaN if there are none.
    noise_psd : float
        The floor that this noise puts on the PSD of the gridded profiles, in m^3/rad:
        ``point_noise^2 * mean(1 / counts) * B / pi``.
    level_angle : float
        Tilt in rad of the patch plane that levelling removed (0 if none).
    gridding : {"cell_mean", "point"}
        How :func:`rough_map.psd.patch_roughness` should read these heights.
        ``"cell_mean"`` (:func:`grid_points`): the mean of k points at random places in a
        cell is, on average over where they fall, the mean of the surface over the cell,
        for any k: the grid is the surface seen through a B x B box filter. Its scatter
        about that box mean (the surface's variation within the cell and the sensor noise,
        divided by k, less what the centroid correction removes) is independent from cell
        to cell, a white floor that ``noise_psd`` estimates and the estimator subtracts.
        ``"point"`` (:func:`grid_lattice`): each cell holds the one point on its centre, a
        sample of the surface at the node.
    max_gap : float, optional
        Longest gap in m the estimator fills in a profile (None: its default); a patch cut
        from a raster takes the survey's (:func:`rough_map.patch.surface.surface_max_gap`).
    """

    heights: np.ndarray
    counts: np.ndarray
    spec: PatchSpec
    n_points: int
    point_noise: float
    noise_psd: float
    level_angle: float = 0.0
    gridding: str = "cell_mean"
    max_gap: float | None = None

    @property
    def fill_fraction(self) -> float:
        """Fraction of cells with at least one point."""
        return np.count_nonzero(self.counts) / self.counts.size

    @property
    def points_per_cell(self) -> float:
        """Mean number of points in the filled cells."""
        filled = self.counts > 0
        return float(self.counts[filled].mean()) if filled.any() else 0.0


def check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """Validate an N x 3 cloud in m; returns a float64 array of its finite rows."""
    pts = _as_cloud(points, name)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        if not finite.any():
            raise InputError(f"{name}: all {pts.shape[0]} points have NaN or infinite values")
        log.debug("%s: dropping %d non-finite points", name, int((~finite).sum()))
        pts = pts[finite]
    return pts


def grid_points(
    points: np.ndarray,
    spec: PatchSpec | None = None,
    *,
    min_points: int = 100,
    estimate_noise: bool = True,
    roll: float | None = None,
    pitch: float | None = None,
    level: bool = True,
    level_threshold: float = math.radians(2.0),
) -> GriddedPatch:
    """Cut the patch of interest out of a cloud and grid it (mean z per cell).

    With ``level`` (the default) the patch is levelled on its own least-squares plane:
    if that plane is tilted by more than ``level_threshold`` rad, the cloud is rotated
    about the patch centre so that the plane is horizontal, and gridded again. This is the
    tilt compensation a rover without an IMU can do: viewing a surface from a tilted frame
    shears it (x moves by about -pitch * z), which adds a little high-wavenumber power and
    lowers R by several per cent at 4 degrees; levelling removes it. It also measures a
    sloping patch along its surface, as profilometers do.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in the vehicle frame (x forward, y left, z up). Points with NaN or
        infinite coordinates are ignored.
    spec : PatchSpec, optional
        Patch geometry; default the paper's 0.896 m square 1 m ahead at 8 mm.
    min_points : int
        Fewest points inside the patch; fewer raise :class:`~rough_map.errors.PatchError`.
    estimate_noise : bool
        Estimate the point noise and its PSD floor from the scatter within cells.
    roll, pitch : float, optional
        Vehicle tilt in rad: compensate it (paper Eq. 11) on the fly, chunk by chunk.
    level : bool
        Level the patch on its own plane (see above).
    level_threshold : float
        Smallest plane tilt in rad that triggers levelling.

    Returns
    -------
    GriddedPatch
    """
    spec = PatchSpec() if spec is None else _check_spec(spec)
    check_int("min_points", min_points, low=0, high=2**62, unit="points")
    check_bool("estimate_noise", estimate_noise)
    check_bool("level", level)
    check_real("level_threshold", level_threshold, "rad", low=0.0, high=math.pi / 2)
    for name, angle in (("roll", roll), ("pitch", pitch)):
        check_real(name, angle, "rad", low=-math.pi / 2, high=math.pi / 2, none=True)
    pts = _as_cloud(points)
    rot = None
    if roll is not None or pitch is not None:
        rot = rotation_matrix(check_angle("roll", roll or 0.0), check_angle("pitch", pitch or 0.0))
    angle = 0.0
    offset = None
    if level:
        normal, centre_z = _plane(pts, spec, rot)
        if normal is not None:
            angle = math.acos(min(1.0, float(normal[2])))
        if normal is not None and angle > level_threshold:
            lev = levelling_rotation(normal)
            centre = np.array([spec.ahead, spec.lateral, centre_z])
            rot = lev if rot is None else lev @ rot
            offset = centre - lev @ centre  # rotate about the patch centre
            log.debug("levelling the patch by %.2f deg", math.degrees(angle))
        else:
            angle = 0.0
    grid = _grid(pts, spec, rot, offset, min_points, estimate_noise)
    if angle:
        grid = dataclasses.replace(grid, level_angle=angle)
    return grid


def _plane(
    pts: np.ndarray, spec: PatchSpec, rot: np.ndarray | None, n_sample: int = 1_200
) -> tuple[np.ndarray | None, float]:
    """Least-squares plane of about ``n_sample`` of the patch's points: every k-th point
    of the cloud, and when most of those fall outside the patch (a wide lidar scan), a
    denser subsample sized by how many fell inside.

    Returns the unit normal (z > 0) and the plane's z at the patch centre; (None, nan) if
    too few points fall in the patch.
    """
    step = max(1, len(pts) // n_sample)
    sums, count = _plane_sums(pts[::step], spec, rot)
    if count < n_sample // 4 and step > 1:
        step = max(1, step * count // n_sample)
        sums, count = _plane_sums(pts[::step], spec, rot)
    if count < 10:
        return None, math.nan
    sx, sy, sxx, syy, sxy, sz, sxz, syz = sums
    ata = [[count, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]]
    try:
        coef = np.linalg.solve(np.array(ata), np.array([sz, sxz, syz]))
    except np.linalg.LinAlgError:
        return None, math.nan
    normal = np.array([-coef[1], -coef[2], 1.0])
    return normal / np.linalg.norm(normal), float(coef[0])


def _plane_sums(
    q: np.ndarray, spec: PatchSpec, rot: np.ndarray | None
) -> tuple[tuple[float, ...], int]:
    """The sums of the 3 x 3 normal equations of a plane through the points of ``q`` over
    the patch (neither lstsq on the points nor a BLAS product of the (N, 3) design matrix:
    both far slower for three columns), and how many points they hold."""
    x, y, z = transform_columns(q, rot) if rot is not None else (q[:, 0], q[:, 1], q[:, 2])
    dx, dy = x - spec.ahead, y - spec.lateral
    ok = (np.abs(dx) < 0.5 * spec.n * spec.spacing) & (np.abs(dy) < 0.5 * spec.rows * spec.row_step)
    ok &= np.isfinite(z)
    count = int(ok.sum())
    if count < 10:
        return (), count
    dx, dy, z = dx[ok], dy[ok], z[ok]
    sums = (
        dx.sum(),
        dy.sum(),
        (dx * dx).sum(),
        (dy * dy).sum(),
        (dx * dy).sum(),
        z.sum(),
        (dx * z).sum(),
        (dy * z).sum(),
    )
    return tuple(float(v) for v in sums), count


def _grid(pts, spec, rot, offset, min_points, estimate_noise) -> GriddedPatch:
    """One pass over the points: cell counts, means, centroid correction, noise."""
    n, m = spec.n, spec.rows
    shape = (m + 2, n + 2)  # one border cell on each side collects everything outside
    width, cells = n + 2, (m + 2) * (n + 2)
    inv, inv_y = 1.0 / spec.spacing, 1.0 / spec.row_step
    cx, cy = spec.x0 * inv - 1.0, spec.y0 * inv_y - 1.0
    sample = pts[:: max(1, len(pts) // 2000), 2]
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        if not np.isfinite(pts).all(axis=1).any():
            raise InputError(f"points: all {len(pts)} points have NaN or infinite values")
        sample = pts[np.isfinite(pts).all(axis=1), 2]
    zref = median(sample)
    cnt = np.zeros(cells, dtype=np.intp)
    sz = np.zeros(cells)
    su = np.zeros(cells)  # sums of the in-cell offsets, for the centroids
    sv = np.zeros(cells)
    stride, noise_cell = _noise_plan(len(pts), n, m, estimate_noise)
    moments: list[np.ndarray] = []  # the noise cells' sums of zz, zu, zv, uu, vv, uv
    n_bad = 0
    for s in range(0, len(pts), _CHUNK):
        q = pts[s : s + _CHUNK]
        if rot is not None:
            x, y, z = transform_columns(q, rot, offset)
        else:
            x, y, z = q[:, 0], q[:, 1], q[:, 2]
        u = np.multiply(x, inv)
        u -= cx
        np.fmin(np.fmax(u, 0.0, out=u), n + 1, out=u)  # NaN -> border cell
        v = np.multiply(y, inv_y)
        v -= cy
        np.fmin(np.fmax(v, 0.0, out=v), m + 1, out=v)
        iu = u.astype(np.intp)
        iv = v.astype(np.intp)
        u -= iu
        v -= iv
        cell = iv
        cell *= width
        cell += iu
        z = z - zref
        bad = ~np.isfinite(z)
        if bad.any():
            n_bad += int(bad.sum())
            cell[bad] = 0
            z[bad] = 0.0
        cnt += np.bincount(cell, minlength=cells)
        sz += np.bincount(cell, z, minlength=cells)
        su += np.bincount(cell, u, minlength=cells)
        sv += np.bincount(cell, v, minlength=cells)
        if noise_cell is not None:
            moments = _add_moments(moments, noise_cell, cell, (z, u, v), n, m, stride)
    if n_bad:
        log.debug("ignored %d points with non-finite z", n_bad)
    inner = (slice(1, -1), slice(1, -1))
    counts = cnt.reshape(shape)[inner]
    n_in = int(counts.sum())
    if n_in < min_points:
        raise PatchError(
            f"only {n_in} of {len(pts)} points fall in the patch "
            f"x in [{spec.x0:.3f}, {spec.x0 + n * spec.spacing:.3f}] m, "
            f"y in [{spec.y0:.3f}, {spec.y0 + m * spec.row_step:.3f}] m (need {min_points}); "
            "is the cloud in the vehicle frame (x forward, y left, z up, metres)?"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sz.reshape(shape)[inner] / counts
        # The points of a cell do not average to its centre: refer each mean to the centre
        # with the local gradient, so slopes do not turn point positions into height noise.
        du = (su.reshape(shape)[inner] / counts - 0.5) * spec.spacing
        dv = (sv.reshape(shape)[inner] / counts - 0.5) * spec.row_step
        gx, gy = _gradient(mean, spec.spacing, spec.row_step)
        shift = gx * du
        shift += gy * dv
    used = np.isfinite(shift)  # empty cells, and cells without a neighbour, keep their mean
    shift[~used] = 0.0
    heights = mean - shift + zref
    point_noise = noise_psd = math.nan
    if estimate_noise:
        point_noise = _noise(moments, (cnt, sz, su, sv), (gx, gy, used), spec, stride)
        noise_psd = _floor(point_noise, counts, spec.spacing)
    return GriddedPatch(heights, counts, spec, n_in, point_noise, noise_psd)


def _gradient(z: np.ndarray, step: float, row_step: float) -> tuple[np.ndarray, np.ndarray]:
    """The gradient of a grid along x (columns ``step`` m apart) and y (rows ``row_step``
    m apart): central differences inside, one-sided at the edges (np.gradient's
    arithmetic, without its overhead)."""
    gx = np.empty_like(z)
    gy = np.empty_like(z)
    gx[:, 1:-1] = (z[:, 2:] - z[:, :-2]) / (2.0 * step)
    gx[:, 0] = (z[:, 1] - z[:, 0]) / step
    gx[:, -1] = (z[:, -1] - z[:, -2]) / step
    gy[1:-1] = (z[2:] - z[:-2]) / (2.0 * row_step)
    gy[0] = (z[1] - z[0]) / row_step
    gy[-1] = (z[-1] - z[-2]) / row_step
    return gx, gy


def _floor(point_noise: float, counts: np.ndarray, spacing: float) -> float:
    """The floor in m^3/rad that point noise puts on the PSD of the gridded profiles:
    ``point_noise^2 * mean(1 / counts) * B / pi``, the mean over the filled cells."""
    if not math.isfinite(point_noise):
        return math.nan
    hist = np.bincount(counts.ravel())[1:]
    inv_n = float((hist / np.arange(1, hist.size + 1)).sum() / hist.sum())
    return point_noise**2 * inv_n * spacing / math.pi


def _add_moments(
    moments: list, noise_cell: np.ndarray, cell: np.ndarray, zuv, n: int, m: int, stride: int
) -> list:
    """Add a chunk's sums of zz, zu, zv, uu, vv, uv over the noise cells (the cells of
    every ``stride``-th row, numbered by ``noise_cell``; -1 for the others) to
    ``moments``, empty before the first chunk; return it.

    The noise pools these cells only: their scatter is as good an estimate as all cells'
    (within 1-3 % at 4 to 50 points per cell), at a quarter of the cost per point and per
    cell. The picked points' arrays, of a size that varies, die with this call: held over
    to the next chunk, they fragmented the heap, and glibc giving back its top and
    refaulting it doubled the time.
    """
    sub = noise_cell[cell]
    pick = np.flatnonzero(sub >= 0)
    sub = sub[pick]
    z, u, v = (a[pick] for a in zuv)
    size = (m // stride) * n
    sums = [np.bincount(sub, c, minlength=size) for c in (z * z, z * u, z * v, u * u, v * v, u * v)]
    if not moments:
        return sums
    for acc, add in zip(moments, sums, strict=True):
        acc += add
    return moments


def _noise_plan(
    n_points: int, n: int, m: int, estimate_noise: bool
) -> tuple[int, np.ndarray | None]:
    """The row stride of the noise cells for a cloud of ``n_points`` on a grid of ``m``
    rows of ``n`` cells, and the cells' numbers (:func:`_noise_cells`; None without a
    noise estimate)."""
    stride = _DENSE_STRIDE if n_points >= _DENSE * n * m else _NOISE_STRIDE
    return stride, (_noise_cells(n, m, stride)[0] if estimate_noise else None)


@functools.lru_cache(maxsize=8)
def _noise_cells(n: int, m: int, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells of rows S, 2S, ... (S = ``stride``) of a grid of ``m`` rows of ``n``
    cells: for each cell of the grid with its border (flat), its number among them or -1;
    and for each of them, its flat index in the grid with its border and in the grid
    without."""
    width = n + 2
    index = np.full((m + 2, width), -1, dtype=np.intp)
    rows = index[stride : m + 1 : stride, 1:-1]
    rows[...] = np.arange(rows.size).reshape(rows.shape)
    r, c = np.divmod(np.flatnonzero(index.ravel() >= 0), width)
    out = (index.ravel(), r * width + c, (r - 1) * n + c - 1)
    for a in out:
        a.flags.writeable = False
    return out


def _noise(moments: list, sums: tuple, gradient: tuple, spec: PatchSpec, stride: int) -> float:
    """Pooled scatter in m of the points about the plane the gridding refers each cell to:
    the cell mean, and the gradient ``gx, gy`` (m/m, along x and y; only where ``used``)
    of the centroid correction. Over the cells of every ``stride``-th row only, whose
    sums of zz, zu, zv, uu, vv, uv ``moments`` holds; ``sums`` are the count, z, u and v
    sums of every cell of the grid with its border.

    A cell's grid value misses the cell's box mean by the mean over its ``k`` points of
    their departures from that plane (sensor noise, the surface's curvature inside the
    cell, and the difference between the local slope and the gradient of the cell means);
    the sum of squared departures about their mean has ``k - 1`` degrees of freedom, so
    it estimates the variance of one departure without a model of what makes it up.
    """
    _, full, inner = _noise_cells(spec.n, spec.rows, stride)
    cnt, sz, su, sv = sums
    gx, gy, used = (a.ravel() for a in gradient)
    k = cnt[full]
    sel = np.flatnonzero(k >= 3)
    if sel.size == 0:
        return math.nan
    k = k[sel]
    f, g = full[sel], inner[sel]
    sz, su, sv = sz[f], su[f], sv[f]
    szz, szu, szv, suu, svv, suv = (a[sel] for a in moments)
    use = used[g]
    ax = np.where(use, gx[g], 0.0) * spec.spacing  # the slope in m per cell
    ay = np.where(use, gy[g], 0.0) * spec.row_step
    with np.errstate(invalid="ignore", divide="ignore"):
        mean, ub, vb = sz / k, su / k, sv / k
        ssr = szz - mean * sz
        ssr -= 2.0 * ax * (szu - ub * sz) + 2.0 * ay * (szv - vb * sz)
        ssr += (
            ax * ax * (suu - ub * su) + 2.0 * ax * ay * (suv - ub * sv) + ay * ay * (svv - vb * sv)
        )
    ok = np.isfinite(ssr)
    if not ok.any():
        return math.nan
    dof = k[ok] - 1
    var_c = ssr[ok] / dof
    # Pool over cells, leaving out only gross outliers. Trimming a fixed share of the most
    # scattered cells would bias the pool low by the tail of its chi-square law: 12 % at
    # 4 points per cell, which flattens w and lowers R on sparse clouds.
    med = median(var_c)
    keep = var_c <= 50.0 * med if med > 0 else np.ones(var_c.shape, dtype=bool)
    return math.sqrt(max(float(np.sum(var_c[keep] * dof[keep]) / np.sum(dof[keep])), 0.0))


def grid_lattice(
    points: np.ndarray, spec: PatchSpec, lattice: Lattice, *, min_points: int = 100
) -> GriddedPatch:
    """The patch of a cloud on a regular lattice, read on the lattice: the patch moved onto
    its nodes at its step (:func:`rough_map.patch.lattice.lattice_patch`), one node per
    cell, NaN where a node is missing, ``gridding="point"``. Neither levelled nor
    tilt-compensated: rotating the points would take them off the lattice (a height map
    is already in its own frame), and the estimator removes each profile's trend.

    Raises
    ------
    PatchError
        Fewer than ``min_points`` nodes over the patch.
    """
    check_int("min_points", min_points, low=0, high=2**62, unit="points")
    on = lattice_patch(spec, lattice)
    grid = _grid(_as_cloud(points), on, None, None, min_points, False)
    return dataclasses.replace(grid, gridding="point")


def extract_patch(
    points: np.ndarray,
    spec: PatchSpec | None = None,
    *,
    roll: float | None = None,
    pitch: float | None = None,
    min_points: int = 100,
    level: bool = True,
) -> GriddedPatch:
    """Grid the patch of interest, compensating tilt first when roll or pitch is given.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in the vehicle frame.
    spec : PatchSpec, optional
        Patch geometry.
    roll, pitch : float, optional
        Vehicle tilt in rad (paper Eq. 11).
    min_points : int
        Fewest points inside the patch.
    level : bool
        Level the patch on its own plane (see :func:`grid_points`).
    """
    return grid_points(points, spec, roll=roll, pitch=pitch, min_points=min_points, level=level)
