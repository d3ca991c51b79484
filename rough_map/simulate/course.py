"""Simulate a traverse: world, drive, sensors, and a traverse folder that validates.

Each frame gets

* ``clouds/NNNNNN.npy``: what a dense range sensor (depth camera, close-range lidar) sees
  of the ground around the patch of interest, in the vehicle frame, float32, with Gaussian
  noise along z;
* optionally ``left/NNNNNN.png`` and ``right/NNNNNN.png``: the rectified stereo pair of an
  XB3-like rig, rendered by ray casting (:func:`rough_map.simulate.render.render_stereo`);
* the true ``label`` (class under the patch centre) and the IMU roll and pitch.

The true world is saved as ``world_truth.npz`` (heights, class map, spacing, origin).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rough_map.errors import InputError
from rough_map.simulate.world import (
    COURSES,
    build_world,
    course_layout,
    drive,
)
from rough_map.types import HeightField

log = logging.getLogger(__name__)

TRUTH_FILE = "world_truth.npz"


@dataclass(frozen=True)
class SensorSpec:
    """The simulated range sensor.

    Attributes
    ----------
    ahead, half_extent : float
        Centre (m ahead of the vehicle) and half side (m) of the square footprint covered.
    points_per_cell : float
        Mean points per 8 mm x 8 mm cell.
    noise : float
        Standard deviation of the range noise along z, m.
    imu_noise : float
        Standard deviation of the IMU roll/pitch error, rad.
    """

    ahead: float = 1.0
    half_extent: float = 0.55
    points_per_cell: float = 12.0
    noise: float = 0.0003
    imu_noise: float = math.radians(0.1)


def save_world(world: HeightField, path: Path) -> None:
    """Write a world as .npz (atomic).

    Uncompressed: float heights at 2 mm hardly compress (by 10 %) and deflating them took
    longer than simulating the clouds.
    """
    from rough_map.io.pointcloud import atomic_output

    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            heights=world.heights.astype(np.float32),
            classes=(world.classes if world.classes is not None else np.zeros(0)).astype(np.int8),
            spacing=world.spacing,
            origin=np.asarray(world.origin),
            class_names=np.asarray(world.class_names),
        )


def load_world(path: str | Path) -> HeightField:
    """Read a world written by :func:`save_world`."""
    from rough_map.errors import FileFormatError

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as d:
            return HeightField(
                d["heights"].astype(float),
                float(d["spacing"]),
                tuple(float(v) for v in d["origin"]),
                d["classes"].astype(int) if d["classes"].size else None,
                tuple(str(c) for c in d["class_names"]),
            )
    except (OSError, ValueError, KeyError) as exc:
        raise FileFormatError(path, f"not a rough_map world file: {exc}") from None


def sense_cloud(
    world: HeightField, pose: np.ndarray, sensor: SensorSpec, rng: np.random.Generator
) -> np.ndarray:
    """Points of the ground around the patch, in the vehicle frame (m), float32.

    ``pose`` is ``(x, y, z, roll, pitch, yaw)`` of the vehicle in the world.
    """
    from rough_map.patch import rotation_matrix

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
    progress: bool = False,
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
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    Path
        The ``traverse.json`` written.
    """
    import cv2
    from tqdm import tqdm

    from rough_map.config import TraverseSpec
    from rough_map.io.pointcloud import atomic_output
    from rough_map.io.traverse import find_traverse_file, save_traverse

    if course not in COURSES:
        raise InputError(f"unknown course {course!r}; expected one of {COURSES}")
    sensor = sensor or SensorSpec()
    out = Path(out_dir)
    try:
        find_traverse_file(out)
    except Exception:
        pass
    else:
        raise InputError(f"{out} already holds a traverse; choose a new --out folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "clouds").mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    segments, defects = course_layout(course, length, seed)
    world = build_world(segments, defects, spacing=world_spacing, seed=seed, width=width)
    save_world(world, out / TRUTH_FILE)
    poses = drive(
        world,
        segments[0].start,
        segments[-1].end - sensor.ahead - 0.5,
        speed=speed,
        rate=rate,
        seed=seed,
    )
    calib = None
    if images:
        from rough_map.io.stereo import StereoCalibration
        from rough_map.simulate.render import render_stereo
        from rough_map.simulate.textures import TextureSet

        calib = StereoCalibration.xb3_default()
        textures = TextureSet(seed=seed)
        step = max(1, int(round(0.004 / world_spacing)))
        view = HeightField(
            world.heights[::step, ::step],
            world.spacing * step,
            world.origin,
            world.classes[::step, ::step],
            world.class_names,
        )
        (out / "left").mkdir(exist_ok=True)
        (out / "right").mkdir(exist_ok=True)
    frames = []
    bar = tqdm(total=len(poses), desc=f"simulate {course}", unit="frame", disable=not progress)
    for i, (t, x, y, z, roll, pitch, yaw) in enumerate(poses):
        pose6 = np.array([x, y, z, roll, pitch, yaw])
        cloud_rel = f"clouds/{i:06d}.npy"
        with atomic_output(out / cloud_rel) as tmp:
            np.save(tmp, sense_cloud(world, pose6, sensor, rng))
        centre = (x + sensor.ahead * math.cos(yaw), y + sensor.ahead * math.sin(yaw))
        label = _class_at(world, *centre)
        frame = {
            "t": float(t),
            "pose": {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw},
            "cloud": cloud_rel,
            "label": label,
            "imu": {
                "roll": roll + rng.normal(0, sensor.imu_noise),
                "pitch": pitch + rng.normal(0, sensor.imu_noise),
            },
        }
        if images and i % max(1, int(image_every)) == 0:
            left, right, _ = render_stereo(
                view, pose6, calib, textures, seed=seed * 100003 + i, color=True
            )
            for side, img in (("left", left), ("right", right)):
                rel = f"{side}/{i:06d}.png"
                with atomic_output(out / rel) as tmp:
                    if not cv2.imwrite(str(tmp), img):
                        raise InputError(f"could not write {out / rel}")
                frame[side] = rel
        frames.append(frame)
        bar.update()
    bar.close()
    spec = TraverseSpec.model_validate(
        {
            "schema_version": "1.0",
            "name": f"sim-{course}-seed{seed}",
            "crs": {"code": "local", "origin": {"lat": 40.3515, "lon": 18.1750, "alt": 50.0}},
            "calibration": calib.model_dump() if calib is not None else None,
            "height_field": TRUTH_FILE,
            "metadata": {
                "simulator": {
                    "course": course,
                    "seed": seed,
                    "speed_m_s": speed,
                    "rate_hz": rate,
                    "world_spacing_m": world_spacing,
                    "sensor": sensor.__dict__,
                },
                "segments": [s.__dict__ for s in segments],
                "defects": [d.__dict__ for d in defects],
            },
            "frames": frames,
        }
    )
    path = save_traverse(spec, out)
    log.info("wrote %d frames of the %s course to %s", len(frames), course, out)
    json.dumps(spec.metadata)  # the metadata must stay JSON
    return path


def _class_at(world: HeightField, x: float, y: float) -> str:
    j = int(round((x - world.origin[0]) / world.spacing))
    i = int(round((y - world.origin[1]) / world.spacing))
    j = min(max(j, 0), world.heights.shape[1] - 1)
    i = min(max(i, 0), world.heights.shape[0] - 1)
    return world.class_names[int(world.classes[i, j])]
