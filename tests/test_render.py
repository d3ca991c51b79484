"""The stereo renderer: true depth, consistency of the two views, textures, and the stereo
pipeline's accuracy on rendered ground.

Measured when these tests were written (XB3-like rig, default StereoConfig: patch path,
ground prior, row_step 1; 4 mm world):

* tilted textured plane (z = 0.01 + 0.05 x + 0.02 y), |dz| of the points over the patch,
  per class: median 0.82-0.93 mm, 95th percentile 1.9-2.2 mm, mean +0.2 to +0.4 mm;
* rough ground (FFT-filtered white noise, rms 5 mm, 3 cm correlation): height error median
  0.9 mm, 95th percentile 2.8 mm, correlation with the truth 0.96; depth of the left pixels
  of the patch window: all valid, median |dZ| 1.3 mm, 95th percentile 5.2 mm;
* gravel (terrain.generate, seed 0), patch estimates from the stereo cloud vs the true
  heights at the same points: rms 4.62 vs 4.59 mm, w -2.68 vs -2.84, R 0.64 x the truth.

The thresholds below leave about 50 % headroom.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rough_map import terrain
from rough_map.config import Pose
from rough_map.errors import InputError
from rough_map.patch import DEFAULT_SPACING, grid_points
from rough_map.psd import patch_roughness
from rough_map.simulate.render import render_stereo
from rough_map.simulate.textures import DEFAULT_TEXTURES, TextureSet, value_noise
from rough_map.stereo import (
    StereoCalibration,
    compute_disparity,
    patch_window,
    stereo_to_cloud,
)
from rough_map.types import HeightField

CLASSES = tuple(DEFAULT_TEXTURES)
SPACING = 0.004


@pytest.fixture(scope="module")
def calib() -> StereoCalibration:
    return StereoCalibration.xb3_default()


@pytest.fixture(scope="module")
def window(calib):
    return patch_window(calib)


def world(heights: np.ndarray, cls: int | np.ndarray = 3) -> HeightField:
    classes = np.broadcast_to(np.asarray(cls), heights.shape).astype(int)
    return HeightField(heights, SPACING, origin=(-0.5, -1.5), classes=classes, class_names=CLASSES)


def rough_heights(shape=(750, 1000), rms=0.005, corr=0.03, seed=1) -> np.ndarray:
    """White noise low-passed by a Gaussian of correlation length ``corr`` m, scaled to rms."""
    rng = np.random.default_rng(seed)
    ky = np.fft.fftfreq(shape[0], SPACING)[:, None]
    kx = np.fft.rfftfreq(shape[1], SPACING)[None, :]
    gain = np.exp(-((np.pi * corr * np.hypot(kx, ky)) ** 2) / 2)
    h = np.fft.irfft2(np.fft.rfft2(rng.standard_normal(shape)) * gain, shape)
    return h * (rms / h.std())


def stripes(shape=(750, 1000)) -> np.ndarray:
    """One class per 0.18 m stripe along x, across the patch (|y| <= 0.45 m)."""
    y = -1.5 + SPACING * np.arange(shape[0])
    cls = np.clip(np.floor((y + 0.45) / 0.18), 0, len(CLASSES) - 1).astype(int)
    return np.broadcast_to(cls[:, None], shape)


#: A tilted plane z = P0 + PX x + PY y (m): flat, textured, and not the vehicle's z = 0
#: (on which the ground prior would make the residual exactly zero everywhere).
P0, PX, PY = 0.01, 0.05, 0.02


def plane_z(x, y):
    return P0 + PX * x + PY * y


@pytest.fixture(scope="module")
def flat(calib, window):
    """The tilted plane with every class in view, rendered once."""
    x = -0.5 + SPACING * np.arange(1000)
    y = -1.5 + SPACING * np.arange(750)
    heights = plane_z(x[None, :], y[:, None])
    return render_stereo(world(heights, stripes()), (0, 0, 0, 0, 0, 0), calib, rows=window.rows)


@pytest.fixture(scope="module")
def flat_cloud(calib, flat):
    return stereo_to_cloud(flat[0], flat[1], calib)


@pytest.fixture(scope="module")
def rough(calib, window):
    hf = world(rough_heights())
    return hf, render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, rows=window.rows)


def plane_depth(calib: StereoCalibration) -> np.ndarray:
    """Closed-form depth Z of every left pixel on the plane z = P0 + PX x + PY y."""
    v, u = np.mgrid[0 : calib.height, 0 : calib.width].astype(float)
    rays = (
        np.stack([(u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy, np.ones_like(u)], axis=-1)
        @ calib.T_vehicle_camera[:3, :3].T
    )  # vehicle-frame rays of unit depth
    t = calib.T_vehicle_camera[:3, 3]
    # t_z + Z r_z = P0 + PX (t_x + Z r_x) + PY (t_y + Z r_y)
    denom = rays[..., 2] - PX * rays[..., 0] - PY * rays[..., 1]
    with np.errstate(divide="ignore"):
        depth = (P0 + PX * t[0] + PY * t[1] - t[2]) / denom
    return np.where(depth > 0, depth, np.nan)


def test_depth_is_exact_on_a_plane(calib, flat, window):
    _, _, depth = flat
    (r0, r1), (c0, c1) = window.rows, window.cols
    truth = plane_depth(calib)
    # float32 ray casting; the world (4 m x 3 m) covers the patch's window.
    np.testing.assert_allclose(depth[r0:r1, c0:c1], truth[r0:r1, c0:c1], atol=2e-5)
    seen = np.isfinite(depth[r0:r1])
    np.testing.assert_allclose(depth[r0:r1][seen], truth[r0:r1][seen], atol=2e-5)
    assert np.isnan(depth[:r0]).all() and np.isnan(depth[r1:]).all()


def test_views_are_consistent(calib, flat, window):
    """Warping the right image by the true disparity reproduces the left one best at zero
    offset: the texture is a function of the world, not of the view."""
    left, right, depth = flat
    r0, r1 = window.rows
    c0, c1 = window.cols
    disparity = calib.focal_baseline / depth
    v, u = np.mgrid[0 : calib.height, 0 : calib.width].astype(np.float32)
    errors = []
    for offset in (-0.5, 0.0, 0.5):
        map_x = np.nan_to_num(u - disparity + offset, nan=-1.0).astype(np.float32)
        warped = cv2.remap(right.astype(np.float32), map_x, v, cv2.INTER_CUBIC)
        diff = left[r0:r1, c0:c1].astype(np.float32) - warped[r0:r1, c0:c1]
        errors.append(float(np.mean(diff**2)))
    assert errors[1] < 0.7 * min(errors[0], errors[2])
    assert errors[1] < 4.0  # DN^2: sensor noise (1 DN per view) and quantisation


@pytest.mark.parametrize("cls", range(len(CLASSES)))
def test_plane_is_reconstructed(flat_cloud, cls):
    y0 = -0.45 + 0.18 * cls
    pts = flat_cloud[(flat_cloud[:, 1] > y0 + 0.01) & (flat_cloud[:, 1] < y0 + 0.17)]
    dz = pts[:, 2] - plane_z(pts[:, 0], pts[:, 1])
    assert len(dz) > 20_000
    assert np.median(np.abs(dz)) < 0.0015
    assert np.percentile(np.abs(dz), 95) < 0.0035
    assert abs(np.mean(dz)) < 0.001


def test_rough_ground_heights(calib, rough):
    hf, (left, right, _) = rough
    pts = stereo_to_cloud(left, right, calib)
    inside = (np.abs(pts[:, 0] - 1.0) < 0.448) & (np.abs(pts[:, 1]) < 0.448)
    pts = pts[inside]
    truth = hf.sample(pts[:, 0], pts[:, 1])
    dz = pts[:, 2] - truth
    assert np.median(np.abs(dz)) < 0.0015
    assert np.percentile(np.abs(dz), 95) < 0.0045
    # The relief is resolved, not just the mean plane.
    assert np.corrcoef(pts[:, 2], truth)[0, 1] > 0.93


def test_rough_ground_depth(calib, rough, window):
    _, (left, right, depth) = rough
    r0, r1 = window.rows
    c0, c1 = window.cols
    disp = compute_disparity(
        left,
        right,
        rows=window.rows,
        cols=window.cols,
        disparities=window.residual,
        prior=window.prior,
    )
    z = calib.focal_baseline / disp[:, c0:c1]
    err = (z - depth[r0:r1, c0:c1])[np.isfinite(z)]
    assert np.isfinite(z).mean() > 0.9
    assert np.median(np.abs(err)) < 0.002
    assert np.percentile(np.abs(err), 95) < 0.008


def test_roughness_parameters_survive_stereo(calib, window):
    """The PSD estimator sees about the same R, w and rms in the stereo cloud as in the true
    heights at the same points (gravel, seeded): what the stereo path is for."""
    hf = world(terrain.generate("gravel", (750, 1000), SPACING, seed=0), CLASSES.index("gravel"))
    left, right, _ = render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, rows=window.rows)
    pts = stereo_to_cloud(left, right, calib)
    truth = pts.copy()
    truth[:, 2] = hf.sample(pts[:, 0], pts[:, 1])
    est = patch_roughness(grid_points(pts).heights, DEFAULT_SPACING)
    ref = patch_roughness(grid_points(truth).heights, DEFAULT_SPACING)
    assert est.rms == pytest.approx(ref.rms, rel=0.1)
    assert abs(est.w - ref.w) < 0.35
    assert 1 / 3 < est.R / ref.R < 3


def test_seed_is_sensor_noise_only(calib):
    hf = world(np.zeros((750, 1000)))
    rows = (400, 440)
    a = render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, seed=0, rows=rows)
    b = render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, seed=0, rows=rows)
    c = render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, seed=1, rows=rows)
    np.testing.assert_array_equal(a[0], b[0])
    diff = a[0][400:440].astype(float) - c[0][400:440]
    assert 0.5 < diff.std() < 3.0  # two independent draws of 1 DN noise, not a new texture
    np.testing.assert_array_equal(a[2], c[2])


def test_pose_forms_agree_and_color(calib):
    hf = world(np.zeros((750, 1000)), np.arange(750)[:, None] * 5 // 750)
    rows = (500, 520)
    pose = (0.1, 0.05, 0.0, 0.0, 0.0, 0.02)
    a = render_stereo(hf, pose, calib, rows=rows, noise_sigma=0)
    b = render_stereo(hf, Pose(x=0.1, y=0.05, yaw=0.02), calib, rows=rows, noise_sigma=0)
    np.testing.assert_array_equal(a[0], b[0])
    left, _, _ = render_stereo(hf, pose, calib, rows=rows, noise_sigma=0, color=True)
    assert left.shape == (calib.height, calib.width, 3) and left.dtype == np.uint8
    gray = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)[500:520].astype(float)
    assert np.abs(gray - a[0][500:520]).mean() < 2.0


def test_classes_look_different():
    n = 20_000
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    textures = TextureSet()
    means = {
        name: textures.albedo(CLASSES, np.full(n, i), x, y).mean() for i, name in enumerate(CLASSES)
    }
    assert means["ploughed_soil"] < means["compact_soil"] < means["dirt_road"]
    assert means["ploughed_soil"] < means["concrete"]
    # Same world point, same albedo; a new texture seed gives a new field.
    np.testing.assert_array_equal(
        textures.albedo(CLASSES, np.zeros(n, int), x, y),
        TextureSet().albedo(CLASSES, np.zeros(n, int), x, y),
    )
    other = TextureSet(seed=1).albedo(CLASSES, np.zeros(n, int), x, y)
    assert not np.allclose(other, textures.albedo(CLASSES, np.zeros(n, int), x, y))


def test_value_noise_is_smooth_and_centred():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-40, 40, 100_000), rng.uniform(-3, 3, 100_000)
    n = value_noise(x, y, 0.01, salt=3)
    assert n.min() >= -1 and n.max() <= 1
    assert abs(n.mean()) < 0.01 and 0.3 < n.std() < 0.5
    near = value_noise(x + 1e-4, y, 0.01, salt=3)
    assert np.abs(near - n).max() < 0.05  # continuous: 1 % of a step moves it little


def test_bad_inputs(calib):
    hf = world(np.zeros((50, 50)))
    with pytest.raises(InputError, match="pose"):
        render_stereo(hf, (0, 0, 0), calib)
    with pytest.raises(InputError, match="rows"):
        render_stereo(hf, (0, 0, 0, 0, 0, 0), calib, rows=(900, 1000))
    with pytest.raises(InputError, match="sees no part of the world"):
        render_stereo(hf, (100.0, 0, 0, 0, 0, 0), calib)
