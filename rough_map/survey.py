"""The roughness of a whole surface: the paper's patch slid over a height raster.

:func:`roughness_raster` cuts windows of ``window`` m a side from a
:class:`~rough_map.io.raster.HeightRaster` every ``stride`` m (default the paper's 0.896 m
patch at half-patch stride), takes the profiles along the raster's rows (west to east) or
columns (north to south), and measures each window with the estimator
(:func:`rough_map.psd.patch_roughness_each`), as a traverse's patch is measured. The result
is a :class:`~rough_map.map.grid.GridMap` in the raster's CRS with one cell per window,
centred on the window's centre and ``stride`` m a side, so each value sits where its window
is. :func:`rough_map.export.survey_files.write_roughness_raster` writes it as GeoTIFFs
(float bands; the ISO 8608 class in a uint8 file with a colour table), PNGs with legends
and a CSV, as one set.

Layers: ``R`` (m³/rad at 1 rad/m), ``w``, ``sigma_R``, ``sigma_w`` (spread between the
window's profiles), ``se_lnR``, ``se_w`` (standard errors of the window's ln R and w),
``rms`` (m, over the window's profiles), ``band_rms`` (m, over the fitted band: no
extrapolation), ``power_law`` (1 where the log spectrum is a line over the band, 0 where R
at 1 rad/m depends on the fit), ``iso_class`` (ISO 8608, A-H) and ``valid``. A window that
cannot be read (too many missing cells) or whose fit contradicts its own spectrum
(:attr:`rough_map.psd.PatchRoughness.consistent`) is nodata in every layer but ``valid``
(0). With ``both_directions`` the reading across (``R_across``, ``w_across``) and the
anisotropy ``ln(R / R_across)`` are added.

The raster is read a band of window rows at a time, so memory stays bounded whatever its
size; ``n_jobs`` spreads the bands over processes, with the same numbers as one process.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from rough_map._cluster import cluster_client
from rough_map.errors import InputError, PatchError
from rough_map.features.frames import (
    check_jobs,
    sigint_deferred,
    start_executor,
    stop_resource_tracker,
)
from rough_map.io.raster import HeightRaster
from rough_map.iso8608 import CLASSES
from rough_map.map.grid import GridMap
from rough_map.map.grid_geometry import GridGeometry
from rough_map.patch._params import check_bool, check_choice, check_real
from rough_map.patch.surface import AUTO_CELLS, surface_max_gap, window_size
from rough_map.psd import PatchRoughness, patch_roughness_each

log = logging.getLogger(__name__)

__all__ = [
    "AUTO_CELLS",
    "DIRECTIONS",
    "SurveySpec",
    "roughness_raster",
    "survey_geometry",
]

#: Directions the profiles run along: the raster's rows (west to east) or columns.
DIRECTIONS = ("rows", "columns")

#: Value layers of a roughness raster: name, units, description.
_VALUES = (
    ("R", "m^3/rad", "roughness: fitted PSD at 1 rad/m"),
    ("w", "1", "waviness: slope of the log PSD"),
    ("sigma_R", "m^3/rad", "spread of R between the window's profiles"),
    ("sigma_w", "1", "spread of w between the window's profiles"),
    ("se_lnR", "1", "standard error of the window's ln R"),
    ("se_w", "1", "standard error of the window's w"),
    ("rms", "m", "rms height of the window's detrended profiles"),
    ("band_rms", "m", "rms height over the fitted band"),
    ("power_law", "1", "1: the log spectrum is a line over the band; 0: R depends on the fit"),
)
_ACROSS = (
    ("R_across", "m^3/rad", "R of the profiles across the chosen direction"),
    ("w_across", "1", "w of the profiles across the chosen direction"),
    ("anisotropy", "1", "ln(R / R_across)"),
)
#: Heights measured in one call of the estimator: 256 windows of 112 x 112 cells (25 MB),
#: fewer of larger windows. Batches of 64 ran the estimator 15 % slower.
_BATCH_CELLS = 256 * 112 * 112
#: Raster rows a job reads at once (about: whole bands of windows).
_STRIP_ROWS = 512


@dataclass(frozen=True)
class SurveySpec:
    """How a raster is read for roughness.

    Attributes
    ----------
    window : float, optional
        Side of a window in m; default the paper's patch, 0.896 m, or :data:`AUTO_CELLS`
        cells of a coarser raster (decimetre cells of airborne lidar: metres).
    stride : float, optional
        Distance in m between the centres of neighbouring windows; default half a window.
    direction : {"rows", "columns"}
        The profiles run along the raster's rows (west to east) or its columns.
    gridding : {"point", "cell_mean"}, optional
        How the raster's heights were sampled (:class:`rough_map.psd.Options`): samples of
        the surface (a DEM interpolated or a CRG grid) or means of many points per cell;
        default the raster's own (:attr:`rough_map.io.raster.HeightRaster.gridding`).
    both_directions : bool
        Also measure the profiles across, and the anisotropy.
    """

    window: float | None = None
    stride: float | None = None
    direction: str = "rows"
    gridding: str | None = None
    both_directions: bool = False

    def __post_init__(self) -> None:
        check_real("window", self.window, "m", low=0.0, high=1e4, low_open=True, none=True)
        check_real("stride", self.stride, "m", low=0.0, high=1e4, low_open=True, none=True)
        check_choice("direction", self.direction, DIRECTIONS)
        if self.gridding is not None:
            check_choice("gridding", self.gridding, ("point", "cell_mean"))
        check_bool("both_directions", self.both_directions)

    def cells(self, spacing: float) -> tuple[int, int]:
        """Window side and stride in cells of ``spacing`` m.

        Raises
        ------
        InputError
            A window of fewer than 8 cells, or a stride below one cell.
        """
        window = self.window_m(spacing)
        size = round(window / spacing)
        step = round((self.stride if self.stride is not None else window / 2) / spacing)
        if size < 8:
            raise InputError(
                f"a window of {window:g} m holds {size} cells of {spacing:g} m; the "
                "estimator needs at least 8 a side: give a larger --window"
            )
        if step < 1:
            raise InputError(f"stride {self.stride:g} m is less than a cell of {spacing:g} m")
        return size, step

    def window_m(self, spacing: float) -> float:
        """The window's side in m on cells of ``spacing`` m."""
        return window_size(spacing, self.window)


def survey_geometry(raster: HeightRaster, spec: SurveySpec) -> GridGeometry:
    """The grid of window cells over ``raster``: one cell per window, ``stride`` m a side,
    centred on the window's centre."""
    size, step = spec.cells(raster.spacing)
    rows = (raster.shape[0] - size) // step + 1 if raster.shape[0] >= size else 0
    cols = (raster.shape[1] - size) // step + 1 if raster.shape[1] >= size else 0
    if rows < 1 or cols < 1:
        raise InputError(
            f"{raster.path.name}: {raster.shape[0]} x {raster.shape[1]} cells of "
            f"{raster.spacing:g} m hold no window of {size} cells"
        )
    b = raster.cell  # in the CRS's units, as the origin
    res = step * b
    west = raster.origin[0] + (size - step) / 2 * b
    north = raster.origin[1] - (size - step) / 2 * b
    return GridGeometry(res, (west, north - rows * res), (rows, cols), raster.crs)


def roughness_raster(
    raster: HeightRaster,
    spec: SurveySpec | None = None,
    *,
    n_jobs: int = 1,
    progress: bool = False,
    scheduler: str | None = None,
    tls: tuple[str, str, str] | None = None,
) -> GridMap:
    """The roughness of every window of ``raster`` (see the module docstring).

    Parameters
    ----------
    raster : HeightRaster
        The heights (:func:`rough_map.io.raster.open_height_raster`).
    spec : SurveySpec, optional
        Window, stride, direction; default the paper's patch at half-patch stride along
        the rows.
    n_jobs : int
        Worker processes (-1: every core); the numbers do not depend on it.
    progress : bool
        A progress bar on stderr.
    scheduler : str, optional
        Address of a Dask scheduler to run the strips on (:mod:`rough_map._cluster`; the
        workers read the raster at the same path); the numbers are those of one process.
    tls : tuple of 3 str, optional
        PEM files (CA, certificate, key) of a ``tls://`` scheduler.

    Returns
    -------
    GridMap
        One cell per window, in the raster's CRS.

    Raises
    ------
    InputError
        A window too small for the raster's cells, or a raster smaller than one window.
    FileFormatError
        The raster cannot be read.
    """
    from tqdm import tqdm

    spec = spec or SurveySpec()
    if spec.gridding is None:
        spec = replace(spec, gridding=raster.gridding)
    geo = survey_geometry(raster, spec)
    size, step = spec.cells(raster.spacing)
    names = [n for n, *_ in _VALUES] + ([n for n, *_ in _ACROSS] if spec.both_directions else [])
    out = {n: np.full(geo.shape, np.nan) for n in names}
    iso = np.full(geo.shape, np.nan)
    valid = np.zeros(geo.shape)
    n_rows, n_cols = geo.shape
    log.info(
        "%s: %d x %d windows of %d cells (%.3g m) every %d cells",
        raster.path.name,
        n_rows,
        n_cols,
        size,
        size * raster.spacing,
        step,
    )
    # a job is a strip of bands of windows, read once: the raster's rows are read once
    # (not once per band they fall in) and in blocks of a few hundred, as GDAL stores them
    per_strip = max(1, math.ceil(_STRIP_ROWS / step))
    strips = [(b, min(per_strip, n_rows - b)) for b in range(0, n_rows, per_strip)]
    results: Iterator[list[dict[str, NDArray[np.float64]]]]
    if scheduler is not None:
        results = _on_cluster(raster, spec, strips, (size, step, n_cols), scheduler, tls)
    elif n_jobs == 1:
        results = (_strip(raster, spec, b, k, size, step, n_cols) for b, k in strips)
    else:
        results = _in_processes(raster, spec, strips, (size, step, n_cols), n_jobs)
    with tqdm(total=n_rows * n_cols, desc="windows", unit="win", disable=not progress) as bar:
        i = 0
        for strip in results:
            for band in strip:
                row = n_rows - 1 - i  # the map's rows run north, the raster's south
                for n in names:
                    out[n][row] = band[n]
                iso[row] = band["iso_class"]
                valid[row] = band["valid"]
                i += 1
                bar.update(n_cols)
    grid = GridMap(geo, attrs={"source": str(raster.path), "window_m": size * raster.spacing})
    for name, units, description in (*_VALUES, *(_ACROSS if spec.both_directions else ())):
        grid.add_layer(name, units=units, description=description, data=out[name])
    grid.add_layer(
        "iso_class",
        units="1",
        description="ISO 8608 class of R",
        kind="class",
        categories=CLASSES,
        data=iso,
    )
    grid.add_layer("valid", units="1", description="1: the window was read", data=valid)
    return grid


def _in_processes(
    raster: HeightRaster,
    spec: SurveySpec,
    strips: list[tuple[int, int]],
    shape: tuple[int, int, int],
    n_jobs: int,
) -> Iterator[list[dict[str, NDArray[np.float64]]]]:
    """The strips measured on this process and ``n_jobs - 1`` loky workers, in order.

    The workers keep two strips each queued; while the next strip due is still on a
    worker, this process measures later ones itself (their readings are small: a few
    hundred kB a strip), so that it works rather than waits, also while the workers start
    (they import rough_map for a second or more)."""
    size, step, n_cols = shape
    workers = check_jobs(n_jobs)
    if workers == 1 or len(strips) < 2:
        yield from (_strip(raster, spec, b, k, size, step, n_cols) for b, k in strips)
        return
    ahead = 2 * (workers - 1)
    futures: dict[int, Any] = {}
    nxt = 0

    def submit(executor: Any) -> Iterable[Any]:
        nonlocal nxt
        while len(futures) < ahead and nxt < len(strips):
            futures[nxt] = executor.submit(_strip, raster, spec, *strips[nxt], *shape)
            nxt += 1
        return futures.values()

    executor = start_executor(workers - 1, submit)
    mine: dict[int, list[dict[str, NDArray[np.float64]]]] = {}  # done here, ahead of turn
    try:
        for k in range(len(strips)):
            while k not in mine:
                submit(executor)
                future = futures.get(k)
                if future is None or future.done() or nxt >= len(strips):
                    break
                mine[nxt] = _strip(raster, spec, *strips[nxt], *shape)
                nxt += 1
            yield mine.pop(k) if k in mine else futures.pop(k).result()
    finally:
        for future in futures.values():
            future.cancel()
        with sigint_deferred():
            executor.shutdown(wait=True)
            stop_resource_tracker()


def _on_cluster(
    raster: HeightRaster,
    spec: SurveySpec,
    strips: list[tuple[int, int]],
    shape: tuple[int, int, int],
    scheduler: str,
    tls: tuple[str, str, str] | None,
) -> Iterator[list[dict[str, NDArray[np.float64]]]]:
    """The strips measured on a Dask cluster, in order."""
    size, step, n_cols = shape
    with cluster_client(scheduler, tls) as client:
        futures = [
            client.submit(_strip, raster, spec, b, k, size, step, n_cols, pure=False)
            for b, k in strips
        ]
        for future in futures:
            yield future.result()


def _strip(
    raster: HeightRaster,
    spec: SurveySpec,
    first_band: int,
    n_bands: int,
    size: int,
    step: int,
    n_cols: int,
) -> list[dict[str, NDArray[np.float64]]]:
    """The readings of ``n_bands`` bands of windows from ``first_band`` on, their rows read
    in one piece."""
    first = first_band * step
    heights = raster.rows(first, (n_bands - 1) * step + size)
    with threadpool_limits(1):  # small matrices per window: threads only cost
        return [
            _band(heights[k * step : k * step + size], raster.spacing, spec, size, step, n_cols)
            for k in range(n_bands)
        ]


def _band(
    heights: NDArray[np.float64],
    spacing: float,
    spec: SurveySpec,
    size: int,
    step: int,
    n_cols: int,
) -> dict[str, NDArray[np.float64]]:
    """The readings of one band of windows, its ``size`` rows of ``heights`` (m)."""
    names = [n for n, *_ in _VALUES] + [n for n, *_ in _ACROSS]
    band = {n: np.full(n_cols, np.nan) for n in (*names, "iso_class")}
    band["valid"] = np.zeros(n_cols)
    along_rows = spec.direction == "rows"
    batch = max(1, _BATCH_CELLS // (size * size))
    for start in range(0, n_cols, batch):
        cols = range(start, min(start + batch, n_cols))
        stack = np.stack([heights[:, j * step : j * step + size] for j in cols])
        if not along_rows:
            stack = stack.transpose(0, 2, 1)
        along = _measure(stack, spacing, spec)
        across = _measure(stack.transpose(0, 2, 1), spacing, spec) if spec.both_directions else None
        for k, j in enumerate(cols):
            r = along[k]
            if not isinstance(r, PatchRoughness) or not r.consistent:
                continue
            band["valid"][j] = 1.0
            for name, value in _values(r).items():
                band[name][j] = value
            band["iso_class"][j] = CLASSES.index(r.iso_class)
            if across is not None and isinstance(across[k], PatchRoughness):
                a = across[k]
                assert isinstance(a, PatchRoughness)
                band["R_across"][j], band["w_across"][j] = a.R, a.w
                band["anisotropy"][j] = math.log(r.R / a.R) if a.R > 0 and r.R > 0 else math.nan
    return band


def _measure(
    stack: NDArray[np.float64], spacing: float, spec: SurveySpec
) -> list[PatchRoughness | PatchError]:
    """The estimator's reading of each window, a PatchError where it refuses one."""
    gridding = spec.gridding or "point"
    return patch_roughness_each(stack, spacing, gridding=gridding, max_gap=surface_max_gap(spacing))


def _values(r: PatchRoughness) -> dict[str, float]:
    return {
        "R": r.R,
        "w": r.w,
        "sigma_R": r.sigma_R,
        "sigma_w": r.sigma_w,
        "se_lnR": r.se_lnR,
        "se_w": r.se_w,
        "rms": r.rms,
        "band_rms": r.band_rms,
        "power_law": 1.0 if r.power_law else 0.0,
    }
