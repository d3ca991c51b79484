"""Many traverses, one map: each mapped on its own, in parallel or on a Dask cluster, then fused.

:func:`run_batch` maps every traverse as ``rough-map map`` does
(:func:`rough_map.workflow.analyse` and :func:`~rough_map.workflow.write_outputs`) into
``OUT/<name>/``, then adds their fusion sums (``map_state.npz``) into one map of all of
them (:func:`fuse_states`: the same Bayesian fusion, as if all their frames had been fused
together) and writes it at the top of ``OUT``.

Where the work runs: in this process, in ``n_jobs`` local processes (joblib), or on the
workers of a Dask cluster (``scheduler="tcp://host:8786"``, which needs
``rough-map[cluster]``). A worker reads the traverse from the path it is given (so workers
need the same view of the data as the client, e.g. a shared file system), maps it in a
temporary folder of its own and sends the files back; the client writes them. The outputs
hold no wall-clock time and no absolute path, so they are the same bytes wherever and in
whatever order the work ran.

A batch is resumable: a traverse whose folder holds a ``batch.json`` with the same
fingerprint (the traverse file's and the model's SHA-256, the settings, the rough_map
version) is not mapped again. Each traverse's folder is written as a set: into a hidden
staging folder swapped in whole when complete (:func:`rough_map._files.output_set`),
so a killed run leaves either the old folder or the new one, never half of one; a finished
traverse stays done. The fused map at the top is a set too: the whole of ``OUT`` is staged
(the traverses' folders and the user's files carried over by hard links) and swapped in.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from rough_map import __version__
from rough_map._cluster import cluster_client
from rough_map._files import (
    PathLike,
    atomic_output,
    clean_dead_temp_dirs,
    clean_stale,
    output_set,
    recover,
    write_error,
)
from rough_map.classify import sha256_file
from rough_map.errors import InputError
from rough_map.export import export_map
from rough_map.export.costmap import CostmapSettings, write_costmap
from rough_map.io.traverse import find_traverse_file, load_traverse
from rough_map.map.tiles import TiledMap
from rough_map.resources import model_base
from rough_map.vehicle import SpeedTable, Vehicle
from rough_map.workflow import (
    AnalysisOptions,
    add_speed_layers,
    analyse_model_file,
    summary,
    write_outputs,
)

log = logging.getLogger(__name__)

__all__ = ["BatchJob", "BatchResult", "fuse_states", "map_traverse_files", "run_batch"]

#: Names the fused map writes at the top of the batch's folder (glob patterns): an old
#: file of these names that a run does not write again is dropped.
FUSED_OUTPUTS = ("map.tif", "map_*.tif", "map_*.png", "map_costmap.*", "batch.json")

#: Prefix of a worker's temporary folder, followed by its process id.
_BATCH_PREFIX = "rough_map_batch_"

#: Name of the file that marks a traverse's folder (or the batch's) as complete.
MARKER = "batch.json"


@dataclass(frozen=True)
class BatchJob:
    """One traverse of a batch: what to map and how (sent to a worker as it is).

    Attributes
    ----------
    traverse : str
        The traverse folder or file, as the workers see it.
    name : str
        Its name (``OUT/<name>/``).
    model : str
        Model name or file.
    resolution : float
        Map cell size, m.
    near_far : str or bool
        As :func:`rough_map.workflow.analyse`'s.
    png : bool
        Draw the layer PNGs.
    n_jobs : int
        Processes for the frames of this traverse.
    allow_outside : tuple of str
        Folders outside the traverse folder its files may be in (``--allow-outside``).
    vehicle : Vehicle, optional
        Speed advice for this vehicle (``v_max`` columns and layers, the costmap).
    speed : float, optional
        With ``vehicle``: the responses at this speed, m/s.
    costmap : CostmapSettings, optional
        The costmap's settings (default :class:`~rough_map.export.costmap.CostmapSettings`).
    """

    traverse: str
    name: str
    model: str
    resolution: float
    near_far: str | bool
    png: bool
    n_jobs: int = 1
    allow_outside: tuple[str, ...] = ()
    vehicle: Vehicle | None = None
    speed: float | None = None
    costmap: CostmapSettings | None = None


@dataclass
class BatchResult:
    """What :func:`run_batch` did.

    Attributes
    ----------
    mapped, skipped : list of str
        Traverses mapped now, and those already done (resumed).
    outputs : dict of str to Path
        The fused map's files.
    summaries : dict of str to dict
        Each traverse's figures (:func:`rough_map.workflow.summary`).
    """

    mapped: list[str]
    skipped: list[str]
    outputs: dict[str, Path]
    summaries: dict[str, dict[str, Any]]


def _model_file(model: str) -> Path:
    return model_base() if model == "default" else Path(model)


def fingerprint(job: BatchJob) -> dict[str, Any]:
    """What decides a traverse's outputs: the traverse file's and the model's SHA-256, the
    settings and the rough_map version (no path, no time)."""
    model = _model_file(job.model)
    model_file = model if model.suffix == ".skops" else model.with_suffix(".skops")
    return {
        "traverse_sha256": sha256_file(find_traverse_file(job.traverse)),
        "model_sha256": sha256_file(model_file) if model_file.is_file() else job.model,
        "resolution_m": job.resolution,
        "near_far": job.near_far,
        "png": job.png,
        "rough_map_version": __version__,
        # only with a vehicle, so that a batch without one keeps its fingerprints
        **(
            {
                "vehicle": job.vehicle.model_dump(mode="json"),
                "speed_m_s": job.speed,
                # as batch.json holds it (tuples as lists), to compare with the saved one
                "costmap": json.loads(json.dumps(asdict(job.costmap or CostmapSettings()))),
            }
            if job.vehicle is not None
            else {}
        ),
    }


def map_traverse_files(job: BatchJob) -> dict[str, bytes]:
    """Map one traverse in a temporary folder; its files by name (run on a worker).

    The marker ``batch.json`` (the fingerprint and the traverse's figures) is among them.
    """
    clean_dead_temp_dirs(_BATCH_PREFIX)
    tmp = Path(tempfile.mkdtemp(prefix=f"{_BATCH_PREFIX}{os.getpid()}_"))
    try:
        result = analyse_model_file(
            load_traverse(job.traverse, allow_outside=job.allow_outside),
            _model_file(job.model),
            AnalysisOptions(
                resolution=job.resolution,
                near_far=job.near_far,
                n_jobs=job.n_jobs,
                vehicle=job.vehicle,
                speed=job.speed,
            ),
        )
        write_outputs(result, tmp, png=job.png, as_set=False, costmap=job.costmap)
        if result.mapper is not None:
            result.mapper.close()  # its tiles on disk
        marker = {
            "traverse": job.name,
            "fingerprint": fingerprint(job),
            "summary": summary(result, job.resolution),
        }
        (tmp / MARKER).write_text(json.dumps(marker, indent=2, sort_keys=True) + "\n")
        files = {}
        for path in sorted(tmp.rglob("*")):
            if path.is_file():
                files[path.relative_to(tmp).as_posix()] = path.read_bytes()
        return files
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _write_set(folder: Path, files: dict[str, bytes]) -> None:
    """Write a traverse's files as a set: staged beside ``folder`` and swapped in whole
    (:func:`rough_map._files.output_set`; the folder is all the batch's)."""
    for rel in files:
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise InputError(f"refusing to write {rel!r} outside {folder}")
    with output_set(folder, owned=("*",)) as stage:
        for rel, data in files.items():
            target = stage / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            with open(target, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())


def _clean_leftovers(out: Path, names: Sequence[str]) -> None:
    """Repair and remove what a killed run left in ``out``: a traverse's folder set aside
    is put back, staged folders and temporary files are removed (those older than this
    run), and rough_map 0.x's ``.fused.*`` folders."""
    for name in names:
        recover(out / name)
    clean_stale(out)
    for path in out.glob(".fused.*"):
        if path.is_dir():
            log.info("removing %s, left by an interrupted run", path.name)
            shutil.rmtree(path, ignore_errors=True)


def _done(folder: Path, job: BatchJob) -> bool:
    marker = folder / MARKER
    if not (marker.is_file() and (folder / "map_state.npz").is_file()):
        return False
    try:
        saved = json.loads(marker.read_text())
    except (OSError, ValueError):
        return False
    return bool(saved.get("fingerprint") == fingerprint(job))


def _jobs(
    traverses: Sequence[PathLike], model: str, resolution: float, near_far: str | bool, png: bool
) -> list[BatchJob]:
    jobs: list[BatchJob] = []
    seen: dict[str, str] = {}
    for t in traverses:
        name = load_traverse(t).name
        if name in seen:
            raise InputError(
                f"two traverses are named {name!r} ({seen[name]} and {t}); "
                "their outputs would share OUT/{name}/: rename one in its traverse file"
            )
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise InputError(f"{t}: traverse name {name!r} cannot name a folder")
        seen[name] = str(t)
        jobs.append(BatchJob(str(t), name, model, resolution, near_far, png))
    return jobs


def run_batch(
    traverses: Sequence[PathLike],
    out_dir: PathLike,
    *,
    model: str = "default",
    resolution: float = 0.1,
    near_far: str | bool = "auto",
    png: bool = True,
    n_jobs: int = 1,
    scheduler: str | None = None,
    tls: tuple[str, str, str] | None = None,
    progress: bool = False,
    allow_outside: Sequence[PathLike] = (),
    vehicle: Vehicle | None = None,
    speed: float | None = None,
    costmap: CostmapSettings | None = None,
) -> BatchResult:
    """Map each traverse into ``out_dir/<name>/`` and fuse them all into ``out_dir``.

    Parameters
    ----------
    traverses : sequence of path
        Traverse folders or files (names must differ).
    out_dir : path
        Output folder.
    model : str
        Model name (``"default"``) or file.
    resolution : float
        Map cell size, m.
    near_far : {"auto", True, False}
        Near-to-far from the stereo images.
    png : bool
        Draw the PNGs.
    n_jobs : int
        Local processes (joblib): across traverses when there are enough, else across the
        frames of each.
    scheduler : str, optional
        Address of a Dask scheduler (``tls://host:8786``, or ``tcp://`` on a trusted
        private network): the traverses are mapped on its workers.
    tls : (ca_file, cert, key), optional
        PEM files for a ``tls://`` scheduler (mutual TLS, encryption required); default
        dask's configuration (``distributed.comm.tls.*``).
    progress : bool
        Progress bar on stderr.
    allow_outside : sequence of path
        Folders outside the traverse folders whose files the traverses may name
        (:func:`rough_map.io.traverse.load_traverse`); default none.
    vehicle : Vehicle, optional
        Speed advice for this vehicle, as ``rough-map map --vehicle`` gives it: in each
        traverse's outputs, and ``v_max`` (with ``v_max_95`` and the responses at ``speed``)
        and the costmap from the fused map's R and w.
    speed : float, optional
        With ``vehicle``: the responses at this speed, m/s.
    costmap : CostmapSettings, optional
        The costmaps' settings.

    Returns
    -------
    BatchResult
    """
    out = Path(out_dir)
    recover(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(out, exc) from None
    if vehicle is None and speed is not None:
        raise InputError("speed gives the responses of a vehicle: name one")
    jobs = [
        replace(j, vehicle=vehicle, speed=speed, costmap=costmap)
        for j in _jobs(traverses, model, resolution, near_far, png)
    ]
    if allow_outside:
        allowed = tuple(str(Path(p).resolve()) for p in allow_outside)
        jobs = [replace(j, allow_outside=allowed) for j in jobs]
    _clean_leftovers(out, [j.name for j in jobs])
    todo = [j for j in jobs if not _done(out / j.name, j)]
    skipped = [j.name for j in jobs if j not in todo]
    if skipped:
        log.info("already mapped, not redone: %s", ", ".join(skipped))
    for name, files in _execute(todo, n_jobs, scheduler, tls, progress):
        _write_set(out / name, files)
        log.info("mapped %s", name)
    summaries = {j.name: json.loads((out / j.name / MARKER).read_text())["summary"] for j in jobs}
    fused = fuse_states([out / j.name / "map_state.npz" for j in jobs])
    fused.attrs["traverses"] = [j.name for j in jobs]
    drive = None
    if vehicle is not None:
        add_speed_layers(fused, SpeedTable(vehicle, _band(summaries)), speed)
        drive = (vehicle.limits.top_speed, costmap)
    outputs = _write_fused(fused, out, png, [j.name for j in jobs], drive)
    return BatchResult([j.name for j in todo], skipped, outputs, summaries)


def fuse_states(paths: Sequence[PathLike], *, margin: float = 1.0) -> Any:
    """One map from the saved states of several traverses (``map_state.npz``): their sums
    added tile by tile (in bounded memory), then the estimates over all their patches plus
    ``margin`` m."""
    tiles = TiledMap.open_saved(paths[0])
    try:
        for path in paths:
            tiles.add_saved(path)
        return tiles.merged(margin=margin, attrs={"name": "batch"})
    finally:
        tiles.close()


def _execute(
    todo: list[BatchJob],
    n_jobs: int,
    scheduler: str | None,
    tls: tuple[str, str, str] | None,
    progress: bool,
) -> Iterator[tuple[str, dict[str, bytes]]]:
    """The files of each job, as they are done, wherever they run."""
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc="traverses", unit="traverse", disable=not progress)
    try:
        if scheduler is not None:
            yield from _on_cluster(todo, scheduler, tls, bar)
        elif n_jobs == 1 or len(todo) < max(n_jobs, 2):
            for job in todo:
                yield job.name, map_traverse_files(replace(job, n_jobs=n_jobs))
                bar.update()
        else:
            from joblib import Parallel, delayed

            parallel = Parallel(n_jobs=n_jobs, return_as="generator_unordered")
            for name, files in parallel(delayed(_named)(job) for job in todo):
                yield name, files
                bar.update()
    finally:
        bar.close()


def _named(job: BatchJob) -> tuple[str, dict[str, bytes]]:
    return job.name, map_traverse_files(job)


def _on_cluster(
    todo: list[BatchJob], scheduler: str, tls: tuple[str, str, str] | None, bar: Any
) -> Iterator[tuple[str, dict[str, bytes]]]:
    client = cluster_client(scheduler, tls)  # InputError without dask.distributed
    from distributed import as_completed

    with client:
        futures = {
            client.submit(
                _named, job, pure=False, key=f"map-{job.name}-{uuid.uuid4().hex[:8]}"
            ): job
            for job in todo
        }
        for future in as_completed(futures):
            name, files = future.result()
            yield name, files
            bar.update()


def _band(summaries: dict[str, dict[str, Any]]) -> tuple[float, float]:
    """The spectrum band (rad/m) the fused map's speed advice integrates over: the one
    the traverses share, else their overlap (logged), or the lowest band where they do not
    overlap."""
    bands = {tuple(s["band_rad_m"]) for s in summaries.values() if s.get("band_rad_m")}
    if not bands:
        raise InputError("no traverse of the batch has a spectrum band to drive over")
    if len(bands) > 1:
        log.info("the traverses were measured over different bands: the fused map's v_max "
                 "integrates over their overlap")  # fmt: skip
    lo, hi = max(b[0] for b in bands), min(b[1] for b in bands)
    return (lo, hi) if lo < hi else sorted(bands)[0]


def _write_fused(
    fused: Any,
    out: Path,
    png: bool,
    names: list[str],
    drive: tuple[float, CostmapSettings | None] | None = None,
) -> dict[str, Path]:
    """The fused map's files at the top of ``out``, with ``batch.json``: the whole folder
    staged and swapped in as a set (:func:`rough_map._files.output_set`), the
    traverses' folders (already in place) and the user's files carried over. With
    ``drive`` (the vehicle's top speed in m/s and the costmap's settings), the costmap."""
    marker = {
        "traverses": names,
        "map_shape": list(fused.shape),
        "resolution_m": fused.resolution,
        "rough_map_version": __version__,
    }
    with output_set(out, owned=FUSED_OUTPUTS) as stage:
        written = export_map(fused, stage, name="map", png=png)
        if drive is not None:
            written.update(write_costmap(fused, stage, drive[0], settings=drive[1]))
        with atomic_output(stage / MARKER) as t:
            t.write_text(json.dumps(marker, indent=2, sort_keys=True) + "\n")
    outputs = {key: out / path.name for key, path in written.items()}
    outputs["batch"] = out / MARKER
    return outputs
