"""Semi-global matching of a rectified pair: the disparity map, and SGM's pixel locking undone.

:func:`compute_disparity` runs OpenCV's ``StereoSGBM`` on a band of rows and columns, over a
range of disparities, optionally on the residual to an expected disparity (a *prior*, e.g.
the ground plane's, :func:`rough_map.stereo.ground.ground_disparity`);
:func:`equalize_subpixel` corrects the crowding of SGM's sub-pixel values towards integers.
:func:`sgbm_raw` is the matcher itself, its raw 1/16 px output, for the patch path of
:func:`rough_map.stereo.stereo_to_cloud`, which triangulates it directly.

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
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.stereo.settings import SGBM_MODES, SGBMConfig

__all__ = ["check_pair", "compute_disparity", "equalize_subpixel", "sgbm_raw"]

log = logging.getLogger(__name__)

#: Pad the images on the left when matching without a prior (see :func:`sgbm_raw`).
PAD_LEFT = True


def _as_gray(image: np.ndarray, name: str) -> np.ndarray:
    """An 8-bit gray image from a gray or BGR one; ``name`` ("left", "right") for errors."""
    import cv2  # heavy: only when matching

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


def check_pair(
    left: np.ndarray, right: np.ndarray, calib: StereoCalibration | None
) -> tuple[np.ndarray, np.ndarray]:
    """The pair as 8-bit gray images, checked against each other and the calibration.

    Parameters
    ----------
    left, right : ndarray of uint8
        Gray ``(H, W)`` or BGR ``(H, W, 3)`` images.
    calib : StereoCalibration, optional
        If given, the images must be its ``width`` x ``height`` px.

    Raises
    ------
    InputError
        Not 8-bit, not gray or BGR, of different sizes, or not the calibration's size.
    """
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


def sgbm_raw(
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
    # OpenCV leaves the first min_d + num_d - 1 columns unmatched: without a prior, pad both
    # images on the left (black) so that the left image's first columns are matched too
    # (where their match is inside the right image; else the matcher sees black and its
    # uniqueness test mostly rejects them).
    pad = max(0, max_d + config.blockSize - (c0 - a0)) if prior is None and PAD_LEFT else 0
    if pad:
        left_band = cv2.copyMakeBorder(left_band, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
        right_band = cv2.copyMakeBorder(right_band, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
    matcher = sgbm_matcher(config, min_d, num_d)
    raw = matcher.compute(np.ascontiguousarray(left_band), np.ascontiguousarray(right_band))
    first = (r0 - b0) // row_step
    return raw[first : first + n_out, pad + c0 - a0 : pad + c1 - a0]


def sgbm_matcher(config: SGBMConfig, min_disparity: int, num_disparities: int) -> Any:
    """OpenCV's ``StereoSGBM`` with ``config``'s parameters over ``min_disparity`` to
    ``min_disparity + num_disparities`` px (a multiple of 16)."""
    import cv2

    return cv2.StereoSGBM.create(
        minDisparity=min_disparity,
        numDisparities=num_disparities,
        blockSize=config.blockSize,
        P1=config.P1,
        P2=config.P2,
        disp12MaxDiff=config.disp12MaxDiff,
        preFilterCap=config.preFilterCap,
        uniquenessRatio=config.uniquenessRatio,
        speckleWindowSize=config.speckleWindowSize,
        speckleRange=config.speckleRange,
        mode=SGBM_MODES[config.mode],
    )


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
    left_g, right_g = check_pair(left, right, None)
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
    raw = sgbm_raw(left_g, right_g, config, (r0, r1), (c0, c1), (min_d, num_d), row_step, prior)
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
