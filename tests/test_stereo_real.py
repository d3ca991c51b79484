"""Stereo on a real pair: the Middlebury 2014 motorcycle (shipped by scikit-image).

The pair is rectified, with a dense ground-truth disparity map (NaN where unknown) and a
published calibration, given here as the two cameras' ROS ``CameraInfo`` files
(tests/data/middlebury_motorcycle_{left,right}.yaml: the right camera's principal point is
``doffs`` = 31.086 px to the right, no hand shift). rough_map's full frame
(:func:`rough_map.stereo.stereo_frame`: SGM, pixel locking undone, the image outlier test,
the left columns matched) is compared with plain OpenCV ``StereoSGBM`` with the same
parameters over the same disparities, those of the scene's depths (2.0-5.5 m; the published
``vmin``/``vmax`` are 2.08-5.21 m).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rough_map.cli.main import main
from rough_map.geometry import CAMERA_AXES_IN_VEHICLE, rotation_matrix
from rough_map.stereo import (
    SGBMConfig,
    StereoConfig,
    compute_disparity,
    disparity_range,
    load_calibration,
    stereo_frame,
)
from rough_map.stereo.matching import sgbm_matcher

cv2 = pytest.importorskip("cv2")

DATA = Path(__file__).parent / "data"
CAMERA_INFO = [DATA / "middlebury_motorcycle_left.yaml", DATA / "middlebury_motorcycle_right.yaml"]
DEPTHS = {"min_depth": 2.0, "max_depth": 5.5}  # m


@pytest.fixture(scope="module")
def motorcycle():
    """Gray left and right images (500 x 741 px) and the true disparity (px, NaN unknown)."""
    data = pytest.importorskip("skimage.data")
    left, right, truth = data.stereo_motorcycle()
    gray = (cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (left, right))
    return *gray, truth


def plain_sgbm(left, right, config: SGBMConfig, disparities) -> np.ndarray:
    """OpenCV StereoSGBM as it comes: float32 px, NaN where invalid."""
    matcher = sgbm_matcher(config, disparities[0], disparities[1])
    raw = matcher.compute(left, right)
    plain = raw.astype(np.float32) / 16
    plain[raw < 16 * disparities[0]] = np.nan
    return plain


def depth_scores(disp, truth, calib) -> tuple[float, float, float]:
    """Coverage (matched fraction of the pixels with a true disparity), median relative depth
    error and fraction of matched pixels whose depth is off by more than 5 %."""
    known = np.isfinite(truth)
    matched = known & np.isfinite(disp)
    z = calib.focal_baseline / (disp[matched] + calib.doffs)
    z_true = calib.focal_baseline / (truth[matched] + calib.doffs)
    rel = np.abs(z - z_true) / z_true
    return matched.sum() / known.sum(), float(np.median(rel)), float((rel > 0.05).mean())


def test_camera_info_calibration_of_the_pair():
    calib = load_calibration(CAMERA_INFO)
    assert calib.doffs == pytest.approx(31.086)
    assert calib.baseline == pytest.approx(0.193001)
    assert (calib.width, calib.height, calib.fx) == (741, 500, 994.978)
    assert calib.rectification is None  # already rectified: no remapping
    # The scene's depths: disparities ~3.8-64.9 px, searched with 1 px to spare.
    assert disparity_range(calib, **DEPTHS) == (2, 80)


def test_middlebury_camera_info_beats_plain_sgbm(motorcycle):
    """Measured: rough_map coverage 0.889, median depth error 0.213 %, 5.02 % of pixels off
    by more than 5 %; plain SGBM 0.841, 0.250 %, 5.24 % (without the image outlier test
    0.915, 0.220 %, 5.94 %; the former ground-square filter 0.825, 0.222 %, 5.54 %)."""
    left, right, truth = motorcycle
    calib = load_calibration(CAMERA_INFO)
    config = StereoConfig()
    frame = stereo_frame(left, right, calib, config, **DEPTHS)
    assert frame.disparities == (2, 80)
    ours = depth_scores(frame.disparity, truth, calib)
    plain = depth_scores(plain_sgbm(left, right, config.sgbm, frame.disparities), truth, calib)
    assert plain[0] > 0.8
    assert ours[0] >= plain[0]  # the bar: >= 95 % of plain's
    assert ours[1] <= 0.9 * plain[1]
    assert ours[2] <= plain[2]
    # The left columns are matched, not blanked (plain SGBM leaves the first 81 empty).
    assert np.isfinite(frame.disparity[:, 20:81]).mean() > 0.5
    # Depths and camera points agree with the calibration.
    z = frame.depth()
    points = frame.camera_points()
    np.testing.assert_allclose(points[:, 2], z[np.isfinite(z)], rtol=1e-6)
    assert 1.9 < np.median(points[:, 2]) < 5.6


def test_subpixel_equalization_lead_over_plain_sgbm(motorcycle):
    """Same SGBM parameters and disparities (the config's, 64), smaller errors: SGM's pixel
    locking undone (``equalize_subpixel``). Measured on the pixels both match: median error
    0.141 vs 0.169 px."""
    left, right, truth = motorcycle
    config = SGBMConfig(numDisparities=64)
    ours = compute_disparity(left, right, config, equalize=True)
    plain = plain_sgbm(left, right, config, (0, 64))
    both = np.isfinite(truth) & np.isfinite(ours) & np.isfinite(plain)
    err_ours, err_plain = np.abs(ours - truth)[both], np.abs(plain - truth)[both]
    assert np.isfinite(ours).sum() > np.isfinite(plain).sum()  # + the left columns
    assert np.median(err_ours) <= 0.9 * np.median(err_plain)
    assert (err_ours > 0.5).mean() <= (err_plain > 0.5).mean()


def test_cli_writes_disparity_and_camera_points(motorcycle, tmp_path, capsys):
    left, right, _ = motorcycle
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    out = tmp_path / "cloud.npy"
    args = ["stereo", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--out", str(out)]
    args += ["--calib", *map(str, CAMERA_INFO), "--full-frame"]
    args += ["--min-depth", "2", "--max-depth", "5.5"]
    args += ["--disparity", str(tmp_path / "d.npy"), "--camera-points", str(tmp_path / "c.npy")]
    assert main(args) == 0
    disp = np.load(tmp_path / "d.npy")
    camera = np.load(tmp_path / "c.npy")
    cloud = np.load(out)
    assert disp.shape == (500, 741) and disp.dtype == np.float32
    assert len(camera) == len(cloud) == np.isfinite(disp).sum()
    # Camera axes: z forward (2-5.5 m searched, 1 px of disparity to spare: 1.97-5.80 m), y
    # down; the default vehicle pose looks along x: vehicle x is the camera's z, z its -y.
    assert 1.95 < camera[:, 2].min() and camera[:, 2].max() < 5.81
    np.testing.assert_allclose(cloud[:, 0], camera[:, 2])
    np.testing.assert_allclose(cloud[:, 2], -camera[:, 1])
    assert "valid disparities" in capsys.readouterr().out
    # The camera's pose on a vehicle: 1.2 m up, 0.3 m back, pitched 10 degrees down.
    pose = np.eye(4)
    pose[:3, :3] = rotation_matrix(pitch=np.radians(10.0)) @ CAMERA_AXES_IN_VEHICLE
    pose[:3, 3] = [-0.3, 0.0, 1.2]
    (tmp_path / "pose.yaml").write_text(f"camera_to_vehicle: {pose.tolist()}\n")
    assert main([*args, "--camera-to-vehicle", str(tmp_path / "pose.yaml")]) == 0
    np.testing.assert_allclose(np.load(out), camera @ pose[:3, :3].T + pose[:3, 3], atol=1e-9)
    capsys.readouterr()
    args[args.index("--disparity") + 1] = str(tmp_path / "d.png")
    assert main(args) == 2
    assert "d.png [suffix]" in capsys.readouterr().err
