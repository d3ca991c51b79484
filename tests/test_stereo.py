"""Stereo -> point cloud: calibration files, geometry known answers, SGM on exact shifts, the
outlier filter, bad inputs, and the CLI on a rendered pair."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from rough_map import patch
from rough_map.cli.main import main
from rough_map.errors import FileFormatError, InputError, SchemaError
from rough_map.geometry import rotation_matrix
from rough_map.simulate.textures import DEFAULT_TEXTURES, value_noise
from rough_map.stereo import (
    SGBMConfig,
    StereoCalibration,
    StereoConfig,
    compute_disparity,
    crop_to_patch,
    disparity_to_points,
    equalize_subpixel,
    fit_ground,
    ground_disparity,
    level_plane,
    patch_rows,
    patch_window,
    plane_from_disparity,
    read_image,
    statistical_outlier_filter,
    statistical_outlier_mask,
    stereo_to_cloud,
    to_vehicle,
)

CONFIGS = Path(__file__).parents[1] / "configs"
#: The paper's patch: 0.896 m square, centre 1 m ahead.
PATCH = patch.PatchSpec()


@pytest.fixture(scope="module")
def calib() -> StereoCalibration:
    return StereoCalibration.xb3_default()


def shifted_pair(shift: float, shape=(200, 480)) -> tuple[np.ndarray, np.ndarray]:
    """A textured pair where every left pixel has disparity ``shift`` px (exact, sub-pixel)."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)

    def texture(x, y):
        t = 1.0 + 0.35 * value_noise(x, y, 1.5, 1) + 0.25 * value_noise(x, y, 4.0, 2)
        return np.clip(np.rint(120 * t), 0, 255).astype(np.uint8)

    return texture(u, v), texture(u + shift, v)  # right(u - d) = left(u)


# --------------------------------------------------------------------------------------------
# Calibration and configuration


def test_xb3_default_sees_the_patch(calib):
    assert (calib.width, calib.height, calib.baseline) == (1280, 960, 0.24)
    window = patch_window(calib)  # raises if the patch is not inside both images
    r0, r1 = window.rows
    assert 0 < r0 < r1 < calib.height
    min_d, num_d = window.disparities
    assert num_d % 16 == 0 and min_d > 0
    # The patch centre on the ground projects inside the window.
    cam = (np.array([1.0, 0.0, 0.0]) - calib.T_vehicle_camera[:3, 3]) @ calib.T_vehicle_camera[
        :3, :3
    ]
    v = calib.fy * cam[1] / cam[2] + calib.cy
    d = calib.focal_baseline / cam[2]
    assert r0 < v < r1 and min_d < d < min_d + num_d
    assert patch_rows(calib, PATCH) == window.rows
    # The residual to the ground's disparity covers +-0.15 m of height: about +-30 px.
    lo, num = window.residual
    assert lo < 0 < lo + num and num <= 96


def test_ground_disparity_known_answer(calib):
    """d0(u, v) is fx B / Z of the ray through (u, v) meeting the plane z = 0."""
    a, b, c = ground_disparity(calib)
    transform = calib.T_vehicle_camera
    for u, v in [(100.0, 900.0), (640.0, 480.0), (1200.0, 300.0)]:
        ray = transform[:3, :3] @ [(u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy, 1.0]
        depth = -transform[2, 3] / ray[2]
        assert a * u + b * v + c == pytest.approx(calib.focal_baseline / depth)
    assert a == pytest.approx(0.0, abs=1e-12)  # a pitched, unrolled rig: d0 depends on v only
    with pytest.raises(InputError, match="above the ground"):
        ground_disparity(calib, ground_z=2.0)


def test_ground_disparity_of_a_tilted_plane(calib):
    """d0(u, v) of the plane z = a x + b y + c, and back to the plane."""
    plane = (0.06, -0.03, 0.02)
    a, b, c = ground_disparity(calib, plane=plane)
    transform = calib.T_vehicle_camera
    for u, v in [(300.0, 700.0), (640.0, 480.0), (1000.0, 300.0)]:
        ray = transform[:3, :3] @ [(u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy, 1.0]
        t = transform[:3, 3]
        # t_z + Z r_z = a (t_x + Z r_x) + b (t_y + Z r_y) + c
        depth = (plane[0] * t[0] + plane[1] * t[1] + plane[2] - t[2]) / (
            ray[2] - plane[0] * ray[0] - plane[1] * ray[1]
        )
        assert a * u + b * v + c == pytest.approx(calib.focal_baseline / depth)
    np.testing.assert_allclose(plane_from_disparity(calib, (a, b, c)), plane, atol=1e-12)
    assert ground_disparity(calib, 0.01) == pytest.approx(
        ground_disparity(calib, plane=(0, 0, 0.01))
    )


@pytest.mark.parametrize(("roll", "pitch"), [(0.0, 0.0), (0.05, 0.0), (0.0, -0.1), (0.04, 0.12)])
def test_level_plane_follows_the_tilt(roll, pitch):
    """Points of level_plane(roll, pitch, g) are at height g once levelled by the vehicle's
    tilt, with rough_map.patch's rotation (pitch nose down, roll left side up)."""
    a, b, c = level_plane(roll, pitch, -0.01)
    x, y = np.meshgrid([0.5, 1.0, 1.5], [-0.4, 0.0, 0.4])
    pts = np.column_stack([x.ravel(), y.ravel(), (a * x + b * y + c).ravel()])
    levelled = pts @ rotation_matrix(roll, pitch).T
    np.testing.assert_allclose(levelled[:, 2], -0.01, atol=1e-12)
    if pitch > 0:
        assert a > 0  # nose down: the ground ahead rises in the vehicle frame


def test_patch_window_around_a_plane(calib):
    """The window follows the plane and an asymmetric band; the slack of the rounding to 16
    disparities is shared between both ends; clip keeps a tall band inside the image."""
    plane = (0.05, 0.0, 0.03)
    window = patch_window(calib, plane=plane, height_tolerance=(-0.02, 0.04))
    assert window.plane == plane and window.band == (-0.02, 0.04)
    assert window.prior == pytest.approx(ground_disparity(calib, plane=plane))
    lo, num = window.residual
    # Box corners (patch + margin, heights -0.02 and +0.04 above the plane): their residual
    # disparities lie inside the range, >= 2 px from both ends, with the slack shared.
    half = PATCH.size / 2 + 0.05
    x, y, dz = np.meshgrid([1 - half, 1 + half], [-half, half], [-0.02, 0.04])
    p = np.column_stack([x.ravel(), y.ravel(), (0.05 * x + 0.03 + dz).ravel()])
    transform = calib.T_vehicle_camera
    cam = (p - transform[:3, 3]) @ transform[:3, :3]
    u = calib.fx * cam[:, 0] / cam[:, 2] + calib.cx
    v = calib.fy * cam[:, 1] / cam[:, 2] + calib.cy
    pa, pb, pc = window.prior
    r = calib.focal_baseline / cam[:, 2] - (pa * u + pb * v + pc)
    assert num % 16 == 0 and lo + 2 <= r.min() and r.max() <= lo + num - 3
    assert abs((r.min() - lo) - (lo + num - 1 - r.max())) < 2
    assert window.rows[0] <= v.min() and v.max() < window.rows[1]
    flat = patch_window(calib, height_tolerance=0.02)
    assert flat.residual[1] == 16 and flat.rows[1] - flat.rows[0] < 500
    with pytest.raises(InputError, match="contain 0"):
        patch_window(calib, height_tolerance=(0.01, 0.05))
    with pytest.raises(InputError, match="not inside the left image"):
        patch_window(calib, height_tolerance=0.6)
    tall = patch_window(calib, height_tolerance=0.6, clip=True)
    assert tall.rows[0] >= 0 and tall.rows[1] <= calib.height


def test_the_default_patch_is_the_default_patch_spec(calib):
    assert patch_window(calib) == patch_window(calib, patch.PatchSpec())


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_calibration_round_trip(calib, tmp_path, suffix):
    path = tmp_path / f"rig{suffix}"
    calib.to_file(path)
    assert StereoCalibration.from_file(path) == calib


def test_calibration_unknown_field(calib, tmp_path):
    data = calib.model_dump() | {"fz": 3.0}
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SchemaError, match="fz"):
        StereoCalibration.from_file(path)


def test_calibration_bad_transform(calib, tmp_path):
    data = calib.model_dump()
    data["camera_to_vehicle"][0][0] = 2.0
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SchemaError, match="not a proper rotation"):
        StereoCalibration.from_file(path)


def test_calibration_unreadable(tmp_path):
    with pytest.raises(FileFormatError, match="cannot read"):
        StereoCalibration.from_file(tmp_path / "missing.yaml")
    bad = tmp_path / "rig.yaml"
    bad.write_text("fx: [1, 2\n")
    with pytest.raises(FileFormatError):
        StereoCalibration.from_file(bad)


def test_config_file_is_the_defaults():
    assert StereoConfig.from_file(CONFIGS / "stereo.yaml") == StereoConfig()


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [("blockSize", 4, "odd"), ("P2", 100, "greater than P1"), ("numDisparities", 100, "16")],
)
def test_sgbm_config_checks(field, value, message):
    with pytest.raises(ValidationError, match=message):
        SGBMConfig(**{field: value})


# --------------------------------------------------------------------------------------------
# Geometry


def test_disparity_to_points_known_answer(calib):
    disp = np.full((4, 6), np.nan, dtype=np.float32)
    disp[1, 2] = 120.0
    disp[3, 5] = 240.0
    pts = disparity_to_points(disp, calib, rows_offset=100)
    z = calib.focal_baseline / np.array([120.0, 240.0])
    np.testing.assert_allclose(pts[:, 2], z)
    np.testing.assert_allclose(pts[:, 0], (np.array([2, 5]) - calib.cx) * z / calib.fx)
    np.testing.assert_allclose(pts[:, 1], (np.array([101, 103]) - calib.cy) * z / calib.fy)
    # Binned rows: row i is the centre of image rows 100 + 2i and 100 + 2i + 1.
    pts2 = disparity_to_points(disp, calib, rows_offset=100, row_step=2)
    np.testing.assert_allclose(pts2[:, 1], (np.array([102.5, 106.5]) - calib.cy) * z / calib.fy)


def test_to_vehicle_puts_the_camera_where_the_calibration_says(calib):
    origin_and_axis = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = to_vehicle(origin_and_axis, calib)
    np.testing.assert_allclose(out[0], [-0.20, 0.12, 1.00])
    axis = out[1] - out[0]
    assert axis[0] > 0 and axis[2] < 0  # looks forward and down
    np.testing.assert_allclose(np.degrees(np.arctan2(-axis[2], axis[0])), 42.0)


def test_patch_outside_the_images_is_an_error(calib):
    with pytest.raises(InputError, match="not inside the left image"):
        patch_window(calib, patch.PatchSpec(lateral=1.5))
    with pytest.raises(InputError, match="behind"):
        patch_window(calib, patch.PatchSpec(ahead=-1.0))


def test_crop_to_patch():
    pts = np.array([[1.0, 0.0, 0.0], [1.0, 0.6, 0.0], [1.0, 0.0, 0.3], [0.4, 0.0, 0.0]])
    np.testing.assert_array_equal(crop_to_patch(pts, PATCH, margin=0.05), pts[[0, 2]])
    np.testing.assert_array_equal(
        crop_to_patch(pts, PATCH, margin=0.05, height_tolerance=0.15), pts[[0]]
    )
    beside = patch.PatchSpec(lateral=0.6)
    np.testing.assert_array_equal(crop_to_patch(pts, beside, margin=0.05), pts[[1]])


# --------------------------------------------------------------------------------------------
# Disparity


@pytest.mark.parametrize("shift", [20.0, 20.5, 33.25])
def test_sgbm_recovers_a_known_shift(shift):
    left, right = shifted_pair(shift)
    disp = compute_disparity(left, right, SGBMConfig(numDisparities=64))
    valid = disp[:, 80:]
    assert np.isfinite(valid).mean() > 0.9
    # SGM's parabolic sub-pixel fit pulls towards integers by up to ~0.15 px.
    assert abs(np.nanmedian(valid) - shift) < 0.2


def test_row_band_and_binning_agree_with_the_full_frame():
    left, right = shifted_pair(25.0)
    config = SGBMConfig(numDisparities=48)
    full = compute_disparity(left, right, config)
    band = compute_disparity(left, right, config, rows=(60, 140), cols=(200, 400))
    assert band.shape == (80, left.shape[1])
    assert np.isnan(band[:, :200]).all() and np.isnan(band[:, 400:]).all()
    np.testing.assert_allclose(np.nanmedian(band[:, 200:400]), np.nanmedian(full[60:140]), atol=0.1)
    binned = compute_disparity(
        left, right, config, rows=(60, 140), row_step=2, disparities=(16, 32)
    )
    assert binned.shape == (40, left.shape[1])
    assert abs(np.nanmedian(binned) - 25.0) < 0.3


@pytest.mark.parametrize("prior", [(0.0, 0.0, 20.0), (0.0, 0.02, 18.0), (0.01, 0.0, 17.0)])
def test_prior_returns_the_full_disparity(prior):
    """The right image is resampled by the prior, SGM matches the residual, d comes back."""
    left, right = shifted_pair(25.0)
    disp = compute_disparity(
        left,
        right,
        SGBMConfig(numDisparities=48),
        prior=prior,
        disparities=(-16, 32),
        cols=(100, 400),
    )
    assert np.isfinite(disp[:, 100:400]).mean() > 0.9
    assert abs(np.nanmedian(disp) - 25.0) < 0.1


def test_trim_drops_the_ends_of_the_range():
    left, right = shifted_pair(20.0)
    kept = compute_disparity(left, right, SGBMConfig(), disparities=(0, 32), trim=1)
    assert np.isfinite(kept).mean() > 0.5
    dropped = compute_disparity(left, right, SGBMConfig(), disparities=(-11, 32), trim=1)
    assert np.isfinite(dropped[:, 80:]).mean() < 0.05  # 20 px is the range's last value


def test_equalize_subpixel_undoes_locking():
    rng = np.random.default_rng(0)
    truth = rng.uniform(100, 160, 200_000)
    frac = truth - np.floor(truth + 0.5)  # in [-0.5, 0.5)
    locked = np.floor(truth + 0.5) + 0.5 * np.sign(frac) * np.abs(2 * frac) ** 2  # monotone
    observed = np.round(locked * 16) / 16  # OpenCV's 1/16 px steps
    corrected = equalize_subpixel(observed.astype(np.float32))
    before, after = np.abs(observed - truth).mean(), np.abs(corrected - truth).mean()
    assert before > 0.08  # 0.083 px
    assert after < 0.4 * before  # 0.030 px: what the 1/16 px steps leave
    narrow = np.full(5000, 120.25, dtype=np.float32)  # no spread: left alone
    np.testing.assert_array_equal(equalize_subpixel(narrow), narrow)


def test_bad_images_are_input_errors(calib):
    left, right = shifted_pair(10.0)
    with pytest.raises(InputError, match="differ in size"):
        compute_disparity(left, right[:, :-1])
    with pytest.raises(InputError, match="uint8"):
        compute_disparity(left.astype(np.float32), right)
    with pytest.raises(InputError, match="shape"):
        compute_disparity(left[None], right[None])
    with pytest.raises(InputError, match="calibration is for 1280x960"):
        stereo_to_cloud(left, right, calib)
    with pytest.raises(InputError, match="rows"):
        compute_disparity(left, right, rows=(150, 120))


def test_bgr_images_are_accepted():
    left, right = shifted_pair(20.0)
    gray = compute_disparity(left, right, SGBMConfig(numDisparities=48))
    bgr = compute_disparity(
        cv2.cvtColor(left, cv2.COLOR_GRAY2BGR),
        cv2.cvtColor(right, cv2.COLOR_GRAY2BGR),
        SGBMConfig(numDisparities=48),
    )
    np.testing.assert_array_equal(np.isnan(gray), np.isnan(bgr))


def test_read_image(tmp_path):
    left, _ = shifted_pair(5.0)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    np.testing.assert_array_equal(read_image(tmp_path / "l.png"), left)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(FileFormatError, match="not an image"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(FileFormatError, match="no such file"):
        read_image(tmp_path / "missing.png")


# --------------------------------------------------------------------------------------------
# Statistical moving-window filter


def test_outlier_filter_removes_spikes_and_keeps_the_surface():
    rng = np.random.default_rng(0)
    n = 50_000
    x, y = rng.uniform(0.5, 1.5, n), rng.uniform(-0.45, 0.45, n)
    z = 0.01 * np.sin(2 * np.pi * x / 0.3) + rng.normal(0, 0.0007, n)
    spikes = rng.choice(n, 300, replace=False)
    z[spikes] += rng.choice([-1, 1], 300) * rng.uniform(0.02, 0.3, 300)
    pts = np.column_stack([x, y, z])
    keep = statistical_outlier_mask(pts)
    assert not keep[spikes].any()
    inliers = np.ones(n, bool)
    inliers[spikes] = False
    assert keep[inliers].mean() > 0.99
    out = statistical_outlier_filter(pts)
    np.testing.assert_array_equal(out, pts[keep])  # order kept


def test_outlier_filter_float32_matches_float64():
    """float32 clouds are filtered in float32 (faster); the decisions are the same."""
    rng = np.random.default_rng(1)
    n = 100_000
    x, y = rng.uniform(0.5, 1.5, n), rng.uniform(-0.5, 0.5, n)
    z = 0.02 * np.sin(2 * np.pi * x / 0.2) + rng.standard_t(3, n) * 0.001
    pts = np.column_stack([x, y, z])
    keep64 = statistical_outlier_mask(pts)
    keep32 = statistical_outlier_mask(pts.astype(np.float32))
    assert 0.9 < keep64.mean() < 1.0
    assert (keep32 != keep64).mean() < 1e-4


def test_outlier_filter_edge_cases():
    assert statistical_outlier_mask(np.zeros((0, 3))).shape == (0,)
    flat = np.column_stack([np.linspace(0, 0.02, 10), np.zeros(10), np.zeros(10)])
    assert statistical_outlier_mask(flat).all()  # MAD 0: min_tolerance keeps them
    assert not statistical_outlier_mask(flat[:2], min_count=3).any()  # isolated window
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        statistical_outlier_mask(np.zeros((5, 2)))


# --------------------------------------------------------------------------------------------
# End to end on a rendered pair, and the CLI


@pytest.fixture(scope="module")
def flat_pair(calib):
    from rough_map.simulate.render import render_stereo
    from rough_map.types import HeightField

    spacing = 0.004
    world = HeightField(
        np.zeros((750, 1000)),
        spacing,
        origin=(-0.5, -1.5),
        classes=np.zeros((750, 1000), int),
        class_names=("gravel",),
    )
    left, right, _ = render_stereo(world, (0, 0, 0, 0, 0, 0), calib, rows=patch_rows(calib, PATCH))
    return left, right


def test_stereo_to_cloud_patch_path(calib, flat_pair):
    pts = stereo_to_cloud(*flat_pair, calib)
    half = PATCH.size / 2 + StereoConfig().crop_margin
    assert len(pts) > 100_000
    assert np.abs(pts[:, 0] - PATCH.ahead).max() <= half + 1e-9
    assert np.abs(pts[:, 1]).max() <= half + 1e-9
    assert np.median(np.abs(pts[:, 2])) < 0.002


def test_cli_stereo(calib, flat_pair, tmp_path, capsys):
    for name, image in zip(("l.png", "r.png"), flat_pair, strict=True):
        cv2.imwrite(str(tmp_path / name), image)
    calib.to_file(tmp_path / "rig.yaml")
    out = tmp_path / "cloud.npy"
    code = main(
        [
            "stereo",
            str(tmp_path / "l.png"),
            str(tmp_path / "r.png"),
            "--calib",
            str(tmp_path / "rig.yaml"),
            "--out",
            str(out),
            "--config",
            str(CONFIGS / "stereo.yaml"),
        ]
    )
    assert code == 0
    cloud = np.load(out)
    assert cloud.shape[1] == 3 and len(cloud) > 100_000
    assert "points" in capsys.readouterr().out
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was moved into place

    code = main(
        [
            "stereo",
            str(tmp_path / "l.png"),
            str(tmp_path / "rig.yaml"),
            "--calib",
            str(tmp_path / "rig.yaml"),
            "--out",
            str(out),
        ]
    )
    assert code == 2
    assert "not an image" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# The patch path's ground fit, a tilted vehicle, and the features of rendered surfaces


ROLL, PITCH = 0.03, 0.08  # rad: left side up, nose down


@pytest.fixture(scope="module")
def tilted_pair(calib):
    """Flat textured ground seen from a rolled and pitched vehicle (origin on the ground)."""
    from rough_map.simulate.render import render_stereo
    from rough_map.types import HeightField

    world = HeightField(
        np.zeros((750, 1000)),
        0.004,
        origin=(-0.5, -1.5),
        classes=np.zeros((750, 1000), int),
        class_names=("compact_soil",),
    )
    rows = patch_window(calib, plane=level_plane(ROLL, PITCH), height_tolerance=0.1).rows
    return render_stereo(world, (0, 0, 0, ROLL, PITCH, 0), calib, rows=rows)[:2]


def _fill(points) -> float:
    return patch.grid_points(points, min_points=1).fill_fraction


def test_fit_ground_finds_the_tilted_ground(calib, tilted_pair):
    """The coarse pass finds the ground 6-12 cm off the vehicle's z = 0 to a fraction of a mm,
    without being told the tilt; the patch path then reconstructs all of it."""
    truth = level_plane(ROLL, PITCH)
    plane, (lo, hi) = fit_ground(*tilted_pair, calib, patch=PATCH)
    for x in (PATCH.ahead - 0.45, PATCH.ahead + 0.45):
        for y in (-0.45, 0.45):
            dz = (plane[0] - truth[0]) * x + (plane[1] - truth[1]) * y + plane[2] - truth[2]
            assert abs(dz) < 0.0005
    assert -0.04 < lo < 0 < hi < 0.04  # flat ground: the smallest band
    for tilt in ({}, {"roll": ROLL, "pitch": PITCH}):
        pts = stereo_to_cloud(*tilted_pair, calib, **tilt)
        dz = pts[:, 2] - (truth[0] * pts[:, 0] + truth[1] * pts[:, 1] + truth[2])
        assert np.median(np.abs(dz)) < 0.0005
        assert _fill(pts) > 0.98


def test_tilt_centres_a_single_pass(calib, tilted_pair):
    """Without the coarse pass, a narrow band around the vehicle's z = 0 misses the far part of
    the tilted ground; the IMU's roll and pitch put the band on the level ground."""
    single = StereoConfig(fit_ground=False, height_tolerance=0.05)
    assert _fill(stereo_to_cloud(*tilted_pair, calib, single)) < 0.7
    pts = stereo_to_cloud(*tilted_pair, calib, single, roll=ROLL, pitch=PITCH)
    assert _fill(pts) > 0.98


FIDELITY_CLASSES = ("compact_soil", "gravel", "ploughed_soil", "dirt_road")


def _truth_cloud(world, step: float = 0.002) -> np.ndarray:
    """Dense, noise-free points of the true surface over the patch and its margin (the vehicle
    is at the world origin, level)."""
    g = np.arange(-0.5, 0.5 + 1e-9, step)
    x, y = np.meshgrid(PATCH.ahead + g, g)
    return np.column_stack([x.ravel(), y.ravel(), world.sample(x.ravel(), y.ravel())])


@pytest.fixture(scope="module", params=FIDELITY_CLASSES)
def surface_features(request, calib):
    """Features (frame_features) of the stereo cloud and of the dense true surface, for one
    simulator surface (terrain.generate, seed 0) rendered from a level vehicle."""
    from rough_map import terrain
    from rough_map.features import frame_features
    from rough_map.simulate.render import render_stereo
    from rough_map.types import HeightField

    names = tuple(DEFAULT_TEXTURES)
    heights = terrain.generate(request.param, (750, 1000), 0.004, seed=0)
    world = HeightField(
        heights,
        0.004,
        origin=(-0.5, -1.5),
        classes=np.full(heights.shape, names.index(request.param)),
        class_names=names,
    )
    left, right, _ = render_stereo(world, (0, 0, 0, 0, 0, 0), calib, rows=(120, 860))
    spec = patch.PatchSpec()
    stereo, _, _ = frame_features(stereo_to_cloud(left, right, calib), spec)
    truth, _, _ = frame_features(_truth_cloud(world), spec)
    assert stereo["valid"] and truth["valid"]
    return request.param, stereo, truth


@pytest.mark.slow
def test_stereo_features_stay_near_the_truth(surface_features):
    """Regression guard: R within a factor 3 and w within 0.3 of the true surface's.

    Measured (default config, seed 0), R ratio / w difference: compact_soil 1.01 / +0.04,
    gravel 1.22 / -0.02, ploughed_soil 0.82 / +0.05, dirt_road 2.42 / -0.16.
    """
    _, stereo, truth = surface_features
    assert 1 / 3 < stereo["R"] / truth["R"] < 3
    assert abs(stereo["w"] - truth["w"]) < 0.3


#: Surfaces on which stereo does not yet meet R +-25 % / w +-0.1 (issue 13's work).
_STEREO_NOT_YET = ("dirt_road",)


@pytest.mark.slow
def test_stereo_features_agree_with_the_true_surface(surface_features, request):
    """The issue's acceptance: features from stereo-reconstructed clouds agree with features
    from the true height field, R within +-25 % and w within +-0.1, on the non-flat classes
    (the rendered simulator surfaces, against a dense noise-free cloud of the true surface at
    the same pose). Met on compact soil, gravel and ploughed soil since the cell-mean
    correction reads the cloud's lateral scale (stereo clouds read 0.2-0.6: the matching
    window smooths across the rows); a strict xfail on the dirt road, so that meeting it
    there fails until the mark is removed."""
    name, stereo, truth = surface_features
    if name in _STEREO_NOT_YET:
        request.applymarker(
            pytest.mark.xfail(
                strict=True,
                reason="not met yet: the stereo error is as large as the terrain's PSD at "
                "120-393 rad/m (see the Limits of rough_map.stereo)",
            )
        )
    assert 0.75 <= stereo["R"] / truth["R"] <= 1.25
    assert abs(stereo["w"] - truth["w"]) <= 0.1


# --------------------------------------------------------------------------------------------
# The package's names, the patch argument and the robust plane fit


def test_one_calibration_and_one_image_reader():
    from rough_map import config
    from rough_map.io import images

    assert StereoCalibration is config.StereoCalibration
    assert read_image is images.read_image


def test_cloud_covers_the_given_patch(calib, flat_pair):
    """stereo_to_cloud returns the points over the PatchSpec it is given (plus the margin)."""
    spec = patch.PatchSpec(ahead=1.05, size=0.8, lateral=0.02)
    by_spec = stereo_to_cloud(*flat_pair, calib, patch=spec)
    half = 0.4 + StereoConfig().crop_margin
    assert np.abs(by_spec[:, 0] - 1.05).max() <= half + 1e-6
    assert np.abs(by_spec[:, 1] - 0.02).max() <= half + 1e-6


def test_fit_plane_trims_outliers():
    """Known plane under 1 mm noise and 5 % outliers; sigma is 1.4826 x the MAD exactly."""
    from scipy.stats import median_abs_deviation

    from rough_map.stereo.ground import fit_plane
    from rough_map.stereo.outliers import MAD_TO_SIGMA

    rng = np.random.default_rng(4)
    n = 20_000
    x, y = rng.uniform(0.5, 1.5, n), rng.uniform(-0.5, 0.5, n)
    z = 0.02 * x - 0.01 * y + 0.003 + rng.normal(0, 0.001, n)
    bad = rng.choice(n, n // 20, replace=False)
    z[bad] += rng.choice([-1, 1], len(bad)) * rng.uniform(0.02, 0.1, len(bad))
    plane, heights, inliers = fit_plane(np.column_stack([x, y, z]), (1.0, 0.0))
    np.testing.assert_allclose(plane, (0.02, -0.01, 0.003), atol=1e-4)
    assert not inliers[bad].any() and inliers.mean() > 0.94
    np.testing.assert_allclose(heights, z - (plane[0] * x + plane[1] * y + plane[2]))
    r = heights[inliers]
    assert MAD_TO_SIGMA * median_abs_deviation(r) == 1.4826 * np.median(np.abs(r - np.median(r)))
