"""File schemas as pydantic models, and safe loading of YAML/JSON into them.

The JSON Schemas in ``data_schema/`` are generated from the models here, by
:func:`write_schemas` or ``rough-map schema --out data_schema``; do not edit them by hand.

A traverse (see :mod:`rough_map.io.traverse`) is described by :class:`TraverseSpec`::

    schema_version: "1.0"
    name: field_a
    crs: local                      # or "EPSG:32633", 32633, {code: local, origin: {...}}
    frames:
      - t: 0.0                      # s
        pose: {x: 0.0, y: 0.0, yaw: 0.1}   # m, rad; z, roll, pitch default to 0
        cloud: clouds/000000.npy    # relative to the traverse folder
        label: gravel

Every model forbids unknown keys, so a typo (``lable:``) is an error rather than ignored;
only ``metadata`` is free-form.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from rough_map._bounded import short
from rough_map._files import atomic_output
from rough_map.calibration_files import (
    Rectification,
    camera_info_values,
    check_principal_point,
    check_rigid_transform,
    opencv_values,
)
from rough_map.config_files import format_location, load_model, schema_error
from rough_map.config_files import load_mapping as load_mapping
from rough_map.errors import InputError
from rough_map.geometry import CAMERA_AXES_IN_VEHICLE, pose_matrix, rotation_matrix
from rough_map.limits import LIMITS

SCHEMA_VERSION = "1.0"
"""Version of the traverse format written by this release."""

_JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _relative_path(value: str) -> str:
    if "\x00" in value:
        raise ValueError(f"{short(value)} holds a NUL character")
    if PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute():
        raise ValueError(f"{short(value)} must be a path relative to the traverse folder")
    return value


RelativePath = Annotated[
    str,
    Field(min_length=1, description="Path relative to the traverse folder (use '/')."),
    AfterValidator(_relative_path),
]


class Pose(_Model):
    """Pose of the vehicle in the world frame.

    ``p_world = Rz(yaw) @ Ry(pitch) @ Rx(roll) @ p_vehicle + (x, y, z)``, with the vehicle
    frame x forward, y left, z up.
    """

    x: float = Field(description="Position east (or local x), m.")
    y: float = Field(description="Position north (or local y), m.")
    z: float = Field(0.0, description="Position up, m.")
    roll: float = Field(0.0, description="Rotation about the vehicle x axis, rad.")
    pitch: float = Field(0.0, description="Rotation about the vehicle y axis, rad.")
    yaw: float = Field(0.0, description="Heading, rotation about the world z axis, rad.")

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform vehicle -> world (rotation, translation in m)."""
        return pose_matrix(self)


class ImuAttitude(_Model):
    """Attitude of the vehicle measured by an IMU (gravity reference)."""

    roll: float = Field(description="Roll, rad.")
    pitch: float = Field(description="Pitch, rad.")


class GeodeticOrigin(_Model):
    """Geodetic position of the origin of a local world frame (WGS84)."""

    lat: float = Field(ge=-90.0, le=90.0, description="Latitude, degrees north.")
    lon: float = Field(ge=-180.0, le=180.0, description="Longitude, degrees east.")
    alt: float = Field(0.0, description="Height above the WGS84 ellipsoid, m.")


class Crs(_Model):
    """Coordinate reference system of the world frame of a traverse."""

    code: str = Field(
        pattern=r"^(local|EPSG:[1-9][0-9]*)$",
        description="'local' for a local metric frame, or 'EPSG:<code>' for a projected CRS.",
    )
    origin: GeodeticOrigin | None = Field(
        None, description="Geodetic origin of a 'local' frame (x east, y north, z up)."
    )

    @model_validator(mode="after")
    def _origin_only_local(self) -> Crs:
        if self.origin is not None and self.code != "local":
            raise ValueError("origin is only meaningful with crs 'local'")
        return self

    @property
    def epsg(self) -> int | None:
        """The EPSG code, or None for a local frame."""
        return None if self.code == "local" else int(self.code.split(":")[1])

    @classmethod
    def from_any(cls, value: Any) -> Crs:
        """A :class:`Crs` from None (local), ``"local"``, ``"EPSG:32633"``, ``32633``, a
        mapping like the traverse file's ``crs``, or a :class:`Crs`.

        Raises
        ------
        InputError
            Anything else, or an invalid code or origin.
        """
        if isinstance(value, Crs):
            return value
        if value is None:
            value = "local"
        try:
            return cls.model_validate(_crs_shorthand(value))
        except (ValueError, ValidationError) as err:
            raise InputError(f"cannot read a CRS from {value!r}: {_first_error(err)}") from None

    def proj_string(self) -> str | None:
        """A CRS definition for GIS tools: ``"EPSG:<n>"``; for a local frame with a geodetic
        origin a transverse Mercator centred on it (x east, y north, m, scale 1 at the
        origin); None for a local frame without origin (an engineering CRS)."""
        if self.epsg is not None:
            return self.code
        if self.origin is None:
            return None
        return (
            f"+proj=tmerc +lat_0={self.origin.lat:.10f} +lon_0={self.origin.lon:.10f} +k=1 "
            "+x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
        )

    @classmethod
    def from_rasterio(cls, crs: Any) -> Crs:
        """The :class:`Crs` of a :class:`rasterio.crs.CRS`, the inverse of :meth:`rasterio`:
        ``EPSG:<n>`` for a projected CRS in metres with an EPSG code, ``local`` for an
        engineering CRS (:data:`LOCAL_WKT`) and ``local`` with its geodetic origin for the
        transverse Mercator of :meth:`proj_string` (the altitude is not kept).

        The CRS's unit is not looked at: a projected CRS in feet is named by its code too.

        Raises
        ------
        InputError
            A geographic CRS (degrees), or one without an EPSG code that is not one of
            rough_map's local frames.
        """
        if crs.is_geographic:
            raise InputError(
                "a geographic CRS (degrees): its cells are not a length; reproject it to a "
                "projected CRS in m (e.g. gdalwarp -t_srs EPSG:326NN for UTM)"
            )
        if not crs.is_projected:  # an engineering CRS: rough_map's local frame
            return cls(code="local")
        epsg = crs.to_epsg()
        if epsg is not None:
            return cls(code=f"EPSG:{epsg}")
        p = crs.to_dict()
        if (
            p.get("proj") == "tmerc"
            and p.get("k", 1) == 1
            and not p.get("x_0")
            and not p.get("y_0")
        ):
            origin = {"lat": float(p.get("lat_0", 0.0)), "lon": float(p.get("lon_0", 0.0))}
            return cls.model_validate({"code": "local", "origin": origin})
        raise InputError("a CRS without an EPSG code; reproject it to one (gdalwarp -t_srs)")

    def rasterio(self) -> Any:
        """This CRS as a :class:`rasterio.crs.CRS` (the one conversion every writer and
        reader uses): the EPSG code; for a local frame with a geodetic origin the transverse
        Mercator of :meth:`proj_string`; without origin the engineering CRS
        :data:`LOCAL_WKT` (metres). A ``rasterio.errors.CRSError`` for a code GDAL does
        not know."""
        from rasterio.crs import CRS

        if self.epsg is not None:
            return CRS.from_epsg(self.epsg)
        proj = self.proj_string()
        return CRS.from_wkt(LOCAL_WKT) if proj is None else CRS.from_proj4(proj)


#: WKT of the engineering CRS of a local frame without geodetic origin (x east, y north, m).
LOCAL_WKT = (
    'LOCAL_CS["rough_map local frame (x east, y north)",LOCAL_DATUM["rough_map local",0],'
    'UNIT["metre",1],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
)


def _first_error(err: Exception) -> str:
    if isinstance(err, ValidationError):
        first = err.errors()[0]
        return f"{format_location(first['loc']) or 'crs'}: {first['msg']}"
    return str(err)


def _crs_shorthand(value: object) -> object:
    """Accept ``"local"``, ``"EPSG:32633"`` (any case) and ``32633`` for ``{code: ...}``."""
    if isinstance(value, bool):
        return value  # bool is an int; let validation reject it
    if isinstance(value, int):
        return {"code": f"EPSG:{value}"}
    if isinstance(value, str):
        code = value.strip()
        if code.lower() == "local":
            return {"code": "local"}
        if code.upper().startswith("EPSG:") and code[5:].strip().isdigit():
            return {"code": f"EPSG:{int(code[5:])}"}
        raise ValueError(f"crs must be 'local', 'EPSG:<code>' or an EPSG integer; got {value!r}")
    return value


_CrsCode = Annotated[str, Field(pattern=r"^([Ll][Oo][Cc][Aa][Ll]|[Ee][Pp][Ss][Gg]:[0-9]+)$")]
CrsField = Annotated[
    Crs, BeforeValidator(_crs_shorthand, json_schema_input_type=_CrsCode | int | Crs)
]


class StereoCalibration(_Model):
    """Intrinsics and extrinsics of a stereo rig, as the rectified pair it gives.

    The rectified images are row-aligned with one focal length and principal point row; the
    right camera sits ``baseline`` m along the left camera's +x axis and its principal point
    column is ``cx_right`` (px; default ``cx``), so a point at depth ``Z`` (m) has disparity
    ``d = u_left - u_right = fx * baseline / Z - doffs`` (px), ``doffs = cx_right - cx``
    (Middlebury's). A raw pair has a ``rectification`` (:func:`rough_map.stereo.rectify_pair`
    applies it). Camera frame: OpenCV (x right, y down, z forward) of the
    *rectified* left camera; vehicle frame: x forward, y left, z up.

    Read from rough_map's YAML/JSON (:meth:`from_file`), ROS ``CameraInfo``
    (:meth:`from_camera_info`) or OpenCV ``FileStorage`` (:meth:`from_opencv`).

    The one calibration of rough_map: a traverse's ``calibration``, the stereo matcher's, the
    renderer's and near-to-far's. Any object with these attributes validates
    (``from_attributes``).
    """

    model_config = ConfigDict(from_attributes=True)

    fx: float = Field(gt=0, description="Focal length along x, px.")
    fy: float = Field(gt=0, description="Focal length along y, px.")
    cx: float = Field(description="Principal point column, px (pixel centres at integers).")
    cy: float = Field(description="Principal point row, px.")
    width: int = Field(gt=0, le=LIMITS.calibration_image_side, description="Image width, px.")
    height: int = Field(gt=0, le=LIMITS.calibration_image_side, description="Image height, px.")
    baseline: float = Field(gt=0, description="Distance between the optical centres, m.")
    camera_to_vehicle: list[list[float]] = Field(
        description="4x4 transform, row-major: left-camera coordinates (m) -> vehicle (m)."
    )
    cx_right: float | None = Field(
        None,
        description="Principal point column of the right rectified image, px; default cx. "
        "cx_right - cx is Middlebury's doffs.",
    )
    rectification: Rectification | None = Field(
        None, description="How to rectify the raw images; absent if they are rectified."
    )

    @field_validator("camera_to_vehicle")
    @classmethod
    def _rigid_transform(cls, value: list[list[float]]) -> list[list[float]]:
        return check_rigid_transform(value)

    @model_validator(mode="after")
    def _principal_point_inside(self) -> StereoCalibration:
        check_principal_point(self)
        return self

    def camera_to_vehicle_matrix(self) -> np.ndarray:
        """The 4x4 transform left camera -> vehicle as an array (m)."""
        return np.asarray(self.camera_to_vehicle, dtype=float)

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix in px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def T_vehicle_camera(self) -> np.ndarray:
        """4x4 transform left camera -> vehicle as an array (m)."""
        return np.asarray(self.camera_to_vehicle, dtype=float)

    @property
    def focal_baseline(self) -> float:
        """``fx * baseline`` in px m: depth ``Z = focal_baseline / (d + doffs)``."""
        return self.fx * self.baseline

    @property
    def doffs(self) -> float:
        """``cx_right - cx``, px (0 without ``cx_right``): disparity ``d = fx B / Z - doffs``."""
        return 0.0 if self.cx_right is None else self.cx_right - self.cx

    @classmethod
    def from_camera_info(
        cls, left: str | Path, right: str | Path, camera_to_vehicle: Any = None
    ) -> StereoCalibration:
        """Read the two cameras' ROS ``CameraInfo`` YAML files; ``camera_to_vehicle`` (4x4,
        m) is the raw left camera's pose (default: at the vehicle origin, looking along x).
        Raises FileFormatError or SchemaError naming the file and field (see
        :mod:`rough_map.calibration_files`)."""
        return cls._checked(camera_info_values(left, right, camera_to_vehicle), right)

    @classmethod
    def from_opencv(cls, path: str | Path, camera_to_vehicle: Any = None) -> StereoCalibration:
        """Read an OpenCV ``FileStorage`` file (``M1 D1 M2 D2 R T``, T in m, optionally ``R1
        R2 P1 P2``); ``camera_to_vehicle`` and errors as :meth:`from_camera_info`."""
        return cls._checked(opencv_values(path, camera_to_vehicle), path)

    @classmethod
    def _checked(cls, values: dict[str, Any], path: str | Path) -> StereoCalibration:
        try:
            return cls.model_validate(values)
        except ValidationError as err:
            raise schema_error(path, err) from err

    @classmethod
    def from_file(cls, path: str | Path) -> StereoCalibration:
        """Read a calibration from YAML (``.yaml``/``.yml``) or JSON (``.json``).

        Raises
        ------
        FileFormatError
            The file cannot be read or parsed.
        SchemaError
            A field is missing, unknown or invalid.
        """
        return load_model(path, cls)

    def to_file(self, path: str | Path) -> None:
        """Write the calibration as YAML (or JSON if ``path`` ends in ``.json``)."""
        path = Path(path)
        data = self.model_dump(exclude_none=True)
        text = (
            json.dumps(data, indent=2)
            if path.suffix.lower() == ".json"
            else yaml.safe_dump(data, sort_keys=False)
        )
        path.write_text(text, encoding="utf-8")

    @classmethod
    def xb3_default(cls) -> StereoCalibration:
        """An XB3-like rig (wide pair, 3.8 mm lenses) as mounted for the paper's patch.

        1280x960 px, ``fx = fy = 985`` px (66 deg horizontal field of view), baseline 0.24 m.
        The left camera is 1.00 m above the ground, 0.20 m behind the vehicle origin and
        0.12 m to the left of the centre line (the rig is centred), pitched down 42 deg. The
        flat 0.896 m patch centred 1 m ahead projects to columns 376-1095 and rows 292-672 of
        the left image (>= 184 px clear of the right image's left edge), disparities 125-193
        px (depth 1.23-1.89 m). Widened by 5 cm and +-0.15 m in height (the patch path's
        search volume) it still fits: columns 298-1198, rows 208-773, disparities 116-217.
        """
        rotation = rotation_matrix(pitch=math.radians(42.0)) @ CAMERA_AXES_IN_VEHICLE
        transform = np.eye(4)
        transform[:3, :3] = rotation
        transform[:3, 3] = [-0.20, 0.12, 1.00]
        return cls(
            fx=985.0,
            fy=985.0,
            cx=639.5,
            cy=479.5,
            width=1280,
            height=960,
            baseline=0.24,
            camera_to_vehicle=transform.tolist(),
        )


def _validated(cls: type[StereoCalibration], values: dict, path: str | Path) -> StereoCalibration:
    try:
        return cls.model_validate(values)
    except ValidationError as err:
        raise schema_error(path, err) from err


class FrameSpec(_Model):
    """One capture along a traverse: time, vehicle pose and the sensor data taken there.

    A frame has a point cloud, a rectified stereo pair, or both.
    """

    t: float = Field(description="Time, s (strictly increasing along the traverse).")
    pose: Pose
    cloud: RelativePath | None = Field(
        None, description="Point cloud in the vehicle frame (m), any format read_cloud reads."
    )
    left: RelativePath | None = Field(None, description="Left rectified image.")
    right: RelativePath | None = Field(None, description="Right rectified image.")
    label: str | None = Field(None, min_length=1, description="Terrain class name.")
    imu: ImuAttitude | None = None

    @model_validator(mode="after")
    def _pairs(self) -> FrameSpec:
        if (self.left is None) != (self.right is None):
            raise ValueError("left and right images come together")
        return self


class SurfaceSpec(_Model):
    """A height raster the frames' patches are cut from, at each frame's pose: a route
    planned over a survey (:mod:`rough_map.io.route`)."""

    path: RelativePath = Field(
        description="Height raster: a GDAL raster, .crg, .las/.laz, or .npy with its spacing."
    )
    spacing: float | None = Field(
        None, gt=0, le=1e3, description="Cell size in m of a .npy grid (its own otherwise)."
    )
    origin: tuple[float, float] | None = Field(
        None, description="World (x, y) in m of the north-west corner of a .npy grid."
    )


class TraverseSpec(_Model):
    """Content of ``traverse.json``/``traverse.yaml``: a run of a vehicle over terrain."""

    model_config = ConfigDict(title="Traverse")

    schema_version: Literal["1.0"] = Field(description="Version of this format.")
    name: str = Field(min_length=1, description="Name of the traverse.")
    crs: CrsField = Field(Crs(code="local"), description="CRS of the world frame.")
    calibration: StereoCalibration | None = Field(
        None, description="Stereo rig (intrinsics in px, baseline in m, camera_to_vehicle)."
    )
    height_field: RelativePath | None = Field(
        None, description="Ground-truth height field (.npz), e.g. from a simulator."
    )
    cloud_frame: Literal["vehicle", "world"] = Field(
        "vehicle",
        description="Frame of the clouds' points: 'vehicle' (x forward, y left, z up, m), or "
        "'world' (the world frame of the poses, as registered scans are): each cloud is then "
        "moved into the vehicle frame with its frame's pose.",
    )
    metadata: dict[str, Any] = Field(
        default_factory=dict, description="Free-form information (source, ground truth, ...)."
    )
    surface: SurfaceSpec | None = Field(
        None,
        description="A height raster the patches are cut from at each frame's pose (a route "
        "over a survey): frames then need no cloud or images.",
    )
    frames: list[FrameSpec] = Field(min_length=1)

    @field_validator("frames")
    @classmethod
    def _frames_have_data(cls, frames: list[FrameSpec], info: ValidationInfo) -> list[FrameSpec]:
        if info.data.get("surface") is not None:
            return frames
        for i, f in enumerate(frames):
            if f.cloud is None and f.left is None:
                raise PydanticCustomError(
                    "frame_data",
                    "a frame needs a cloud or a left/right image pair",
                    {"frame_index": i},
                )
        return frames

    @field_validator("frames")
    @classmethod
    def _times_increase(cls, frames: list[FrameSpec]) -> list[FrameSpec]:
        for i in range(1, len(frames)):
            if not frames[i].t > frames[i - 1].t:
                raise PydanticCustomError(
                    "time_order",
                    "time {t} s is not after frames[{previous}].t = {t_previous} s",
                    {
                        "frame_index": i,
                        "t": frames[i].t,
                        "previous": i - 1,
                        "t_previous": frames[i - 1].t,
                    },
                )
        return frames

    @field_serializer("crs")
    def _crs_short(self, crs: Crs) -> str | dict[str, Any]:
        return crs.code if crs.origin is None else crs.model_dump(mode="json", exclude_none=True)


SCHEMAS: dict[str, type[BaseModel]] = {"traverse": TraverseSpec}
"""Models whose JSON Schema is published in ``data_schema/<name>.schema.json``."""


# --------------------------------------------------------------------------------------------
# Loading


# The loaders live in rough_map.config_files (re-exported here).


# --------------------------------------------------------------------------------------------
# JSON Schemas


def schema_texts() -> dict[str, str]:
    """The JSON Schema text of each model in :data:`SCHEMAS`, by file name."""
    texts = {}
    for name, model in SCHEMAS.items():
        schema = {"$schema": _JSON_SCHEMA_DIALECT, **model.model_json_schema()}
        texts[f"{name}.schema.json"] = json.dumps(schema, indent=2, ensure_ascii=False) + "\n"
    return texts


def write_schemas(out_dir: str | Path) -> list[Path]:
    """Write ``<name>.schema.json`` for every model in :data:`SCHEMAS`.

    Parameters
    ----------
    out_dir : str or Path
        Folder to write into (created if needed), normally ``data_schema/``.

    Returns
    -------
    list of Path
        The files written.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for file_name, text in schema_texts().items():
        target = out_dir / file_name
        with atomic_output(target) as tmp:
            tmp.write_text(text, encoding="utf-8")
        written.append(target)
    return written


# --------------------------------------------------------------------------------------------
# Plain JSON values


def jsonable(value: Any) -> Any:
    """``value`` as plain JSON types, for the JSON files and outputs of rough_map.

    Numpy scalars and arrays become numbers and lists, NaN and inf None (JSON has no
    NaN), paths strings, objects with a ``to_dict()`` (such as
    :class:`rough_map.evaluation.near_far.AccuracyTable`) and dataclasses dicts.

    Raises
    ------
    TypeError
        Something else that JSON cannot hold.
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, Path):
        return str(value)
    if callable(getattr(value, "to_dict", None)):
        return jsonable(value.to_dict())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return jsonable(dataclasses.asdict(value))
    raise TypeError(f"cannot write a {type(value).__name__} as JSON")
