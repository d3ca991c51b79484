"""The patch of interest and how a traverse is measured: :class:`PatchSpec`, the grid
steps of ``spacing: auto`` (:func:`auto_spacing`) and :class:`Extraction`."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rough_map.errors import InputError, PatchError
from rough_map.limits import LIMITS
from rough_map.patch._params import check_choice, check_int, check_real

log = logging.getLogger(__name__)

#: The paper's patch: 112 samples of 8 mm = 0.896 m, centred 1 m ahead.
DEFAULT_SPACING = 0.008
DEFAULT_SIZE = 0.896
DEFAULT_AHEAD = 1.0


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
    row_spacing : float or None
        Width in m of a cell across the direction of travel, and so the distance between
        neighbouring profiles; None (the default): ``spacing``, square cells. Wider rows
        pool more points per cell without giving up the band along the profiles: right
        for ground that is the same across the track over a cell's width
        (:func:`pooled_rows`).
    """

    ahead: float = DEFAULT_AHEAD
    size: float = DEFAULT_SIZE
    spacing: float = DEFAULT_SPACING
    lateral: float = 0.0
    row_spacing: float | None = None

    def __post_init__(self) -> None:
        for name in ("size", "spacing"):
            check_real(name, getattr(self, name), "m", low=0.0, high=1e3, low_open=True)
        for name in ("ahead", "lateral"):
            check_real(name, getattr(self, name), "m", low=-1e3, high=1e3)
        if self.row_spacing is not None:
            check_real("row_spacing", self.row_spacing, "m", low=0.0, high=1e3, low_open=True)
            if float(self.row_spacing) == float(self.spacing):
                object.__setattr__(self, "row_spacing", None)  # square cells: one spelling
            elif not 3 <= self.rows <= LIMITS.patch_samples:
                raise InputError(
                    f"size / row_spacing gives {self.size / self.row_spacing:.6g} profiles "
                    f"(size={self.size:g} m, row_spacing={self.row_spacing:g} m); need 3 "
                    f"to {LIMITS.patch_samples}"
                )
        if self.n < 8:
            raise InputError(
                f"size / spacing gives {self.n} samples per profile; need at least 8 "
                f"(size={self.size} m, spacing={self.spacing} m)"
            )
        if self.n > LIMITS.patch_samples:
            raise InputError(
                f"size / spacing gives {self.size / self.spacing:.6g} samples per profile "
                f"(size={self.size:g} m, "
                f"spacing={self.spacing:g} m); at most {LIMITS.patch_samples}: use a larger spacing"
            )

    @property
    def n(self) -> int:
        """Samples per profile (and number of profiles of square cells)."""
        ratio = self.size / self.spacing
        return int(round(ratio)) if math.isfinite(ratio) else 2**62

    @property
    def row_step(self) -> float:
        """Distance in m between neighbouring profiles: ``row_spacing``, or ``spacing``."""
        return self.spacing if self.row_spacing is None else float(self.row_spacing)

    @property
    def rows(self) -> int:
        """Number of profiles (rows of the grid)."""
        if self.row_spacing is None:
            return self.n
        ratio = self.size / self.row_spacing
        return int(round(ratio)) if math.isfinite(ratio) else 2**62

    @property
    def x0(self) -> float:
        """x in m of the near edge of the patch (vehicle frame)."""
        return self.ahead - 0.5 * self.n * self.spacing

    @property
    def y0(self) -> float:
        """y in m of the right edge of the patch (vehicle frame)."""
        return self.lateral - 0.5 * self.rows * self.row_step

    def corners(self) -> np.ndarray:
        """The four corners (x, y) in m in the vehicle frame, counter-clockwise."""
        x1, y1 = self.x0 + self.n * self.spacing, self.y0 + self.rows * self.row_step
        return np.array([[self.x0, self.y0], [x1, self.y0], [x1, y1], [self.x0, y1]])


#: Fewest points per cell, on average over the patch, that :func:`auto_spacing` asks of a
#: grid step. With 1.9 points per cell at random, e^-1.9 = 15 % of the cells are empty,
#: under the 20 % at which a profile is dropped, and the cells' sampling noise costs less
#: than the band the next coarser step gives up: on power-law ground read against the
#: exact 8 mm patch (``tests/test_density.py``), 1 point per 8 mm cell reads median
#: |ln R| 0.18-0.24 on the 11.2 mm grid (1.96 points per cell) and 0.24-0.27 on the
#: 16 mm one (3.9); 0.5 point per 8 mm cell 0.32-0.33 on the 16 mm grid and 0.28-0.38 on
#: the 22.4 mm one. Fewer points per cell leave too many profiles with gaps.
MIN_POINTS_PER_CELL = 1.9
#: Steps of :func:`spacing_ladder`: the requested spacing times sqrt(2)^k, k = 0 ... 4.
AUTO_STEPS = 5


def spacing_ladder(spec: PatchSpec) -> list[PatchSpec]:
    """The patches :func:`auto_spacing` chooses from, finest first.

    Each is the same square as ``spec`` (same extent, so the same wavenumbers
    ``2 pi k / L``) gridded about sqrt(2) times coarser than the one before: at 8 mm,
    steps of 8, 11.2, 16, 22.4 and 32 mm (112, 80, 56, 40 and 28 samples).
    """
    _check_spec(spec)
    extent = spec.n * spec.spacing
    out: list[PatchSpec] = []
    for k in range(AUTO_STEPS):
        n = max(8, 2 * int(round(spec.n / (2 * math.sqrt(2) ** k))))
        if out and n >= out[-1].n:
            break
        out.append(
            PatchSpec(ahead=spec.ahead, size=extent, spacing=extent / n, lateral=spec.lateral)
        )
    return out


def points_in_patch(points: np.ndarray, spec: PatchSpec) -> int:
    """Points of an N x 3 cloud (vehicle frame, m) over the patch square, without tilt."""
    _check_spec(spec)
    pts = _as_cloud(points)
    inside = np.abs(pts[:, 0] - spec.ahead) < 0.5 * spec.n * spec.spacing
    inside &= np.abs(pts[:, 1] - spec.lateral) < 0.5 * spec.rows * spec.row_step
    return int(np.count_nonzero(inside))


def where_the_cloud_lies(points: np.ndarray, spec: PatchSpec) -> str:
    """For a cloud with (almost) no point over the patch, one short sentence: how many of its
    points are over the patch, where the patch was looked for and where the points are, in
    the vehicle frame (m), with a guess at why; "" when the patch holds at least one point in
    a hundred, the cloud surrounds the patch (it is too sparse, not elsewhere), or it has
    no finite point."""
    _check_spec(spec)
    pts = _as_cloud(points)
    pts = pts[np.isfinite(pts).all(axis=1)]
    inside = points_in_patch(pts, spec) if len(pts) else 0
    if len(pts) == 0 or inside >= 0.01 * len(pts):
        return ""
    x1, y1 = spec.x0 + spec.n * spec.spacing, spec.y0 + spec.rows * spec.row_step
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if lo[0] <= spec.x0 and hi[0] >= x1 and lo[1] <= spec.y0 and hi[1] >= y1:
        return ""  # the cloud surrounds the patch: too sparse, not elsewhere
    box = f"{inside} of {len(pts)} points over the patch (x {spec.x0:.3g}..{x1:.3g}, y "
    box += f"{spec.y0:.3g}..{y1:.3g} m)"
    centre, spread = 0.5 * np.abs(lo + hi)[:2].max(), (hi - lo)[:2].max()
    if centre > 1e3 and centre > 10 * spread:
        cx, cy = 0.5 * (lo[:2] + hi[:2])
        return (
            f"{box}; they lie around x {cx:.1f}, y {cy:.1f} m: a world-frame cloud? read it "
            "at a pose: --at X,Y[,YAW]"
        )
    if spread > 100 * spec.size:
        hint = ": in millimetres? clouds are read in metres"
    else:
        hint = ""
    return f"{box}; they lie at x {lo[0]:.4g}..{hi[0]:.4g}, y {lo[1]:.4g}..{hi[1]:.4g} m{hint}"


def auto_spacing(
    n_points: int,
    spec: PatchSpec | None = None,
    *,
    min_points_per_cell: float = MIN_POINTS_PER_CELL,
) -> PatchSpec:
    """The finest grid of :func:`spacing_ladder` that ``n_points`` points over the patch
    fill with at least ``min_points_per_cell`` points per cell on average.

    A sparse cloud (a lidar gives a few points per 8 mm cell at 1 m, or fewer than one)
    leaves most cells of the 8 mm grid empty or with one point: the profiles break up and
    the sampling noise of the cells swamps the top of the band. A coarser grid keeps the
    same patch and the same low wavenumbers; its band ends lower, at ``pi / B``. R at
    omega0 and w describe the same power law, so they stay comparable with the 8 mm
    reading, with a larger uncertainty (fewer ordinates and profiles).

    Parameters
    ----------
    n_points : int
        Points over the patch square (:func:`points_in_patch`).
    spec : PatchSpec, optional
        The patch and its finest spacing; default the paper's.
    min_points_per_cell : float
        Fewest points per cell asked of the chosen grid.

    Returns
    -------
    PatchSpec
        ``spec`` itself when it is dense enough, else the coarser grid.

    Raises
    ------
    PatchError
        Even the coarsest step (4 times ``spec.spacing``) gets fewer points per cell.
    """
    spec = PatchSpec() if spec is None else _check_spec(spec)
    check_int("n_points", n_points, low=0, high=2**62, unit="points")
    value = min_points_per_cell
    if not (
        isinstance(value, int | float | np.integer | np.floating)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and 0 < value <= 1e9
    ):
        raise InputError(
            f"min_points_per_cell must be > 0 (points per cell, finite); got {value!r:.40}"
        )
    ladder = spacing_ladder(spec)
    for cand in ladder:
        if n_points / cand.n**2 >= min_points_per_cell:
            if cand is not ladder[0]:
                log.info(
                    "spacing auto: %.1f mm grid (%.2f points per %.1f mm cell); band "
                    "%.1f to %.1f rad/m",
                    cand.spacing * 1e3,
                    n_points / spec.n**2,
                    spec.spacing * 1e3,
                    2 * math.pi / (cand.n * cand.spacing),
                    math.pi / cand.spacing,
                )
            return cand
    coarse = ladder[-1]
    raise PatchError(
        f"the cloud is too sparse for any grid: {n_points} points over the patch, "
        f"{n_points / coarse.n**2:.2f} per {coarse.spacing * 1e3:.1f} mm cell (the coarsest "
        f"step) where {min_points_per_cell:g} are needed"
    )


#: Points per cell, on average, that :func:`pooled_rows` widens the rows to hold: on the
#: CAPTIF chipseal swept across the patch, 2, 1 and 0.5 points per 8 mm cell read nearest
#: the exact 8 mm scan with rows 2, 4 and 8 cells wide (``tests/test_density.py``).
POOLED_POINTS_PER_CELL = 4.0
#: Widest pooled rows, in steps along the profile.
MAX_ROW_FACTOR = 16
#: Largest lateral scale of the widened rows (the ground's times their factor): rows stay
#: nearly alike across their width, so their lateral box takes little of the band.
MAX_POOLED_SCALE = 0.5


def pooled_rows(n_points: int, spec: PatchSpec, lateral_scale: float) -> PatchSpec | None:
    """Rows of cells wider across the track, for a sparse cloud over ground that is the
    same across it, or None.

    Ground such as a rut, a swept texture or a road scanned along one line changes little
    across the track: its lateral scale ``a`` (``PatchRoughness.lateral_scale`` of
    :mod:`rough_map.psd`: 0 for ground the same at every y, 1 for isotropic ground) is
    small.
    Averaging its points over a cell ``k`` times wider than long then loses little of the
    band along the profiles, and the estimator corrects for what it loses (the lateral box
    of a stretched surface, :mod:`rough_map.psd._corrections`). So a cloud too sparse for the
    step ``spec.spacing`` keeps that step, and with it the band up to ``pi / B``, instead
    of the coarser square grid of :func:`auto_spacing`, whose band ends lower.

    Parameters
    ----------
    n_points : int
        Points over the patch square (:func:`points_in_patch`).
    spec : PatchSpec
        The patch with square cells and the step asked for.
    lateral_scale : float
        The ground's lateral scale read on the cloud (dimensionless; NaN: not read).

    Returns
    -------
    PatchSpec or None
        ``spec`` with ``row_spacing`` ``k`` times its step: the power of two ``k`` that
        puts nearest :data:`POOLED_POINTS_PER_CELL` points in a cell (at most
        :data:`MAX_ROW_FACTOR`; 1, no pooling, from 2.8 points per cell up), as long as
        ``k * lateral_scale`` stays within :data:`MAX_POOLED_SCALE` and the cells get at
        least :data:`MIN_POINTS_PER_CELL`. None when the cloud is dense enough, the ground is
        not alike across the track, or the scale was not read.
    """
    _check_spec(spec)
    check_int("n_points", n_points, low=0, high=2**62, unit="points")
    density = n_points / (spec.n * spec.rows)
    try:
        a = float(lateral_scale)
    except (TypeError, ValueError):
        raise InputError(
            f"lateral_scale must be a number (dimensionless; NaN: not read), got "
            f"{lateral_scale!r:.40}"
        ) from None
    if spec.row_spacing is not None or density <= 0 or not math.isfinite(a):
        return None
    # the power of two nearest (in ratio) to POOLED_POINTS_PER_CELL points per cell
    k = 2 ** round(math.log2(POOLED_POINTS_PER_CELL / density))
    k = min(k, MAX_ROW_FACTOR)
    while k >= 2 and k * max(a, 0.0) > MAX_POOLED_SCALE:
        k //= 2
    rows = int(round(spec.n / k)) if k >= 2 else spec.n
    if k < 2 or rows < 3 or n_points / (spec.n * rows) < MIN_POINTS_PER_CELL:
        return None
    extent = spec.n * spec.spacing
    return dataclasses.replace(spec, size=extent, row_spacing=extent / rows)


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
    auto_spacing : bool
        ``patch.spacing`` is the finest step: a cloud too sparse for it is gridded
        coarser (:func:`auto_spacing`, :meth:`resolve`). A traverse chooses one step for
        all its frames. Terrain models record a fixed step (False).
    """

    patch: PatchSpec = field(default_factory=PatchSpec)
    use_imu: bool = True
    method: str = "unbiased"
    subtract_noise: bool = True
    auto_spacing: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.patch, PatchSpec):
            raise InputError(f"patch must be a PatchSpec, got {type(self.patch).__name__}")
        check_choice("method", self.method, METHODS)
        for name in ("use_imu", "subtract_noise", "auto_spacing"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be true or false, got {getattr(self, name)!r:.40}")

    def to_dict(self) -> dict[str, Any]:
        """The flat form a model and its card record: ``ahead, size, spacing, lateral`` (m),
        ``use_imu``, ``method``, ``subtract_noise`` (and ``"spacing": "auto"`` when
        :attr:`auto_spacing`, ``row_spacing`` in m when the rows are wider than the
        step)."""
        out: dict[str, Any] = {
            "ahead": self.patch.ahead,
            "size": self.patch.size,
            "spacing": "auto" if self.auto_spacing else self.patch.spacing,
            "lateral": self.patch.lateral,
            "use_imu": self.use_imu,
            "method": self.method,
            "subtract_noise": self.subtract_noise,
        }
        if self.patch.row_spacing is not None:
            out["row_spacing"] = self.patch.row_spacing
        return out

    def any_density(self) -> Extraction:
        """This extraction with its step chosen for each traverse's density from this one
        up (spacing auto, :func:`auto_spacing`): how the frames a model classifies are read,
        so that a traverse too sparse for the model's grid is read on a coarser one rather
        than refused (:func:`rough_map.classify.on_model_grid` maps its spectrum onto the
        model's wavenumbers)."""
        return dataclasses.replace(self, auto_spacing=True)

    def resolve(self, n_points: int) -> Extraction:
        """The extraction with a fixed step: ``self`` unless :attr:`auto_spacing`, else the
        :func:`auto_spacing` step for ``n_points`` points over the patch square.

        Raises
        ------
        PatchError
            Too sparse for even the coarsest step.
        """
        if not self.auto_spacing:
            return self
        patch = auto_spacing(n_points, self.patch)
        return dataclasses.replace(self, patch=patch, auto_spacing=False)

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
        known = {"ahead", "size", "spacing", "lateral", "row_spacing"}
        known |= {"use_imu", "method", "subtract_noise"}
        unknown = sorted(repr(k)[:30] for k in set(value) - known)
        if unknown:
            raise InputError(
                f"unknown extraction settings {', '.join(unknown[:3])}; known: {sorted(known)}"
            )
        keys = ("ahead", "size", "spacing", "lateral", "row_spacing")
        geometry = {k: value[k] for k in keys if k in value}
        options = {k: value[k] for k in ("use_imu", "method", "subtract_noise") if k in value}
        if isinstance(geometry.get("spacing"), str) and geometry["spacing"] == "auto":
            del geometry["spacing"]
            options["auto_spacing"] = True
        return cls(patch=PatchSpec(**geometry), **options)

    @property
    def near_range(self) -> tuple[float, float]:
        """Nearest and farthest x (m, vehicle frame) of the patch: the near field that
        near-to-far learns from."""
        x0 = self.patch.x0
        return x0, x0 + self.patch.n * self.patch.spacing


def _check_spec(spec: Any) -> PatchSpec:
    """``spec`` if it is a :class:`PatchSpec`, else :class:`InputError`."""
    if not isinstance(spec, PatchSpec):
        raise InputError(
            f"spec must be a PatchSpec (patch geometry in m); got {type(spec).__name__}"
        )
    return spec


def _as_cloud(points: np.ndarray, name: str = "points") -> np.ndarray:
    """Shape and dtype checks of an N x 3 cloud, without a pass over the values."""
    try:
        raw = np.asarray(points)
        if raw.dtype.kind not in "biuf":
            raise TypeError(raw.dtype)
        pts = np.asarray(raw, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be a real numeric N x 3 array of x, y, z in m") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3) (x, y, z in m), got {pts.shape}")
    if pts.shape[0] == 0:
        raise InputError(f"{name} is empty (0 points)")
    return pts
