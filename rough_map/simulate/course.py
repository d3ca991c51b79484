"""Simulate a traverse: world, drive, sensors, and a traverse folder that validates.

Each frame gets

* ``clouds/NNNNNN.npy``: what a dense range sensor (depth camera, close-range lidar) sees
  of the ground around the patch of interest, in the vehicle frame, float32, with Gaussian
  noise along z. Only the points the features and the map use are written: the 1.0 m
  square centred on the patch (x 0.5-1.5 m, y -0.5-0.5 m; the 0.896 m patch plus 52 mm
  for tilt compensation and levelling, which use at most 16 mm of it on ploughed soil at
  10 degrees of pitch), out of the sensor's 1.1 m footprint
  (:attr:`SensorSpec.cloud_half_extent`, recorded as ``metadata.cloud_extent``). With
  ``compress`` the clouds are ``clouds/NNNNNN.npz`` instead: 16-bit integer columns
  (steps of 15 um or less), sorted along x and deflated, about 2.6 times smaller
  (:func:`save_cloud_npz`; :func:`rough_map.io.pointcloud.read_cloud` reads them);
* optionally ``left/NNNNNN.png`` and ``right/NNNNNN.png``: the rectified stereo pair of an
  XB3-like rig, rendered by ray casting (:func:`rough_map.simulate.render.render_stereo`);
* the true ``label`` (class under the patch centre) and the IMU roll and pitch.

The true world is saved as ``world_truth.npz`` (heights, class map, spacing, origin): the
heights as int16 steps of at most 10 um with a scale and an offset, the class map deflated
(:mod:`rough_map.io.truth`). A course up to 50 m
(:data:`~rough_map.simulate.world_tiles.WHOLE_LENGTH`) is built whole and its truth written whole
(:func:`~rough_map.io.truth.save_world`), exactly as before long courses were tiled. A
longer one is built in 6 m tiles (:class:`~rough_map.simulate.world_tiles.WorldTiles`) as the
rover drives on: the frames are made in runs of :data:`RUN_LENGTH` m, each on a window of
the world that holds what its wheels, range sensor and cameras see, and the finished
columns go to a truth file of the tiled layout
(:class:`~rough_map.io.truth.TiledWorldWriter`, read a tile at a time by
:class:`~rough_map.io.truth.TiledWorld`). Memory then holds a few tiles: about 0.6 GB
without images and 0.95 GB with them, whatever the length.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output
from rough_map.config import StereoCalibration, TraverseSpec
from rough_map.errors import InputError, RoughMapError
from rough_map.geometry import rotation_matrix
from rough_map.io.traverse import find_traverse_file, save_traverse
from rough_map.io.truth import TRUTH_FILE, TiledWorldWriter, save_world
from rough_map.simulate.render import render_stereo, view_bounds
from rough_map.simulate.textures import TextureSet
from rough_map.simulate.world import (
    CLASS_NAMES,
    COURSES,
    Defect,
    RoverGeometry,
    Segment,
    attitude,
    attitude_reach,
    build_world,
    course_layout,
    drive,
    drive_track,
)
from rough_map.simulate.world_tiles import TILE_LENGTH, WHOLE_LENGTH, WorldTiles, is_tiled
from rough_map.types import HeightField

log = logging.getLogger(__name__)

__all__ = ["CLOUD_STEP", "SensorSpec", "save_cloud_npz", "sense_cloud", "simulate"]

CLOUD_STEP = 2e-5
"""Coarsest step in m of a column of a compressed cloud; a wider column stays float32."""


@dataclass(frozen=True)
class SensorSpec:
    """The simulated range sensor.

    Attributes
    ----------
    ahead, half_extent : float
        Centre (m ahead of the vehicle) and half side (m) of the square footprint covered.
    cloud_half_extent : float or None
        Half side in m of the square around ``(ahead, 0)`` in the vehicle frame whose points
        are kept (None: the whole footprint). The default 0.5 m holds the 0.896 m patch and
        52 mm for tilt compensation and levelling, which move points by at most 16 mm on
        the roughest course (ploughed soil, 10 degrees of pitch).
    points_per_cell : float
        Mean points per 8 mm x 8 mm cell.
    noise : float
        Standard deviation of the range noise along z, m.
    imu_noise : float
        Standard deviation of the IMU roll/pitch error, rad.
    """

    ahead: float = 1.0
    half_extent: float = 0.55
    cloud_half_extent: float | None = 0.5
    points_per_cell: float = 12.0
    noise: float = 0.0003
    imu_noise: float = math.radians(0.1)


def save_cloud_npz(path: str | Path, points: np.ndarray) -> Path:
    """Write a cloud as a compressed .npz of 16-bit columns (atomic).

    Each of x, y, z is stored as uint16 steps over its own range (``x``, ``x_scale``,
    ``x_offset``: ``x_offset + x_scale * x`` in m): 15 um or less for the simulator's
    1.0 m square, and a few um in z, far below the 0.3 mm range noise. A column whose step
    would exceed :data:`CLOUD_STEP` (a range over 1.3 m), or that is not finite, is kept
    as float32. The points are sorted along x, which lets deflate pack the x column:
    about 4.5 bytes a point against 12 for float32 .npy.
    :func:`rough_map.io.pointcloud.read_cloud` reads the file.

    Parameters
    ----------
    path : str or Path
        Target ``.npz`` file; its folder must exist.
    points : ndarray, shape (N, 3)
        x, y, z in m.

    Returns
    -------
    Path
        The file written.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or pts.dtype.kind not in "fiu":
        raise InputError(
            f"points must be a non-empty numeric (N, 3) array of x, y, z in m; "
            f"got shape {pts.shape} and dtype {pts.dtype}"
        )
    pts = pts[np.argsort(pts[:, 0], kind="stable")]
    arrays: dict[str, Any] = {}  # uint16 or float32 columns, float64 scale and offset
    for k, c in enumerate("xyz"):
        col = pts[:, k].astype(np.float64)
        lo, hi = float(col.min()), float(col.max())
        step = (hi - lo) / 65535
        if not step <= CLOUD_STEP:  # also NaN or inf
            arrays[c] = col.astype(np.float32)
            continue
        step = step or CLOUD_STEP
        arrays[c] = np.rint((col - lo) / step).astype(np.uint16)
        arrays[f"{c}_scale"] = np.float64(step)
        arrays[f"{c}_offset"] = np.float64(lo)
    path = Path(path)
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


def sense_cloud(
    world: HeightField, pose: np.ndarray, sensor: SensorSpec, rng: np.random.Generator
) -> np.ndarray:
    """Points of the ground around the patch, in the vehicle frame (m), float32.

    ``pose`` is ``(x, y, z, roll, pitch, yaw)`` of the vehicle in the world. The sensor
    samples its footprint; only the points within ``sensor.cloud_half_extent`` of
    ``(sensor.ahead, 0)`` in the vehicle frame are returned. The crop comes after every
    random draw, so the same ``rng`` gives the same points as an uncropped sensor.
    """
    x, y, z, roll, pitch, yaw = pose
    side = 2 * sensor.half_extent
    n = int(sensor.points_per_cell * (side / 0.008) ** 2)
    xv = rng.uniform(sensor.ahead - sensor.half_extent, sensor.ahead + sensor.half_extent, n)
    yv = rng.uniform(-sensor.half_extent, sensor.half_extent, n)
    c, s = math.cos(yaw), math.sin(yaw)
    xw = x + c * xv - s * yv
    yw = y + s * xv + c * yv
    zw = world.sample(xw, yw)
    ok = np.isfinite(zw)
    pw = np.column_stack([xw[ok], yw[ok], zw[ok]])
    rot = rotation_matrix(roll, pitch, yaw)
    pv = (pw - np.array([x, y, z])) @ rot  # R^T (p_w - t) for every row
    pv[:, 2] += rng.normal(0.0, sensor.noise, len(pv))
    if sensor.cloud_half_extent is not None:
        h = sensor.cloud_half_extent
        pv = pv[(np.abs(pv[:, 0] - sensor.ahead) <= h) & (np.abs(pv[:, 1]) <= h)]
    return pv.astype(np.float32)


def simulate(
    out_dir: str | Path,
    course: str = "mixed",
    *,
    length: float | None = None,
    speed: float = 0.5,
    rate: float = 2.0,
    seed: int = 0,
    images: bool = True,
    image_every: int = 1,
    sensor: SensorSpec | None = None,
    world_spacing: float = 0.002,
    width: float = 4.0,
    compress: bool = False,
    progress: bool = False,
    whole_length: float = WHOLE_LENGTH,
    tile_length: float = TILE_LENGTH,
) -> Path:
    """Simulate a traverse of ``course`` and write it to ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        New folder (it must not hold a traverse already).
    course : str
        One of :data:`rough_map.simulate.world.COURSES`.
    length : float, optional
        Course length in m (defaults per course: 36, 36, 42, 22, 120).
    speed : float
        Rover speed in m/s (paper: 0.3-0.7).
    rate : float
        Frame rate in Hz (paper: 2).
    seed : int
        Seed of the world, the drive and the sensors.
    images : bool
        Render stereo pairs (a few seconds a frame).
    image_every : int
        Render the pair of every n-th frame only.
    sensor : SensorSpec, optional
        The range sensor.
    world_spacing : float
        Cell size of the world in m. 2 mm keeps the wavelengths that a mean over an 8 mm
        cell folds back into the band; the renderer gets a 4 mm copy.
    width : float
        Extent of the world across the course in m (the cameras see about 6 m wide at 3 m).
    compress : bool
        Write the clouds as compressed ``.npz`` (:func:`save_cloud_npz`, about 2.6 times
        smaller) instead of float32 ``.npy``.
    progress : bool
        Show a progress bar on stderr.
    whole_length : float
        A course up to this long (m) is built in one piece (:func:`build_world`); a longer
        one tile by tile (:class:`~rough_map.simulate.world_tiles.WorldTiles`), read in windows
        along the drive, and its truth written in tiles
        (:class:`~rough_map.io.truth.TiledWorldWriter`), so that memory does not grow
        with the length.
    tile_length : float
        Length in m of the tiles of a longer course.

    Returns
    -------
    Path
        The ``traverse.json`` written.
    """
    from tqdm import tqdm

    if course not in COURSES:
        raise InputError(f"unknown course {course!r}; expected one of {COURSES}")
    sensor = sensor or SensorSpec()
    _check_crop(sensor.cloud_half_extent)
    segments, defects = course_layout(course, length, seed)
    tiles = None
    if is_tiled(segments, whole_length):  # checks the tiles' arguments before writing
        tiles = WorldTiles(
            segments,
            defects,
            spacing=world_spacing,
            seed=seed,
            width=width,
            tile_length=tile_length,
        )
    out = _new_folder(Path(out_dir))
    rng = np.random.default_rng(seed)
    camera = _Camera(seed, out) if images else None
    every = max(1, int(image_every))
    start, end = segments[0].start, segments[-1].end - sensor.ahead - 0.5

    bar_args = {"desc": f"simulate {course}", "unit": "frame", "disable": not progress}
    if tiles is None:
        world = build_world(segments, defects, spacing=world_spacing, seed=seed, width=width)
        save_world(world, out / TRUTH_FILE)
        poses = drive(world, start, end, speed=speed, rate=rate, seed=seed)
        if camera is not None:
            camera.look_at(world)
        bar = tqdm(total=len(poses), **bar_args)
        frames = []
        for i, pose in enumerate(poses):
            frame = _record_frame(out, i, pose, world, sensor, rng, compress)
            if camera is not None and i % every == 0:
                frame.update(camera.record(i, np.asarray(pose[1:])))
            frames.append(frame)
            bar.update()
    else:
        track = drive_track(start, end, speed=speed, rate=rate, seed=seed)
        bar = tqdm(total=len(track[0]), **bar_args)
        with TiledWorldWriter(
            out / TRUTH_FILE, tiles.shape, world_spacing, tiles.origin, CLASS_NAMES
        ) as writer:
            tiles.sink = writer.append
            frames = _drive_tiles(out, tiles, track, sensor, rng, camera, every, compress, bar)
            tiles.finish()
    bar.close()
    settings = {
        "course": course,
        "seed": seed,
        "speed_m_s": speed,
        "rate_hz": rate,
        "world_spacing_m": world_spacing,
        "sensor": sensor.__dict__,
    }
    calib = camera.calib if camera is not None else None
    spec = _traverse_spec(settings, sensor, calib, segments, defects, frames, compress)
    path = save_traverse(spec, out)
    log.info("wrote %d frames of the %s course to %s", len(frames), course, out)
    return path


#: Frames are simulated in runs along this many m of the drive, each on one window of a
#: tiled world (the window reaches about 7 m further for the cameras).
RUN_LENGTH = 4.0


def _drive_tiles(
    out: Path,
    tiles: WorldTiles,
    track: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    sensor: SensorSpec,
    rng: np.random.Generator,
    camera: _Camera | None,
    every: int,
    compress: bool,
    bar: Any,
) -> list[dict[str, Any]]:
    """The frames of a drive over a tiled world, in runs of :data:`RUN_LENGTH` m: each run
    reads the window of the world its wheels, sensor and cameras see, then releases what
    lies behind. The same random streams as on a world built whole, frame after frame."""
    t, x, y, yaw = track
    rover = RoverGeometry()
    y_reach = float(np.abs(y).max(initial=0.0))
    behind = attitude_reach(rover, tiles.spacing) + 2 * tiles.spacing
    align = _Camera.step(tiles.spacing)
    frames: list[dict[str, Any]] = []
    i = 0
    while i < len(x):
        j = max(i + 1, int(np.searchsorted(x, x[i] + RUN_LENGTH)))
        run = slice(i, j)
        ground = tiles.window(x[i] - behind, x[j - 1] + behind, align=align)
        z, roll, pitch = attitude(ground, x[run], y[run], yaw[run], rover=rover, y_reach=y_reach)
        del ground
        poses = np.column_stack([t[run], x[run], y[run], z, roll, pitch, yaw[run]])
        rendered = {k for k in range(i, j) if camera is not None and k % every == 0}
        lo, hi = _seen(poses[:, 1:], [k - i for k in sorted(rendered)], sensor, camera)
        world = tiles.window(min(lo, x[i] - behind), max(hi, x[j - 1] + behind), align=align)
        if camera is not None:
            camera.look_at(world)
        for k, pose in zip(range(i, j), poses, strict=True):
            frame = _record_frame(out, k, pose, world, sensor, rng, compress)
            if camera is not None and k in rendered:
                frame.update(camera.record(k, np.asarray(pose[1:])))
            frames.append(frame)
            bar.update()
        del world
        if camera is not None:
            camera.view = None
        if j < len(x):
            tiles.release(x[j] - behind - 1.0)
        i = j
    return frames


def _seen(
    poses: np.ndarray, rendered: list[int], sensor: SensorSpec, camera: _Camera | None
) -> tuple[float, float]:
    """World x range (m) that the range sensor of every pose ``(x, y, z, roll, pitch,
    yaw)`` and the cameras of the poses ``rendered`` (indices) see, with a margin."""
    x, yaw = poses[:, 0], poses[:, 5]
    reach = sensor.half_extent * (np.abs(np.cos(yaw)) + np.abs(np.sin(yaw)))
    lo = float(np.min(x + sensor.ahead * np.cos(yaw) - reach))
    hi = float(np.max(x + sensor.ahead * np.cos(yaw) + reach))
    if camera is not None:
        for k in rendered:
            x0, x1, _, _ = view_bounds(poses[k], camera.calib)
            lo, hi = min(lo, x0), max(hi, x1)
    return lo - 0.05, hi + 0.05


def _check_crop(crop: float | None) -> None:
    """Refuse a cloud crop that is not a length; warn of one too small for the patch."""
    if crop is not None and not (isinstance(crop, int | float) and 0 < crop < math.inf):
        raise InputError(f"cloud_half_extent must be a positive length in m or None, got {crop!r}")
    if crop is not None and crop < 0.47:
        log.warning(
            "clouds cropped to %.3f m around the patch centre: the default 0.896 m patch "
            "needs 0.448 m and a margin for tilt compensation",
            crop,
        )


def _new_folder(out: Path) -> Path:
    """``out`` with a ``clouds`` folder, created; refused if it holds a traverse already."""
    try:
        find_traverse_file(out)
    except RoughMapError:
        pass
    else:
        raise InputError(f"{out} already holds a traverse; choose a new --out folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "clouds").mkdir(exist_ok=True)
    return out


def _record_frame(
    out: Path,
    i: int,
    pose: np.ndarray,
    world: HeightField,
    sensor: SensorSpec,
    rng: np.random.Generator,
    compress: bool,
) -> dict[str, Any]:
    """Sense and write frame ``i``'s cloud; its traverse entry (time, pose, cloud, true
    label, IMU attitude with noise). ``pose`` is ``(t, x, y, z, roll, pitch, yaw)``."""
    t, x, y, z, roll, pitch, yaw = (float(v) for v in pose)
    cloud_rel = f"clouds/{i:06d}.{'npz' if compress else 'npy'}"
    cloud = sense_cloud(world, np.array([x, y, z, roll, pitch, yaw]), sensor, rng)
    if compress:
        save_cloud_npz(out / cloud_rel, cloud)
    else:
        with atomic_output(out / cloud_rel) as tmp, open(tmp, "wb") as fh:
            np.save(fh, cloud)
    centre = (x + sensor.ahead * math.cos(yaw), y + sensor.ahead * math.sin(yaw))
    return {
        "t": t,
        "pose": {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw},
        "cloud": cloud_rel,
        "label": _class_at(world, *centre),
        "imu": {
            "roll": roll + rng.normal(0, sensor.imu_noise),
            "pitch": pitch + rng.normal(0, sensor.imu_noise),
        },
    }


class _Camera:
    """The XB3-like stereo rig of the simulated rover, rendering into ``left/``, ``right/``.

    The renderer gets a 4 mm copy of the world (it sees no finer detail at 1280x960)."""

    def __init__(self, seed: int, out: Path) -> None:
        self.calib = StereoCalibration.xb3_default()
        self.textures = TextureSet(seed=seed)
        self.seed = seed
        self.out = out
        self.view: HeightField | None = None
        (out / "left").mkdir(exist_ok=True)
        (out / "right").mkdir(exist_ok=True)

    @staticmethod
    def step(spacing: float) -> int:
        """Every how many cells of a world of ``spacing`` m the renderer's copy keeps."""
        return max(1, int(round(0.004 / spacing)))

    def look_at(self, world: HeightField) -> None:
        """Render ``world`` (or a window of it holding the views) from now on."""
        step = self.step(world.spacing)
        classes = world.classes[::step, ::step] if world.classes is not None else None
        self.view = HeightField(
            world.heights[::step, ::step],
            world.spacing * step,
            world.origin,
            classes,
            world.class_names,
        )

    def record(self, i: int, pose6: np.ndarray) -> dict[str, str]:
        """Render and write frame ``i``'s pair from ``(x, y, z, roll, pitch, yaw)``; the
        traverse entries ``left`` and ``right``."""
        import cv2

        assert self.view is not None, "look_at a world first"
        left, right, _ = render_stereo(
            self.view, pose6, self.calib, self.textures, seed=self.seed * 100003 + i, color=True
        )
        written = {}
        for side, img in (("left", left), ("right", right)):
            rel = f"{side}/{i:06d}.png"
            with atomic_output(self.out / rel) as tmp:
                if not cv2.imwrite(str(tmp), img):
                    raise InputError(f"could not write {self.out / rel}")
            written[side] = rel
        return written


def _traverse_spec(
    settings: dict[str, Any],
    sensor: SensorSpec,
    calib: StereoCalibration | None,
    segments: list[Segment],
    defects: list[Defect],
    frames: list[dict[str, Any]],
    compress: bool,
) -> TraverseSpec:
    """The traverse document of a simulated run (validated)."""
    metadata = {
        "simulator": settings,
        "cloud_extent": _cloud_extent(sensor),
        "cloud_storage": (
            {"format": "npz", "dtype": "uint16", "max_step_m": CLOUD_STEP}
            if compress
            else {"format": "npy", "dtype": "float32"}
        ),
        "segments": [s.__dict__ for s in segments],
        "defects": [d.__dict__ for d in defects],
    }
    json.dumps(metadata)  # the metadata must stay JSON
    return TraverseSpec.model_validate(
        {
            "schema_version": "1.0",
            "name": f"sim-{settings['course']}-seed{settings['seed']}",
            "crs": {"code": "local", "origin": {"lat": 40.3515, "lon": 18.1750, "alt": 50.0}},
            "calibration": calib.model_dump() if calib is not None else None,
            "height_field": TRUTH_FILE,
            "metadata": metadata,
            "frames": frames,
        }
    )


def _cloud_extent(sensor: SensorSpec) -> dict[str, Any]:
    """Where the points of the clouds lie (the crop), for ``metadata.cloud_extent``."""
    crop = sensor.cloud_half_extent
    full = crop is None or crop >= sensor.half_extent
    h = sensor.half_extent if crop is None or full else crop
    return {
        "frame": "vehicle",
        "x_m": [round(sensor.ahead - h, 6), round(sensor.ahead + h, 6)],
        "y_m": [round(-h, 6), round(h, 6)],
        "cropped": not full,
        "description": (
            "the sensor's whole footprint (a square level in the world, so about this "
            "in the vehicle frame)"
            if full
            else f"the points of the sensor's {2 * sensor.half_extent:g} m footprint within "
            f"{h:g} m of the patch centre ({sensor.ahead:g} m ahead), in the vehicle frame"
        ),
    }


def _class_at(world: HeightField, x: float, y: float) -> str | None:
    """Class name of the world cell nearest to (x, y) m; None without a class map."""
    if world.classes is None:
        return None
    j = int(round((x - world.origin[0]) / world.spacing))
    i = int(round((y - world.origin[1]) / world.spacing))
    j = min(max(j, 0), world.heights.shape[1] - 1)
    i = min(max(i, 0), world.heights.shape[0] - 1)
    return world.class_names[int(world.classes[i, j])]
