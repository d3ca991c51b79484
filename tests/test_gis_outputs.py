"""Outputs that GIS tools read natively: class names in GDAL, a QGIS style, a layers tag
that lists the bands, the path as GeoJSON (rough-map map)."""

import json
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import rasterio

from rough_map.cli.main import main
from rough_map.config import Crs
from rough_map.export.profiles import class_colour
from rough_map.export.vector import path_feature_collection
from rough_map.io.traverse import load_traverse
from rough_map.workflow import analyse


@pytest.fixture(scope="module")
def mapped(small_traverse: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("gis") / "map"
    assert main(["-q", "map", str(small_traverse), "--out", str(out), "--no-png"]) == 0
    return out


def test_the_class_raster_names_its_classes_for_gdal(mapped: Path) -> None:
    tif = mapped / "map_class.tif"
    with rasterio.open(tif) as ds:
        names = json.loads(ds.tags(1)["class_names"])
    band = ET.parse(f"{tif}.aux.xml").getroot().find("PAMRasterBand")
    assert band is not None and band.get("band") == "1"
    assert [c.text for c in band.iter("Category")] == names
    rows = band.find("GDALRasterAttributeTable").findall("Row")
    assert [[f.text for f in r.findall("F")][:2] for r in rows] == [
        [str(i), n] for i, n in enumerate(names)
    ]
    assert [int(f.text) for f in rows[0].findall("F")[2:]] == list(class_colour(names[0], 0))


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="no gdalinfo (gdal-bin)")
def test_gdalinfo_lists_the_categories(mapped: Path) -> None:
    out = subprocess.run(["gdalinfo", str(mapped / "map_class.tif")], capture_output=True,
                         text=True, check=True).stdout  # fmt: skip
    with rasterio.open(mapped / "map_class.tif") as ds:
        names = json.loads(ds.tags(1)["class_names"])
    block = out.split("Categories:")[1].split("Metadata:")[0]
    assert [line.split(":", 1)[1].strip() for line in block.strip().splitlines()] == names
    assert "<GDALRasterAttributeTable" in out


def test_a_qgis_style_sits_beside_the_class_raster(mapped: Path) -> None:
    with rasterio.open(mapped / "map_class.tif") as ds:
        names = json.loads(ds.tags(1)["class_names"])
    root = ET.parse(mapped / "map_class.qml").getroot()
    renderer = root.find("pipe/rasterrenderer")
    assert renderer is not None and renderer.get("type") == "paletted"
    entries = renderer.findall("colorPalette/paletteEntry")
    assert [(e.get("value"), e.get("label")) for e in entries] == [
        (str(i), n) for i, n in enumerate(names)
    ]
    r, g, b = class_colour(names[1], 1)
    assert entries[1].get("color") == f"#{r:02x}{g:02x}{b:02x}"


def test_the_layers_tag_lists_exactly_the_bands(mapped: Path) -> None:
    for tif in ("map.tif", "map_class.tif"):
        with rasterio.open(mapped / tif) as ds:
            assert json.loads(ds.tags()["layers"]) == list(ds.descriptions), tif


def test_the_path_and_frames_are_geojson_in_lon_lat(mapped: Path, small_traverse: Path) -> None:
    from rasterio.warp import transform

    data = json.loads((mapped / "map_path.geojson").read_text())
    assert data["type"] == "FeatureCollection" and "rough_map_crs" not in data
    path, *frames = data["features"]
    assert path["geometry"]["type"] == "LineString" and path["properties"]["name"] == "path"
    trav = load_traverse(small_traverse)
    assert len(frames) == len(trav.frames)
    lon = [f["geometry"]["coordinates"][0] for f in frames]
    lat = [f["geometry"]["coordinates"][1] for f in frames]
    assert all(-180 <= v <= 180 for v in lon) and all(-90 <= v <= 90 for v in lat)
    # back to the traverse's frame: within a millimetre of the poses
    x, y = transform("EPSG:4326", trav.spec.crs.rasterio(), lon, lat)
    poses = trav.poses()
    np.testing.assert_allclose(x, poses[:, 0], atol=1e-3)
    np.testing.assert_allclose(y, poses[:, 1], atol=1e-3)
    props = frames[0]["properties"]
    assert {"frame", "t_s", "distance_m", "valid", "R_m3_per_rad", "w", "iso_class", "class",
            "level"} <= set(props)  # fmt: skip
    labels = (mapped / "labels.csv").read_text().splitlines()
    head = labels[0].split(",")
    first = dict(zip(head, labels[1].split(","), strict=True))
    assert props["class"] == first["filtered_class"] and props["level"] == first["level"]


def test_a_local_frame_without_origin_stays_in_metres(small_traverse: Path) -> None:
    result = analyse(load_traverse(small_traverse), None, near_far=False)
    data = path_feature_collection(result.features, Crs(code="local"))
    assert "metres" in data["rough_map_crs"]
    xy = np.array([f["geometry"]["coordinates"] for f in data["features"][1:]])
    np.testing.assert_allclose(xy[:, 0], result.features["x"], atol=1e-3)
    json.dumps(data, allow_nan=False)  # no NaN in the file: unknown numbers are null
