"""Any calibrated rig: its calibration from any format, and its raw pair rectified.

:func:`load_calibration` reads rough_map's own calibration file, the two cameras' ROS
``CameraInfo`` files or an OpenCV ``FileStorage`` file, told apart by their content.
:func:`rectify_pair` undistorts and rotates a raw pair into the rectified pair the
calibration describes (``cv2.initUndistortRectifyMap`` + ``cv2.remap``, as ROS
``image_proc`` does); a calibration without ``rectification`` leaves the images as they are.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from rough_map.calibration_files import is_opencv_file
from rough_map.config import StereoCalibration, load_mapping, load_model, schema_error
from rough_map.errors import InputError, SchemaError
from rough_map.stereo.matching import check_pair

__all__ = ["load_calibration", "rectify_pair"]

PathArg = str | Path

#: What the remap tables depend on.
_MAP_FIELDS = {"fx", "fy", "cx", "cy", "cx_right", "width", "height", "rectification"}


def load_calibration(
    paths: PathArg | Sequence[PathArg], camera_to_vehicle: Any = None
) -> StereoCalibration:
    """A :class:`StereoCalibration` from any format rough_map reads.

    Parameters
    ----------
    paths : path or sequence of 1 or 2 paths
        Two paths: the left and right cameras' ROS ``CameraInfo`` YAML files. One path: an
        OpenCV ``FileStorage`` file (XML, or YAML starting ``%YAML:1.0`` or holding
        ``!!opencv-matrix``), else rough_map's own YAML/JSON
        (``configs/stereo_calibration.yaml``).
    camera_to_vehicle : array_like (4, 4), optional
        For the foreign formats, the raw left camera -> vehicle transform (m); default: the
        camera at the vehicle origin looking along its x axis. rough_map's own files carry
        theirs.

    Raises
    ------
    FileFormatError, SchemaError
        Unreadable or invalid files; the message names the file and the field.
    InputError
        Neither one nor two paths.
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    paths = list(paths)
    if len(paths) == 2:
        return StereoCalibration.from_camera_info(paths[0], paths[1], camera_to_vehicle)
    if len(paths) != 1:
        raise InputError(f"expected 1 calibration file or 2 CameraInfo files, got {len(paths)}")
    path = Path(paths[0])
    if is_opencv_file(path):
        return StereoCalibration.from_opencv(path, camera_to_vehicle)
    data = load_mapping(path)
    if "projection_matrix" in data:
        raise SchemaError(
            path,
            "a ROS CameraInfo file holds one camera: give the left and the right camera's files",
            "projection_matrix",
        )
    calib = load_model(path, StereoCalibration)
    if camera_to_vehicle is not None:
        try:
            pose = np.asarray(camera_to_vehicle, dtype=float).tolist()
            calib = StereoCalibration.model_validate(
                calib.model_dump() | {"camera_to_vehicle": pose}
            )
        except ValidationError as err:
            raise schema_error(path, err) from None
        except (TypeError, ValueError):
            raise SchemaError(
                path, "must be a 4x4 matrix of numbers", "camera_to_vehicle"
            ) from None
    return calib


def rectify_pair(
    left: np.ndarray, right: np.ndarray, calib: StereoCalibration
) -> tuple[np.ndarray, np.ndarray]:
    """The rectified pair of ``calib`` from a raw one.

    Parameters
    ----------
    left, right : ndarray of uint8
        Raw images, gray ``(H, W)`` or BGR ``(H, W, 3)``, of the calibration's size.
    calib : StereoCalibration
        The rig; without ``rectification`` the (gray) images are returned unchanged.

    Returns
    -------
    (ndarray, ndarray) of uint8
        Gray rectified left and right images, same size: undistorted with each camera's
        ``K`` and ``D``, rotated by its ``R``, projected with the rectified left camera
        (``fx, fy, cx, cy``) and right camera (``cx_right``) (bilinear; pixels that see
        outside the raw image are 0).

    Raises
    ------
    InputError
        Images of different sizes, not 8-bit, or not of the calibration's size.
    """
    import cv2  # heavy: only when rectifying

    left_g, right_g = check_pair(left, right, calib)
    if calib.rectification is None:
        return left_g, right_g
    maps = _maps(calib.model_dump_json(include=_MAP_FIELDS))
    left_r, right_r = (
        cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)
        for image, (map_x, map_y) in zip((left_g, right_g), maps, strict=True)
    )
    return left_r, right_r


@functools.lru_cache(maxsize=4)
def _maps(key: str) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The remap tables (float32 x and y maps) of both cameras for the JSON of a calibration's
    intrinsics and rectification: built once per rig, not per frame."""
    import cv2

    c = json.loads(key)
    rect = c["rectification"]
    cx_right = c["cx"] if c["cx_right"] is None else c["cx_right"]
    maps = []
    for side, cx in (("left", c["cx"]), ("right", cx_right)):
        new = np.array([[c["fx"], 0.0, cx], [0.0, c["fy"], c["cy"]], [0.0, 0.0, 1.0]])
        maps.append(
            cv2.initUndistortRectifyMap(
                np.asarray(rect[f"{side}_matrix"], dtype=float),
                np.asarray(rect[f"{side}_distortion"], dtype=float),
                np.asarray(rect[f"{side}_rotation"], dtype=float),
                new,
                (c["width"], c["height"]),
                cv2.CV_32FC1,
            )
        )
    return tuple(maps)
