"""One pass over a traverse's frames: each cloud (or stereo pair) is read once.

For every frame the pass gives what the rest of rough_map needs from the raw data:

* its feature row and patch spectrum (:func:`rough_map.features.frame_features`);
* optionally a :class:`HeightSample`: the world heights of its points, summed per cell of a
  lattice of the map's cell size, from which a map's elevation layer is built.

Nothing reads a cloud again after this pass. :func:`iter_frames` sends the frames to worker
processes (joblib) in chunks and yields them in frame order: ``n_jobs=2`` gives the same
bytes as ``n_jobs=1``. Each worker runs single-threaded (BLAS pinned with threadpoolctl,
OpenCV told so): the processes use the cores, and the per-frame matrices are small.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from rough_map._blas import one_blas_thread
from rough_map.config import StereoCalibration
from rough_map.errors import FileFormatError, InputError
from rough_map.features.extract import GriddedFrame, grid_frame, measure_frames
from rough_map.geometry import pose_matrix, rotation_matrix, transform_columns
from rough_map.io.pointcloud import read_cloud
from rough_map.io.raster import HeightRaster, shared_height_raster
from rough_map.io.traverse import Traverse
from rough_map.patch import Extraction, GriddedPatch
from rough_map.patch._params import check_int
from rough_map.patch.surface import cut_patch
from rough_map.stereo import read_image, stereo_to_cloud

log = logging.getLogger(__name__)

#: Largest world coordinate (m, |x| and |y|) of a point kept in a frame's height sample:
#: beyond any projected CRS (UTM northings reach 1e7 m).
MAX_WORLD_M = 1e9

__all__ = [
    "SOURCES",
    "FrameJob",
    "FrameOutput",
    "FramePass",
    "FrameStream",
    "HeightSample",
    "check_jobs",
    "frame_jobs",
    "iter_frames",
    "process_frame",
    "process_frames",
    "process_points",
    "read_points",
    "start_workers",
]

#: Where the points of a frame come from: the frame's cloud, its stereo pair, or the cloud
#: when there is one ("auto").
SOURCES = ("auto", "cloud", "stereo")

#: Frames per task sent to a worker: enough to make the hand-over cheap, few enough that
#: results stream back steadily, the processes share the work evenly and memory stays flat.
#: A cloud takes a few ms, a stereo pair about 100 ms.
CHUNK = 32
STEREO_CHUNK = 4


@dataclass(frozen=True)
class FrameJob:
    """What one frame's processing needs, and nothing else (cheap to send to a worker).

    Attributes
    ----------
    index : int
        Frame index in the traverse.
    t : float
        Time, s.
    pose : tuple of 6 float
        ``(x, y, z, roll, pitch, yaw)`` of the vehicle in the world, m and rad.
    label : str
        Terrain class name ("" unlabelled).
    cloud, left, right : Path or None
        The frame's files.
    imu : tuple of 2 float or None
        IMU roll and pitch, rad.
    world_cloud : bool
        The cloud is in the world frame (``cloud_frame``): moved by ``pose`` when read.
    surface : tuple, optional
        ``(path, spacing, origin)`` of the height raster the patch is cut from at the
        pose (a route over a survey: the traverse's ``surface``), instead of points.
    """

    index: int
    t: float
    pose: tuple[float, float, float, float, float, float]
    label: str = ""
    cloud: Path | None = None
    left: Path | None = None
    right: Path | None = None
    imu: tuple[float, float] | None = None
    world_cloud: bool = False
    surface: tuple[str, float | None, tuple[float, float] | None] | None = None


def frame_jobs(traverse: Traverse) -> list[FrameJob]:
    """The :class:`FrameJob` of every frame of ``traverse``, with its paths resolved (and
    checked to stay inside the traverse folder: :meth:`Traverse.resolve`)."""
    jobs = []
    resolve = traverse.resolver()
    surface = surface_of(traverse)
    for i, f in enumerate(traverse.frames):
        p = f.pose
        jobs.append(
            FrameJob(
                index=i,
                t=f.t,
                pose=(p.x, p.y, p.z, p.roll, p.pitch, p.yaw),
                label=f.label or "",
                cloud=None if f.cloud is None else resolve(f.cloud, f"frames[{i}].cloud"),
                left=None if f.left is None else resolve(f.left, f"frames[{i}].left"),
                right=None if f.right is None else resolve(f.right, f"frames[{i}].right"),
                imu=None if f.imu is None else (f.imu.roll, f.imu.pitch),
                world_cloud=traverse.spec.cloud_frame == "world",
                surface=surface,
            )
        )
    return jobs


def surface_of(
    traverse: Traverse,
) -> tuple[str, float | None, tuple[float, float] | None] | None:
    """The traverse's ``surface`` as a :attr:`FrameJob.surface` (its path resolved and
    checked), None without one."""
    spec = traverse.spec.surface
    if spec is None:
        return None
    path = traverse.resolve(spec.path, "surface.path")
    return str(path), spec.spacing, spec.origin


def open_surface(surface: tuple[str, float | None, tuple[float, float] | None]) -> HeightRaster:
    """The height raster of a :attr:`FrameJob.surface`, opened once per process (again
    when the file changes: :func:`rough_map.io.raster.shared_height_raster`)."""
    return shared_height_raster(*surface)


@dataclass(frozen=True)
class HeightSample:
    """World heights of a frame's points, summed per cell of a lattice.

    Cell ``(row, col)`` covers x in ``[col * resolution, (col + 1) * resolution)`` and y in
    ``[row * resolution, (row + 1) * resolution)`` (m, world frame): the lattice every
    :class:`~rough_map.map.grid_geometry.GridGeometry` of that cell size is aligned on.

    Attributes
    ----------
    resolution : float
        Cell size, m.
    rows, cols : ndarray of int64, shape (M,)
        Lattice cells holding points.
    sums : ndarray, shape (M,)
        Sum of the heights (world z, m) of the points in each cell.
    counts : ndarray, shape (M,)
        Number of points in each cell.
    """

    resolution: float
    rows: NDArray[np.int64]
    cols: NDArray[np.int64]
    sums: NDArray[np.float64]
    counts: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.rows.size)


@dataclass(frozen=True)
class FrameOutput:
    """The result of one frame: its feature row, spectrum and height sample.

    Attributes
    ----------
    index : int
        Frame index.
    row : dict
        Scalar feature columns, with the frame's ``frame``, ``t``, ``x``, ``y``, ``yaw`` and
        ``label`` (see :func:`rough_map.features.frame_features`).
    omega : ndarray or None
        Wavenumbers of the spectrum, rad/m (None for an invalid frame).
    psd : ndarray or None
        Patch-mean PSD, m³/rad (None for an invalid frame).
    heights : HeightSample or None
        The frame's world heights (None when not asked for, or without points).
    """

    index: int
    row: dict[str, Any]
    omega: NDArray[np.float64] | None
    psd: NDArray[np.float64] | None
    heights: HeightSample | None = None


@dataclass(frozen=True)
class FramePass:
    """How the frames are processed.

    Attributes
    ----------
    extraction : Extraction
        The patch, the IMU tilt compensation and the estimator.
    source : {"auto", "cloud", "stereo"}
        Where the points come from (:data:`SOURCES`).
    calibration : StereoCalibration or None
        The rig, for stereo frames.
    min_points : int
        Fewest points in the patch for a valid frame.
    min_fill : float
        Smallest fraction of filled cells for a valid frame.
    height_resolution : float or None
        Cell size in m of the :class:`HeightSample` of each frame; None: none.
    height_points : int
        Most points of a cloud summed into its height sample (every k-th point of a
        larger cloud): 8,000 give each 0.1 m cell of the elevation layer a few points
        from every frame that sees it, and it is seen by many.
    features : bool
        Measure the patch (False: height samples only).
    asked : Extraction or None
        The extraction asked for when ``spacing auto`` chose ``extraction``'s step for the
        traverse; None: ``extraction`` itself.
    """

    extraction: Extraction = field(default_factory=Extraction)
    source: str = "auto"
    calibration: StereoCalibration | None = None
    min_points: int = 2000
    min_fill: float = 0.7
    height_resolution: float | None = None
    height_points: int = 8_000
    features: bool = True
    asked: Extraction | None = None

    @property
    def requested(self) -> Extraction:
        """The extraction asked for: :attr:`asked`, or :attr:`extraction` when the step
        was not chosen for the traverse."""
        return self.asked or self.extraction

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise InputError(f"source must be 'auto', 'cloud' or 'stereo', got {self.source!r}")
        r = self.height_resolution
        if r is not None and not (math.isfinite(r) and r > 0):
            raise InputError(f"height_resolution must be a cell size > 0 in m, got {r!r}")


def process_frame(job: FrameJob, settings: FramePass) -> FrameOutput:
    """Features (and height sample) of one frame; never raises for a bad frame.

    A frame without the points asked for (no stereo pair, an unreadable or missing file)
    gets an invalid row saying why.
    """
    if job.surface is not None:
        return _measure([_surface_stage(job, settings)])[0]
    points, reason = read_points(job, settings)
    return process_points(points, job, settings, reason)


def process_points(
    points: NDArray[np.float64] | None,
    job: FrameJob,
    settings: FramePass,
    reason: str = "no points",
) -> FrameOutput:
    """:func:`process_frame` of points already read (vehicle frame, m; None: an invalid
    row saying ``reason``)."""
    return _measure([_grid_stage(points, job, settings, reason)])[0]


class _Gridded(NamedTuple):
    """A frame after its points were read: gridded, its heights sampled (the points are
    not kept)."""

    job: FrameJob
    frame: GriddedFrame
    heights: HeightSample | None


def _grid_stage(
    points: NDArray[np.float64] | None, job: FrameJob, settings: FramePass, reason: str
) -> _Gridded:
    if points is None:
        row = {"valid": False, "reason": reason, "n_points": 0}
        frame = GriddedFrame(row, None, settings.extraction)
    elif not settings.features:
        row = {"valid": False, "reason": "not measured", "n_points": 0}
        frame = GriddedFrame(row, None, settings.extraction)
    else:
        ex = settings.extraction
        roll = pitch = None
        if ex.use_imu and job.imu is not None:
            roll, pitch = job.imu
        frame = grid_frame(
            points,
            ex,
            roll=roll,
            pitch=pitch,
            min_points=settings.min_points,
            min_fill=settings.min_fill,
        )
    heights = None
    if points is not None and settings.height_resolution is not None:
        heights = height_sample(points, job, settings.height_resolution, settings.height_points)
    return _Gridded(job, frame, heights)


def _surface_stage(job: FrameJob, settings: FramePass) -> _Gridded:
    """A frame of a route over a raster: its patch cut from the raster at its pose."""
    assert job.surface is not None
    ex = settings.extraction
    x, y, _, _, _, yaw = job.pose
    row: dict[str, Any] = {"valid": False, "reason": "", "n_points": 0}
    try:
        grid, nodes = cut_patch(open_surface(job.surface), (x, y, yaw), ex.patch)
    except FileFormatError as exc:
        row["reason"] = f"unreadable: {exc}"
        return _Gridded(job, GriddedFrame(row, None, ex), None)
    row.update(
        n_points=grid.n_points,
        fill=grid.fill_fraction,
        point_noise=math.nan,
        noise_psd=math.nan,
        level_angle=0.0,
    )
    measured: GriddedPatch | None = grid
    if not settings.features:
        row["reason"], measured = "not measured", None
    elif grid.n_points == 0:
        row["reason"], measured = "the patch is off the surface (no height there)", None
    heights = None
    if settings.height_resolution is not None and len(nodes):
        heights = height_sample(nodes, job, settings.height_resolution, settings.height_points)
    return _Gridded(job, GriddedFrame(row, measured, ex), heights)


def _measure(gridded: Sequence[_Gridded]) -> list[FrameOutput]:
    """The outputs of gridded frames, their patches measured in one batch."""
    results = measure_frames([g.frame for g in gridded])
    out = []
    for g, (row, omega, psd) in zip(gridded, results, strict=True):
        x, y, _, _, _, yaw = g.job.pose
        row.update(frame=g.job.index, t=g.job.t, x=x, y=y, yaw=yaw, label=g.job.label)
        spec = g.frame.extraction.patch
        c, s = math.cos(yaw), math.sin(yaw)
        row.update(
            patch_x=x + c * spec.ahead - s * spec.lateral,
            patch_y=y + s * spec.ahead + c * spec.lateral,
        )
        out.append(FrameOutput(g.job.index, row, omega, psd, g.heights))
    return out


def _uses_stereo(job: FrameJob, settings: FramePass) -> bool:
    return settings.source == "stereo" or (settings.source == "auto" and job.cloud is None)


def read_points(job: FrameJob, settings: FramePass) -> tuple[NDArray[np.float64] | None, str]:
    """The frame's points in the vehicle frame (m), or None and why not."""
    if job.surface is not None:
        return None, "the patch is cut from the surface, not read from points"
    use_stereo = _uses_stereo(job, settings)
    try:
        if not use_stereo:
            if job.cloud is None:
                return None, "no point cloud"
            points = read_cloud(job.cloud)
            if job.world_cloud:  # p_vehicle = R^T (p_world - t)
                m = pose_matrix(job.pose)
                points = (points - m[:3, 3]) @ m[:3, :3]
            return points, ""
        if job.left is None or job.right is None:
            # Stereo is often recorded at a lower rate than the clouds: not an error of the run.
            return None, "no stereo pair"
        if settings.calibration is None:
            raise InputError("stereo needs a 'calibration' in the traverse")
        left, right = read_image(job.left), read_image(job.right)
        spec = settings.extraction.patch
        return stereo_to_cloud(left, right, settings.calibration, patch=spec), ""
    except FileFormatError as exc:
        return None, f"unreadable: {exc}"


def height_sample(
    points: NDArray[np.float64], job: FrameJob, resolution: float, most: int
) -> HeightSample:
    """World heights of (at most ``most`` of) a frame's points, summed per lattice cell.

    A cloud of more than ``most`` points is thinned to every k-th point (deterministic).
    """
    pts = points[:: -(-len(points) // most)] if len(points) > most else points
    x, y, z, roll, pitch, yaw = job.pose
    xw, yw, zw = transform_columns(pts, rotation_matrix(roll, pitch, yaw), (x, y, z))
    # Beyond MAX_WORLD_M no point is ground on any map (and its cell index would overflow).
    reach = min(MAX_WORLD_M, 2.0**60 * resolution)
    ok = (np.abs(xw) <= reach) & (np.abs(yw) <= reach) & np.isfinite(zw)
    if not ok.all():
        xw, yw, zw = xw[ok], yw[ok], zw[ok]
    if xw.size == 0:
        empty = np.empty(0, dtype=np.int64)
        return HeightSample(resolution, empty, empty, np.empty(0), np.empty(0))
    cols = np.floor(xw * (1.0 / resolution)).astype(np.int64)
    rows = np.floor(yw * (1.0 / resolution)).astype(np.int64)
    r0, c0 = int(rows.min()), int(cols.min())
    height, width = int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1
    sums: NDArray[np.float64]
    counts: NDArray[np.float64]
    if height * width >= 2**62:  # cells too far apart for one integer key: pairs
        pairs, inverse = np.unique(np.column_stack([rows, cols]), axis=0, return_inverse=True)
        inverse = inverse.ravel()
        sums = np.bincount(inverse, weights=zw, minlength=len(pairs)).astype(np.float64)
        counts = np.bincount(inverse, minlength=len(pairs)).astype(np.float64)
        return HeightSample(resolution, pairs[:, 0], pairs[:, 1], sums, counts)
    key = (rows - r0) * width + (cols - c0)
    if height * width <= 4 * key.size + 4096:  # a small box: count in place
        counts = np.bincount(key, minlength=height * width).astype(np.float64)
        sums = np.bincount(key, weights=zw, minlength=height * width).astype(np.float64)
        cells = np.flatnonzero(counts)
        sums, counts = sums[cells], counts[cells]
    else:  # points spread far apart: sort them instead
        cells, inverse = np.unique(key, return_inverse=True)
        sums = np.bincount(inverse, weights=zw, minlength=cells.size).astype(np.float64)
        counts = np.bincount(inverse, minlength=cells.size).astype(np.float64)
    return HeightSample(resolution, cells // width + r0, cells % width + c0, sums, counts)


def process_frames(jobs: Sequence[FrameJob], settings: FramePass) -> list[FrameOutput]:
    """:func:`process_frame` of each job, single-threaded (the unit of work of a worker):
    each frame's points are read, gridded and dropped, then all the patches are measured
    in one vectorised pass (the same numbers as one frame at a time)."""
    stereo = settings.source != "cloud" and any(j.left is not None for j in jobs)
    if stereo:
        import cv2

        cv2.setNumThreads(1)
    with one_blas_thread():
        gridded = []
        for job in jobs:
            if job.surface is not None:
                gridded.append(_surface_stage(job, settings))
                continue
            points, reason = read_points(job, settings)
            gridded.append(_grid_stage(points, job, settings, reason))
        return _measure(gridded)


def start_workers(n_jobs: int) -> None:
    """Start the worker processes of a coming frame pass (``n_jobs`` as
    :func:`iter_frames` takes it) now, so that they import rough_map while this process is
    still loading the model; nothing for one process. :func:`iter_frames` takes them over."""
    workers = check_jobs(n_jobs)
    if workers == 1:
        return

    start_executor(workers - 1, lambda ex: [ex.submit(_ready) for _ in range(workers - 1)])


def start_executor(processes: int, first: Callable[[Any], Iterable[Any]]) -> Any:
    """loky's reusable executor of ``processes`` workers, started with its first tasks
    (``first(executor)`` submits them and returns their futures) in
    :func:`children_ignore_sigint`. A Ctrl-C taken as that block ends cancels the tasks
    not started and shuts the workers down (and loky's resource tracker) before it goes
    on."""
    from joblib.externals.loky import get_reusable_executor

    executor, futures = None, []
    try:
        with children_ignore_sigint():
            executor = get_reusable_executor(max_workers=processes)
            futures = list(first(executor))
    except BaseException:
        for future in futures:
            future.cancel()
        if executor is not None:
            with sigint_deferred():
                executor.shutdown(wait=True)
                stop_resource_tracker()
        raise
    return executor


@contextmanager
def sigint_deferred() -> Iterator[None]:
    """A Ctrl-C in this block is taken when it ends: the block runs to its end first.

    For the steps that a ``KeyboardInterrupt`` raised half-way would leave broken, such as
    loky's shut-down of its workers (their semaphores then stay registered, and loky's
    resource tracker prints a warning and tracebacks as the run exits). Outside the main
    thread the block does nothing (signals reach the main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def later(signum: int, frame: object) -> None:
        caught.append(signum)

    previous = signal.signal(signal.SIGINT, later)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught and callable(previous):
        previous(signal.SIGINT, None)  # the default handler raises KeyboardInterrupt
    elif caught and previous == signal.SIG_DFL:
        raise KeyboardInterrupt


@contextmanager
def children_ignore_sigint() -> Iterator[None]:
    """Processes started in this block ignore SIGINT, a disposition they inherit.

    Ctrl-C reaches every process of the terminal's group; only this one acts on it (one
    line, exit 130, the pool shuts the workers down): a worker would print a traceback and
    leave loky's semaphores behind. It is blocked here too: Linux keeps a blocked signal
    pending though ignored, so a Ctrl-C as the workers start is taken when the block ends
    (ignored alone, it was lost). Outside the main thread the block does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _ready() -> bool:
    """A worker's first task: unpickling it imports this module."""
    return True


def check_jobs(n_jobs: int) -> int:
    """The number of worker processes for ``n_jobs`` (joblib's convention: -1 all cores)."""
    if not isinstance(n_jobs, int) or n_jobs == 0 or n_jobs < -(os.cpu_count() or 1):
        raise InputError(f"n_jobs must be a positive number of processes or -1, got {n_jobs!r}")
    return n_jobs if n_jobs > 0 else max(1, (os.cpu_count() or 1) + 1 + n_jobs)


def iter_frames(
    jobs: Sequence[FrameJob],
    settings: FramePass,
    *,
    n_jobs: int = 1,
    chunk: int = CHUNK,
    progress: bool = False,
    desc: str = "frames",
    prime: int = 0,
) -> FrameStream:
    """:func:`process_frame` of every job, in order, over ``n_jobs`` processes.

    The workers start at once, before the first output is asked for: a caller can start the
    pass, then load what it needs to use the outputs (a model) while they work.

    Parameters
    ----------
    jobs : sequence of FrameJob
        The frames (:func:`frame_jobs`).
    settings : FramePass
        How to process them.
    n_jobs : int
        Worker processes (joblib; -1 all cores). 1 runs in this process, as the outputs
        are asked for.
    chunk : int
        Frames per task (stereo frames: :data:`STEREO_CHUNK` unless given).
    progress : bool
        Progress bar on stderr.
    desc : str
        Its label.
    prime : int
        Chunks to queue on the workers at once (at least two per worker are kept queued
        anyway): work for them while this process does something else first.

    Returns
    -------
    FrameStream
        Iterates the :class:`FrameOutput` of every job, in the order of ``jobs``, the same
        for any ``n_jobs``; :meth:`FrameStream.close` stops it early.
    """
    workers = check_jobs(n_jobs)
    check_int("prime", prime, low=0, high=2**31, unit="chunks")
    if chunk == CHUNK and any(_uses_stereo(j, settings) for j in jobs[:chunk]):
        chunk = STEREO_CHUNK
    chunks = [list(jobs[i : i + chunk]) for i in range(0, len(jobs), chunk)]
    return FrameStream(chunks, settings, workers, prime, progress, desc)


class FrameStream:
    """The outputs of a frame pass under way (:func:`iter_frames`), in frame order.

    The chunks run on this process and ``workers - 1`` joblib (loky) workers, so ``-j 2``
    costs one extra process, not two. The workers always have chunks queued. This process
    hands the results on in order (the caller fuses them into the map between two chunks)
    and, whenever the next result is not ready yet, takes the next unstarted chunk itself
    instead of waiting. So the share of chunks it computes adapts to what the caller does
    with them: a caller with little work leaves this process about ``1 / workers`` of the
    chunks; a busy one fewer. The outputs are those of :func:`process_frames` whichever
    process ran them.
    """

    def __init__(
        self,
        chunks: list[list[FrameJob]],
        settings: FramePass,
        workers: int,
        prime: int = 0,
        progress: bool = False,
        desc: str = "frames",
    ) -> None:
        self.settings = settings
        #: the model file whose card the pass started from (:func:`start_frame_pass`)
        self.card = ""
        self.jobs = [job for c in chunks for job in c]  # the frames, in order
        self._chunks = chunks
        self._progress = (sum(len(c) for c in chunks), progress, desc)
        self._futures: dict[int, Any] = {}
        self._unstarted = iter(range(len(chunks)))
        self._executor: Any = None
        self._ahead = 2 * (workers - 1)  # chunks kept queued on the workers
        # results this process may hold ahead of their turn: as many as the workers were
        # given at the start, so that it does not wait while they work off that queue
        self._hold = max(prime, self._ahead)
        if workers > 1 and len(chunks) > 1:

            def first(executor: Any) -> Iterable[Any]:
                self._executor = executor
                self._submit(self._hold)
                return self._futures.values()

            self._executor = start_executor(workers - 1, first)

    def _submit(self, upto: int) -> None:
        while len(self._futures) < upto:
            nxt = next(self._unstarted, None)
            if nxt is None:
                return
            self._futures[nxt] = self._executor.submit(
                process_frames, self._chunks[nxt], self.settings
            )

    def __iter__(self) -> Iterator[FrameOutput]:
        from tqdm import tqdm

        total, progress, desc = self._progress
        bar = tqdm(total=total, desc=desc, unit="frame", disable=not progress)
        try:
            for outputs in self._outputs():
                bar.update(len(outputs))
                yield from outputs
        finally:
            bar.close()
            self.close()

    def _outputs(self) -> Iterator[list[FrameOutput]]:
        if self._executor is None:
            for c in self._chunks:
                yield process_frames(c, self.settings)
            return
        mine: dict[int, list[FrameOutput]] = {}  # done here, ahead of their turn
        for k in range(len(self._chunks)):
            while k not in mine:
                self._submit(self._ahead)
                future = self._futures.get(k)
                if future is None or future.done() or len(mine) >= self._hold:
                    break  # ready, or this process is far enough ahead: wait for it
                nxt = next(self._unstarted, None)
                if nxt is None:
                    break
                mine[nxt] = process_frames(self._chunks[nxt], self.settings)
            yield mine.pop(k) if k in mine else self._futures.pop(k).result()

    def close(self) -> None:
        """Stop: cancel the chunks not started, and let the workers go."""
        if self._executor is None:
            return
        for f in self._futures.values():
            f.cancel()
        self._futures.clear()
        # The workers would idle for minutes holding their memory: the map's merge and
        # export come next, and need it more. So would loky's resource tracker (about
        # 40 MB), which has nothing left to track; a later pass starts a new one.
        with sigint_deferred():
            self._executor.shutdown(wait=True)
            self._executor = None
            stop_resource_tracker()


def stop_resource_tracker() -> None:
    """Stop loky's resource-tracker process once no executor is left (POSIX)."""
    from joblib.externals.loky.backend import resource_tracker

    tracker = resource_tracker._resource_tracker
    stop = getattr(tracker, "_stop", None)
    if stop is None or os.name != "posix":
        return
    try:
        stop()
    except (OSError, RuntimeError) as exc:  # it is only memory: never fail the run for it
        log.debug("could not stop loky's resource tracker: %s", exc)
