"""Stereo pair -> point cloud of the patch of interest (paper section 3.2).

The pipeline of the paper, step by step:

1. *Disparity map*: semi-global matching (OpenCV ``StereoSGBM``) on a rectified pair,
   :func:`compute_disparity`. Disparities are in pixels, NaN where invalid.
2. *3-D points*: ``Z = fx B / d`` in the left camera frame, :func:`disparity_to_points`, then
   to the vehicle frame with the rig's extrinsics, :func:`to_vehicle`.
3. *Statistical moving-window filter*: a robust median/MAD test of the heights in small
   windows of the ground plane, :func:`statistical_outlier_filter`; the points it rejects
   that enough neighbours in the image support are kept (relief steeper than a window is
   not noise). The full frame, which need not be ground, uses the image test alone
   (:func:`image_outlier_mask`).
4. *Patch of interest*: only points over the patch footprint are kept.

:func:`stereo_to_cloud` chains the four. With ``restrict_to_patch=True`` (the default, the
*patch path*) it matches only what can see the patch, in two passes:

* *coarse*: SGM on the pair binned 4x4, over the patch and +-0.25 m of height around the
  expected ground (the vehicle's ``z = 0``, or the level ground of an IMU tilt,
  :func:`level_plane`); a robust plane fit to those points, refined by aligning the images
  themselves on it, gives the ground plane under the patch and the band of heights its
  relief spans (:func:`fit_ground`);
* *fine*: SGM at full resolution on the image rows and columns that see the patch
  (:func:`patch_window`), on the residual to that plane's disparity
  (:func:`ground_disparity`, the ``prior`` of :func:`compute_disparity`) over that band only
  (typically 16-32 disparities instead of 80-112). The points come straight from OpenCV's
  raw output through one 4x4 reprojection matrix (camera, vehicle frame and prior folded in),
  every second image column by default (``col_step``), and the filter works on their height
  above the plane in windows aligned on the patch.

Why the ground prior, and why the coarse pass aligns the images on its plane: see
:mod:`rough_map.stereo.matching` and :mod:`rough_map.stereo.coarse`.

On one thread (as in each worker process of a frame-parallel run), ``stereo_to_cloud`` of
the XB3-like rig's 1280x960 pairs takes 45-55 ms of CPU per frame: coarse pass 9-10 ms,
full-resolution SGM (with the warp of the right band) 27-35 ms, points 2 ms, outlier filter
7 ms; against about 100 ms for the former single pass over +-0.15 m around ``z = 0`` and
0.5 s for the full frame. Decoding the pair's colour PNG files (OpenCV, libpng) adds
38-40 ms and ``frame_features`` 7 ms: 95-100 ms per frame in all, 20 frames/s on two cores
(``benchmarks/bench_stereo.py``, which times the decoding alone and plain SGBM on the full
image in the same run). The coarse pass also makes the patch path follow ground that is not
at the vehicle's ``z = 0``: on the ploughed course the vehicle pitches by up to 13 degrees
and the ground under the patch lies up to 0.3 m off that plane, where the single pass lost
10-40 % of the patch.

Limits: the stereo error adds, on rendered ground, 2e-10 to 2e-9 m^3/rad at 112 rad/m and
1e-10 to 3e-10 m^3/rad at 224 rad/m. That dominates the high wavenumbers of very smooth
patches (detrended rms below about 2 mm), whose ``w`` then comes out too flat. On the
simulator's surfaces it is as large as the terrain's own PSD at 120-393 rad/m: against a
dense noise-free cloud of the true surface, ``frame_features`` of single stereo frames
(compact soil, gravel, ploughed soil, dirt road; seeds 0-2) give R 0.56-2.4x the truth and
``w`` -0.16 to +0.15 off (-0.02 on average), 6 frames of 12 within the issue's +-25 % and
+-0.1. (Before the cell-mean correction read the cloud's lateral scale it was R 0.47-1.8x,
``w`` +0.05 on average, 5 of 12: the matching window smooths across the rows, so stereo
clouds read a lateral scale of 0.2-0.6, see :mod:`rough_map.psd._corrections`.) Moving the
prior by a fraction of a pixel (a 2 mm change of plane) moves R by +-40 % and ``w`` by
+-0.1 on a given frame (tests/test_stereo.py,
``test_stereo_features_agree_with_the_true_surface``: met at seed 0 on compact soil, gravel
and ploughed soil, xfail on the dirt road).

Any calibrated rig: :func:`load_calibration` reads rough_map's calibration, the two
cameras' ROS ``CameraInfo`` files or an OpenCV ``FileStorage`` file; a raw pair is rectified
first (:func:`rectify_pair`); :func:`stereo_frame` gives the disparity map and the
camera-frame points of a whole frame of any scene, over the disparities of the depths that
matter (:func:`disparity_range`).

Conventions
-----------
* Images are matched rectified, undistorted and row-aligned, with one focal length and
  principal point row; the right principal point column may differ (``cx_right``,
  ``doffs = cx_right - cx``; 0 for OpenCV ``stereoRectify`` with ``CALIB_ZERO_DISPARITY``).
  The left camera is the reference; the right camera sits ``baseline`` metres along the
  left camera's +x axis, so a point at depth ``Z`` has disparity ``d = u_left - u_right =
  fx * baseline / Z - doffs``.
* Pixel ``(u, v)`` = (column, row); integer coordinates are pixel centres (OpenCV).
* Camera frame: OpenCV, x right, y down, z forward. Vehicle frame: x forward, y left, z up.
  ``camera_to_vehicle`` maps left-camera coordinates to vehicle coordinates.
* Images are 8-bit grayscale (``uint8``, shape ``(height, width)``) or 8-bit BGR
  (``(height, width, 3)``, converted to gray).

Modules
-------
=====================  ====================================================================
``settings``           :class:`StereoConfig` (``configs/stereo.yaml``), :class:`SGBMConfig`,
                       :class:`OutlierFilterConfig`
``matching``           SGM: :func:`compute_disparity`, :func:`equalize_subpixel`
``ground``             planes of the vehicle frame and their disparities:
                       :func:`ground_disparity`, :func:`plane_from_disparity`,
                       :func:`level_plane`
``window``             what sees the patch: :func:`patch_window`, :func:`patch_rows`
``triangulation``      :func:`disparity_to_points`, :func:`to_vehicle`, :func:`crop_to_patch`
``outliers``           the statistical moving-window filter, and the image test
                       (:func:`image_outlier_mask`) that rescues what it wrongly rejects
``coarse``             the coarse pass: :func:`fit_ground`
``rectify``            :func:`load_calibration` (any format), :func:`rectify_pair`
``frame``              whole frames: :func:`stereo_frame`, :func:`disparity_range`
``cloud``              :func:`stereo_to_cloud` and its paths
=====================  ====================================================================

The calibration is :class:`rough_map.config.StereoCalibration` (re-exported here), the patch
of interest a :class:`rough_map.patch.PatchSpec`, and :func:`read_image` reads an image file
(:mod:`rough_map.io.images`).
"""

from rough_map.config import StereoCalibration
from rough_map.io.images import read_image
from rough_map.stereo.cloud import stereo_to_cloud
from rough_map.stereo.coarse import fit_ground
from rough_map.stereo.frame import StereoFrame, disparity_range, stereo_frame
from rough_map.stereo.ground import Plane, ground_disparity, level_plane, plane_from_disparity
from rough_map.stereo.matching import compute_disparity, equalize_subpixel
from rough_map.stereo.outliers import (
    image_outlier_mask,
    image_support,
    statistical_outlier_filter,
    statistical_outlier_mask,
)
from rough_map.stereo.rectify import load_calibration, rectify_pair
from rough_map.stereo.settings import OutlierFilterConfig, SGBMConfig, StereoConfig
from rough_map.stereo.triangulation import crop_to_patch, disparity_to_points, to_vehicle
from rough_map.stereo.window import PatchWindow, patch_rows, patch_window

__all__ = [
    "OutlierFilterConfig",
    "PatchWindow",
    "Plane",
    "SGBMConfig",
    "StereoCalibration",
    "StereoConfig",
    "StereoFrame",
    "compute_disparity",
    "crop_to_patch",
    "disparity_range",
    "disparity_to_points",
    "equalize_subpixel",
    "fit_ground",
    "ground_disparity",
    "image_outlier_mask",
    "image_support",
    "level_plane",
    "load_calibration",
    "patch_rows",
    "patch_window",
    "plane_from_disparity",
    "read_image",
    "rectify_pair",
    "statistical_outlier_filter",
    "statistical_outlier_mask",
    "stereo_frame",
    "stereo_to_cloud",
    "to_vehicle",
]
