"""The settings of the stereo pipeline: the matcher, the outlier filter and the patch path.

:class:`StereoConfig` is what :func:`rough_map.stereo.stereo_to_cloud` needs besides the
calibration; ``configs/stereo.yaml`` holds the defaults, and any missing key of such a file
takes them. The calibration itself is :class:`rough_map.config.StereoCalibration`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from rough_map.config import load_model

__all__ = ["SGBM_MODES", "OutlierFilterConfig", "SGBMConfig", "StereoConfig"]

#: OpenCV's ``StereoSGBM`` mode constants by the names :class:`SGBMConfig` takes.
SGBM_MODES = {"SGBM": 0, "HH": 1, "SGBM_3WAY": 2, "HH4": 3}


#: Largest integer OpenCV takes (int32).
_INT32 = 2**31 - 1


class SGBMConfig(BaseModel):
    """Parameters of OpenCV ``StereoSGBM``, named as in OpenCV.

    Defaults are those of ``configs/stereo.yaml``. ``P1 = 8 * blockSize**2`` and ``P2 = 32 *
    blockSize**2`` are OpenCV's recommendation for one channel. ``SGBM_3WAY`` is the fastest
    mode and the only one OpenCV runs on several threads.

    Attributes
    ----------
    minDisparity : int
        Smallest disparity searched, px, counted from the disparity at infinity (``-doffs``,
        0 for a rig without ``cx_right``); only where no depths are given (see
        :func:`~rough_map.stereo.frame.disparity_range`).
    numDisparities : int
        Number of disparities searched, px, a positive multiple of 16, where no nearest
        depth is given. 256 covers depths from ``fx B / 256`` = 0.92 m for the XB3-like rig;
        the patch path derives its range from the geometry (see
        :func:`~rough_map.stereo.window.patch_window`), the full frame from ``min_depth`` and
        ``max_depth``.
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

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # OpenCV's names, on purpose: the YAML keys map 1:1 onto cv2.StereoSGBM.create.
    minDisparity: int = Field(0, ge=-65_536, le=65_536)
    numDisparities: int = Field(256, gt=0, le=4096, multiple_of=16)
    blockSize: int = Field(5, ge=1, le=11)
    P1: int = Field(200, ge=0, le=_INT32)
    P2: int = Field(800, ge=0, le=_INT32)
    disp12MaxDiff: int = Field(1, ge=-_INT32, le=_INT32)
    preFilterCap: int = Field(63, ge=1, le=63)
    uniquenessRatio: int = Field(10, ge=0, le=100)
    speckleWindowSize: int = Field(100, ge=0, le=1_000_000)
    speckleRange: int = Field(2, ge=0, le=_INT32)
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
    radius : int
        The image test of whole frames (:func:`image_outlier_mask`, any scene): half side
        of the neighbourhood of each pixel, px.
    disparity_tolerance : float
        The image test: largest disparity difference of a supporting neighbour, px.
    support : int
        The image test: fewest supporting neighbours a pixel needs.

    The ground windows (``cell``, ``k``, ``min_tolerance``, ``min_count``) judge the patch
    path's points, on the ground; the image test judges the full frame's pixels.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    cell: float = Field(0.024, ge=1e-4, le=100)
    k: float = Field(3.5, gt=0)
    min_tolerance: float = Field(0.003, ge=0)
    min_count: int = Field(3, ge=1, le=_INT32)
    radius: int = Field(2, ge=1, le=5)
    disparity_tolerance: float = Field(0.5, ge=0)
    support: int = Field(12, ge=0, le=_INT32)


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
        :func:`compute_disparity`) instead of the disparity itself; see the notes of
        :mod:`rough_map.stereo`. Without it there is no coarse pass: one pass over
        ``height_tolerance``.
    equalize_subpixel : bool
        Correct SGM's pixel locking with :func:`equalize_subpixel` before triangulating, in
        the full-frame path and in the patch path without ``ground_prior``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    sgbm: SGBMConfig = Field(default_factory=SGBMConfig)
    outlier_filter: OutlierFilterConfig | None = Field(default_factory=OutlierFilterConfig)
    height_tolerance: float = Field(0.25, ge=0)
    fit_ground: bool = True
    coarse_scale: int = Field(4, ge=2, le=8)
    band_margin: float = Field(0.015, ge=0)
    min_band: float = Field(0.025, ge=0)
    crop_margin: float = Field(0.05, ge=0)
    margin_px: int = Field(2, ge=0, le=65_536)
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
        return load_model(path, cls)
