"""From one frame's points to its features, and from the frames' rows to a :class:`FeatureTable`.

For the points of one frame (vehicle frame) :func:`frame_features`

1. optionally compensates tilt with the frame's IMU roll and pitch (paper Eq. 11);
2. cuts and grids the patch of interest (:func:`rough_map.patch.grid_points`);
3. estimates R, w and their uncertainty along the direction of travel, and the same across
   it (anisotropy), with the gap policy of :mod:`rough_map.psd`;
4. records whether the patch is valid, and why not: too few points, too many empty cells,
   a patch the estimator refuses. An invalid frame never stops the run.

:mod:`rough_map.features.frames` runs it over a traverse's frames (reading each cloud or
stereo pair once) and :func:`feature_table` gathers the rows.

What is measured, and how, is one :class:`rough_map.patch.Extraction` (the patch, the IMU
use, the estimator and its noise floor), as a terrain model records it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from rough_map.errors import InputError, PatchError, RoughMapError
from rough_map.features.table import (
    BOOL_COLUMNS,
    COLUMNS,
    INT_COLUMNS,
    TEXT_COLUMNS,
    FeatureTable,
)
from rough_map.patch import (
    Extraction,
    GriddedPatch,
    Lattice,
    PatchSpec,
    find_lattice,
    grid_lattice,
    grid_points,
    lattice_patch,
    points_in_patch,
    pooled_rows,
    where_the_cloud_lies,
)
from rough_map.patch._params import check_int, check_real
from rough_map.psd import PatchRoughness, patch_roughness, patch_roughness_each

log = logging.getLogger(__name__)

__all__ = [
    "GriddedFrame",
    "cloud_roughness",
    "feature_table",
    "frame_features",
    "grid_frame",
    "inconsistency",
    "measure_frames",
]

#: A frame's scalar features (a row of :data:`~rough_map.features.table.COLUMNS`), its
#: wavenumbers in rad/m and its patch-mean PSD in m³/rad (None for an invalid frame).
FrameResult = tuple[dict[str, Any], np.ndarray | None, np.ndarray | None]


def frame_features(
    points: np.ndarray,
    extraction: Extraction | PatchSpec | None = None,
    *,
    roll: float | None = None,
    pitch: float | None = None,
    min_points: int = 2000,
    min_fill: float = 0.7,
) -> FrameResult:
    """Features of one frame's cloud; never raises for a bad patch (valid=False instead).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The cloud in the vehicle frame, m.
    extraction : Extraction or PatchSpec, optional
        Patch and estimator options (a PatchSpec: that patch with the default estimator);
        default the paper's. Its ``use_imu`` is not used: the tilt comes from ``roll`` and
        ``pitch``. With ``auto_spacing`` the step is chosen for this cloud (a traverse
        chooses one for all its frames instead: :func:`rough_map.features.traverse_features`).
    roll, pitch : float, optional
        Vehicle attitude in rad to compensate (paper Eq. 11); None: no compensation.
    min_points : int
        Fewest points in the patch for a valid frame.
    min_fill : float
        Smallest fraction of filled cells for a valid frame.

    Returns
    -------
    row : dict
        The scalar columns (``valid``, ``reason``, ``n_points``, and when the patch could be
        gridded ``fill``, ``point_noise`` in m, ``noise_psd`` in m³/rad, ``level_angle`` in
        rad, and when valid ``R`` in m³/rad, ``w``, ``sigma_R``, ``sigma_w``, ``se_lnR``,
        ``se_w``, ``rms`` in m,
        ``iso_class``, ``R_lat``, ``w_lat``, ``fit_residual``).
    omega : ndarray or None
        Wavenumbers in rad/m of the spectrum (None when invalid).
    psd : ndarray or None
        Patch-mean PSD in m³/rad (None when invalid).
    """
    return measure_frames(
        [
            grid_frame(
                points, extraction, roll=roll, pitch=pitch, min_points=min_points, min_fill=min_fill
            )
        ]
    )[0]


class GriddedFrame(NamedTuple):
    """A frame between :func:`grid_frame` and :func:`measure_frames`: its row so far, its
    gridded patch (None when the frame is already invalid) and the extraction to measure
    it with."""

    row: dict[str, Any]
    grid: GriddedPatch | None
    extraction: Extraction


def grid_frame(
    points: np.ndarray,
    extraction: Extraction | PatchSpec | None = None,
    *,
    roll: float | None = None,
    pitch: float | None = None,
    min_points: int = 2000,
    min_fill: float = 0.7,
) -> GriddedFrame:
    """The first half of :func:`frame_features` (same parameters): cut and grid the patch
    (on its nodes for a cloud on a lattice: :func:`cloud_roughness`), and decide whether it
    has enough points and filled cells to be measured. The points are not needed after
    it."""
    ex = _as_extraction(extraction)
    check_int("min_points", min_points, low=0, high=2**62, unit="points")
    check_real("min_fill", min_fill, "", low=0.0, high=1.0)
    for name, angle in (("roll", roll), ("pitch", pitch)):
        check_real(name, angle, "rad", low=-math.pi / 2, high=math.pi / 2, none=True)
    row: dict[str, Any] = {"valid": False, "reason": "", "n_points": 0}
    try:
        on_lattice = _lattice_extraction(points, ex)
        if on_lattice is not None:
            ex = on_lattice[0]
            grid = grid_lattice(points, ex.patch, on_lattice[1], min_points=min_points)
        else:
            ex = ex.resolve(points_in_patch(points, ex.patch)) if ex.auto_spacing else ex
            grid = grid_points(points, ex.patch, roll=roll, pitch=pitch, min_points=min_points)
    except RoughMapError as exc:
        where = where_the_cloud_lies(points, ex.patch) if "points" in str(exc) else ""
        row["reason"] = f"too few points: {where or exc}" if "points" in str(exc) else str(exc)
        return GriddedFrame(row, None, ex)
    row.update(
        n_points=grid.n_points,
        fill=grid.fill_fraction,
        point_noise=grid.point_noise,
        noise_psd=grid.noise_psd,
        level_angle=grid.level_angle,
    )
    if grid.fill_fraction < min_fill:
        row["reason"] = f"too many gaps: {grid.fill_fraction:.0%} of cells filled"
        return GriddedFrame(row, None, ex)
    return GriddedFrame(row, grid, ex)


def measure_frames(frames: Sequence[GriddedFrame]) -> list[FrameResult]:
    """The second half of :func:`frame_features`: the roughness of each gridded frame along
    the direction of travel and across it, for many frames in one vectorised pass.

    The patches are stacked by estimator settings (step, shape, noise floor subtracted or
    not) and measured with :func:`rough_map.psd.patch_roughness_each`, which gives a patch
    the same numbers alone or in any batch: a traverse's frames measured in chunks and one
    frame measured by the online mapper agree to the last bit.
    """
    results: list[FrameResult | None] = [None] * len(frames)
    groups: dict[tuple[Any, ...], list[tuple[int, GriddedPatch]]] = {}
    for i, (row, grid, ex) in enumerate(frames):
        if grid is None:
            results[i] = (row, None, None)
            continue
        opts = _options(grid, ex)
        key = (ex.patch.spacing, ex.patch.row_step, grid.heights.shape, *opts.items())
        groups.setdefault(key, []).append((i, grid))
    for (spacing, row_step, _, *items), group in groups.items():
        opts = dict(items)
        subtract = opts["subtract_noise"]
        for start in range(0, len(group), MEASURE_BATCH):
            members = group[start : start + MEASURE_BATCH]
            floors = np.array([g.noise_psd for _, g in members])
            if row_step == spacing:
                # each frame's profiles along the direction of travel (rows), then across it
                stack = np.stack([h for _, g in members for h in (g.heights, g.heights.T)])
                floors = np.repeat(floors, 2)
                both = patch_roughness_each(
                    stack, spacing, noise_psd=floors if subtract else None, **opts
                )
                lon, lat = both[0::2], both[1::2]
            else:  # rows wider than the step: the two directions have their own steps
                lon = patch_roughness_each(
                    np.stack([g.heights for _, g in members]),
                    spacing,
                    noise_psd=floors if subtract else None,
                    row_spacing=row_step,
                    **opts,
                )
                lat = patch_roughness_each(
                    np.stack([g.heights.T for _, g in members]),
                    row_step,
                    noise_psd=floors * (row_step / spacing) if subtract else None,
                    row_spacing=spacing,
                    **opts,
                )
            for k, (i, _) in enumerate(members):
                results[i] = _measured(frames[i].row, lon[k], lat[k])
    return [r for r in results if r is not None]


#: Most frames whose patches :func:`measure_frames` measures in one call: a worker's chunk
#: of 32 frames of 112 x 112 cells takes about 23 MB of temporaries. Fewer frames at a time
#: take less memory but were slower (0.77 against 0.69 ms a frame for 16).
MEASURE_BATCH = 32


def _measured(
    row: dict[str, Any], lon: PatchRoughness | PatchError, lat: PatchRoughness | PatchError
) -> FrameResult:
    """A frame's result from its two estimates. A refusal along the direction of travel
    makes the frame invalid; one across it (ground the same across the track, whose
    lateral profiles are flat to within the sensor's noise) leaves ``R_lat`` and ``w_lat``
    NaN in a valid frame."""
    if isinstance(lon, PatchError):
        row["reason"] = str(lon)
        return row, None, None
    if not lon.consistent:
        row["reason"] = inconsistency(lon)
        return row, None, None
    if isinstance(lat, PatchError):
        log.debug("no roughness across the track: %s", lat)
    assert isinstance(lon, PatchRoughness)
    across = lat if isinstance(lat, PatchRoughness) else None
    row.update(
        valid=True,
        R=lon.R,
        w=lon.w,
        sigma_R=lon.sigma_R,
        sigma_w=lon.sigma_w,
        se_lnR=lon.se_lnR,
        se_w=lon.se_w,
        rms=lon.rms,
        iso_class=lon.iso_class,
        R_lat=math.nan if across is None else across.R,
        w_lat=math.nan if across is None else across.w,
        fit_residual=lon.fit_residual,
        lateral_scale=lon.lateral_scale,
        omega_noise=lon.omega_noise,
        band_rms=lon.band_rms,
        centre_psd=lon.centre_psd,
        omega_centre=lon.omega_centre,
        rms_ratio=lon.rms_ratio,
        curvature_z=lon.curvature_z,
    )
    return row, lon.omega, lon.psd


def inconsistency(rough: PatchRoughness) -> str:
    """Why a reading that fails its own consistency check
    (:attr:`rough_map.psd.PatchRoughness.consistent`) is not reported."""
    return (
        f"the fit contradicts its patch: R {rough.R:.3g} m³/rad and w {rough.w:.2f} give "
        f"{rough.rms_ratio * rough.band_rms * 1e3:.3g} mm rms over the band, the patch "
        f"{rough.band_rms * 1e3:.3g} mm (more than 2x off)"
    )


def cloud_roughness(
    points: np.ndarray,
    extraction: Extraction | PatchSpec | None = None,
    *,
    roll: float | None = None,
    pitch: float | None = None,
    min_points: int = 100,
) -> tuple[GriddedPatch, PatchRoughness]:
    """The gridded patch of one cloud and its roughness along the direction of travel.

    Unlike :func:`frame_features` this raises for a patch it cannot measure, and keeps the
    whole :class:`~rough_map.patch.GriddedPatch` and :class:`~rough_map.psd.PatchRoughness`
    (``rough-map features CLOUD`` shows them).

    A cloud on a regular lattice (a height map exported as points) is read on its nodes,
    at the lattice's step (:func:`rough_map.patch.find_lattice`), whatever the step asked.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The cloud in the vehicle frame, m.
    extraction : Extraction or PatchSpec, optional
        Patch and estimator options; default the paper's. With ``auto_spacing`` the grid
        step is chosen for this cloud's density (:func:`rough_map.patch.auto_spacing`);
        a sparse cloud over ground that is the same across the track keeps the step and
        is gridded in wider rows instead (:func:`rough_map.patch.pooled_rows`). The
        returned grid's ``spec`` says which.
    roll, pitch : float, optional
        Vehicle attitude in rad to compensate (paper Eq. 11); None: no compensation.
    min_points : int
        Fewest points in the patch.

    Raises
    ------
    RoughMapError
        Too few points in the patch, or a patch the estimator refuses.
    """
    asked = _as_extraction(extraction)
    try:
        return _cloud_roughness(points, asked, roll, pitch, min_points)
    except PatchError as exc:
        where = where_the_cloud_lies(points, asked.patch) if "points" in str(exc) else ""
        if not where:
            raise
        raise PatchError(where) from None


def _cloud_roughness(
    points: np.ndarray,
    asked: Extraction,
    roll: float | None,
    pitch: float | None,
    min_points: int,
) -> tuple[GriddedPatch, PatchRoughness]:
    """:func:`cloud_roughness` of a checked extraction."""
    on_lattice = _lattice_extraction(points, asked)
    if on_lattice is not None:
        grid = grid_lattice(points, asked.patch, on_lattice[1], min_points=min_points)
        return grid, _fit(grid, on_lattice[0], grid.heights)
    if not asked.auto_spacing:
        grid = grid_points(points, asked.patch, roll=roll, pitch=pitch, min_points=min_points)
        return grid, _fit(grid, asked, grid.heights)
    n_in = points_in_patch(points, asked.patch)
    ex = asked.resolve(n_in)
    grid = grid_points(points, ex.patch, roll=roll, pitch=pitch, min_points=min_points)
    rough = _fit(grid, ex, grid.heights)
    wide = pooled_rows(n_in, asked.patch, rough.lateral_scale)
    if wide is None:
        return grid, rough
    log.info(
        "rows pooled: lateral scale %.2f, %.1f mm step with rows %.1f mm wide "
        "(%.2f points per cell); band %.1f to %.1f rad/m",
        rough.lateral_scale,
        wide.spacing * 1e3,
        wide.row_step * 1e3,
        n_in / (wide.n * wide.rows),
        2 * math.pi / (wide.n * wide.spacing),
        math.pi / wide.spacing,
    )
    ex = dataclasses.replace(ex, patch=wide)
    grid = grid_points(points, wide, roll=roll, pitch=pitch, min_points=min_points)
    return grid, _fit(grid, ex, grid.heights)


def _lattice_extraction(points: np.ndarray, ex: Extraction) -> tuple[Extraction, Lattice] | None:
    """For a cloud on a regular lattice (:func:`rough_map.patch.find_lattice`), the fixed
    extraction on the lattice and the lattice; None for any other cloud."""
    lattice = find_lattice(points, ex.patch)
    if lattice is None:
        return None
    patch = lattice_patch(ex.patch, lattice)
    log.info(
        "the cloud lies on a %.1f mm lattice: read on it, %d x %d nodes, band %.1f to %.1f rad/m",
        patch.spacing * 1e3,
        patch.n,
        patch.n,
        2 * math.pi / (patch.n * patch.spacing),
        math.pi / patch.spacing,
    )
    return dataclasses.replace(ex, patch=patch, auto_spacing=False), lattice


def _as_extraction(extraction: Extraction | PatchSpec | None) -> Extraction:
    if isinstance(extraction, PatchSpec):
        return Extraction(patch=extraction)
    if extraction is None:
        return Extraction()
    if not isinstance(extraction, Extraction):
        raise InputError(
            "extraction must be an Extraction, a PatchSpec (geometry in m) or None; got "
            f"{type(extraction).__name__}"
        )
    return extraction


def _options(grid: GriddedPatch, ex: Extraction) -> dict[str, Any]:
    """The estimator's options for a gridded patch other than its floor: ``ex``'s method,
    whether the floor is subtracted (when ``ex`` says so and the patch has an estimate of
    it), the gridding and, for a patch cut from a raster, the longest gap filled."""
    opts = {
        "method": ex.method,
        "subtract_noise": ex.subtract_noise and math.isfinite(grid.noise_psd),
        "gridding": grid.gridding,
    }
    if grid.max_gap is not None:
        opts["max_gap"] = grid.max_gap
    return opts


def _fit(grid: GriddedPatch, ex: Extraction, heights: np.ndarray) -> PatchRoughness:
    """:func:`rough_map.psd.patch_roughness` of a gridded patch's rows (``heights``)."""
    opts = _options(grid, ex)
    floor = grid.noise_psd if opts["subtract_noise"] else None
    spec = ex.patch
    rough = patch_roughness(
        heights, spec.spacing, noise_psd=floor, row_spacing=spec.row_spacing, **opts
    )
    assert isinstance(rough, PatchRoughness)  # one patch, one estimate
    return rough


def feature_table(
    rows: list[dict[str, Any]],
    spectra: list[np.ndarray | None],
    omega: np.ndarray | None,
    spec: PatchSpec,
    name: str,
) -> FeatureTable:
    """The table of the frames' rows and spectra (the patch's wavenumbers when no frame
    is valid)."""
    if omega is None:
        omega = 2 * np.pi * np.arange(1, spec.n // 2 + 1) / (spec.n * spec.spacing)
    log_psd = np.full((len(rows), omega.size), np.nan)
    for i, s in enumerate(spectra):
        if s is not None:
            log_psd[i] = np.log10(s)
    return FeatureTable(_columns(rows), omega, log_psd, name, spec.row_spacing)


def _columns(rows: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    cols = {}
    for c in COLUMNS:
        if c in TEXT_COLUMNS:
            cols[c] = np.array([str(r.get(c, "") or "") for r in rows], dtype=object)
        elif c in BOOL_COLUMNS:
            cols[c] = np.array([bool(r.get(c, False)) for r in rows])
        elif c in INT_COLUMNS:
            cols[c] = np.array([int(r.get(c, 0)) for r in rows])
        else:
            cols[c] = np.array([float(r.get(c, math.nan)) for r in rows])
    return cols
