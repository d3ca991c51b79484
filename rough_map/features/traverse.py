"""A traverse's features table, from one pass over its frames (:mod:`.frames`).

:func:`traverse_features` runs the pass of :mod:`rough_map.features.frames` and gathers the
rows (:class:`FeatureCollector`); :func:`traverse_pass` sets the pass up, and with
``spacing: auto`` chooses one grid step for the whole traverse (:func:`resolve_spacing`);
:func:`feature_tables` computes or reads the tables of several traverses.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map._files import PathLike
from rough_map.errors import InputError, PatchError, RoughMapError
from rough_map.features.extract import cloud_roughness, feature_table
from rough_map.features.files import read_features
from rough_map.features.frames import (
    SOURCES,
    FrameOutput,
    FramePass,
    FrameStream,
    check_jobs,
    frame_jobs,
    iter_frames,
    open_surface,
    read_points,
    surface_of,
)
from rough_map.features.table import FeatureTable
from rough_map.io.model_files import card_extraction
from rough_map.io.traverse import Traverse, load_traverse
from rough_map.patch import Extraction, points_in_patch, pooled_rows
from rough_map.patch.surface import surface_patch_spec

log = logging.getLogger(__name__)

__all__ = [
    "PRIME_CHUNKS",
    "SPACING_SAMPLES",
    "FeatureCollector",
    "feature_tables",
    "resolve_spacing",
    "start_frame_pass",
    "traverse_features",
    "traverse_pass",
]


def traverse_features(
    traverse: Traverse | PathLike,
    extraction: Extraction | Mapping[str, Any] | None = None,
    *,
    source: str = "auto",
    min_points: int = 2000,
    min_fill: float = 0.7,
    n_jobs: int = 1,
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
    n_jobs : int
        Processes for the frames (-1: every core); the table is the same for any number.
    progress : bool
        Progress bar on stderr.

    Raises
    ------
    InputError
        An unknown ``source``, or ``"stereo"`` for a traverse without a calibration.
    """
    if not isinstance(traverse, Traverse):
        traverse = load_traverse(traverse)
    settings = traverse_pass(
        traverse, extraction, source=source, min_points=min_points, min_fill=min_fill
    )
    collect = FeatureCollector(traverse.name, settings.extraction)
    for out in iter_frames(
        frame_jobs(traverse),
        settings,
        n_jobs=n_jobs,
        progress=progress,
        desc=f"features {traverse.name}",
    ):
        collect.add(out)
    return collect.table()


#: Chunks queued on the workers when a map's frame pass starts before its model is loaded:
#: about two seconds of work for light clouds, what importing scikit-learn and matplotlib
#: and loading the model take.
PRIME_CHUNKS = 32


def start_frame_pass(
    traverse: Traverse,
    model: Any,
    *,
    resolution: float,
    n_jobs: int,
    progress: bool = False,
) -> FrameStream | None:
    """Start the frame pass of :func:`rough_map.workflow.analyse` (features and heights of
    every frame) on worker processes before the model is loaded, so that loading it (and
    importing scikit-learn) does not hold the workers up.

    The model's feature extraction is read from its card
    (:func:`rough_map.io.model_files.card_extraction`); ``analyse`` checks it against the
    loaded model. Returns None, and nothing starts, for one process or a model without a
    readable card (or not given by name or path).

    Parameters
    ----------
    traverse : Traverse
        The traverse.
    model : str, Path or other
        The model's name or file, as :func:`rough_map.workflow.analyse_model_file` takes it.
    resolution : float
        The map's cell size in m (the lattice of the frames' height samples).
    n_jobs : int
        Processes (-1: every core).
    progress : bool
        Progress bar on stderr.
    """
    if check_jobs(n_jobs) == 1 or not isinstance(model, str | Path):
        return None
    card = card_extraction(model)
    if card is None:
        return None
    reading = Extraction.from_dict(card).any_density()
    settings = traverse_pass(traverse, reading, height_resolution=resolution, features=True)
    stream = iter_frames(
        frame_jobs(traverse),
        settings,
        n_jobs=n_jobs,
        progress=progress,
        desc=traverse.name,
        prime=PRIME_CHUNKS,
    )
    stream.card = str(model)
    return stream


def traverse_pass(
    traverse: Traverse,
    extraction: Extraction | Mapping[str, Any] | None = None,
    *,
    source: str = "auto",
    **options: Any,
) -> FramePass:
    """The :class:`FramePass` of a traverse (its calibration for stereo frames).

    Raises
    ------
    InputError
        An unknown ``source``, or ``"stereo"`` for a traverse without a calibration.
    """
    if source not in SOURCES:
        raise InputError(f"source must be 'auto', 'cloud' or 'stereo', got {source!r}")
    calibration = traverse.spec.calibration
    if source == "stereo" and calibration is None:
        raise InputError(f"{traverse.name}: stereo needs a 'calibration' in the traverse")
    ex = Extraction.from_dict(extraction)
    settings = FramePass(ex, source, calibration, **options)
    surface = surface_of(traverse)
    if surface is not None:  # a route over a raster: the patch on the raster's cells
        raster = open_surface(surface)
        patch = surface_patch_spec(raster, ex.patch)
        log.info(
            "%s: patches cut from %s, %d x %d cells of %.4g m",
            traverse.name,
            raster.path.name,
            patch.n,
            patch.n,
            patch.spacing,
        )
        chosen = dataclasses.replace(ex, patch=patch, auto_spacing=False)
        return dataclasses.replace(settings, extraction=chosen, asked=ex)
    if ex.auto_spacing:
        chosen = resolve_spacing(traverse, settings)
        settings = dataclasses.replace(settings, extraction=chosen, asked=ex)
    return settings


#: Frames, spread along a traverse, whose density chooses its grid step.
SPACING_SAMPLES = 9
#: The same for stereo frames: a pair costs ~90 ms to match and stereo is dense at 1 m.
STEREO_SPACING_SAMPLES = 3


def resolve_spacing(traverse: Traverse, settings: FramePass) -> Extraction:
    """One grid step for every frame of a traverse (``spacing: auto``).

    The median number of points over the patch of up to :data:`SPACING_SAMPLES` frames
    (:data:`STEREO_SPACING_SAMPLES` stereo pairs) spread along the traverse chooses it
    (:func:`rough_map.patch.auto_spacing`), so that
    every row of the features table has the same wavenumbers. When they are sparse and
    their ground is the same across the track, the step asked for is kept with wider rows
    (:func:`rough_map.patch.pooled_rows`). The spacing asked for is kept
    when no sampled frame has points, or when they are too sparse for any step (the frames
    are then marked invalid, each saying why).
    """
    ex = settings.extraction
    jobs = frame_jobs(traverse)
    stereo = settings.source == "stereo" or (
        settings.source == "auto" and bool(jobs) and jobs[0].cloud is None
    )
    samples = STEREO_SPACING_SAMPLES if stereo else SPACING_SAMPLES
    picks = sorted({round(i) for i in np.linspace(0, len(jobs) - 1, samples)})
    counts, clouds = [], []
    for i in picks if jobs else []:
        points, _ = read_points(jobs[i], settings)
        if points is not None:
            counts.append(points_in_patch(points, ex.patch))
            clouds.append(points)
    fixed = dataclasses.replace(ex, auto_spacing=False)
    if not counts:
        return fixed
    median = int(np.median(counts))
    try:
        chosen = ex.resolve(median)
    except PatchError as exc:
        log.warning("%s: %s; keeping the %g mm grid", traverse.name, exc, ex.patch.spacing * 1e3)
        return fixed
    pooled = _pooled(clouds, median, ex, chosen)
    log.info(
        "%s: %.1f mm grid%s, %.2f points per %.1f mm cell (median of %d frames)",
        traverse.name,
        (pooled or chosen).patch.spacing * 1e3,
        "" if pooled is None else f" in rows {pooled.patch.row_step * 1e3:.1f} mm wide",
        median / ex.patch.n**2,
        ex.patch.spacing * 1e3,
        len(counts),
    )
    return pooled or chosen


def _pooled(
    clouds: list[NDArray[np.float64]], median: int, asked: Extraction, chosen: Extraction
) -> Extraction | None:
    """The extraction with pooled rows (:func:`rough_map.patch.pooled_rows`) when the
    sampled frames are sparse and their ground, read on the ``chosen`` grid, is the same
    across the track (the median of their lateral scales); else None."""
    if pooled_rows(median, asked.patch, 0.0) is None:
        return None  # dense enough: not worth reading the frames
    scales = []
    for points in clouds:
        try:
            scales.append(cloud_roughness(points, chosen)[1].lateral_scale)
        except RoughMapError:
            continue
    scale = float(np.nanmedian(scales)) if np.isfinite(scales).any() else float("nan")
    wide = pooled_rows(median, asked.patch, scale)
    return None if wide is None else dataclasses.replace(chosen, patch=wide)


class FeatureCollector:
    """Gathers :class:`FrameOutput` rows, in frame order, into a :class:`FeatureTable`."""

    def __init__(self, name: str, extraction: Extraction) -> None:
        self.name = name
        self.extraction = extraction
        self.rows: list[dict[str, Any]] = []
        self.spectra: list[NDArray[np.float64] | None] = []
        self.omega: NDArray[np.float64] | None = None

    def add(self, out: FrameOutput) -> None:
        """Append one frame's row and spectrum."""
        if out.omega is not None:
            self.omega = out.omega
        if not out.row["valid"]:
            log.info("frame %d invalid: %s", out.index, out.row["reason"])
        self.rows.append(out.row)
        self.spectra.append(out.psd)

    def table(self) -> FeatureTable:
        """The table of the frames added so far (logs how many are invalid)."""
        n = len(self.rows)
        n_invalid = sum(not r["valid"] for r in self.rows)
        if n_invalid:
            log.warning("%s: %d of %d frames have no valid patch", self.name, n_invalid, n)
        return feature_table(self.rows, self.spectra, self.omega, self.extraction.patch, self.name)


def feature_tables(
    sources: Sequence[PathLike | Traverse],
    extraction: Extraction | Mapping[str, Any] | None = None,
    *,
    n_jobs: int = 1,
    progress: bool = False,
) -> list[FeatureTable]:
    """Feature tables of traverses, computing them or reading them from files.

    Parameters
    ----------
    sources : sequence of str, Path or Traverse
        Traverses, their folders or files (features are computed with ``extraction``), or features
        tables (``.csv``/``.parquet`` written by ``rough-map features``, read as they are).
    extraction : Extraction or dict, optional
        The patch and estimator options (:class:`rough_map.patch.Extraction`, or its
        ``to_dict`` form as a model records it); default the paper's.
    n_jobs : int
        Processes for the frames of each traverse (-1: every core).
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    list of FeatureTable
    """
    ex = Extraction.from_dict(extraction)
    tables = []
    for source in sources:
        if isinstance(source, Traverse):
            tables.append(traverse_features(source, ex, n_jobs=n_jobs, progress=progress))
            continue
        path = Path(source)
        if path.is_file() and path.suffix.lower() in (".csv", ".parquet"):
            tables.append(read_features(path))
        else:
            tables.append(traverse_features(path, ex, n_jobs=n_jobs, progress=progress))
    return tables
