"""Stereo calibrations written by other tools: ROS ``CameraInfo`` YAML and OpenCV ``FileStorage``.

Each reader returns the values of a :class:`rough_map.config.StereoCalibration` (a plain
mapping, validated there): the *rectified* rig (one focal length, the two principal point
columns, the baseline) and, for a pair that still needs rectifying, the
:class:`Rectification` that turns the raw images into it.

* ROS ``CameraInfo`` (one YAML file per camera, as ``camera_calibration`` writes them):
  ``camera_matrix`` (K, raw intrinsics), ``distortion_coefficients`` (D),
  ``rectification_matrix`` (R, raw -> rectified rotation) and ``projection_matrix`` (P, the
  rectified camera). The right camera's ``P[0, 3] = -fx * baseline``; its ``P[0, 2]`` may
  differ from the left's (Middlebury's ``doffs = cx_right - cx``).
* OpenCV ``FileStorage`` (YAML/XML/JSON, as ``stereoCalibrate``/``stereoRectify`` samples
  write them): ``M1``, ``D1``, ``M2``, ``D2`` (raw intrinsics and distortion), ``R``, ``T``
  (right camera from left: ``x2 = R x1 + T``, T in m), the image size
  (``image_width``/``image_height``, ``width``/``height`` or ``image_size``), and
  optionally ``R1``, ``R2``, ``P1``, ``P2`` from ``stereoRectify``; without them
  ``cv2.stereoRectify`` (``CALIB_ZERO_DISPARITY``, ``alpha = 0``) computes them.

This module sits below :mod:`rough_map.config` (which imports it); it parses and checks,
and every error names the file and the field.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from rough_map._bounded import (
    clip,
    parse_document,
    parse_json,
    parse_yaml,
    read_document_text,
    short,
)
from rough_map.errors import FileFormatError, SchemaError
from rough_map.geometry import CAMERA_AXES_IN_VEHICLE
from rough_map.limits import LIMITS

__all__ = [
    "Rectification",
    "camera_info_values",
    "check_principal_point",
    "check_rigid_transform",
    "default_camera_to_vehicle",
    "is_opencv_file",
    "opencv_values",
]


#: Tolerance of "the identity" and "the same row" checks (dimensionless, px).
_EPS = 1e-9


def _matrix_3x3(value: list[list[float]]) -> list[list[float]]:
    if np.asarray(value, dtype=float).shape != (3, 3):
        raise ValueError(f"must be 3x3, got shape {np.asarray(value).shape}")
    return value


def _distortion(value: list[float]) -> list[float]:
    if len(value) not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"OpenCV takes 4, 5, 8, 12 or 14 coefficients, got {len(value)}")
    return value


class Rectification(BaseModel):
    """How the raw images become the rectified pair of a :class:`StereoCalibration`.

    Per camera, the raw intrinsics (px), the distortion coefficients (OpenCV's order, ``k1
    k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]``, ROS ``plumb_bob`` /
    ``rational_polynomial``) and the rotation from the raw to the rectified camera frame
    (ROS ``R``, OpenCV ``R1``/``R2``). The rectified cameras are the calibration's own
    ``fx, fy, cx, cy`` (left) and ``cx_right`` (right); the images keep their size.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    left_matrix: list[list[float]] = Field(description="Raw left camera matrix K, 3x3, px.")
    left_distortion: list[float] = Field(description="Raw left distortion coefficients.")
    left_rotation: list[list[float]] = Field(description="Raw -> rectified left rotation, 3x3.")
    right_matrix: list[list[float]] = Field(description="Raw right camera matrix K, 3x3, px.")
    right_distortion: list[float] = Field(description="Raw right distortion coefficients.")
    right_rotation: list[list[float]] = Field(description="Raw -> rectified right rotation, 3x3.")

    _check_3x3 = field_validator("left_matrix", "left_rotation", "right_matrix", "right_rotation")(
        _matrix_3x3
    )
    _check_distortion = field_validator("left_distortion", "right_distortion")(_distortion)


def check_rigid_transform(value: list[list[float]]) -> list[list[float]]:
    """Validate ``camera_to_vehicle``: 4x4, last row [0, 0, 0, 1], a proper rotation."""
    m = np.asarray(value, dtype=float)
    if m.shape != (4, 4):
        raise ValueError(f"camera_to_vehicle must be 4x4, got shape {m.shape}")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError("camera_to_vehicle last row must be [0, 0, 0, 1]")
    r = m[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: not a rotation
        proper = np.allclose(r @ r.T, np.eye(3), atol=1e-5) and np.linalg.det(r) > 0
    if not proper:
        raise ValueError("camera_to_vehicle rotation block is not a proper rotation")
    return value


def check_principal_point(calib: Any) -> None:
    """Validate that the principal point (cx, cy) lies inside the image (px)."""
    if not (0 <= calib.cx < calib.width and 0 <= calib.cy < calib.height):
        raise ValueError("principal point (cx, cy) must lie inside the image")


def default_camera_to_vehicle() -> np.ndarray:
    """A camera at the vehicle origin looking along the vehicle's x axis (4x4, m)."""
    transform = np.eye(4)
    transform[:3, :3] = CAMERA_AXES_IN_VEHICLE
    return transform


def _rectified_pose(camera_to_vehicle: Any, path: Path, rotation: np.ndarray) -> list[list[float]]:
    """``camera_to_vehicle`` of the raw left camera (4x4, m; default
    :func:`default_camera_to_vehicle`) moved onto the rectified left camera, whose frame is
    the raw one rotated by ``rotation`` (raw -> rectified)."""
    if camera_to_vehicle is None:
        transform = default_camera_to_vehicle()
    else:
        try:
            transform = np.asarray(camera_to_vehicle, dtype=float)
        except (TypeError, ValueError):
            raise SchemaError(
                path, "must be a 4x4 matrix of numbers", "camera_to_vehicle"
            ) from None
        if transform.shape != (4, 4):
            raise SchemaError(
                path, f"must be 4x4, got shape {transform.shape}", "camera_to_vehicle"
            )
    undo = np.eye(4)
    undo[:3, :3] = rotation.T  # rectified -> raw
    return (transform @ undo).tolist()


# --------------------------------------------------------------------------------------------
# ROS CameraInfo


def _read_yaml(path: Path) -> dict[str, Any]:
    data = parse_document(path, kind="yaml")
    if not isinstance(data, dict):
        raise SchemaError(path, f"expected a mapping at the top level, got {type(data).__name__}")
    return data


def _ros_matrix(
    data: Mapping[str, Any], path: Path, key: str, shape: tuple[int, int]
) -> np.ndarray:
    """``{rows, cols, data}`` of a CameraInfo file as an array of ``shape`` (cols may be any
    for the distortion: ``shape[1] = -1``)."""
    node = data.get(key)
    if node is None:
        raise SchemaError(path, "missing (not a ROS CameraInfo file?)", key)
    values = node.get("data") if isinstance(node, dict) else node
    try:
        array = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise SchemaError(path, "data must be a list of numbers", key) from None
    if shape[1] == -1:
        return array.reshape(-1)
    if array.size != shape[0] * shape[1]:
        raise SchemaError(path, f"expected {shape[0]}x{shape[1]} values, got {array.size}", key)
    array = array.reshape(shape)
    if not np.all(np.isfinite(array)):
        raise SchemaError(path, "values must be finite", key)
    return array


def _camera_info(path: Path) -> dict[str, Any]:
    data = _read_yaml(path)
    model = str(data.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial", ""):
        raise SchemaError(
            path,
            f"{short(model)} is not supported (plumb_bob, rational_polynomial)",
            "distortion_model",
        )
    size = []
    for key in ("image_width", "image_height"):
        value = data.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise SchemaError(path, f"must be a positive integer (px), got {short(value)}", key)
        size.append(value)
    return {
        "size": tuple(size),
        "K": _ros_matrix(data, path, "camera_matrix", (3, 3)),
        "D": _ros_matrix(data, path, "distortion_coefficients", (1, -1)),
        "R": _ros_matrix(data, path, "rectification_matrix", (3, 3)),
        "P": _ros_matrix(data, path, "projection_matrix", (3, 4)),
    }


def camera_info_values(
    left_path: str | Path, right_path: str | Path, camera_to_vehicle: Any = None
) -> dict[str, Any]:
    """The values of a ``StereoCalibration`` from the two cameras' ROS ``CameraInfo`` YAML.

    Parameters
    ----------
    left_path, right_path : str or Path
        The left (reference) and right camera's files.
    camera_to_vehicle : array_like (4, 4), optional
        Raw left camera -> vehicle (m); default :func:`default_camera_to_vehicle`.

    Raises
    ------
    FileFormatError
        A file cannot be read or parsed.
    SchemaError
        A field is missing or invalid, or the two ``P`` do not form a horizontal rectified
        pair (the message names the file and the field).
    """
    left_path, right_path = Path(left_path), Path(right_path)
    left, right = _camera_info(left_path), _camera_info(right_path)
    if right["size"] != left["size"]:
        raise SchemaError(
            right_path, f"{right['size']} differs from the left's {left['size']}", "image_width"
        )
    p1, p2 = left["P"], right["P"]
    for path, p in ((left_path, p1), (right_path, p2)):
        if not (p[0, 0] > 0 and p[1, 1] > 0) or np.any(np.abs(p[2] - [0, 0, 1, 0]) > _EPS):
            raise SchemaError(
                path, "expected [[fx 0 cx Tx] [0 fy cy Ty] [0 0 1 0]]", "projection_matrix"
            )
    if abs(p1[0, 3]) > _EPS or abs(p1[1, 3]) > _EPS:
        raise SchemaError(
            left_path, "the left camera's P[0,3] and P[1,3] must be 0", "projection_matrix"
        )
    same = np.allclose(
        p1[:2, :3][[0, 1, 1], [0, 1, 2]], p2[:2, :3][[0, 1, 1], [0, 1, 2]], atol=1e-6
    )
    if not same or abs(p2[1, 3]) > _EPS:
        raise SchemaError(
            right_path,
            "fx, fy, cy and P[1,3] must equal the left camera's (a horizontal rectified pair)",
            "projection_matrix",
        )
    baseline = -p2[0, 3] / p2[0, 0]
    if not baseline > 0:
        raise SchemaError(
            right_path,
            f"P[0,3] = -fx * baseline must be negative, got {p2[0, 3]}",
            "projection_matrix",
        )
    values = _rectified_values(
        p1, p2, left["size"], _rectified_pose(camera_to_vehicle, left_path, left["R"])
    )
    raw = (left["K"], left["D"], left["R"], right["K"], right["D"], right["R"])
    values["rectification"] = _rectification(raw, (p1, p2))
    return values


def _rectified_values(
    p1: np.ndarray, p2: np.ndarray, size: Any, camera_to_vehicle: Any
) -> dict[str, Any]:
    """The :class:`~rough_map.config.StereoCalibration` fields of a rectified pair from its
    3 x 4 projection matrices (px; ``P2[0, 3] = -fx * baseline``, baseline in m)."""
    return {
        "fx": float(p1[0, 0]),
        "fy": float(p1[1, 1]),
        "cx": float(p1[0, 2]),
        "cy": float(p1[1, 2]),
        "cx_right": float(p2[0, 2]),
        "width": size[0],
        "height": size[1],
        "baseline": float(-p2[0, 3] / p2[0, 0]),
        "camera_to_vehicle": camera_to_vehicle,
    }


def _rectification(
    raw: tuple[np.ndarray, ...], projections: tuple[np.ndarray, np.ndarray]
) -> dict[str, Any] | None:
    """The :class:`Rectification` values of ``raw = (K1, D1, R1, K2, D2, R2)``, or None when
    the raw images already are the rectified ones (no distortion, R identity, K = P)."""
    k1, d1, r1, k2, d2, r2 = raw
    done = all(
        not np.any(np.abs(d) > _EPS)
        and np.allclose(r, np.eye(3), atol=1e-9)
        and np.allclose(k, p[:, :3], atol=1e-6)
        for k, d, r, p in ((k1, d1, r1, projections[0]), (k2, d2, r2, projections[1]))
    )
    if done:
        return None
    return {
        "left_matrix": k1.tolist(),
        "left_distortion": d1.tolist(),
        "left_rotation": r1.tolist(),
        "right_matrix": k2.tolist(),
        "right_distortion": d2.tolist(),
        "right_rotation": r2.tolist(),
    }


# --------------------------------------------------------------------------------------------
# OpenCV FileStorage


def is_opencv_file(path: str | Path) -> bool:
    """True for a file ``cv2.FileStorage`` wrote: XML, YAML with ``%YAML:1.0`` or
    ``!!opencv-matrix`` (PyYAML cannot read those), or JSON with ``"opencv-matrix"``."""
    path = Path(path)
    if path.suffix.lower() == ".xml":
        return True
    try:
        with path.open("rb") as stream:
            head = stream.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return False
    return (
        head.lstrip().startswith("%YAML:1.0")
        or "!!opencv-matrix" in head
        or '"opencv-matrix"' in head  # FileStorage's JSON
    )


def _node(
    fs: Any, path: Path, key: str, shape: tuple[int, ...] | None, required: bool = True
) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        if required:
            raise SchemaError(
                path,
                "missing (an OpenCV FileStorage stereo calibration needs M1 D1 M2 D2 R T)",
                key,
            )
        return None
    if node.isMap():  # !!opencv-matrix
        array = node.mat()
    elif node.isSeq():  # [w, h]
        array = np.asarray([node.at(i).real() for i in range(node.size())])
    else:  # a number
        array = np.asarray([node.real()])
    if array is None:
        raise SchemaError(path, "not a matrix", key)
    array = np.asarray(array, dtype=float)
    if shape is not None:
        if array.size != int(np.prod(shape)):
            raise SchemaError(
                path, f"expected {'x'.join(map(str, shape))} values, got {array.size}", key
            )
        array = array.reshape(shape)
    if not np.all(np.isfinite(array)):
        raise SchemaError(path, "values must be finite", key)
    return array


class _DocNode:
    """A value of a parsed FileStorage document with the few ``cv2.FileNode`` methods the
    reader uses."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def empty(self) -> bool:
        return self.value is None

    def isMap(self) -> bool:  # OpenCV's method names
        return isinstance(self.value, dict)

    def isSeq(self) -> bool:
        return isinstance(self.value, list)

    def size(self) -> int:
        return len(self.value)

    def at(self, i: int) -> _DocNode:
        return _DocNode(self.value[i])

    def real(self) -> float:
        if isinstance(self.value, bool) or not isinstance(self.value, int | float):
            raise ValueError(f"expected a number, got {short(self.value, 30)}")
        return float(self.value)

    def mat(self) -> np.ndarray | None:
        data = self.value.get("data")
        if not isinstance(data, list):
            return None
        return np.asarray(data, dtype=float)  # ValueError for anything but numbers


class _DocStorage:
    """A parsed FileStorage document with the ``cv2.FileStorage`` methods the reader uses."""

    def __init__(self, data: dict[str, Any]) -> None:
        self.data = data

    def isOpened(self) -> bool:
        return True

    def getNode(self, key: str) -> _DocNode:
        return _DocNode(self.data.get(key))

    def release(self) -> None:
        pass


def _opencv_document(path: Path) -> dict[str, Any]:
    """An OpenCV FileStorage YAML or JSON file as a mapping (bounded parsing)."""
    text = read_document_text(path)
    if text.lstrip().startswith("{"):
        data = parse_json(text, path)
    else:
        data = parse_yaml(text, path, opencv=True)
    if not isinstance(data, dict):
        raise SchemaError(path, f"expected a mapping at the top level, got {type(data).__name__}")
    return data


def _cv_message(err: BaseException) -> str:
    """The last line of an OpenCV error, short (its first lines name OpenCV's sources)."""
    cause = err.__cause__ or err.__context__ if isinstance(err, SystemError) else None
    text = " ".join(str(cause or err).split())
    return clip(text.rsplit("error: ", 1)[-1], 100)


def _required(fs: Any, path: Path, key: str, shape: tuple[int, ...] | None) -> np.ndarray:
    array = _node(fs, path, key, shape)
    assert array is not None  # required: _node raised
    return array


def _image_size(fs: Any, path: Path) -> tuple[int, int]:
    for w_key, h_key in (("image_width", "image_height"), ("width", "height")):
        w, h = _node(fs, path, w_key, (1,), False), _node(fs, path, h_key, (1,), False)
        if w is not None and h is not None:
            size = (int(w[0]), int(h[0]))
            break
    else:
        both = _node(fs, path, "image_size", (2,), False)
        if both is None:
            raise SchemaError(
                path, "missing: give image_width and image_height (px)", "image_width"
            )
        size = (int(both[0]), int(both[1]))
    if min(size) <= 0 or max(size) > LIMITS.calibration_image_side:
        raise SchemaError(
            path,
            f"must be in 1..{LIMITS.calibration_image_side} px, got {short(size)}",
            "image_width",
        )
    return size


def opencv_values(path: str | Path, camera_to_vehicle: Any = None) -> dict[str, Any]:
    """The values of a ``StereoCalibration`` from an OpenCV ``FileStorage`` file.

    Parameters
    ----------
    path : str or Path
        YAML, XML or JSON written by ``cv2.FileStorage`` (see the module notes for the keys).
    camera_to_vehicle : array_like (4, 4), optional
        Raw left camera -> vehicle (m); default :func:`default_camera_to_vehicle`.

    Raises
    ------
    FileFormatError
        The file cannot be read.
    SchemaError
        A key is missing or malformed, or the rig is not side by side (left camera on the
        left); the message names the file and the key.
    """
    import cv2  # heavy: only for OpenCV files

    path = Path(path)
    try:
        size_bytes = path.stat().st_size if path.is_file() else -1
    except OSError:
        size_bytes = -1
    if size_bytes < 0:
        raise FileFormatError(path, "cannot read: no such file")
    if size_bytes > LIMITS.document:
        raise FileFormatError(path, f"larger than {LIMITS.document // 2**20} MB")
    fs: Any
    if path.suffix.lower() == ".xml":
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as err:
            raise FileFormatError(
                path, "not an OpenCV FileStorage file: " + _cv_message(err)
            ) from None
    else:  # YAML or JSON: read by rough_map's bounded parsers (OpenCV's can abort)
        fs = _DocStorage(_opencv_document(path))
    try:
        if not fs.isOpened():
            raise FileFormatError(path, "not an OpenCV FileStorage file")
        m1, m2 = (_required(fs, path, k, (3, 3)) for k in ("M1", "M2"))
        d1, d2 = (_required(fs, path, k, None).reshape(-1) for k in ("D1", "D2"))
        rot = _required(fs, path, "R", (3, 3))
        t = _required(fs, path, "T", (3,))
        size = _image_size(fs, path)
        stored = [
            _node(fs, path, k, s, False)
            for k, s in (("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4)))
        ]
    except (cv2.error, SystemError, OverflowError, ValueError, TypeError) as err:
        if isinstance(err, FileFormatError):
            raise
        raise FileFormatError(path, "malformed OpenCV FileStorage: " + _cv_message(err)) from None
    finally:
        fs.release()
    for key, d in (("D1", d1), ("D2", d2)):
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise SchemaError(
                path, f"OpenCV takes 4, 5, 8, 12 or 14 coefficients, got {d.size}", key
            )
    r1: Any
    r2: Any
    p1: Any
    p2: Any
    if any(s is None for s in stored):
        try:
            r1, r2, p1, p2, *_ = cv2.stereoRectify(
                m1, d1, m2, d2, size, rot, t.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0
            )
        except cv2.error as err:
            message = " ".join(str(err).split())[-120:]
            raise SchemaError(path, f"cv2.stereoRectify failed: {message}", "R") from None
    else:
        r1, r2, p1, p2 = stored
    if not p2[0, 0] > 0 or abs(p2[1, 3]) > 1e-6 * abs(p2[0, 0]) or not p2[0, 3] < 0:
        raise SchemaError(
            path,
            "not a side-by-side rig with the right camera on the right "
            "(P2[0,3] must be negative, P2[1,3] zero)",
            "T",
        )
    values = _rectified_values(
        p1, p2, size, _rectified_pose(camera_to_vehicle, path, np.asarray(r1))
    )
    values["rectification"] = _rectification((m1, d1, r1, m2, d2, r2), (p1, p2))
    return values
