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
(:func:`save_world`, :func:`load_world`).
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

HEIGHT_STEP = 1e-5
"""Coarsest step in m of the stored true heights; a wider relief is stored as float32."""

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


def save_world(world: HeightField, path: Path) -> None:
    """Write a world as .npz (atomic).

    The heights are int16 steps of ``(max - min) / 65534``, at most :data:`HEIGHT_STEP`
    (10 um; 6 um on a random course), with ``height_scale`` and ``height_offset`` in m:
    half the bytes of float32, and far below the 2 mm cells' roughness. A relief over
    0.65 m is stored as float32. The heights are not deflated (at 2 mm they hardly
    compress, by 10 %, and deflating them took longer than simulating the clouds); the
    class map is, to almost nothing.
    """
    heights = world.heights
    lo, hi = float(heights.min()), float(heights.max())  # NaN if any height is NaN
    step = (hi - lo) / 65534
    members: dict[str, tuple[np.ndarray, bool]] = {}
    if step <= HEIGHT_STEP:  # False for NaN or inf
        step = step or HEIGHT_STEP
        q = np.empty(heights.shape, dtype=np.int16)
        rows = max(1, 2**21 // max(1, heights.shape[1]))  # row blocks: small temporaries
        for r in range(0, heights.shape[0], rows):
            q[r : r + rows] = np.rint((heights[r : r + rows] - lo) / step) - 32767
        members["heights"] = (q, False)
        members["height_scale"] = (np.float64(step), False)
        members["height_offset"] = (np.float64(lo + 32767 * step), False)
    else:
        log.info("world relief %.3f m: true heights stored as float32", hi - lo)
        members["heights"] = (heights.astype(np.float32), False)
    classes = world.classes if world.classes is not None else np.zeros(0)
    members["classes"] = (classes.astype(np.int8), True)
    members["spacing"] = (np.float64(world.spacing), False)
    members["origin"] = (np.asarray(world.origin, dtype=np.float64), False)
    members["class_names"] = (np.asarray(world.class_names), False)
    _write_npz(path, members)


def _write_npz(path: Path, members: dict[str, tuple[np.ndarray, bool]]) -> None:
    """An .npz archive (atomic) with each member deflated or stored as asked."""
    import zipfile

    from rough_map._files import atomic_output

    with atomic_output(path) as tmp, zipfile.ZipFile(tmp, "w", allowZip64=True) as zf:
        for name, (array, deflate) in members.items():
            info = zipfile.ZipInfo(f"{name}.npy")
            info.compress_type = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)


def load_world(path: str | Path) -> HeightField:
    """Read a world written by :func:`save_world` (float heights of older files too)."""
    import zipfile

    from rough_map.errors import FileFormatError

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as d:
            heights = d["heights"].astype(np.float64)
            if "height_scale" in d.files:
                heights *= float(d["height_scale"])
                heights += float(d["height_offset"])
            return HeightField(
                heights,
                float(d["spacing"]),
                tuple(float(v) for v in d["origin"]),
                d["classes"].astype(int) if d["classes"].size else None,
                tuple(str(c) for c in d["class_names"]),
            )
    except (OSError, ValueError, KeyError, AttributeError, zipfile.BadZipFile) as exc:
        raise FileFormatError(path, f"not a rough_map world file: {exc}") from None


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
    from rough_map._files import atomic_output

    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or pts.dtype.kind not in "fiu":
        raise InputError(
            f"points must be a non-empty numeric (N, 3) array of x, y, z in m; "
            f"got shape {pts.shape} and dtype {pts.dtype}"
        )
    pts = pts[np.argsort(pts[:, 0], kind="stable")]
    arrays: dict[str, np.ndarray] = {}
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
    from rough_map.geometry import rotation_matrix

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

    Returns
    -------
    Path
        The ``traverse.json`` written.
    """
    import cv2
    from tqdm import tqdm

    from rough_map._files import atomic_output
    from rough_map.config import TraverseSpec
    from rough_map.io.traverse import find_traverse_file, save_traverse

    if course not in COURSES:
        raise InputError(f"unknown course {course!r}; expected one of {COURSES}")
    sensor = sensor or SensorSpec()
    crop = sensor.cloud_half_extent
    if crop is not None and not (isinstance(crop, int | float) and 0 < crop < math.inf):
        raise InputError(f"cloud_half_extent must be a positive length in m or None, got {crop!r}")
    if crop is not None and crop < 0.47:
        log.warning(
            "clouds cropped to %.3f m around the patch centre: the default 0.896 m patch "
            "needs 0.448 m and a margin for tilt compensation",
            crop,
        )
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
        from rough_map.config import StereoCalibration
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
        cloud_rel = f"clouds/{i:06d}.{'npz' if compress else 'npy'}"
        cloud = sense_cloud(world, pose6, sensor, rng)
        if compress:
            save_cloud_npz(out / cloud_rel, cloud)
        else:
            with atomic_output(out / cloud_rel) as tmp, open(tmp, "wb") as fh:
                np.save(fh, cloud)
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
                "cloud_extent": _cloud_extent(sensor),
                "cloud_storage": (
                    {"format": "npz", "dtype": "uint16", "max_step_m": CLOUD_STEP}
                    if compress
                    else {"format": "npy", "dtype": "float32"}
                ),
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


def _cloud_extent(sensor: SensorSpec) -> dict:
    """Where the points of the clouds lie (the crop), for ``metadata.cloud_extent``."""
    full = sensor.cloud_half_extent is None or sensor.cloud_half_extent >= sensor.half_extent
    h = sensor.half_extent if full else sensor.cloud_half_extent
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


def _class_at(world: HeightField, x: float, y: float) -> str:
    j = int(round((x - world.origin[0]) / world.spacing))
    i = int(round((y - world.origin[1]) / world.spacing))
    j = min(max(j, 0), world.heights.shape[1] - 1)
    i = min(max(i, 0), world.heights.shape[0] - 1)
    return world.class_names[int(world.classes[i, j])]
