"""From frames to features: the one place that turns a traverse into a :class:`FeatureTable`.

For each frame of a :class:`~rough_map.io.traverse.Traverse` :func:`traverse_features`

1. takes the frame's point cloud (vehicle frame), or reconstructs one from its stereo pair;
2. optionally compensates tilt with the frame's IMU roll and pitch (paper Eq. 11);
3. cuts and grids the patch of interest (:func:`rough_map.patch.grid_points`);
4. estimates R, w and their uncertainty along the direction of travel, and the same across
   it (anisotropy), with the gap policy of :mod:`rough_map.psd`;
5. records whether the patch is valid, and why not: too few points, too many empty cells,
   a patch the estimator refuses, no stereo pair to take the points from, an unreadable
   file. An invalid frame never stops the run.

What is measured, and how, is one :class:`rough_map.patch.Extraction` (the patch, the IMU
use, the estimator and its noise floor), as a terrain model records it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import PathLike
from rough_map.config import StereoCalibration
from rough_map.errors import FileFormatError, InputError, RoughMapError
from rough_map.features.files import read_features
from rough_map.features.table import (
    BOOL_COLUMNS,
    COLUMNS,
    INT_COLUMNS,
    TEXT_COLUMNS,
    FeatureTable,
)
from rough_map.io.traverse import Traverse, load_traverse
from rough_map.patch import Extraction, GriddedPatch, PatchSpec, grid_points
from rough_map.psd import PatchRoughness, patch_roughness
from rough_map.stereo import read_image, stereo_to_cloud

log = logging.getLogger(__name__)

__all__ = [
    "SOURCES",
    "cloud_roughness",
    "feature_tables",
    "frame_features",
    "traverse_features",
]

#: Where the points of a frame come from (:func:`traverse_features`'s ``source``).
SOURCES = ("auto", "cloud", "stereo")

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
        ``pitch``.
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
        rad, and when valid ``R`` in m³/rad, ``w``, ``sigma_R``, ``sigma_w``, ``rms`` in m,
        ``iso_class``, ``R_lat``, ``w_lat``, ``fit_residual``).
    omega : ndarray or None
        Wavenumbers in rad/m of the spectrum (None when invalid).
    psd : ndarray or None
        Patch-mean PSD in m³/rad (None when invalid).
    """
    ex = _as_extraction(extraction)
    spec = ex.patch
    row: dict[str, Any] = {"valid": False, "reason": "", "n_points": 0}
    try:
        grid = grid_points(points, spec, roll=roll, pitch=pitch, min_points=min_points)
    except RoughMapError as exc:
        row["reason"] = f"too few points: {exc}" if "points" in str(exc) else str(exc)
        return row, None, None
    row.update(
        n_points=grid.n_points,
        fill=grid.fill_fraction,
        point_noise=grid.point_noise,
        noise_psd=grid.noise_psd,
        level_angle=grid.level_angle,
    )
    if grid.fill_fraction < min_fill:
        row["reason"] = f"too many gaps: {grid.fill_fraction:.0%} of cells filled"
        return row, None, None
    try:
        lon = _fit(grid, ex, grid.heights)
        lat = _fit(grid, ex, grid.heights.T)
    except RoughMapError as exc:
        row["reason"] = str(exc)
        return row, None, None
    row.update(
        valid=True,
        R=lon.R,
        w=lon.w,
        sigma_R=lon.sigma_R,
        sigma_w=lon.sigma_w,
        rms=lon.rms,
        iso_class=lon.iso_class,
        R_lat=lat.R,
        w_lat=lat.w,
        fit_residual=lon.fit_residual,
    )
    return row, lon.omega, lon.psd


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

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The cloud in the vehicle frame, m.
    extraction : Extraction or PatchSpec, optional
        Patch and estimator options; default the paper's.
    roll, pitch : float, optional
        Vehicle attitude in rad to compensate (paper Eq. 11); None: no compensation.
    min_points : int
        Fewest points in the patch.

    Raises
    ------
    RoughMapError
        Too few points in the patch, or a patch the estimator refuses.
    """
    ex = _as_extraction(extraction)
    grid = grid_points(points, ex.patch, roll=roll, pitch=pitch, min_points=min_points)
    return grid, _fit(grid, ex, grid.heights)


def _as_extraction(extraction: Extraction | PatchSpec | None) -> Extraction:
    if isinstance(extraction, PatchSpec):
        return Extraction(patch=extraction)
    return extraction or Extraction()


def _fit(grid: GriddedPatch, ex: Extraction, heights: np.ndarray) -> PatchRoughness:
    """:func:`rough_map.psd.patch_roughness` of a gridded patch's rows (``heights``: the
    grid's heights, or their transpose for the lateral direction), with the noise floor
    subtracted when ``ex`` says so and the patch has an estimate of it."""
    subtract = ex.subtract_noise and math.isfinite(grid.noise_psd)
    rough = patch_roughness(
        heights,
        ex.patch.spacing,
        method=ex.method,
        noise_psd=grid.noise_psd if subtract else None,
        subtract_noise=subtract,
        gridding=grid.gridding,
    )
    assert isinstance(rough, PatchRoughness)  # one patch, one estimate
    return rough


def traverse_features(
    traverse: Traverse | PathLike,
    extraction: Extraction | Mapping[str, Any] | None = None,
    *,
    source: str = "auto",
    min_points: int = 2000,
    min_fill: float = 0.7,
    progress: bool = False,
) -> FeatureTable:
    """Features of every frame of a traverse.

    Parameters
    ----------
    traverse : Traverse or path
        A loaded traverse, or its folder / file.
    extraction : Extraction or dict, optional
        The patch, the IMU tilt compensation, the estimator and its noise floor
        (:class:`rough_map.patch.Extraction`, or its ``to_dict`` form as a model records
        it); default the paper's.
    source : {"auto", "cloud", "stereo"}
        Where the points come from: the frame's cloud, its stereo pair, or the cloud when
        there is one ("auto").
    min_points : int
        Fewest points in the patch for a valid frame.
    min_fill : float
        Smallest fraction of filled cells for a valid frame.
    progress : bool
        Progress bar on stderr.

    Raises
    ------
    InputError
        An unknown ``source``, or ``"stereo"`` for a traverse without a calibration.
    """
    from tqdm import tqdm

    ex = Extraction.from_dict(extraction)
    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    if source not in SOURCES:
        raise InputError(f"source must be 'auto', 'cloud' or 'stereo', got {source!r}")
    if source == "stereo" and traverse.spec.calibration is None:
        raise InputError(f"{traverse.name}: stereo needs a 'calibration' in the traverse")
    frames = _FrameSource(traverse, ex.patch, source)  # reads nothing until a frame needs it
    n = len(traverse)
    rows: list[dict[str, Any]] = []
    spectra: list[np.ndarray | None] = []
    omega = None
    for i in tqdm(range(n), desc=f"features {traverse.name}", unit="frame", disable=not progress):
        row, om, psd = frames.features(i, ex, min_points=min_points, min_fill=min_fill)
        if om is not None:
            omega = om
        if not row["valid"]:
            log.info("frame %d invalid: %s", i, row["reason"])
        rows.append(row)
        spectra.append(psd)
    n_invalid = sum(not r["valid"] for r in rows)
    if n_invalid:
        log.warning("%s: %d of %d frames have no valid patch", traverse.name, n_invalid, n)
    return _table(rows, spectra, omega, ex.patch, traverse.name)


def _table(
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
    return FeatureTable(_columns(rows), omega, log_psd, name)


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


class _FrameSource:
    """The points of a traverse's frames: their clouds, or clouds reconstructed from their
    stereo pairs (lazily, so clouds-only runs need no OpenCV)."""

    def __init__(self, traverse: Traverse, spec: PatchSpec, source: str) -> None:
        self.traverse = traverse
        self.spec = spec
        self.source = source

    @property
    def calib(self) -> StereoCalibration:
        if self.traverse.spec.calibration is None:
            raise InputError(f"{self.traverse.name}: stereo needs a 'calibration' in the traverse")
        return self.traverse.spec.calibration

    def features(self, i: int, ex: Extraction, *, min_points: int, min_fill: float) -> FrameResult:
        """:func:`frame_features` of frame ``i`` with its time, pose and label, or an
        invalid row saying why there are no points: no stereo pair, an unreadable file."""
        frame = self.traverse.frames[i]
        row, omega, psd = self._features(i, ex, min_points=min_points, min_fill=min_fill)
        row.update(
            frame=i,
            t=frame.t,
            x=frame.pose.x,
            y=frame.pose.y,
            yaw=frame.pose.yaw,
            label=frame.label or "",
        )
        return row, omega, psd

    def _features(self, i: int, ex: Extraction, *, min_points: int, min_fill: float) -> FrameResult:
        frame = self.traverse.frames[i]
        use_stereo = self.source == "stereo" or (self.source == "auto" and frame.cloud is None)
        if use_stereo and (frame.left is None or frame.right is None):
            # Stereo is often recorded at a lower rate than the clouds: not an error of the run.
            return {"valid": False, "reason": "no stereo pair", "n_points": 0}, None, None
        try:
            points = self.stereo_cloud(i) if use_stereo else self.traverse.load_cloud(i)
        except FileFormatError as exc:
            return {"valid": False, "reason": f"unreadable: {exc}", "n_points": 0}, None, None
        roll = pitch = None
        if ex.use_imu and frame.imu is not None:
            roll, pitch = frame.imu.roll, frame.imu.pitch
        return frame_features(
            points, ex, roll=roll, pitch=pitch, min_points=min_points, min_fill=min_fill
        )

    def stereo_cloud(self, i: int) -> np.ndarray:
        """The cloud of frame ``i``'s stereo pair (vehicle frame, m), over the patch."""
        frame = self.traverse.frames[i]
        if frame.left is None or frame.right is None:
            raise InputError(f"{self.traverse.name}: frame {i} has no stereo pair")
        left = read_image(self.traverse.resolve(frame.left))
        right = read_image(self.traverse.resolve(frame.right))
        return stereo_to_cloud(left, right, self.calib, patch=self.spec)


def feature_tables(
    sources: Sequence[PathLike],
    extraction: Extraction | Mapping[str, Any] | None = None,
    *,
    progress: bool = False,
) -> list[FeatureTable]:
    """Feature tables of traverses, computing them or reading them from files.

    Parameters
    ----------
    sources : sequence of str or Path
        Traverse folders or files (features are computed with ``extraction``), or features
        tables (``.csv``/``.parquet`` written by ``rough-map features``, read as they are).
    extraction : Extraction or dict, optional
        The patch and estimator options (:class:`rough_map.patch.Extraction`, or its
        ``to_dict`` form as a model records it); default the paper's.
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    list of FeatureTable
    """
    ex = Extraction.from_dict(extraction)
    tables = []
    for source in sources:
        path = Path(source)
        if path.is_file() and path.suffix.lower() in (".csv", ".parquet"):
            tables.append(read_features(path))
        else:
            tables.append(traverse_features(path, ex, progress=progress))
    return tables
