"""The vehicle path and its frames as GeoJSON, which GIS tools (QGIS, GDAL's ogr, geopandas,
web maps) read natively.

``map_path.geojson`` is one FeatureCollection (RFC 7946):

* a ``LineString`` feature ``path``: the poses of the frames in order;
* a ``Point`` feature per frame at its pose, with properties ``frame``, ``t_s``,
  ``distance_m``, ``valid``, ``R_m3_per_rad``, ``w``, ``iso_class``, ``label`` (the true
  class, when known) and, with a model, ``class`` (filtered), ``class_confidence``,
  ``level`` and ``defect``. Unknown numbers are ``null``.

Coordinates are longitude and latitude (WGS 84, degrees), as RFC 7946 asks, converted from
the traverse's CRS (an EPSG code, or a local frame with a geodetic origin). A local frame
without a geodetic origin cannot be placed on the Earth: its coordinates are then x and y in
metres of that frame, and the collection says so in its ``rough_map_crs`` member, which
GIS tools ignore.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import iso8608
from rough_map._files import atomic_output
from rough_map.classify import TerrainPrediction
from rough_map.config import Crs
from rough_map.features import FeatureTable

__all__ = ["path_feature_collection", "write_path_geojson"]


def _lon_lat(crs: Crs, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Longitude and latitude (degrees) of points in ``crs``; None for a local frame
    without a geodetic origin."""
    if crs.epsg is None and crs.origin is None:
        return None
    from rasterio.warp import transform

    ok = np.isfinite(x) & np.isfinite(y)
    lon, lat = np.full(x.shape, np.nan), np.full(y.shape, np.nan)
    if ok.any():
        lo, la = transform(crs.rasterio(), "EPSG:4326", x[ok].tolist(), y[ok].tolist())
        lon[ok], lat[ok] = lo, la
    return lon, lat


def _number(v: Any, digits: int = 6) -> float | None:
    v = float(v)
    return float(f"{v:.{digits}g}") if math.isfinite(v) else None


def path_feature_collection(
    features: FeatureTable, crs: Crs, prediction: TerrainPrediction | None = None
) -> dict[str, Any]:
    """The GeoJSON FeatureCollection of :func:`write_path_geojson`, as a dict."""
    x, y = np.asarray(features["x"], float), np.asarray(features["y"], float)
    geo = _lon_lat(crs, x, y)
    cx, cy, places = (geo[0], geo[1], 8) if geo is not None else (x, y, 3)
    ok = np.isfinite(cx) & np.isfinite(cy)
    coords = [
        [round(float(a), places), round(float(b), places)] for a, b in zip(cx, cy, strict=True)
    ]
    R = np.asarray(features["R"], float)
    iso = iso8608.iso_class(R)
    distance = features.distance()
    frames = []
    for i in range(len(features)):
        if not ok[i]:
            continue
        props: dict[str, Any] = {
            "frame": int(features["frame"][i]),
            "t_s": _number(features["t"][i], 9),
            "distance_m": _number(distance[i]),
            "valid": bool(features.valid[i]),
            "R_m3_per_rad": _number(R[i]),
            "w": _number(features["w"][i]),
            "iso_class": str(iso[i]),
            "label": str(features["label"][i]) if "label" in features.columns else "",
        }
        if prediction is not None:
            props["class"] = str(prediction.filtered_class[i])
            props["class_confidence"] = _number(prediction.filtered_confidence[i], 4)
            props["level"] = str(prediction.level[i])
            defect = prediction.defect
            props["defect"] = bool(defect[i]) if defect is not None else False
            novelty = None if prediction.novelty is None else _number(prediction.novelty[i], 3)
            props["novelty"] = novelty
            props["novel"] = None if novelty is None else bool(novelty > 1)
        frames.append({"type": "Feature", "id": i + 1, "properties": props,
                       "geometry": {"type": "Point", "coordinates": coords[i]}})  # fmt: skip
    line = [coords[i] for i in range(len(features)) if ok[i]]
    path = {
        "type": "Feature",
        "id": 0,
        "properties": {"name": "path", "frames": len(line)},
        "geometry": {"type": "LineString", "coordinates": line} if len(line) >= 2 else None,
    }
    out: dict[str, Any] = {"type": "FeatureCollection", "name": features.name}
    if geo is None:
        out["rough_map_crs"] = "local frame without a geodetic origin: x, y in metres"
    out["features"] = [path, *frames]
    return out


def write_path_geojson(
    features: FeatureTable,
    crs: Crs,
    path: str | Path,
    prediction: TerrainPrediction | None = None,
) -> Path:
    """Write the path and the frames of a traverse as GeoJSON (see the module docstring).

    Parameters
    ----------
    features : FeatureTable
        The traverse's features: poses ``x``, ``y`` (m, in ``crs``), ``t`` (s), R, w.
    crs : Crs
        The CRS of the poses (the map's).
    path : str or Path
        The ``.geojson`` file (written atomically).
    prediction : TerrainPrediction, optional
        The model's classes for the same frames.

    Returns
    -------
    Path
        ``path``.
    """
    collection = path_feature_collection(features, crs, prediction)
    path = Path(path)
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(collection, allow_nan=False), encoding="utf-8")
    return path
