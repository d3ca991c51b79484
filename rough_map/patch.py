"""From a point cloud in the vehicle frame to the height grid of the patch of interest.

The paper (section 3.2) looks at the patch 0.90 m x 0.90 m about 1 m ahead of the rover,
sampled every B = 8 mm. :func:`grid_points` cuts a ``size`` x ``size`` metre square centred
``ahead`` metres in front of the vehicle origin (and ``lateral`` metres to the left), and
averages the z of the points falling in each ``spacing`` x ``spacing`` cell. Rows of the grid
are longitudinal profiles (along x, the direction of travel); row 0 is the rightmost
(most negative y) profile and column 0 the nearest sample.

Tilt (paper Eq. 11): the cloud is expressed in the vehicle frame, which rolls and pitches
with the terrain. :func:`compensate_tilt` rotates it into a gravity-aligned frame with the
IMU's roll and pitch; the PSD is little affected by tilts of a few degrees, so this is
optional.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rough_map.errors import InputError, PatchError
from rough_map.geometry import rotation_matrix, transform_columns

log = logging.getLogger(__name__)

#: The paper's patch: 112 samples of 8 mm = 0.896 m, centred 1 m ahead.
DEFAULT_SPACING = 0.008
DEFAULT_SIZE = 0.896
DEFAULT_AHEAD = 1.0

_CHUNK = 65536  # points per pass: keeps the temporaries in cache


@dataclass(frozen=True)
class PatchSpec:
    """Where the patch of interest is and how it is sampled.

    Attributes
    ----------
    ahead : float
        Distance in m from the vehicle origin to the patch centre, along x.
    size : float
        Side of the square patch in m.
    spacing : float
        Grid step B in m.
    lateral : float
        Offset in m of the patch centre to the left (+y).
    """

    ahead: float = DEFAULT_AHEAD
    size: float = DEFAULT_SIZE
    spacing: float = DEFAULT_SPACING
    lateral: float = 0.0

    def __post_init__(self) -> None:
        for name in ("size", "spacing"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive length in m, got {v!r}")
        for name in ("ahead", "lateral"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise InputError(f"{name} must be a finite distance in m, got {v!r}")
        if self.n < 8:
            raise InputError(
                f"size / spacing gives {self.n} samples per profile; need at least 8 "
                f"(size={self.size} m, spacing={self.spacing} m)"
            )

    @property
    def n(self) -> int:
        """Samples per profile and number of profiles."""
        return int(round(self.size / self.spacing))

    @property
    def x0(self) -> float:
        """x in m of the near edge of the patch (vehicle frame)."""
        return self.ahead - 0.5 * self.n * self.spacing

    @property
    def y0(self) -> float:
        """y in m of the right edge of the patch (vehicle frame)."""
        return self.lateral - 0.5 * self.n * self.spacing

    def corners(self) -> np.ndarray:
        """The four corners (x, y) in m in the vehicle frame, counter-clockwise."""
        x1, y1 = self.x0 + self.n * self.spacing, self.y0 + self.n * self.spacing
        return np.array([[self.x0, self.y0], [x1, self.y0], [x1, y1], [self.x0, y1]])


#: Estimators of :func:`rough_map.psd.patch_roughness` an :class:`Extraction` may name.
METHODS = ("unbiased", "paper")


@dataclass(frozen=True)
class Extraction:
    """How the frames of a traverse become features: the patch and the estimator options.

    The one extraction spec of rough_map. It is built once, from a model's record
    (:meth:`from_dict` of ``TerrainModel.extraction_``) or from the command line, and passed
    to the features, the workflow, near-to-far and the CLI; nothing else holds a default
    patch.

    Attributes
    ----------
    patch : PatchSpec
        Where the patch is and how it is gridded (m).
    use_imu : bool
        Compensate the frames' IMU roll and pitch (paper Eq. 11).
    method : {"unbiased", "paper"}
        The PSD fit (:func:`rough_map.psd.patch_roughness`).
    subtract_noise : bool
        Subtract the noise floor estimated from the within-cell scatter.
    """

    patch: PatchSpec = field(default_factory=PatchSpec)
    use_imu: bool = True
    method: str = "unbiased"
    subtract_noise: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.patch, PatchSpec):
            raise InputError(f"patch must be a PatchSpec, got {type(self.patch).__name__}")
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("use_imu", "subtract_noise"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be true or false, got {getattr(self, name)!r}")

    def to_dict(self) -> dict[str, Any]:
        """The flat form a model and its card record: ``ahead, size, spacing, lateral`` (m),
        ``use_imu``, ``method``, ``subtract_noise``."""
        return {
            "ahead": self.patch.ahead,
            "size": self.patch.size,
            "spacing": self.patch.spacing,
            "lateral": self.patch.lateral,
            "use_imu": self.use_imu,
            "method": self.method,
            "subtract_noise": self.subtract_noise,
        }

    @classmethod
    def from_dict(cls, value: Mapping[str, Any] | Extraction | None) -> Extraction:
        """An :class:`Extraction` from :meth:`to_dict`'s form (missing keys take the
        defaults), an :class:`Extraction`, or None (the defaults).

        Raises
        ------
        InputError
            An unknown key or an invalid value.
        """
        if isinstance(value, Extraction):
            return value
        if value is None:
            return cls()
        if not isinstance(value, Mapping):
            raise InputError(f"extraction must be a mapping, got {type(value).__name__}")
        known = {"ahead", "size", "spacing", "lateral", "use_imu", "method", "subtract_noise"}
        unknown = sorted(set(value) - known)
        if unknown:
            raise InputError(f"unknown extraction settings {unknown}; known: {sorted(known)}")
        geometry = {k: value[k] for k in ("ahead", "size", "spacing", "lateral") if k in value}
        options = {k: value[k] for k in ("use_imu", "method", "subtract_noise") if k in value}
        return cls(patch=PatchSpec(**geometry), **options)

    @property
    def near_range(self) -> tuple[float, float]:
        """Nearest and farthest x (m, vehicle frame) of the patch: the near field that
        near-to-far learns from."""
        x0 = self.patch.x0
        return x0, x0 + self.patch.n * self.patch.spacing


@dataclass(frozen=True, eq=False)
class GriddedPatch:
    """Height grid of a patch, with what the gridding learned about the points.

    Attributes
    ----------
    heights : ndarray, shape (n, n)
        Mean z in m per cell; NaN where no point fell. Rows are longitudinal profiles.
    counts : ndarray of int, shape (n, n)
        Points per cell.
    spec : PatchSpec
        The patch geometry.
    n_points : int
        Points inside the patch.
    point_noise : float
        Estimated standard deviation in m of a single point about the local surface
        (pooled within-cell scatter, less the part explained by the local slope); NaN if
        no cell has 3 or more points.
    noise_psd : float
        The floor that this noise puts on the PSD of the gridded profiles, in m^3/rad:
        ``point_noise^2 * mean(1 / counts) * B / pi``.
    level_angle : float
        Tilt in rad of the patch plane that levelling removed (0 if none).
    """

    heights: np.ndarray
    counts: np.ndarray
    spec: PatchSpec
    n_points: int
    point_noise: float
    noise_psd: float
    level_angle: float = 0.0

    @property
    def fill_fraction(self) -> float:
        """Fraction of cells with at least one point."""
        return float(np.mean(self.counts > 0))

    @property
    def points_per_cell(self) -> float:
        """Mean number of points in the filled cells."""
        filled = self.counts > 0
        return float(self.counts[filled].mean()) if filled.any() else 0.0

    @property
    def gridding(self) -> str:
        """How :func:`rough_map.psd.patch_roughness` should read these heights.

        ``"cell_mean"`` when the cells average many points (4 or more on average), so the
        grid is the surface seen through a B x B box filter; ``"point"`` for sparse clouds,
        where a cell holds about one sample of the surface.
        """
        return "cell_mean" if self.points_per_cell >= 4 else "point"


def _as_cloud(points: np.ndarray, name: str = "points") -> np.ndarray:
    """Shape and dtype checks of an N x 3 cloud, without a pass over the values."""
    try:
        pts = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric N x 3 array of x, y, z in m") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3) (x, y, z in m), got {pts.shape}")
    if pts.shape[0] == 0:
        raise InputError(f"{name} is empty (0 points)")
    return pts


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


def _check_angle(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or abs(value) > math.pi / 2:
        raise InputError(f"{name} must be an angle in rad within +-pi/2, got {value!r}")
    return value


def levelling_rotation(normal: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns ``normal`` into +z (no yaw is introduced)."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    axis = np.cross(n, [0.0, 0.0, 1.0])
    s = np.linalg.norm(axis)
    c = float(n[2])
    if s < 1e-15:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def compensate_tilt(points: np.ndarray, roll: float, pitch: float) -> np.ndarray:
    """Rotate vehicle-frame points into the gravity-aligned frame (paper Eq. 11).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in the vehicle frame.
    roll, pitch : float
        Vehicle roll and pitch in rad (e.g. from the IMU).

    Returns
    -------
    ndarray, shape (N, 3)
        ``R_v^w @ p`` for every point.
    """
    rot = rotation_matrix(_check_angle("roll", roll), _check_angle("pitch", pitch))
    return np.column_stack(transform_columns(_as_cloud(points), rot))


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
    spec = spec or PatchSpec()
    pts = _as_cloud(points)
    rot = None
    if roll is not None or pitch is not None:
        rot = rotation_matrix(
            _check_angle("roll", roll or 0.0), _check_angle("pitch", pitch or 0.0)
        )
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
    pts: np.ndarray, spec: PatchSpec, rot: np.ndarray | None, n_sample: int = 10_000
) -> tuple[np.ndarray | None, float]:
    """Least-squares plane of a subsample of the patch's points.

    Returns the unit normal (z > 0) and the plane's z at the patch centre; (None, nan) if
    too few points fall in the patch.
    """
    q = pts[:: max(1, len(pts) // n_sample)]
    x, y, z = transform_columns(q, rot) if rot is not None else (q[:, 0], q[:, 1], q[:, 2])
    half = 0.5 * spec.n * spec.spacing
    dx, dy = x - spec.ahead, y - spec.lateral
    ok = (np.abs(dx) < half) & (np.abs(dy) < half) & np.isfinite(z)
    if ok.sum() < 10:
        return None, math.nan
    a = np.column_stack([np.ones(int(ok.sum())), dx[ok], dy[ok]])
    try:  # normal equations: 3 x 3, much cheaper than lstsq on the points
        coef = np.linalg.solve(a.T @ a, a.T @ z[ok])
    except np.linalg.LinAlgError:
        return None, math.nan
    normal = np.array([-coef[1], -coef[2], 1.0])
    return normal / np.linalg.norm(normal), float(coef[0])


def _grid(pts, spec, rot, offset, min_points, estimate_noise) -> GriddedPatch:
    """One pass over the points: cell counts, means, centroid correction, noise."""
    n = spec.n
    width = n + 2  # one border cell on each side collects everything outside
    inv = 1.0 / spec.spacing
    cx = spec.x0 * inv - 1.0
    cy = spec.y0 * inv - 1.0
    sample = pts[:: max(1, len(pts) // 2000), 2]
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        if not np.isfinite(pts).all(axis=1).any():
            raise InputError(f"points: all {len(pts)} points have NaN or infinite values")
        sample = pts[np.isfinite(pts).all(axis=1), 2]
    zref = float(np.median(sample))
    cnt = np.zeros(width * width, dtype=np.intp)
    sz = np.zeros(width * width)
    szz = np.zeros(width * width)
    su = np.zeros(width * width)  # sums of the in-cell offsets, for the centroids
    sv = np.zeros(width * width)
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
        v = np.multiply(y, inv)
        v -= cy
        np.fmin(np.fmax(v, 0.0, out=v), n + 1, out=v)
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
        cnt += np.bincount(cell, minlength=width * width)
        sz += np.bincount(cell, z, minlength=width * width)
        su += np.bincount(cell, u, minlength=width * width)
        sv += np.bincount(cell, v, minlength=width * width)
        if estimate_noise:
            z *= z
            szz += np.bincount(cell, z, minlength=width * width)
    if n_bad:
        log.debug("ignored %d points with non-finite z", n_bad)
    inner = (slice(1, -1), slice(1, -1))
    counts = cnt.reshape(width, width)[inner]
    n_in = int(counts.sum())
    if n_in < min_points:
        raise PatchError(
            f"only {n_in} of {len(pts)} points fall in the patch "
            f"x in [{spec.x0:.3f}, {spec.x0 + n * spec.spacing:.3f}] m, "
            f"y in [{spec.y0:.3f}, {spec.y0 + n * spec.spacing:.3f}] m (need {min_points}); "
            "is the cloud in the vehicle frame (x forward, y left, z up, metres)?"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sz.reshape(width, width)[inner] / counts
        # The points of a cell do not average to its centre: refer each mean to the centre
        # with the local gradient, so slopes do not turn point positions into height noise.
        du = (su.reshape(width, width)[inner] / counts - 0.5) * spec.spacing
        dv = (sv.reshape(width, width)[inner] / counts - 0.5) * spec.spacing
        gy, gx = np.gradient(mean, spec.spacing)
    heights = mean - np.nan_to_num(gx * du + gy * dv) + zref
    point_noise = noise_psd = math.nan
    if estimate_noise:
        point_noise, noise_psd = _noise(mean, counts, szz.reshape(width, width)[inner], spec)
    return GriddedPatch(heights, counts, spec, n_in, point_noise, noise_psd)


def _noise(mean: np.ndarray, counts: np.ndarray, szz: np.ndarray, spec: PatchSpec):
    """Pooled within-cell scatter, less the local slope's share (B^2 |grad z|^2 / 12)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ss = szz - counts * mean * mean  # sum of squares about the cell mean, m^2
        gy, gx = np.gradient(mean, spec.spacing)
    slope_var = (gx * gx + gy * gy) * spec.spacing**2 / 12.0
    ok = (counts >= 3) & np.isfinite(slope_var) & np.isfinite(ss)
    if not ok.any():
        return math.nan, math.nan
    var_c = ss[ok] / (counts[ok] - 1) - slope_var[ok]
    dof = counts[ok] - 1
    # Pool over cells, ignoring the 5 % most scattered (edges, outliers).
    keep = var_c <= np.quantile(var_c, 0.95)
    var = float(np.sum(var_c[keep] * dof[keep]) / np.sum(dof[keep]))
    var = max(var, 0.0)
    inv_n = float(np.mean(1.0 / counts[counts > 0]))
    return math.sqrt(var), var * inv_n * spec.spacing / math.pi


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
