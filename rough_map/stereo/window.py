"""The part of the images, and the disparities, that can see the patch of interest.

The patch path of :func:`rough_map.stereo.stereo_to_cloud` matches only the image rows and
columns that see the patch (:func:`patch_window`), on the residual to the ground plane's
disparity, over the heights of interest: a box over the patch's footprint, projected into
the left image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rough_map.config import StereoCalibration
from rough_map.errors import InputError
from rough_map.patch import PatchSpec
from rough_map.stereo.ground import Plane, ground_disparity

__all__ = ["PatchWindow", "patch_rows", "patch_window"]


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


def patch_window(
    calib: StereoCalibration,
    patch: PatchSpec | None = None,
    ground_z: float = 0.0,
    *,
    height_tolerance: float | tuple[float, float] = 0.15,
    crop_margin: float = 0.05,
    margin_px: int = 8,
    plane: Plane | None = None,
    clip: bool = False,
) -> PatchWindow:
    """Image rows, columns and disparities that see the patch of interest.

    The patch is the square ``|x - ahead| <= size/2``, ``|y - lateral| <= size/2`` of the
    vehicle frame (``patch.ahead``, ``patch.size``, ``patch.lateral``) widened by
    ``crop_margin``, on the ground plane (``z = ground_z``, or
    ``plane``) widened by ``height_tolerance``. The corners of that box are projected into the
    left image; a box projects inside the convex hull of its corners, so their extremes bound
    it, and bound the residual ``d - d0`` too (affine in ``(u, v)`` on each face).

    Parameters
    ----------
    calib : StereoCalibration
        The rig.
    patch : PatchSpec, optional
        The patch of interest: its centre ``ahead`` of the vehicle origin and ``lateral``
        to its left, and its side ``size`` (m); default ``PatchSpec()``, the paper's.
    ground_z : float
        Height of flat ground in the vehicle frame, m; ignored if ``plane`` is given.
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
    patch = PatchSpec() if patch is None else patch
    if isinstance(height_tolerance, tuple | list):
        lo, hi = float(height_tolerance[0]), float(height_tolerance[1])
    else:
        lo, hi = -float(height_tolerance), float(height_tolerance)
    if not lo <= 0 <= hi:
        raise InputError(f"the height band must contain 0 (the ground), got ({lo}, {hi}) m")
    pa, pb, pc = (0.0, 0.0, float(ground_z)) if plane is None else map(float, plane)
    u, v, d = _project_box(
        calib, patch, patch.size / 2.0 + crop_margin, (pa, pb, pc), (lo, hi), clip
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
    # Disparities above -doffs (in front of the camera): 0 up for a rig without doffs.
    lowest = math.floor(-calib.doffs)
    disparities = _search_range(max(lowest, math.floor(d.min()) - 2), math.ceil(d.max()) + 2)
    return PatchWindow(
        rows=rows,
        cols=cols,
        disparities=(max(lowest, disparities[0]), disparities[1]),
        prior=prior,
        residual=residual,
        plane=(pa, pb, pc),
        band=(lo, hi),
    )


def _project_box(
    calib: StereoCalibration,
    patch: PatchSpec,
    half: float,
    plane: Plane,
    band: tuple[float, float],
    clip: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left-image ``u, v`` and disparity ``d`` (px) of the corners of the box ``|x - ahead|,
    |y - lateral| <= half`` (m) over ``plane``, heights ``band`` (m) above it, checked to be
    in view (with ``clip``, only the corners on the plane); see :func:`patch_window`."""
    ahead, lateral = patch.ahead, patch.lateral
    pa, pb, pc = plane
    corners = np.array(
        [
            [x, y, pa * x + pb * y + pc + dz]
            for x in (ahead - half, ahead + half)
            for y in (lateral - half, lateral + half)
            for dz in (band[0], 0.0, band[1])
        ]
    )
    transform = calib.T_vehicle_camera
    cam = (corners - transform[:3, 3]) @ transform[:3, :3]  # R^T (p - t)
    if np.any(cam[:, 2] <= 0.05):
        raise InputError("the patch of interest is behind or too close to the left camera")
    u = calib.fx * cam[:, 0] / cam[:, 2] + calib.cx
    v = calib.fy * cam[:, 1] / cam[:, 2] + calib.cy
    d = calib.focal_baseline / cam[:, 2] - calib.doffs
    # With clip, only the ground corners (dz = 0) must be inside the images.
    check = np.arange(len(u)) % 3 == 1 if clip else slice(None)
    uc, vc, dc = u[check], v[check], d[check]
    if uc.min() < 0 or uc.max() > calib.width - 1 or vc.min() < 0 or vc.max() > calib.height - 1:
        raise InputError(
            f"the patch of interest ({patch.size:g} m square, {ahead:g} m ahead) is not inside "
            f"the left image: it spans u {uc.min():.0f}..{uc.max():.0f}, "
            f"v {vc.min():.0f}..{vc.max():.0f}"
        )
    if (uc - dc).min() < 0:
        raise InputError(
            "the patch of interest is not inside the right image (u - d reaches "
            f"{(uc - dc).min():.0f} px)"
        )
    return u, v, d


def _search_range(lo: int, hi: int) -> tuple[int, int]:
    """``(minDisparity, numDisparities)`` covering ``lo..hi`` px, the rounding up of
    ``numDisparities`` to a multiple of 16 shared between both ends."""
    num = 16 * math.ceil((hi - lo) / 16)
    return lo - (num - (hi - lo)) // 2, num


def patch_rows(
    calib: StereoCalibration,
    patch: PatchSpec,
    ground_z: float = 0.0,
    *,
    height_tolerance: float = 0.15,
    margin_px: int = 8,
) -> tuple[int, int]:
    """Row band ``(r0, r1)`` of the left image that sees the patch, px; see
    :func:`patch_window` (``patch`` the patch of interest, ``ground_z`` and
    ``height_tolerance`` in m)."""
    return patch_window(
        calib, patch, ground_z, height_tolerance=height_tolerance, margin_px=margin_px
    ).rows
