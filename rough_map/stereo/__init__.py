"""Stereo pair -> point cloud of the patch of interest (paper section 3.2).

The pipeline of the paper, step by step:

1. *Disparity map*: semi-global matching (OpenCV ``StereoSGBM``) on a rectified pair,
   :func:`compute_disparity`. Disparities are in pixels, NaN where invalid.
2. *3-D points*: ``Z = fx B / d`` in the left camera frame, :func:`disparity_to_points`, then
   to the vehicle frame with the rig's extrinsics, :func:`to_vehicle`.
3. *Statistical moving-window filter*: a robust median/MAD test of the heights in small
   windows of the ground plane, :func:`statistical_outlier_filter`.
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

On the XB3-like rig's 1280x960 pair of the benchmark (rough compact soil, 16 residual
disparities) that is 85-100 ms of CPU per frame on a busy 2-core machine, about 2/3 of it
SGM (which runs on both cores), against 220-320 ms for the former single pass over +-0.15 m
around ``z = 0`` and about 1 s for the full frame (``benchmarks/bench_stereo.py``). Frames
of the simulator's courses, whose relief needs 32 disparities and whose patch looks bigger
when the vehicle pitches down, take 100-200 ms (the single pass: 240-340 ms). The coarse pass
also makes the patch path follow ground that is not at the vehicle's ``z = 0``: on the
ploughed course the vehicle pitches by up to 13 degrees and the ground under the patch lies
up to 0.3 m off that plane, where the single pass lost 10-40 % of the patch.

Why the ground prior
--------------------
The rig looks at the ground obliquely, so the disparity of flat ground grows by about
0.15 px per image row. SGM assumes locally constant disparity: on such a ramp its
aggregation (top-down in the 3WAY mode) biases the disparity low, its blocks straddle the
ramp, and its parabolic sub-pixel fit crowds values towards integers ("pixel locking"),
which on the ramp makes a sawtooth of +-0.2 px with a period of about 1 cm along the
ground. Gridded at 8 mm that error lands inside the wavelengths the PSD estimator fits: on
rendered terrain it raised the PSD at 224-393 rad/m 2-9x and flattened ``w`` by 0.5-1.0.
Resampling the right image by the flat ground's disparity makes the ground fronto-parallel
to the matcher; the PSD then follows the truth within a factor of about 1.5 across the band
and ``w`` within about 0.2 (tests/test_render.py). The per-point errors are about 1 mm
either way: they hide the difference.

Why the plane is aligned on the images
--------------------------------------
Pixel locking is worst where all residuals are nearly the same: a surface that *is* the
prior's plane, give or take a fraction of a pixel, comes back locked onto the prior, with
its offset lost. The plane SGM finds in the coarse pass is off by a few tenths of a pixel
(1-2 mm), so the fine pass would inherit that error on smooth ground. Aligning the binned
images directly on a plane (Gauss-Newton on three disparity parameters over thousands of
pixels, no integer search) finds it to about 0.01 px; on a rendered tilted plane the
points then lie within 0.15 mm (median) of the truth, against 0.8-0.9 mm for a prior at
``z = 0``.

Limits: the stereo error adds, on rendered ground, 2e-10 to 2e-9 m^3/rad at 112 rad/m and
1e-10 to 3e-10 m^3/rad at 224 rad/m. That dominates the high wavenumbers of very smooth
patches (detrended rms below about 2 mm), whose ``w`` then comes out too flat. On the
simulator's surfaces it is as large as the terrain's own PSD at 120-393 rad/m: against a
dense noise-free cloud of the true surface, ``frame_features`` of single stereo frames
(compact soil, gravel, ploughed soil, dirt road; seeds 0-2) give R 0.45-1.5x the truth and
``w`` +0.2 to -0.03 off (+0.09 on average), 4-5 frames of 12 within the issue's +-25 % and
+-0.1, with the one-pass patch path as with this one: moving the prior by a fraction of a
pixel (a 2 mm change of plane) moves R by +-40 % and ``w`` by +-0.1 on a given frame
(tests/test_stereo.py, ``test_stereo_features_agree_with_the_true_surface``, xfail).

Conventions
-----------
* Images are rectified, undistorted, row-aligned and share one pinhole matrix ``K``
  (``cx`` equal in both views, i.e. OpenCV ``stereoRectify`` with ``CALIB_ZERO_DISPARITY``).
  The left camera is the reference; the right camera sits ``baseline`` metres along the
  left camera's +x axis, so a point at depth ``Z`` has disparity ``d = u_left - u_right =
  fx * baseline / Z``.
* Pixel ``(u, v)`` = (column, row); integer coordinates are pixel centres (OpenCV).
* Camera frame: OpenCV, x right, y down, z forward. Vehicle frame: x forward, y left, z up.
  ``camera_to_vehicle`` maps left-camera coordinates to vehicle coordinates.
* Images are 8-bit grayscale (``uint8``, shape ``(height, width)``) or 8-bit BGR
  (``(height, width, 3)``, converted to gray).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from rough_map.config import StereoCalibration
from rough_map.errors import FileFormatError, InputError

log = logging.getLogger(__name__)

# The paper's patch, as rough_map.patch.DEFAULT_SIZE / DEFAULT_AHEAD (io does not import
# patch: data flows io -> patch).
#: Side of the patch of interest, default (m): 112 cells of 8 mm.
PATCH_SIZE = 0.896
#: Distance of the patch centre ahead of the vehicle origin, default (m).
PATCH_AHEAD = 1.0

_SGBM_MODES = {"SGBM": 0, "HH": 1, "SGBM_3WAY": 2, "HH4": 3}


# --------------------------------------------------------------------------------------------
# Calibration and configuration
# --------------------------------------------------------------------------------------------


class SGBMConfig(BaseModel):
    """Parameters of OpenCV ``StereoSGBM``, named as in OpenCV.

    Defaults are those of ``configs/stereo.yaml``. ``P1 = 8 * blockSize**2`` and ``P2 = 32 *
    blockSize**2`` are OpenCV's recommendation for one channel. ``SGBM_3WAY`` is the fastest
    mode and the only one OpenCV runs on several threads.

    Attributes
    ----------
    minDisparity : int
        Smallest disparity searched, px.
    numDisparities : int
        Number of disparities searched, px, a positive multiple of 16. 256 covers depths from
        ``fx B / 256`` = 0.92 m for the XB3-like rig; the patch path overrides both from the
        geometry (see :func:`patch_window`).
    blockSize : int
        Odd matching block side, px.
    P1, P2 : int
        Penalties for disparity changes of 1 px and of more than 1 px between neighbours.
    disp12MaxDiff : int
        Largest left-right consistency difference, px; negative to disable.
    preFilterCap : int
        Clip of the x-derivative prefilter.
    uniquenessRatio : int
        Margin in % by which the best cost must beat the second best.
    speckleWindowSize : int
        Largest size in px of a disparity blob treated as speckle and removed; 0 disables.
    speckleRange : int
        Largest disparity variation within a connected blob, px.
    mode : {"SGBM", "HH", "SGBM_3WAY", "HH4"}
        OpenCV SGBM variant.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # OpenCV's names, on purpose: the YAML keys map 1:1 onto cv2.StereoSGBM.create.
    minDisparity: int = 0
    numDisparities: int = Field(256, gt=0, multiple_of=16)
    blockSize: int = Field(5, ge=1, le=11)
    P1: int = Field(200, ge=0)
    P2: int = Field(800, ge=0)
    disp12MaxDiff: int = 1
    preFilterCap: int = Field(63, ge=1, le=63)
    uniquenessRatio: int = Field(10, ge=0, le=100)
    speckleWindowSize: int = Field(100, ge=0)
    speckleRange: int = Field(2, ge=0)
    mode: Literal["SGBM", "HH", "SGBM_3WAY", "HH4"] = "SGBM_3WAY"

    @model_validator(mode="after")
    def _check(self) -> SGBMConfig:
        if self.blockSize % 2 == 0:
            raise ValueError(f"blockSize must be odd, got {self.blockSize}")
        if self.P2 <= self.P1:
            raise ValueError(f"P2 ({self.P2}) must be greater than P1 ({self.P1})")
        return self


class OutlierFilterConfig(BaseModel):
    """Parameters of :func:`statistical_outlier_filter`.

    Attributes
    ----------
    cell : float
        Side of the square ground-plane window, m.
    k : float
        Rejection threshold in robust standard deviations (``1.4826 * MAD``).
    min_tolerance : float
        Smallest tolerated deviation from the window median, m; keeps a flat, quantised
        window from rejecting everything when its MAD is about zero.
    min_count : int
        Windows with fewer points are dropped as isolated.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    cell: float = Field(0.024, gt=0)
    k: float = Field(3.5, gt=0)
    min_tolerance: float = Field(0.003, ge=0)
    min_count: int = Field(3, ge=1)


class StereoConfig(BaseModel):
    """Everything :func:`stereo_to_cloud` needs besides the calibration (``configs/stereo.yaml``).

    Attributes
    ----------
    sgbm : SGBMConfig
        Matcher parameters.
    outlier_filter : OutlierFilterConfig or None
        The statistical moving-window filter; ``None`` disables it.
    height_tolerance : float
        Heights in m above and below the expected ground (the vehicle's ``z = 0``, or the
        level ground under an IMU tilt) that the patch path searches: the coarse pass
        (:func:`fit_ground`) looks for the ground there, and without it (``fit_ground``
        off, or a failed fit) the full-resolution pass does.
    fit_ground : bool
        Patch path with ``ground_prior``: fit the ground plane under the patch in a coarse
        pass, then match at full resolution around that plane only, over the relief the
        coarse pass found (a fraction of ``height_tolerance``).
    coarse_scale : int
        Binning of the coarse pass's images, each way.
    band_margin : float
        Margin in m added to the relief (0.2th-99.8th percentile of the coarse heights
        above the fitted plane) for the fine search.
    min_band : float
        Smallest height, m, searched above and below the fitted plane.
    crop_margin : float
        Margin in m around the patch footprint kept in the returned cloud.
    margin_px : int
        Extra image rows and columns matched on each side of the patch's window, px (the
        window already holds the patch, its margin and the searched heights).
    col_step : int
        Patch path: keep the points of every ``col_step``-th image column only; matching is
        still at full resolution. 2 (the default) leaves about 9 points per 8 mm cell of the
        patch, halves the cost of the points, the filter and the gridding downstream, and
        changes R and w by much less than their scatter between stereo frames (SGM's errors
        are correlated over its 5-px blocks, so the dropped columns add little information).
    row_step : int
        Image rows averaged into one before matching (vertical binning, see
        :func:`compute_disparity`), in both paths. 2 is about 1.5x faster and keeps the
        disparity precision, but the matching blocks then span ~3 cm of ground along the
        profiles: it low-passes them (PSD 0.3-0.7x the truth above 200 rad/m).
    ground_prior : bool
        Patch path: match the residual to the ground plane's disparity (``prior`` of
        :func:`compute_disparity`) instead of the disparity itself; see the module notes.
        Without it there is no coarse pass: one pass over ``height_tolerance``.
    equalize_subpixel : bool
        Correct SGM's pixel locking with :func:`equalize_subpixel` before triangulating, in
        the full-frame path and in the patch path without ``ground_prior``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    sgbm: SGBMConfig = Field(default_factory=SGBMConfig)
    outlier_filter: OutlierFilterConfig | None = Field(default_factory=OutlierFilterConfig)
    height_tolerance: float = Field(0.25, ge=0)
    fit_ground: bool = True
    coarse_scale: int = Field(4, ge=2, le=8)
    band_margin: float = Field(0.015, ge=0)
    min_band: float = Field(0.025, ge=0)
    crop_margin: float = Field(0.05, ge=0)
    margin_px: int = Field(2, ge=0)
    col_step: int = Field(2, ge=1, le=4)
    row_step: int = Field(1, ge=1, le=8)
    ground_prior: bool = True
    equalize_subpixel: bool = True

    @classmethod
    def from_file(cls, path: str | Path) -> StereoConfig:
        """Read ``configs/stereo.yaml``-style YAML or JSON; missing keys take the defaults.

        Raises
        ------
        FileFormatError
            The file cannot be read or parsed.
        SchemaError
            A key is unknown or a value invalid.
        """
        from rough_map.config import load_model

        return load_model(path, cls)


# --------------------------------------------------------------------------------------------
# Images and disparity
# --------------------------------------------------------------------------------------------


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as 8-bit grayscale, shape ``(height, width)``.

    Raises
    ------
    FileFormatError
        The file is missing or not an image OpenCV can decode.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise FileFormatError(path, "not an image OpenCV can decode")
    return image


def _as_gray(image: np.ndarray, name: str) -> np.ndarray:
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InputError(f"{name} image must be uint8 (8-bit), got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise InputError(
            f"{name} image must be (height, width) gray or (height, width, 3) BGR, "
            f"got shape {image.shape}"
        )
    return image


def _check_pair(
    left: np.ndarray, right: np.ndarray, calib: StereoCalibration | None
) -> tuple[np.ndarray, np.ndarray]:
    left_g, right_g = _as_gray(left, "left"), _as_gray(right, "right")
    if left_g.shape != right_g.shape:
        raise InputError(
            f"left and right images differ in size: {left_g.shape[::-1]} vs "
            f"{right_g.shape[::-1]} (width, height)"
        )
    if calib is not None and left_g.shape != (calib.height, calib.width):
        raise InputError(
            f"images are {left_g.shape[1]}x{left_g.shape[0]} px but the calibration is for "
            f"{calib.width}x{calib.height} px"
        )
    return left_g, right_g


def _sgbm_raw(
    left_g: np.ndarray,
    right_g: np.ndarray,
    config: SGBMConfig,
    rows: tuple[int, int],
    cols: tuple[int, int],
    disparities: tuple[int, int],
    row_step: int,
    prior: tuple[float, float, float] | None,
) -> np.ndarray:
    """OpenCV's raw SGBM output (int16, 1/16 px) for the rows and columns asked for.

    The arguments are those of :func:`compute_disparity`, checked (gray images, ``rows`` and
    ``cols`` inside them, ``disparities[1]`` a multiple of 16). Returns shape
    ``(ceil((r1 - r0) / row_step), c1 - c0)``; invalid pixels hold ``(min_d - 1) * 16``.
    """
    import cv2

    height, width = left_g.shape
    r0, r1 = rows
    c0, c1 = cols
    min_d, num_d = disparities
    max_d = min_d + num_d - 1
    n_out = -(-(r1 - r0) // row_step)
    r1_full = r0 + n_out * row_step  # may pass the image bottom: padded below
    # Widen the band by 2 blocks (of binned rows) each way, in whole groups of row_step rows.
    b0 = r0 - row_step * min(r0 // row_step, 2 * config.blockSize)
    b1 = min(height, r1_full + row_step * 2 * config.blockSize)
    b1 -= (b1 - b0) % row_step
    # Left pixels can only match once u - max_d >= 0: keep that much image left of c0, and
    # with negative disparities (residuals) |min_d| right of c1.
    a0 = max(0, c0 - max(max_d, 0) - config.blockSize)
    a1 = min(width, c1 + max(-min_d, 0) + config.blockSize)
    left_band = left_g[b0:b1, a0:a1]
    if prior is None:
        right_band = right_g[b0:b1, a0:a1]
    else:
        # right_w(u, v) = right(u - d0(u, v), v): a match at residual r means d = r + d0(u - r).
        # d0 is affine in (u, v), so the resampling is an affine warp (bicubic).
        a, b, c = prior
        warp = np.array([[1.0 - a, -b, (1.0 - a) * a0 - b * b0 - c], [0.0, 1.0, float(b0)]])
        right_band = cv2.warpAffine(
            right_g,
            warp,
            (a1 - a0, b1 - b0),
            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    if row_step > 1:
        size = (a1 - a0, (b1 - b0) // row_step)
        left_band = cv2.resize(left_band, size, interpolation=cv2.INTER_AREA)
        right_band = cv2.resize(right_band, size, interpolation=cv2.INTER_AREA)
    matcher = cv2.StereoSGBM.create(
        minDisparity=min_d,
        numDisparities=num_d,
        blockSize=config.blockSize,
        P1=config.P1,
        P2=config.P2,
        disp12MaxDiff=config.disp12MaxDiff,
        preFilterCap=config.preFilterCap,
        uniquenessRatio=config.uniquenessRatio,
        speckleWindowSize=config.speckleWindowSize,
        speckleRange=config.speckleRange,
        mode=_SGBM_MODES[config.mode],
    )
    raw = matcher.compute(np.ascontiguousarray(left_band), np.ascontiguousarray(right_band))
    first = (r0 - b0) // row_step
    return raw[first : first + n_out, c0 - a0 : c1 - a0]


def _disparity_range(config: SGBMConfig, disparities: tuple[int, int] | None) -> tuple[int, int]:
    if disparities is None:
        return config.minDisparity, config.numDisparities
    return int(disparities[0]), 16 * max(1, math.ceil(disparities[1] / 16))


def compute_disparity(
    left: np.ndarray,
    right: np.ndarray,
    config: SGBMConfig | None = None,
    rows: tuple[int, int] | None = None,
    *,
    cols: tuple[int, int] | None = None,
    disparities: tuple[int, int] | None = None,
    row_step: int = 1,
    prior: tuple[float, float, float] | None = None,
    equalize: bool = False,
    trim: int = 0,
) -> np.ndarray:
    """Disparity of a rectified pair by semi-global matching (OpenCV ``StereoSGBM``).

    Parameters
    ----------
    left, right : ndarray of uint8
        Rectified images, gray ``(H, W)`` or BGR ``(H, W, 3)``, same size.
    config : SGBMConfig, optional
        Matcher parameters; defaults to ``SGBMConfig()``.
    rows : (int, int), optional
        Compute only image rows ``r0 <= v < r1`` (px). SGM runs on the band widened by
        ``2 * blockSize`` rows on each side so that the matching blocks and the vertical
        aggregation paths are complete at the band's edges.
    cols : (int, int), optional
        Only left-image columns ``c0 <= u < c1`` (px) are needed; the images are cropped to
        what those columns can match before matching and the rest of the output is NaN.
    disparities : (int, int), optional
        ``(minDisparity, numDisparities)`` in px overriding the config's (``numDisparities``
        is rounded up to a multiple of 16). With a ``prior``, the range of ``d - d0``.
    row_step : int
        Average the images over groups of ``row_step`` rows before matching (vertical
        binning). SGM does ``row_step`` times less work and the disparity precision is kept,
        but the blocks then span ``row_step`` times more rows: on the rig's oblique view of
        the ground that low-passes the longitudinal profiles.
    prior : (float, float, float), optional
        Expected disparity ``d0(u, v) = a u + b v + c`` in px, e.g. of the flat ground
        (:func:`ground_disparity`; a plane's disparity is affine in ``(u, v)``). The right
        image is resampled (bicubic) so that ``d0`` becomes zero, SGM matches the residual
        ``d - d0``, and ``d`` is returned. Ground seen obliquely then looks fronto-parallel
        to the matcher: its blocks no longer straddle a disparity ramp (which costs SGM
        noise and a bias), and the search only has to cover the heights of interest.
    equalize : bool
        Correct pixel locking with :func:`equalize_subpixel` on what SGM matched (before the
        prior is added back). Leave it off with a prior: the residual of smooth ground
        crowds near zero instead of spreading over the sub-pixel range as the correction
        assumes.
    trim : int
        Drop matches within ``trim`` px of the ends of the searched range: surfaces outside
        the range match wrongly and such matches pile up there.

    Returns
    -------
    ndarray of float32, shape (ceil((r1 - r0) / row_step), W)
        Disparity ``u_left - u_right`` in px (full-resolution pixels, OpenCV's 1/16 px
        steps unless corrected); NaN where no valid match was found. Row ``i`` is image row
        ``r0 + row_step * i + (row_step - 1) / 2`` (the centre of its group).

    Raises
    ------
    InputError
        Images of different sizes or not 8-bit, or a band outside the image.
    """
    config = config or SGBMConfig()
    left_g, right_g = _check_pair(left, right, None)
    height, width = left_g.shape
    r0, r1 = (0, height) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= r0 < r1 <= height:
        raise InputError(f"rows must satisfy 0 <= r0 < r1 <= {height}, got ({r0}, {r1})")
    min_d, num_d = _disparity_range(config, disparities)
    max_d = min_d + num_d - 1
    c0, c1 = (0, width) if cols is None else (int(cols[0]), int(cols[1]))
    if not 0 <= c0 < c1 <= width:
        raise InputError(f"cols must satisfy 0 <= c0 < c1 <= {width}, got ({c0}, {c1})")
    if row_step < 1:
        raise InputError(f"row_step must be >= 1, got {row_step}")
    n_out = -(-(r1 - r0) // row_step)
    raw = _sgbm_raw(left_g, right_g, config, (r0, r1), (c0, c1), (min_d, num_d), row_step, prior)
    band = raw.astype(np.float32) * np.float32(1.0 / 16.0)
    band[raw < min_d * 16] = np.nan
    if trim > 0:
        with np.errstate(invalid="ignore"):
            band[(band < min_d + trim) | (band > max_d - trim)] = np.nan
    if equalize:
        band = equalize_subpixel(band)
    if prior is not None:
        u = np.arange(c0, c1, dtype=np.float64)[None, :]
        v = (r0 + row_step * np.arange(raw.shape[0]) + 0.5 * (row_step - 1))[:, None]
        band = (band + prior[0] * (u - band) + prior[1] * v + prior[2]).astype(np.float32)
    out = np.full((n_out, width), np.nan, dtype=np.float32)
    out[: raw.shape[0], c0:c1] = band
    log.debug(
        "SGBM rows %d-%d/%d cols %d-%d disparities %d+%d: %.0f%% valid",
        r0,
        r1,
        row_step,
        c0,
        c1,
        min_d,
        num_d,
        100.0 * np.isfinite(band).mean(),
    )
    return out


def equalize_subpixel(disp: np.ndarray, min_span: float = 16.0) -> np.ndarray:
    """Undo SGM's pixel locking by equalising the histogram of the sub-pixel parts.

    SGM refines each integer disparity by fitting a parabola to the costs at ``d - 1, d,
    d + 1``; the costs are not parabolic, so the refined values crowd towards integers
    ("pixel locking", Shimizu and Okutomi 2001): on the rig's slanted ground the error is a
    sawtooth of +-0.2 px with a period of one pixel of disparity, about 1 cm along the
    ground, right inside the wavelengths the PSD estimator fits. Where the map holds many
    pixels whose true disparities spread over many integers (ground seen obliquely), the true
    sub-pixel parts are uniformly distributed, so mapping each observed part
    ``r = d - round(d)`` through the empirical CDF of all of them, ``r' = F(r) - 1/2``,
    restores a uniform distribution and removes most of the sawtooth (measured on rendered
    ground: the error's dependence on the true sub-pixel part drops from -0.20..+0.09 px to
    -0.05..0 px). The cut is at ``r = -1/2``, where fewest values fall.

    Parameters
    ----------
    disp : ndarray
        Disparities in px (NaN where invalid), e.g. from :func:`compute_disparity`.
    min_span : float
        Smallest spread (5th to 95th percentile) of the valid disparities, px, for which the
        uniform assumption is made; below it ``disp`` is returned unchanged.

    Returns
    -------
    ndarray of float32
        Corrected disparities, px, NaN where ``disp`` is.
    """
    disp = np.asarray(disp, dtype=np.float32)
    values = disp[np.isfinite(disp)]
    if values.size < 1000:
        return disp.copy()
    lo, hi = np.percentile(values, [5, 95])
    if hi - lo < min_span:
        return disp.copy()
    whole = np.floor(disp + 0.5)
    # OpenCV's disparities are multiples of 1/16 px: 16 possible sub-pixel parts.
    bins = np.clip(np.rint((disp - whole) * 16), -8, 7)
    finite = np.isfinite(bins)
    index = bins[finite].astype(np.int64) + 8
    counts = np.bincount(index, minlength=16)
    cdf = (np.cumsum(counts) - 0.5 * counts) / counts.sum() - 0.5
    out = np.full_like(disp, np.nan)
    out[finite] = whole[finite] + cdf[index]
    return out


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


#: A plane ``z = a x + b y + c`` of the vehicle frame, m.
Plane = tuple[float, float, float]


@dataclass(frozen=True)
class PatchWindow:
    """The part of the left image, and the disparities, that can see the patch of interest.

    Attributes
    ----------
    rows : (int, int)
        Row band ``r0 <= v < r1``, px.
    cols : (int, int)
        Column band ``c0 <= u < c1``, px.
    disparities : (int, int)
        ``(minDisparity, numDisparities)`` in px, ``numDisparities`` a multiple of 16.
    prior : (float, float, float)
        Disparity of the ground plane ``d0(u, v) = a u + b v + c``, px
        (:func:`ground_disparity`).
    residual : (int, int)
        ``(minDisparity, numDisparities)`` of ``d - d0`` over the window, px. When
        ``numDisparities`` is rounded up to a multiple of 16, the slack is shared between both
        ends of the range.
    plane : (float, float, float)
        The ground plane ``z = a x + b y + c`` of the vehicle frame (m) the window is built
        around.
    band : (float, float)
        Heights ``(lo, hi)`` in m above that plane the window sees, ``lo < 0 < hi``.
    """

    rows: tuple[int, int]
    cols: tuple[int, int]
    disparities: tuple[int, int]
    prior: tuple[float, float, float]
    residual: tuple[int, int]
    plane: tuple[float, float, float] = (0.0, 0.0, 0.0)
    band: tuple[float, float] = (-0.15, 0.15)


def level_plane(roll: float = 0.0, pitch: float = 0.0, ground_z: float = 0.0) -> Plane:
    """The level ground seen from a tilted vehicle: ``z = a x + b y + c`` in the vehicle frame.

    The vehicle -> level rotation is ``Ry(pitch) Rx(roll)`` (as
    :func:`rough_map.patch.rotation_matrix`, pitch positive nose down, roll positive left side
    up); the level ground is the plane ``ground_z`` m above the vehicle origin in the level
    frame. With no tilt it is ``z = ground_z``.
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    # Third row of Ry(pitch) Rx(roll): the level frame's z axis in vehicle coordinates.
    nx, ny, nz = -sp, cp * sr, cp * cr
    if nz <= 0.1:
        raise InputError(f"roll {roll} rad and pitch {pitch} rad tilt the vehicle too far")
    return (-nx / nz, -ny / nz, ground_z / nz)


def patch_window(
    calib: StereoCalibration,
    ahead: float = PATCH_AHEAD,
    size: float = PATCH_SIZE,
    ground_z: float = 0.0,
    *,
    lateral: float = 0.0,
    height_tolerance: float | tuple[float, float] = 0.15,
    crop_margin: float = 0.05,
    margin_px: int = 8,
    plane: Plane | None = None,
    clip: bool = False,
) -> PatchWindow:
    """Image rows, columns and disparities that see the patch of interest.

    The patch is the square ``|x - ahead| <= size/2``, ``|y - lateral| <= size/2`` of the
    vehicle frame widened by ``crop_margin``, on the ground plane (``z = ground_z``, or
    ``plane``) widened by ``height_tolerance``. The corners of that box are projected into the
    left image; a box projects inside the convex hull of its corners, so their extremes bound
    it, and bound the residual ``d - d0`` too (affine in ``(u, v)`` on each face).

    Parameters
    ----------
    calib : StereoCalibration
        The rig.
    ahead : float
        Distance of the patch centre ahead of the vehicle origin, m.
    size : float
        Side of the patch, m.
    ground_z : float
        Height of flat ground in the vehicle frame, m; ignored if ``plane`` is given.
    lateral : float
        Offset of the patch centre to the left (+y), m.
    height_tolerance : float or (float, float)
        Heights above and below the ground the window must still see, m: ``t`` for
        ``-t..+t``, or ``(lo, hi)``.
    crop_margin : float
        Margin around the patch, m.
    margin_px : int
        Extra rows and columns on each side, px.
    plane : (float, float, float), optional
        Ground plane ``z = a x + b y + c`` of the vehicle frame (m), e.g.
        :func:`level_plane` of the IMU's tilt, or the plane fitted by the patch path's
        coarse pass.
    clip : bool
        Clip the window to the images instead of raising when the box leaves them (the
        patch itself, on the ground, must still be inside).

    Returns
    -------
    PatchWindow

    Raises
    ------
    InputError
        The patch is behind the camera or not entirely inside both images.
    """
    half = size / 2.0 + crop_margin
    if isinstance(height_tolerance, tuple | list):
        lo, hi = float(height_tolerance[0]), float(height_tolerance[1])
    else:
        lo, hi = -float(height_tolerance), float(height_tolerance)
    if not lo <= 0 <= hi:
        raise InputError(f"the height band must contain 0 (the ground), got ({lo}, {hi}) m")
    pa, pb, pc = (0.0, 0.0, float(ground_z)) if plane is None else map(float, plane)
    corners = np.array(
        [
            [x, y, pa * x + pb * y + pc + dz]
            for x in (ahead - half, ahead + half)
            for y in (lateral - half, lateral + half)
            for dz in (lo, 0.0, hi)
        ]
    )
    transform = calib.T_vehicle_camera
    cam = (corners - transform[:3, 3]) @ transform[:3, :3]  # R^T (p - t)
    if np.any(cam[:, 2] <= 0.05):
        raise InputError("the patch of interest is behind or too close to the left camera")
    u = calib.fx * cam[:, 0] / cam[:, 2] + calib.cx
    v = calib.fy * cam[:, 1] / cam[:, 2] + calib.cy
    d = calib.focal_baseline / cam[:, 2]
    # With clip, only the ground corners (dz = 0) must be inside the images.
    check = np.arange(len(u)) % 3 == 1 if clip else slice(None)
    uc, vc, dc = u[check], v[check], d[check]
    if uc.min() < 0 or uc.max() > calib.width - 1 or vc.min() < 0 or vc.max() > calib.height - 1:
        raise InputError(
            f"the patch of interest ({size:g} m square, {ahead:g} m ahead) is not inside the "
            f"left image: it spans u {uc.min():.0f}..{uc.max():.0f}, "
            f"v {vc.min():.0f}..{vc.max():.0f}"
        )
    if (uc - dc).min() < 0:
        raise InputError(
            "the patch of interest is not inside the right image (u - d reaches "
            f"{(uc - dc).min():.0f} px)"
        )
    prior = ground_disparity(calib, plane=(pa, pb, pc))
    r = d - (prior[0] * u + prior[1] * v + prior[2])
    residual = _search_range(math.floor(r.min()) - 2, math.ceil(r.max()) + 2)
    rows = (
        max(0, math.floor(v.min()) - margin_px),
        min(calib.height, math.ceil(v.max()) + 1 + margin_px),
    )
    cols = (
        max(0, math.floor(u.min()) - margin_px),
        min(calib.width, math.ceil(u.max()) + 1 + margin_px),
    )
    disparities = _search_range(max(0, math.floor(d.min()) - 2), math.ceil(d.max()) + 2)
    return PatchWindow(
        rows=rows,
        cols=cols,
        disparities=(max(0, disparities[0]), disparities[1]),
        prior=prior,
        residual=residual,
        plane=(pa, pb, pc),
        band=(lo, hi),
    )


def _search_range(lo: int, hi: int) -> tuple[int, int]:
    """``(minDisparity, numDisparities)`` covering ``lo..hi`` px, the rounding up of
    ``numDisparities`` to a multiple of 16 shared between both ends."""
    num = 16 * math.ceil((hi - lo) / 16)
    return lo - (num - (hi - lo)) // 2, num


def ground_disparity(
    calib: StereoCalibration, ground_z: float = 0.0, *, plane: Plane | None = None
) -> tuple[float, float, float]:
    """Disparity of a ground plane of the vehicle frame, ``d0 = a u + b v + c``.

    The plane is ``z = ground_z``, or ``z = pa x + pb y + pc`` if ``plane = (pa, pb, pc)``,
    i.e. ``g . p = pc`` with ``g = (-pa, -pb, 1)``. A left-camera ray through pixel ``(u, v)``
    with unit depth has vehicle-frame direction ``m = R (xn, yn, 1)``, ``xn = (u - cx) / fx``,
    ``yn = (v - cy) / fy``, from the camera centre ``t``; it meets the plane at depth
    ``Z = (pc - g . t) / (g . m)``, so ``d0 = fx B / Z`` is affine in ``(u, v)``. Pixels
    looking above the horizon get ``d0 <= 0``.

    Returns
    -------
    (float, float, float)
        ``(a, b, c)``: px per px of u, px per px of v, px.
    """
    transform = calib.T_vehicle_camera
    pa, pb, pc = (0.0, 0.0, float(ground_z)) if plane is None else map(float, plane)
    g = np.array([-pa, -pb, 1.0])
    height = pc - float(g @ transform[:3, 3])
    if height >= 0:
        raise InputError(f"the camera must be above the ground (ground plane z = {pc} m)")
    k = calib.focal_baseline / height
    r20, r21, r22 = g @ transform[:3, :3]
    a = k * r20 / calib.fx
    b = k * r21 / calib.fy
    c = k * (r22 - r20 * calib.cx / calib.fx - r21 * calib.cy / calib.fy)
    return (float(a), float(b), float(c))


def patch_rows(
    calib: StereoCalibration,
    ahead: float = PATCH_AHEAD,
    size: float = PATCH_SIZE,
    ground_z: float = 0.0,
    *,
    lateral: float = 0.0,
    height_tolerance: float = 0.15,
    margin_px: int = 8,
) -> tuple[int, int]:
    """Row band ``(r0, r1)`` of the left image that sees the patch; see :func:`patch_window`."""
    return patch_window(
        calib,
        ahead,
        size,
        ground_z,
        lateral=lateral,
        height_tolerance=height_tolerance,
        margin_px=margin_px,
    ).rows


def disparity_to_points(
    disp: np.ndarray, calib: StereoCalibration, rows_offset: int = 0, row_step: int = 1
) -> np.ndarray:
    """3-D points in the left camera frame from a disparity map.

    Parameters
    ----------
    disp : ndarray, shape (h, W)
        Disparity in px (NaN or <= 0 where invalid), e.g. from :func:`compute_disparity`.
    calib : StereoCalibration
        The rig.
    rows_offset : int
        Image row of ``disp[0]``, px (``r0`` of a row band).
    row_step : int
        Rows binned per row of ``disp`` (see :func:`compute_disparity`): row ``i`` is image
        row ``rows_offset + row_step * i + (row_step - 1) / 2``.

    Returns
    -------
    ndarray of float64, shape (N, 3)
        ``(X, Y, Z)`` in m in the left camera frame (OpenCV), one per valid pixel, in row-major
        pixel order: ``Z = fx B / d``, ``X = (u - cx) Z / fx``, ``Y = (v - cy) Z / fy``.
    """
    disp = np.asarray(disp)
    if disp.ndim != 2:
        raise InputError(f"disp must be 2-D, got shape {disp.shape}")
    height, width = disp.shape
    with np.errstate(invalid="ignore"):
        valid = disp > 0  # False for NaN
    z = calib.focal_baseline / disp[valid].astype(np.float64)
    # Normalised image coordinates per column and per row, picked per valid pixel.
    x_norm = (np.arange(width) - calib.cx) / calib.fx
    rows = rows_offset + row_step * np.arange(height) + 0.5 * (row_step - 1)
    y_norm = (rows - calib.cy) / calib.fy
    points = np.empty((z.size, 3))
    points[:, 0] = np.broadcast_to(x_norm, disp.shape)[valid] * z
    points[:, 1] = np.broadcast_to(y_norm[:, None], disp.shape)[valid] * z
    points[:, 2] = z
    return points


def to_vehicle(points: np.ndarray, calib: StereoCalibration) -> np.ndarray:
    """Left-camera points (N, 3), m, to the vehicle frame (N, 3), m."""
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {points.shape}")
    transform = calib.T_vehicle_camera
    # Column by column rather than ``points @ R.T``: an (N, 3) x (3, 3) product goes through
    # BLAS, whose threads cost more than the arithmetic (and spin on a busy machine).
    x, y, z = (np.ascontiguousarray(c) for c in points.T)
    out = np.empty_like(points)
    for i in range(3):
        r = transform[i]
        out[:, i] = r[0] * x + r[1] * y + r[2] * z + r[3]
    return out


def _reprojection(
    calib: StereoCalibration,
    origin: tuple[float, float],
    steps: tuple[float, float],
    prior: tuple[float, float, float] | None,
) -> np.ndarray:
    """4x4 ``Q`` for ``cv2.reprojectImageTo3D`` from raw SGBM output straight to the vehicle.

    Pixel ``(j, i)`` of the raw map is image pixel ``u = u0 + su j``, ``v = v0 + sv i``
    (``origin = (u0, v0)``, ``steps = (su, sv)``); its value is ``16 r``, ``r`` the matched
    disparity, or the residual to ``prior`` (then ``d = r + d0(u - r, v)``). Every step, from
    ``(j, i, 16 r)`` to ``(u, v, d)``, to the camera frame, to the vehicle frame, is linear in
    homogeneous coordinates, so one matrix does all: one pass, no float64 temporaries.
    """
    u0, v0 = origin
    su, sv = steps
    pa, pb, pc = prior if prior is not None else (0.0, 0.0, 0.0)
    to_image = np.array(
        [
            [su, 0.0, 0.0, u0],
            [0.0, sv, 0.0, v0],
            [pa * su, pb * sv, (1.0 - pa) / 16.0, pa * u0 + pb * v0 + pc],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    ratio = calib.fx / calib.fy
    to_camera = np.array(
        [
            [1.0, 0.0, 0.0, -calib.cx],
            [0.0, ratio, 0.0, -calib.cy * ratio],
            [0.0, 0.0, 0.0, calib.fx],
            [0.0, 0.0, 1.0 / calib.baseline, 0.0],
        ]
    )
    return calib.T_vehicle_camera @ to_camera @ to_image


def _window_xyz(
    raw: np.ndarray,
    calib: StereoCalibration,
    window: PatchWindow,
    *,
    ahead: float,
    half: float,
    lateral: float,
    trim: int = 1,
    row_step: int = 1,
    col_step: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicle-frame coordinates of raw SGBM output (over the window's residual search) as
    float32 images ``x, y, z``, the height ``dz`` above the window's plane, and the mask of the
    pixels to keep: matched inside the search range less ``trim`` px at each end, over the
    footprint ``|x - ahead|, |y - lateral| <= half`` and within the window's ``band``.
    ``col_step`` keeps every ``col_step``-th column only.
    """
    import cv2

    if col_step > 1:
        raw = raw[:, ::col_step]
    raw = np.ascontiguousarray(raw)
    min_d, num_d = window.residual
    q = _reprojection(
        calib,
        (window.cols[0], window.rows[0] + 0.5 * (row_step - 1)),
        (col_step, row_step),
        window.prior,
    )
    x, y, z = cv2.split(cv2.reprojectImageTo3D(raw, q))
    keep = (raw >= 16 * (min_d + trim)) & (raw <= 16 * (min_d + num_d - 1 - trim))
    keep &= np.abs(x - np.float32(ahead)) <= np.float32(half)
    keep &= np.abs(y - np.float32(lateral)) <= np.float32(half)
    pa, pb, pc = (np.float32(v) for v in window.plane)
    lo, hi = window.band
    dz = z - pa * x - pb * y - pc
    keep &= (dz >= np.float32(lo)) & (dz <= np.float32(hi))
    return x, y, z, dz, keep


def _window_cloud(
    raw: np.ndarray, calib: StereoCalibration, window: PatchWindow, **kwargs
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept pixels of :func:`_window_xyz` as float32 columns ``x, y, z, dz``."""
    x, y, z, dz, keep = _window_xyz(raw, calib, window, **kwargs)
    return x[keep], y[keep], z[keep], dz[keep]


def _plane_from_disparity(calib: StereoCalibration, prior: tuple[float, float, float]) -> Plane:
    """The plane ``z = a x + b y + c`` of the vehicle frame whose disparity is ``prior``
    (the inverse of :func:`ground_disparity`)."""
    al, be, ga = prior
    m = np.array([al * calib.fx, be * calib.fy, ga + al * calib.cx + be * calib.cy])
    transform = calib.T_vehicle_camera
    w = transform[:3, :3] @ m  # = k g, g = (-a, -b, 1), k = fx B / (c - g . t)
    if not w[2] < 0:
        raise InputError("the ground plane's disparity puts the camera below the ground")
    g = w / w[2]
    return (float(-g[0]), float(-g[1]), float(calib.focal_baseline / w[2] + g @ transform[:3, 3]))


def _align_plane(
    left: np.ndarray,
    right: np.ndarray,
    rows: tuple[int, int],
    cols: tuple[int, int],
    prior: tuple[float, float, float],
    mask: np.ndarray,
    iterations: int = 5,
) -> tuple[float, float, float] | None:
    """Refine a plane's disparity ``d = a u + b v + c`` by aligning the images directly.

    Gauss-Newton on ``left(u, v) = right(u - d(u, v), v) + o`` (a brightness offset ``o``)
    over the ``mask`` pixels of ``rows x cols``. Three parameters from thousands of pixels:
    no pixel locking, so the plane is found to a few hundredths of a pixel, which SGM around
    it cannot do for a surface that is itself nearly that plane (its residual disparities
    then all lock onto the same integer). Returns None if it does not converge.
    """
    import cv2

    if np.count_nonzero(mask) < 100:
        return None
    # Only the bounding box of the mask (the patch) is needed.
    in_rows = np.flatnonzero(mask.any(axis=1))
    in_cols = np.flatnonzero(mask.any(axis=0))
    mask = mask[in_rows[0] : in_rows[-1] + 1, in_cols[0] : in_cols[-1] + 1]
    r0, r1 = rows[0] + int(in_rows[0]), rows[0] + int(in_rows[-1]) + 1
    c0, c1 = cols[0] + int(in_cols[0]), cols[0] + int(in_cols[-1]) + 1
    ref = left[r0:r1, c0:c1].astype(np.float32)
    weight = mask.astype(np.float32)
    v, u = np.mgrid[r0:r1, c0:c1].astype(np.float32)
    u -= np.float32(0.5 * (c0 + c1))  # centred: a better conditioned system
    v -= np.float32(0.5 * (r0 + r1))
    uc, vc = 0.5 * (c0 + c1), 0.5 * (r0 + r1)
    a, b, c = prior
    c += a * uc + b * vc  # d = a (u - uc) + b (v - vc) + c
    for k in range(iterations):
        # right_w(j, i) = right(u - d(u, v), v) for u = c0 + j, v = r0 + i.
        warp = np.array(
            [
                [1.0 - a, -b, (1.0 - a) * c0 - b * r0 - (c - a * uc - b * vc)],
                [0.0, 1.0, float(r0)],
            ]
        )
        warped = cv2.warpAffine(
            right,
            warp,
            (c1 - c0, r1 - r0),
            flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.float32)
        # d right / d x at the sampled points (the warp stretches x by 1 - a).
        gx = cv2.Sobel(warped, cv2.CV_32F, 1, 0, ksize=3, scale=0.125 / (1.0 - a))
        error = ref - warped
        gw = gx * weight
        # Residual e = J . delta with J = -gx (u, v, 1) for (a, b, c) and 1 for the offset.
        cols_j = (gw * u, gw * v, gw, weight)
        signs = (-1.0, -1.0, -1.0, 1.0)
        jtj = np.empty((4, 4))
        jte = np.empty(4)
        full = (gx * u, gx * v, gx, np.ones_like(gx))
        for i in range(4):
            jte[i] = signs[i] * float((cols_j[i] * error).sum())
            for j in range(i, 4):
                jtj[i, j] = jtj[j, i] = signs[i] * signs[j] * float((cols_j[i] * full[j]).sum())
        try:
            step = np.linalg.solve(jtj, jte)
        except np.linalg.LinAlgError:
            return None
        a, b, c = a + step[0], b + step[1], c + step[2]
        # The image noise leaves steps of ~0.01 px: converged below that, or close to it.
        change = abs(step[2]) + abs(step[0]) * (c1 - c0) / 2 + abs(step[1]) * (r1 - r0) / 2
        if change < 0.01 or (k == iterations - 1 and change < 0.05):
            return (float(a), float(b), float(c - a * uc - b * vc))
    log.debug("plane alignment did not converge (last step %s)", step)
    return None


def _scaled(calib: StereoCalibration, scale: int) -> StereoCalibration:
    """The rig seen through images binned ``scale`` x ``scale`` (pixel centres kept)."""
    return calib.model_copy(
        update={
            "fx": calib.fx / scale,
            "fy": calib.fy / scale,
            "cx": (calib.cx + 0.5) / scale - 0.5,
            "cy": (calib.cy + 0.5) / scale - 0.5,
            "width": calib.width // scale,
            "height": calib.height // scale,
        }
    )


def _fit_plane(
    points: np.ndarray, centre: tuple[float, float]
) -> tuple[Plane, np.ndarray, np.ndarray]:
    """Robust least-squares plane ``z = a x + b y + c`` (trimmed at 3 sigma, sigma from the
    MAD, three times); returns it, the heights of all points above it and the inlier mask."""
    x = points[:, 0].astype(np.float64) - centre[0]
    y = points[:, 1].astype(np.float64) - centre[1]
    z = points[:, 2].astype(np.float64)
    keep = np.ones(len(z), dtype=bool)
    coef = np.zeros(3)
    res = z
    for _ in range(3):
        xs, ys, zs = x[keep], y[keep], z[keep]
        # 3x3 normal equations from elementwise sums: dot products would go through BLAS,
        # whose threads cost more than the arithmetic (and spin on a busy machine).
        sxy = float((xs * ys).sum())
        sx, sy = float(xs.sum()), float(ys.sum())
        ata = np.array(
            [
                [float((xs * xs).sum()), sxy, sx],
                [sxy, float((ys * ys).sum()), sy],
                [sx, sy, float(len(zs))],
            ]
        )
        atb = np.array([float((xs * zs).sum()), float((ys * zs).sum()), float(zs.sum())])
        coef = np.linalg.solve(ata, atb)
        res = z - (coef[0] * x + coef[1] * y + coef[2])
        kept = res[keep]
        sigma = 1.4826 * float(np.median(np.abs(kept - np.median(kept))))
        new = np.abs(res) <= max(3.0 * sigma, 0.005)
        if np.array_equal(new, keep):
            break
        keep = new
    a, b, c = (float(v) for v in coef)
    return (a, b, c - a * centre[0] - b * centre[1]), res, keep


def fit_ground(
    left: np.ndarray,
    right: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    ahead: float = PATCH_AHEAD,
    size: float = PATCH_SIZE,
    lateral: float = 0.0,
    plane: Plane | None = None,
) -> tuple[Plane, tuple[float, float]] | None:
    """The coarse pass of the patch path: the ground plane under the patch and its relief.

    SGM on the pair binned ``config.coarse_scale`` times each way, over the patch and
    ``config.height_tolerance`` m above and below ``plane`` (default ``z = 0``, or e.g.
    :func:`level_plane` of the IMU's tilt), on the residual to that plane's disparity. A plane
    is fitted to the points over the patch footprint (least squares, trimmed at 3 robust
    sigma), then refined by aligning the binned images on it directly (see the module notes:
    SGM alone leaves it a few tenths of a pixel off). The heights of the points above it,
    0.2th to 99.8th percentile, widened by ``config.band_margin`` and to at least
    ``+-config.min_band``, give the band the fine pass searches. The binned images are 16x
    cheaper to match and need a quarter of the disparities: 15-20 ms of CPU in all.

    Parameters
    ----------
    left, right : ndarray of uint8
        Rectified pair, gray or BGR.
    calib : StereoCalibration
        The rig.
    config : StereoConfig, optional
        Settings; defaults to ``StereoConfig()``.
    ahead, size, lateral : float
        The patch, m (see :func:`stereo_to_cloud`).
    plane : (float, float, float), optional
        Expected ground ``z = a x + b y + c`` in the vehicle frame, m.

    Returns
    -------
    ((float, float, float), (float, float)) or None
        The plane ``(a, b, c)`` and the height band ``(lo, hi)`` in m around it; None when
        fewer than 10 % of the patch's coarse pixels matched (no texture, occlusion).
    """
    import cv2

    config = config or StereoConfig()
    left_g, right_g = _check_pair(left, right, calib)
    scale = config.coarse_scale
    small = _scaled(calib, scale)
    size_px = (small.width, small.height)
    crop = (small.height * scale, small.width * scale)
    left_s = cv2.resize(left_g[: crop[0], : crop[1]], size_px, interpolation=cv2.INTER_AREA)
    right_s = cv2.resize(right_g[: crop[0], : crop[1]], size_px, interpolation=cv2.INTER_AREA)
    tol = config.height_tolerance
    window = patch_window(
        small,
        ahead,
        size,
        lateral=lateral,
        height_tolerance=tol,
        crop_margin=config.crop_margin,
        margin_px=2,
        plane=plane,
        clip=True,
    )
    raw = _sgbm_raw(
        left_s, right_s, config.sgbm, window.rows, window.cols, window.residual, 1, window.prior
    )
    half = size / 2.0 + config.crop_margin
    x, y, z, _, keep = _window_xyz(raw, small, window, ahead=ahead, half=half, lateral=lateral)
    expected = (window.rows[1] - window.rows[0]) * (window.cols[1] - window.cols[0])
    n = int(np.count_nonzero(keep))
    if n < max(100, 0.1 * expected):
        log.debug("coarse ground fit: only %d points, no fit", n)
        return None
    points = np.column_stack([x[keep], y[keep], z[keep]])
    fitted, heights, inliers = _fit_plane(points, (ahead, lateral))
    # SGM's plane is off by a few tenths of a pixel where the ground is nearly planar: refine
    # it on the images themselves, over the plane's inliers.
    mask = np.zeros_like(keep)
    mask[keep] = inliers
    sgm = ground_disparity(small, plane=fitted)
    aligned = _align_plane(left_s, right_s, window.rows, window.cols, sgm, mask)
    if aligned is not None:
        # Check the alignment stayed near SGM's plane (within 1 binned px over the window).
        (r0, r1), (c0, c1) = window.rows, window.cols
        shift = max(
            abs((aligned[0] - sgm[0]) * u + (aligned[1] - sgm[1]) * v + (aligned[2] - sgm[2]))
            for u in (c0, c1)
            for v in (r0, r1)
        )
        try:
            if shift > 1.0:
                raise InputError(f"it moved {shift:.2f} px from SGM's plane")
            fitted = _plane_from_disparity(small, aligned)
        except InputError as exc:
            log.debug("aligned plane rejected: %s", exc)
        else:
            heights = points[:, 2] - (
                fitted[0] * points[:, 0] + fitted[1] * points[:, 1] + fitted[2]
            )
    lo, hi = np.quantile(heights, [0.002, 0.998])
    lo = max(-tol, min(float(lo) - config.band_margin, -config.min_band))
    hi = min(tol, max(float(hi) + config.band_margin, config.min_band))
    log.debug(
        "coarse ground fit: %d points, plane z = %.4f x + %.4f y + %.4f, band %.3f..%.3f m",
        n,
        *fitted,
        lo,
        hi,
    )
    return fitted, (lo, hi)


# --------------------------------------------------------------------------------------------
# Statistical moving-window filter
# --------------------------------------------------------------------------------------------


def statistical_outlier_mask(
    points: np.ndarray,
    cell: float = 0.024,
    k: float = 3.5,
    min_tolerance: float = 0.003,
    min_count: int = 3,
) -> np.ndarray:
    """Inliers of the statistical moving-window filter; see :func:`statistical_outlier_filter`.

    Returns
    -------
    ndarray of bool, shape (N,)
        True for the points kept.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must have shape (N, 3), got {points.shape}")
    if not cell > 0:
        raise InputError(f"cell must be positive (m), got {cell}")
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    if points.dtype != np.float32:
        points = points.astype(np.float64, copy=False)
    x, y, z = (np.ascontiguousarray(c) for c in points.T)
    return _window_outlier_mask(
        x, y, z, (float(x.min()), float(y.min())), cell, k, min_tolerance, min_count
    )


def _window_outlier_mask(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    origin: tuple[float, float],
    cell: float,
    k: float,
    min_tolerance: float,
    min_count: int,
) -> np.ndarray:
    """The filter on coordinate columns, windows ``cell`` m square from ``origin`` (x0, y0).

    One sort orders the points by window, then by height: the window index plus the height
    scaled into [0, 1); the medians are read at each window's middle. float64 keeps the
    height to ~1e-11 of the cloud's z range. float32 columns are sorted in float32 (twice as
    fast) when that still resolves heights to 1/32 of ``min_tolerance`` (2^24 steps share
    window index and height).
    """
    n = z.shape[0]
    ix = ((x - x.dtype.type(origin[0])) * x.dtype.type(1.0 / cell)).astype(np.int32)
    iy = ((y - y.dtype.type(origin[1])) * y.dtype.type(1.0 / cell)).astype(np.int32)
    np.maximum(ix, 0, out=ix)  # float rounding at the origin
    np.maximum(iy, 0, out=iy)
    nx = int(ix.max()) + 1
    n_keys = nx * (int(iy.max()) + 1)
    key = iy * nx + ix if n_keys < 2**31 else iy.astype(np.int64) * nx + ix
    z0 = float(z.min())
    span = float(z.max()) - z0
    bits = max(1, n_keys - 1).bit_length()  # of the window index
    dtype = (
        np.float32
        if z.dtype == np.float32
        and min_tolerance > 0
        and span * 2.0 ** (bits - 22) <= min_tolerance / 32
        else np.float64
    )
    # Largest fraction that cannot round up into the next window index.
    top = 1.0 - 2.0 ** (bits - (22 if dtype == np.float32 else 51))
    scale = span / top or 1.0
    zs = (z.astype(dtype, copy=False) - dtype(z0)) * dtype(1.0 / scale)
    np.minimum(zs, dtype(top), out=zs)
    fkey = key.astype(dtype)
    keyed = fkey + zs
    g = np.sort(keyed)
    key_sorted = g.astype(np.int64)
    starts = np.flatnonzero(np.diff(key_sorted, prepend=-1))
    counts = np.diff(starts, append=n)
    cells = key_sorted[starts]
    centre = dtype(0.5) * (g[starts + (counts - 1) // 2] + g[starts + counts // 2])  # + median
    if n_keys <= 4 * n + 1024:
        lookup = np.empty(n_keys, dtype=np.int32)
        lookup[cells] = np.arange(len(cells), dtype=np.int32)
        window = lookup[key]
    else:  # sparse clouds over large areas: no dense table
        window = np.searchsorted(cells, key)
    deviation = np.abs(keyed - centre[window])  # < 1, in units of scale
    np.minimum(deviation, dtype(top), out=deviation)
    # Same trick for the MAD: the windows (hence starts and counts) are the same.
    d = np.sort(fkey + deviation)
    mad = dtype(0.5) * (d[starts + (counts - 1) // 2] + d[starts + counts // 2]) - cells
    tolerance = np.maximum(dtype(k * 1.4826) * mad, dtype(min_tolerance / scale))
    tolerance[counts < min_count] = -1.0  # isolated windows: drop every point
    keep = deviation <= tolerance[window]
    log.debug("outlier filter: %d of %d points rejected", n - int(np.count_nonzero(keep)), n)
    return keep


def statistical_outlier_filter(
    points: np.ndarray,
    cell: float = 0.024,
    k: float = 3.5,
    min_tolerance: float = 0.003,
    min_count: int = 3,
) -> np.ndarray:
    """The paper's statistical moving-window filter: drop height outliers, window by window.

    The ground plane (x, y) is cut into square windows of side ``cell``. In each window the
    median height ``m`` and the median absolute deviation ``MAD = median |z - m|`` are
    computed, and a point is kept if ``|z - m| <= max(k * 1.4826 * MAD, min_tolerance)``
    (``1.4826 * MAD`` estimates the standard deviation of Gaussian heights, and unlike the
    standard deviation itself is not inflated by the outliers it is meant to find). Windows
    holding fewer than ``min_count`` points are dropped as isolated. The windows are fixed
    squares, not centred on each point. It is vectorised, two sorts of ``window index + scaled
    height``, in float32 for float32 points when that resolves heights to 1/32 of
    ``min_tolerance``: 15-20 ms of CPU for the 285 000 points of a stereo patch (float32) on
    a busy 2-core machine, 25-35 ms in float64, where open3d's ``remove_statistical_outlier``
    (a k-nearest-neighbour distance test) took 1.1-1.5 s in the same run. The patch path of
    :func:`stereo_to_cloud` runs it on the heights above the fitted ground plane, in windows
    aligned on the patch's corner.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in m in a frame with z up (vehicle or world).
    cell : float
        Window side, m. Several grid cells of the patch (8 mm) wide, small enough that the
        terrain's own relief inside a window is mostly below the noise.
    k : float
        Threshold in robust standard deviations.
    min_tolerance : float
        Smallest tolerated deviation, m.
    min_count : int
        Smallest number of points in a window.

    Returns
    -------
    ndarray, shape (M, 3)
        The points kept, in their original order.
    """
    return np.asarray(points)[statistical_outlier_mask(points, cell, k, min_tolerance, min_count)]


# --------------------------------------------------------------------------------------------
# The pipeline
# --------------------------------------------------------------------------------------------


def crop_to_patch(
    points: np.ndarray,
    ahead: float = PATCH_AHEAD,
    size: float = PATCH_SIZE,
    margin: float = 0.05,
    height_tolerance: float | None = None,
    ground_z: float = 0.0,
    lateral: float = 0.0,
) -> np.ndarray:
    """Points of the vehicle frame over the patch footprint.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Points in the vehicle frame, m.
    ahead, size : float
        Patch centre distance ahead of the vehicle origin and patch side, m.
    margin : float
        Margin added around the footprint, m.
    height_tolerance : float, optional
        If given, also drop points with ``|z - ground_z| > height_tolerance`` (m).
    ground_z : float
        Ground height in the vehicle frame, m.
    lateral : float
        Offset of the patch centre to the left (+y), m.

    Returns
    -------
    ndarray, shape (M, 3)
        The points kept, in their original order.
    """
    half = size / 2.0 + margin
    inside = (np.abs(points[:, 0] - ahead) <= half) & (np.abs(points[:, 1] - lateral) <= half)
    if height_tolerance is not None:
        inside &= np.abs(points[:, 2] - ground_z) <= height_tolerance
    return points[inside]


def stereo_to_cloud(
    left: np.ndarray,
    right: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig | None = None,
    *,
    restrict_to_patch: bool = True,
    ahead: float = PATCH_AHEAD,
    size: float = PATCH_SIZE,
    lateral: float = 0.0,
    roll: float | None = None,
    pitch: float | None = None,
) -> np.ndarray:
    """Point cloud in the vehicle frame from a rectified stereo pair (paper section 3.2).

    Parameters
    ----------
    left, right : ndarray of uint8
        Rectified images, gray ``(H, W)`` or BGR ``(H, W, 3)``, of the calibration's size.
    calib : StereoCalibration
        The rig.
    config : StereoConfig, optional
        Matcher, filter and window settings; defaults to ``StereoConfig()``.
    restrict_to_patch : bool
        If True (the patch path), match only what can see the patch: with
        ``config.fit_ground``, a coarse pass (:func:`fit_ground`) finds the ground plane under
        the patch and its relief, then SGM runs on the rows and columns that see the patch
        (:func:`patch_window`) and on the residual to that plane's disparity over the relief
        only; the points over the patch footprint plus ``config.crop_margin`` and inside the
        relief band are returned, those of every ``config.col_step``-th image column. If
        False, match the full frame with the config's disparity range and return every valid
        point.
    ahead, size, lateral : float
        Patch centre distance ahead of the vehicle origin, patch side, and offset of the
        patch centre to the left, m.
    roll, pitch : float, optional
        Vehicle tilt in rad (e.g. the IMU's; conventions of :func:`level_plane`). The patch
        path then expects level ground rather than the vehicle's ``z = 0`` plane. It only
        centres the coarse search (or, without ``config.fit_ground``, the search itself);
        the cloud stays in the vehicle frame.

    Returns
    -------
    ndarray of float64, shape (N, 3)
        Points ``(x, y, z)`` in m in the vehicle frame (x forward, y left, z up), after the
        statistical moving-window filter if ``config.outlier_filter`` is set.

    Raises
    ------
    InputError
        Images of different sizes, not 8-bit, or not matching the calibration; a patch
        outside the images.
    """
    config = config or StereoConfig()
    left_g, right_g = _check_pair(left, right, calib)
    f = config.outlier_filter
    if restrict_to_patch:
        x, y, z, dz = _patch_cloud(
            left_g, right_g, calib, config, ahead, size, lateral, roll, pitch
        )
        if f is not None and len(z):
            # Heights above the ground plane (not z): a sloping plane adds no spread to the
            # windows, which are aligned on the footprint's corner.
            half = size / 2.0 + config.crop_margin
            keep = _window_outlier_mask(
                x, y, dz, (ahead - half, lateral - half), f.cell, f.k, f.min_tolerance, f.min_count
            )
            x, y, z = x[keep], y[keep], z[keep]
        points = np.empty((len(z), 3))
        points[:, 0] = x
        points[:, 1] = y
        points[:, 2] = z
    else:
        disp = compute_disparity(
            left_g,
            right_g,
            config.sgbm,
            row_step=config.row_step,
            equalize=config.equalize_subpixel,
        )
        points = to_vehicle(disparity_to_points(disp, calib, 0, config.row_step), calib)
        if f is not None:
            points = points[
                statistical_outlier_mask(points, f.cell, f.k, f.min_tolerance, f.min_count)
            ]
    log.debug("stereo cloud: %d points", len(points))
    return points


def _patch_cloud(
    left_g: np.ndarray,
    right_g: np.ndarray,
    calib: StereoCalibration,
    config: StereoConfig,
    ahead: float,
    size: float,
    lateral: float,
    roll: float | None,
    pitch: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The patch path of :func:`stereo_to_cloud` before the outlier filter: float32 columns
    ``x, y, z`` (vehicle frame) and ``dz``, the height above the ground plane searched."""
    nominal = None if roll is None and pitch is None else level_plane(roll or 0.0, pitch or 0.0)
    common = {
        "lateral": lateral,
        "crop_margin": config.crop_margin,
        "margin_px": config.margin_px,
    }
    # The search volume around the expected ground; this also checks the patch is in view.
    window = patch_window(
        calib,
        ahead,
        size,
        height_tolerance=config.height_tolerance,
        plane=nominal,
        clip=True,
        **common,
    )
    if config.fit_ground and config.ground_prior:
        fit = fit_ground(
            left_g, right_g, calib, config, ahead=ahead, size=size, lateral=lateral, plane=nominal
        )
        if fit is not None:
            try:
                window = patch_window(
                    calib, ahead, size, height_tolerance=fit[1], plane=fit[0], clip=True, **common
                )
            except InputError as exc:  # a wild fit: keep the whole search volume
                log.debug("fitted ground rejected: %s", exc)
    half = size / 2.0 + config.crop_margin
    if config.ground_prior:
        # Ground outside the searched volume (e.g. beyond the patch in the band's top rows)
        # can only match wrongly; such matches pile up at the ends of the search range
        # (trimmed) or reconstruct outside the volume (cropped).
        raw = _sgbm_raw(
            left_g,
            right_g,
            config.sgbm,
            window.rows,
            window.cols,
            window.residual,
            config.row_step,
            window.prior,
        )
        return _window_cloud(
            raw,
            calib,
            window,
            ahead=ahead,
            half=half,
            lateral=lateral,
            row_step=config.row_step,
            col_step=config.col_step,
        )
    # Without the prior: the disparity itself, optionally equalised (slower, kept for
    # comparison).
    disp = compute_disparity(
        left_g,
        right_g,
        config.sgbm,
        window.rows,
        cols=window.cols,
        disparities=window.disparities,
        row_step=config.row_step,
        equalize=config.equalize_subpixel,
        trim=1,
    )
    if config.col_step > 1:
        disp[:, np.arange(disp.shape[1]) % config.col_step != 0] = np.nan
    pts = to_vehicle(disparity_to_points(disp, calib, window.rows[0], config.row_step), calib)
    pa, pb, pc = window.plane
    dz = pts[:, 2] - (pa * pts[:, 0] + pb * pts[:, 1] + pc)
    lo, hi = window.band
    inside = (
        (np.abs(pts[:, 0] - ahead) <= half)
        & (np.abs(pts[:, 1] - lateral) <= half)
        & (dz >= lo)
        & (dz <= hi)
    )
    x, y, z = (np.ascontiguousarray(c, dtype=np.float32) for c in pts[inside].T)
    return x, y, z, dz[inside].astype(np.float32)
