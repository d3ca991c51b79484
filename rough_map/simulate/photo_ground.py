"""Flat worlds textured with real ground photographs, seen by the rover's left camera.

The simulator's own textures (:mod:`rough_map.simulate.textures`) are noise the project
made; near-to-far must also work on ground nobody here made. scikit-image ships CC0
photographs of ground (:func:`skimage.data.brick`, ``gravel``, ``grass`` and the moon's
surface, ``moon``; grey, 512 x 512 px). :func:`photo_world` lays them out as a class map
(segments along the path and patches beside it), and :func:`render_photo_ground` renders
what the left camera sees of that flat world from a pose: every pixel's ray meets the
ground plane (:func:`rough_map.geometry.pixel_to_ground`), the photo of the class there is
sampled at ``texel`` m per photo pixel (tiled), from a mip-map level that matches the
pixel's footprint on the ground (no aliasing far away), tinted per class (``color``) or
left grey, and sensor noise is added.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rough_map.config import StereoCalibration, TraverseSpec
from rough_map.geometry import pixel_to_ground, pose_matrix
from rough_map.io.traverse import Traverse, save_traverse
from rough_map.types import HeightField

__all__ = [
    "PHOTOS",
    "TINTS",
    "PhotoGround",
    "drive_straight",
    "photo_world",
    "render_photo_ground",
    "true_near_labels",
    "write_photo_traverse",
]

#: The scikit-image ground photographs used as classes.
PHOTOS: tuple[str, ...] = ("brick", "gravel", "grass", "moon")

#: Colour (B, G, R in [0, 1]) the grey photo of each class is tinted with for colour worlds.
TINTS: dict[str, tuple[float, float, float]] = {
    "brick": (0.42, 0.50, 0.85),
    "gravel": (0.66, 0.64, 0.62),
    "grass": (0.30, 0.70, 0.42),
    "moon": (0.48, 0.66, 0.80),
}


@cache
def _pyramid(name: str, levels: int = 7) -> tuple[NDArray[np.float32], ...]:
    import cv2
    import skimage.data

    image = np.asarray(getattr(skimage.data, name)(), dtype=np.float32) / np.float32(255.0)
    out: list[NDArray[np.float32]] = [image]
    for _ in range(levels - 1):
        out.append(np.asarray(cv2.pyrDown(out[-1], borderType=cv2.BORDER_WRAP), np.float32))
    return tuple(out)


@dataclass(frozen=True)
class PhotoGround:
    """How the classes of a photo world look.

    Attributes
    ----------
    names : tuple of str
        Class names, each the name of a :data:`PHOTOS` photograph.
    texel : float
        Ground size of one photo pixel, m (the photo repeats every ``512 * texel`` m).
    color : bool
        Tint each class (:data:`TINTS`); False leaves the photos grey, where the looks of
        the classes overlap.
    noise : float
        Standard deviation of the sensor noise, grey levels (8 bit).
    """

    names: tuple[str, ...] = PHOTOS
    texel: float = 0.002
    color: bool = True
    noise: float = 2.0
    tints: dict[str, tuple[float, float, float]] = field(default_factory=lambda: dict(TINTS))


def photo_world(
    order: tuple[int, ...],
    *,
    segment: float = 3.0,
    width: float = 5.0,
    spacing: float = 0.02,
    n_patches: int = 6,
    seed: int = 0,
    names: tuple[str, ...] = PHOTOS,
) -> HeightField:
    """A flat world: path segments of the classes ``order`` (indices into ``names``),
    ``segment`` m each from x = 0, on a strip ``width`` m wide centred on y = 0, with
    ``n_patches`` rectangles of random classes beside the path (|y| > 0.8 m).

    Returns
    -------
    HeightField
        Heights 0, ``classes`` and ``class_names``; origin (-1, -width / 2) m.
    """
    rng = np.random.default_rng(seed)
    length = segment * len(order) + 1.0
    nx, ny = round((length + 1.0) / spacing), round(width / spacing)
    origin = (-1.0, -width / 2)
    x = origin[0] + spacing * np.arange(nx)
    y = origin[1] + spacing * np.arange(ny)
    seg = np.clip(np.floor(x / segment).astype(int), 0, len(order) - 1)
    classes = np.broadcast_to(np.asarray(order)[seg][None, :], (ny, nx)).copy()
    for _ in range(n_patches):
        cx, w, h = rng.uniform(0.0, length), rng.uniform(1.0, 3.0), rng.uniform(0.6, 1.5)
        side = rng.choice([-1.0, 1.0])
        y0 = side * 0.8 if side > 0 else -0.8 - h
        rows = (y >= y0) & (y <= y0 + h)
        cols = np.abs(x - cx) <= w / 2
        classes[np.ix_(rows, cols)] = int(rng.integers(len(names)))
    return HeightField(
        np.zeros((ny, nx)), spacing, origin=origin, classes=classes, class_names=tuple(names)
    )


def drive_straight(
    length: float, step: float = 0.25, *, wiggle: float = 0.04, seed: int = 0
) -> NDArray[np.float64]:
    """Poses ``(x, y, z, roll, pitch, yaw)`` every ``step`` m along y = 0 from x = -0.5 m,
    the heading wobbling by up to ``wiggle`` rad."""
    rng = np.random.default_rng(seed)
    x = np.arange(-0.5, length, step)
    phase = rng.uniform(0, 2 * math.pi)
    yaw = wiggle * np.sin(x / 1.7 + phase)
    zeros = np.zeros_like(x)
    return np.column_stack([x, zeros, zeros, zeros, zeros, yaw])


def render_photo_ground(
    world: HeightField,
    pose: NDArray[np.float64] | tuple[float, ...],
    calib: StereoCalibration,
    ground: PhotoGround,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """The left image (8-bit BGR) of the flat photo world from ``pose`` (see the module
    notes); sky and ground outside the world are black."""
    import cv2

    assert world.classes is not None
    h, w = calib.height, calib.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    g = pixel_to_ground(calib, u, v)  # (h, w, 3) in the vehicle frame
    transform = pose_matrix(np.asarray(pose, dtype=float))
    world_xy = g @ transform[:3, :3].T + transform[:3, 3]
    wx, wy = world_xy[..., 0], world_xy[..., 1]
    # Pixel footprint on the ground, m: the larger step to the next pixel down or across.
    with np.errstate(invalid="ignore"):
        dv = np.linalg.norm(np.diff(g, axis=0, append=g[-1:] * np.nan), axis=-1)
        du = np.linalg.norm(np.diff(g, axis=1, append=g[:, -1:] * np.nan), axis=-1)
        foot = np.fmax(np.nan_to_num(dv, nan=np.inf), np.nan_to_num(du, nan=np.inf))
    ok = np.isfinite(wx) & np.isfinite(foot)
    col = np.rint((wx - world.origin[0]) / world.spacing)
    row = np.rint((wy - world.origin[1]) / world.spacing)
    ny, nx = world.shape
    ok &= (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    cls = np.full((h, w), -1)
    cls[ok] = world.classes[row[ok].astype(int), col[ok].astype(int)]
    out = np.zeros((h, w, 3), dtype=np.float32)
    level = np.clip(np.floor(np.log2(np.maximum(foot / ground.texel, 1.0))), 0, 6)
    for c, name in enumerate(world.class_names):
        photo_name = ground.names[c] if c < len(ground.names) else name
        pyramid = _pyramid(photo_name)
        mean = float(pyramid[0].mean())
        for lv in np.unique(level[cls == c]).astype(int):
            sel = (cls == c) & (level == lv)
            scale = ground.texel * 2.0**lv
            mx = (wx[sel] / scale).astype(np.float32).reshape(1, -1)
            my = (wy[sel] / scale).astype(np.float32).reshape(1, -1)
            img = pyramid[lv]
            mx = np.mod(mx, img.shape[1])
            my = np.mod(my, img.shape[0])
            val = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)[0]
            grey = val / mean * 0.45
            if ground.color:
                tint = np.asarray(ground.tints[photo_name], dtype=np.float32)
                out[sel] = grey[:, None] * tint[None, :] * 1.2
            else:
                out[sel] = grey[:, None]
    rng = np.random.default_rng(seed)
    image = out * 255.0 + rng.normal(0.0, ground.noise, out.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def true_near_labels(
    world: HeightField, poses: NDArray[np.float64], ahead: float = 1.0
) -> list[str | None]:
    """The class of the world under the point ``ahead`` m in front of each pose (the
    centre of the near-field patch): the labels a perfect geometric classifier gives."""
    assert world.classes is not None
    out: list[str | None] = []
    for x, y, _, _, _, yaw in poses:
        px, py = x + ahead * math.cos(yaw), y + ahead * math.sin(yaw)
        col = round((px - world.origin[0]) / world.spacing)
        row = round((py - world.origin[1]) / world.spacing)
        inside = 0 <= row < world.shape[0] and 0 <= col < world.shape[1]
        c = int(world.classes[row, col]) if inside else -1
        out.append(world.class_names[c] if c >= 0 else None)
    return out


def write_photo_traverse(
    out: str | Path,
    world: HeightField,
    poses: NDArray[np.float64],
    calib: StereoCalibration,
    ground: PhotoGround,
    labels: list[str | None] | None = None,
) -> Traverse:
    """Render the left image of every pose into ``out/left`` (and a copy of it into
    ``out/right``: this is no stereo pair) and write a traverse
    (``traverse.yaml``) with the ``labels`` (default :func:`true_near_labels`), frames
    1 s apart; returns it loaded."""
    import cv2

    folder = Path(out)
    (folder / "left").mkdir(parents=True, exist_ok=True)
    (folder / "right").mkdir(parents=True, exist_ok=True)
    labels = true_near_labels(world, poses) if labels is None else labels
    frames = []
    for i, (pose, label) in enumerate(zip(poses, labels, strict=True)):
        image = render_photo_ground(world, pose, calib, ground, seed=i)
        cv2.imwrite(str(folder / f"left/{i:03d}.png"), image)
        # a traverse's frames carry both images; near-to-far only reads the left one
        cv2.imwrite(str(folder / f"right/{i:03d}.png"), image)
        x, y, z, roll, pitch, yaw = (float(v) for v in pose)
        frame = {
            "t": float(i),
            "pose": {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw},
            "left": f"left/{i:03d}.png",
            "right": f"right/{i:03d}.png",
        }
        if label is not None:
            frame["label"] = label
        frames.append(frame)
    spec = TraverseSpec.model_validate(
        {"schema_version": "1.0", "name": folder.name, "calibration": calib.model_dump(),
         "frames": frames}
    )  # fmt: skip
    save_traverse(spec, folder)
    return Traverse.from_spec(spec, folder)
