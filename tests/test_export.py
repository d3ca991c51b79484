"""Export of maps: COG GeoTIFFs, PNGs, grid_map bags (rough_map.export)."""

import json
import math

import numpy as np
import pytest
import rasterio

from rough_map.config import Crs
from rough_map.errors import InputError
from rough_map.export import export_map
from rough_map.export.geotiff import (
    block_side,
    class_colours,
    overview_factors,
    value_layers,
    write_class_geotiff,
    write_values_geotiff,
)
from rough_map.export.gridmap_msg import read_gridmap_bag, write_gridmap_bag
from rough_map.export.png import (
    display_units,
    drawn_texts,
    layer_figure,
    layer_views,
    scale_bar_length,
    write_pngs,
)
from rough_map.export.profiles import CLASS_COLOURS, OTHER_CLASS_COLOURS, class_colour
from rough_map.features import FeatureTable
from rough_map.map import (
    EmptyMapWarning,
    from_grid_map,
    fuse_cell_probabilities,
    fuse_traverse,
)
from rough_map.patch import PatchSpec

NAMES = ("concrete", "dirt_road", "gravel")
E0, N0 = 500_123.4, 4_470_321.7  # UTM-sized coordinates: the transform must keep them


def table(x, y, yaw, R, valid=True):
    x = np.asarray(x, float)
    n = x.size
    full = lambda v: np.broadcast_to(np.asarray(v, float), (n,)).copy()  # noqa: E731
    cols = {
        "frame": np.arange(n),
        "t": np.arange(n) * 0.5,
        "x": x,
        "y": full(y),
        "yaw": full(yaw),
        "R": full(R),
        "w": full(2.2),
        "sigma_R": full(R) * 0.2,
        "sigma_w": full(0.1),
        "valid": np.broadcast_to(np.asarray(valid, bool), (n,)).copy(),
    }
    return FeatureTable(cols, np.zeros(0), np.zeros((n, 0)), "export-test")


@pytest.fixture
def patches():
    """Three patches far apart, each with its own R, class and level; yaw varies."""
    x = E0 + np.array([0.0, 4.0, 8.0])
    y = N0 + np.array([0.0, 1.0, -1.0])
    yaw = np.array([0.3, 2.0, -1.1])
    R = np.array([1e-5, 1e-4, 1e-3])
    probs = np.eye(3) * 0.8 + 0.2 / 3
    return table(x, y, yaw, R), probs, np.array([0.0, 1.0, 2.0])


@pytest.fixture
def utm_map(patches):
    ft, probs, levels = patches
    return fuse_traverse(ft, probs, NAMES, levels, resolution=0.1, crs="EPSG:32633")


# -- GeoTIFF --------------------------------------------------------------------------------


def test_cell_centres_read_back_lie_on_their_patch(tmp_path, patches, utm_map):
    ft, _, _ = patches
    path = write_values_geotiff(utm_map, tmp_path / "m.tif")
    spec = PatchSpec()
    with rasterio.open(path) as ds:
        band = ds.descriptions.index("R") + 1
        R = ds.read(band)
        for k in range(3):
            rows, cols = np.nonzero(np.isclose(R, ft["R"][k], rtol=1e-5))
            assert len(rows) > 50
            xs, ys = rasterio.transform.xy(ds.transform, rows, cols)  # pixel centres
            xs, ys = np.asarray(xs), np.asarray(ys)
            yaw = ft["yaw"][k]
            cx = ft["x"][k] + spec.ahead * math.cos(yaw)
            cy = ft["y"][k] + spec.ahead * math.sin(yaw)
            # the centroid of the cells is the patch centre, within half a cell
            assert math.hypot(xs.mean() - cx, ys.mean() - cy) < 0.05
            # and every cell centre lies in the oriented patch
            u = (xs - cx) * math.cos(yaw) + (ys - cy) * math.sin(yaw)
            v = -(xs - cx) * math.sin(yaw) + (ys - cy) * math.cos(yaw)
            assert np.all(np.abs(u) <= spec.size / 2 + 1e-6)
            assert np.all(np.abs(v) <= spec.size / 2 + 1e-6)
        # the file's rows are north-up: the map's last row is the file's first
        assert ds.transform.e < 0
        np.testing.assert_array_equal(np.isnan(R), np.isnan(np.flipud(utm_map["R"])))


@pytest.mark.filterwarnings("ignore:Use `@` matmul:PendingDeprecationWarning")  # rasterio 1.4
def test_transform_is_from_origin_at_the_north_west_corner(tmp_path, utm_map):
    """The map's origin is its south-west corner; the file's transform starts north-west."""
    geo = utm_map.geometry
    west, south, _, north = geo.bounds
    assert north == pytest.approx(south + geo.shape[0] * geo.resolution)
    expected = rasterio.transform.from_origin(west, north, geo.resolution, geo.resolution)
    assert geo.transform() == expected
    path = write_values_geotiff(utm_map, tmp_path / "m.tif", layers=["R"])
    with rasterio.open(path) as ds:
        assert ds.transform == expected
        # the GDAL geotransform it replaced
        assert ds.transform.to_gdal() == (west, geo.resolution, 0.0, north, 0.0, -geo.resolution)
        # the centre of the file's last row is the centre of the map's first (southern) row
        x, y = rasterio.transform.xy(ds.transform, ds.height - 1, 0)
        assert (x, y) == pytest.approx((west + geo.resolution / 2, south + geo.resolution / 2))


def test_value_bands_names_units_nodata_overviews(tmp_path, utm_map):
    path = write_values_geotiff(utm_map, tmp_path / "m.tif")
    with rasterio.open(path) as ds:
        assert ds.driver == "GTiff" and ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert set(ds.dtypes) == {"float32"} and math.isnan(ds.nodata)
        names = list(ds.descriptions)
        assert names[:5] == ["R", "w", "sigma_R", "sigma_w", "level"]
        assert names == value_layers(utm_map)
        assert {"count", "last_seen", "p_gravel"} <= set(names) and "class" not in names
        assert ds.tags(1)["units"] == "m^3/rad" and ds.tags(2)["units"] == "1"
        assert ds.units[:2] == ("m^3/rad", "1")  # GDAL's unit type, as QGIS shows it
        level = ds.tags(names.index("level") + 1)
        assert json.loads(level["categories"]) == ["low", "medium", "high"]
        assert level["VALUE_2"] == "high"
        assert json.loads(ds.tags()["class_names"]) == list(NAMES)
        assert ds.overviews(1) and ds.overviews(1)[0] == 2
        assert ds.crs.to_epsg() == 32633
        assert ds.block_shapes[0][0] > 1  # tiled, not stripped
        np.testing.assert_allclose(ds.read(2), np.flipud(utm_map["w"]).astype("f4"))
    assert not list(tmp_path.glob(".*")) and not list(tmp_path.glob("*.aux.xml"))


def test_class_band_colour_table_and_names(tmp_path, utm_map):
    path = write_class_geotiff(utm_map, tmp_path / "c.tif")
    with rasterio.open(path) as ds:
        assert ds.count == 1 and ds.dtypes[0] == "uint8" and ds.nodata == 255
        assert ds.descriptions == ("class",)
        assert ds.colorinterp[0] == rasterio.enums.ColorInterp.palette
        table = ds.colormap(1)
        assert table[0] == (*CLASS_COLOURS["concrete"], 255) and table[255][3] == 0
        assert len({table[i] for i in range(3)}) == 3
        tags = ds.tags(1)
        assert json.loads(tags["class_names"]) == list(NAMES)
        assert [tags[f"CLASS_{i}"] for i in range(3)] == list(NAMES)
        data = ds.read(1)
        assert set(np.unique(data)) == {0, 1, 2, 255}
        expect = np.flipud(np.where(np.isnan(utm_map["class"]), 255, utm_map["class"]))
        np.testing.assert_array_equal(data, expect)
        assert ds.overviews(1)
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"


def test_one_class_colour_everywhere(strip_map):
    """GeoTIFF colour tables, layer PNGs and report figures take one colour per class."""
    from matplotlib import colormaps

    from rough_map.export import figures, png

    tab10 = colormaps["tab10"]
    assert OTHER_CLASS_COLOURS == tuple(
        tuple(int(round(255 * v)) for v in tab10(i)[:3]) for i in range(10)
    )
    names = ("gravel", "asphalt", "lava", "concrete")
    table = class_colours(names)
    assert table[0][:3] == CLASS_COLOURS["gravel"] and table[1][:3] == OTHER_CLASS_COLOURS[1]
    assert [table[i][:3] for i in range(4)] == [class_colour(n, i) for i, n in enumerate(names)]
    assert figures.class_colour is class_colour
    layer_colours = png._colours(strip_map, "class")
    assert layer_colours == [
        tuple(v / 255 for v in class_colour(n, i)) for i, n in enumerate(LONG_NAMES)
    ]


def test_gtiff_fallback_keeps_overviews(tmp_path, utm_map):
    path = write_values_geotiff(
        utm_map, tmp_path / "g.tif", profile={"driver": "GTiff"}, layers=["R", "w"]
    )
    with rasterio.open(path) as ds:
        assert ds.descriptions == ("R", "w") and ds.overviews(1) and ds.profile["tiled"]


@pytest.mark.parametrize(
    ("crs", "check"),
    [
        (Crs.from_any("EPSG:32633"), lambda c: c.to_epsg() == 32633),
        (
            Crs.from_any({"code": "local", "origin": {"lat": 40.3515, "lon": 18.175, "alt": 50.0}}),
            lambda c: (
                c.to_dict().get("proj") == "tmerc"
                and c.to_dict()["lat_0"] == pytest.approx(40.3515)
                and c.to_dict()["lon_0"] == pytest.approx(18.175)
                and c.to_dict().get("k", c.to_dict().get("k_0")) == 1
            ),
        ),
        (Crs.from_any("local"), lambda c: c.to_wkt().startswith("LOCAL_CS")),
    ],
    ids=["epsg", "local-tmerc", "local-engineering"],
)
def test_crs_is_written(tmp_path, patches, crs, check):
    ft, probs, levels = patches
    g = fuse_traverse(ft, probs, NAMES, levels, crs=crs)
    path = write_values_geotiff(g, tmp_path / "m.tif", layers=["R"])
    with rasterio.open(path) as ds:
        assert ds.crs is not None and check(ds.crs)
        assert ds.tags()["crs_code"] == crs.code
        if crs.origin:
            o = crs.origin
            assert json.loads(ds.tags()["geodetic_origin"]) == [o.lat, o.lon, o.alt]


def test_overview_factors():
    assert overview_factors((5, 8)) == [2]
    assert overview_factors((40, 150)) == [2, 4, 8, 16]
    assert overview_factors((16, 16)) == [2]


def test_write_is_atomic_and_replaces(tmp_path, utm_map):
    path = tmp_path / "m.tif"
    path.write_bytes(b"old")
    write_values_geotiff(utm_map, path, layers=["R"])
    with rasterio.open(path) as ds:
        assert ds.descriptions == ("R",)
    with pytest.raises(InputError, match="not a class layer"):
        write_class_geotiff(utm_map, tmp_path / "x.tif", "R")
    assert not (tmp_path / "x.tif").exists() and not list(tmp_path.glob(".*"))


# -- PNG, grid_map bag, export_map ----------------------------------------------------------


def test_scale_bar_length():
    assert scale_bar_length(12.0) == 2.0
    assert scale_bar_length(100.0) == 20.0
    assert scale_bar_length(0.9) == 0.2
    with pytest.raises(InputError, match="positive length"):
        scale_bar_length(0.0)


def test_pngs(tmp_path, utm_map):
    import matplotlib.image as mpimg

    paths = write_pngs(utm_map, tmp_path, "m", layers=["R", "class"])
    assert set(paths) == {"R", "class"}
    for p in paths.values():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        img = mpimg.imread(p)
        assert img.ndim == 3 and img.shape[1] > 400


LONG_NAMES = (
    "concrete_with_expansion_joints",
    "dirt_road_after_rain",
    "coarse_gravel_pile",
    "compact_soil_of_the_orchard",
    "ploughed_soil_deep_furrows",
    "asphalt_with_potholes",
)


@pytest.fixture
def strip_map():
    """A long narrow near-field strip (12 m of patches along x) in a map with 6 m of room
    around it, six classes with long names, and a far-field cell 3 m to the side."""
    n = 25
    x = E0 + np.linspace(0.0, 12.0, n)
    ft = table(x, N0, 0.0, np.geomspace(1e-5, 1e-3, n))
    k = len(LONG_NAMES)
    probs = np.full((n, k), 0.1 / (k - 1))
    probs[np.arange(n), np.arange(n) % k] = 0.9
    g = fuse_traverse(ft, probs, LONG_NAMES, np.arange(n) % 3, margin=6.0)
    g.attrs["track"] = np.column_stack([x, np.full(n, N0)])
    cells = g.cells_at([E0 + 5.0], [N0 + 3.0])
    fuse_cell_probabilities(g, cells, np.full(k, 1 / k), 0.3, group="far", t=5.0)
    return g


def _boxes_overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.mark.parametrize("layer", ["class", "level", "R", "p_dirt_road_after_rain", "count"])
def test_png_texts_do_not_overlap_and_fit(strip_map, layer):
    fig = layer_figure(strip_map, layer)
    fig.canvas.draw()  # places the axis labels
    renderer = fig.canvas.get_renderer()
    texts = drawn_texts(fig)
    shown = {t.get_text() for t in texts}
    if layer == "class":  # a legend entry per class, each name whole
        assert set(LONG_NAMES) <= shown
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts]
    width, height = fig.bbox.width, fig.bbox.height
    for k, (text, box) in enumerate(boxes):
        assert box.x0 >= 0 and box.y0 >= 0 and box.x1 <= width and box.y1 <= height, text
        for other, box2 in boxes[k + 1 :]:
            assert not _boxes_overlap(box, box2), (text, other)


def test_png_keys_sit_off_the_map(strip_map):
    fig = layer_figure(strip_map, "class")
    renderer = fig.canvas.get_renderer()
    fig.canvas.draw()
    map_box = fig.axes[0].get_window_extent(renderer)
    keys = [a for a in fig.findobj() if a.get_gid() in ("scale-bar", "path-key")]
    assert {a.get_gid() for a in keys} == {"scale-bar", "path-key"}
    keys += fig.legends
    assert fig.legends, "the classes have a legend"
    for artist in keys:
        assert not _boxes_overlap(artist.get_window_extent(renderer), map_box), artist


def test_png_probability_scale_is_0_to_1(strip_map):
    data = strip_map["p_dirt_road_after_rain"]
    assert 0 < np.nanmin(data) and np.nanmax(data) < 1  # the data's own range is narrower
    fig = layer_figure(strip_map, "p_dirt_road_after_rain")
    norm = fig.axes[0].images[0].norm
    assert (norm.vmin, norm.vmax) == (0.0, 1.0)
    bar = fig.axes[1]  # the colour bar
    assert tuple(bar.get_xlim()) == (0.0, 1.0)


def test_png_near_field_is_cropped_to_its_data(strip_map):
    x0, y0, x1, _ = strip_map.geometry.bounds
    rows, cols = np.nonzero(np.isfinite(strip_map["R"]))
    res = strip_map.resolution
    data_x = (x0 + cols.min() * res, x0 + (cols.max() + 1) * res)
    data_y = (y0 + rows.min() * res, y0 + (rows.max() + 1) * res)
    views = layer_views(strip_map)
    assert views["R"] == views["class"] == views["p_asphalt_with_potholes"]  # one extent
    fig = layer_figure(strip_map, "R")
    ax = fig.axes[0]
    (vx0, vx1), (vy0, vy1) = ax.get_xlim(), ax.get_ylim()
    assert data_x[0] - 0.5 <= vx0 <= data_x[0] and data_x[1] <= vx1 <= data_x[1] + 0.5
    assert vy0 <= data_y[0] and data_y[1] <= vy1
    # the map is 6 m wider than the data on each side; the picture shows mostly data
    assert (vx1 - vx0) < 0.6 * (x1 - x0)
    known = np.isfinite(strip_map["R"]).sum() * res**2
    assert known / ((vx1 - vx0) * (vy1 - vy0)) > 0.4
    # the far field has its own extent, around its one cell 3 m to the side
    far = views["far_p_asphalt_with_potholes"]
    assert far[2] <= N0 + 3.0 <= far[3] and far[1] - far[0] <= 2.0 + 1e-6  # 20 cells


def test_png_units_are_written_one_way(strip_map):
    assert display_units("m^3/rad") == "m³/rad" and display_units("1") == ""
    fig = layer_figure(strip_map, "R")
    labels = " ".join(t.get_text() for t in drawn_texts(fig))
    assert "m³/rad" in labels and "m^" not in labels


def test_drawing_figures_leaves_the_backend_alone(tmp_path, strip_map):
    """No pyplot: a notebook's backend (here svg) is the same after drawing figures."""
    import matplotlib

    from rough_map.export import figures

    before = matplotlib.get_backend()
    matplotlib.use("svg")
    try:
        omega = np.geomspace(1.0, 100.0, 30)
        a = figures.profile_psd_fit(omega, 1e-4 * omega**-2.0, 1e-4, -2.0, tmp_path / "a.png")
        x0, y0, x1, y1 = strip_map.geometry.bounds
        b = figures.map_layers({"R": strip_map["R"]}, (x0, x1, y0, y1), tmp_path / "b.png")
        layer_figure(strip_map, "R")
        assert matplotlib.get_backend() == "svg"
        for p in (a, b):
            assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        matplotlib.use(before)


def test_gridmap_bag_round_trip(tmp_path, utm_map):
    path = write_gridmap_bag(utm_map, tmp_path / "bag")
    assert list(path.glob("*.mcap")) and (path / "metadata.yaml").is_file()
    (msg,) = read_gridmap_bag(path)
    back = from_grid_map(msg)
    assert back.shape == utm_map.shape and back.resolution == utm_map.resolution
    np.testing.assert_allclose(back.geometry.origin, utm_map.geometry.origin, atol=1e-6)
    assert msg.frame_id == "map"
    for name in ("R", "w", "class", "count", "p_gravel"):
        np.testing.assert_allclose(
            back[name], utm_map[name].astype("f4"), rtol=1e-6, equal_nan=True, err_msg=name
        )
    assert "sum_lnR" not in msg.layers  # internal layers stay home
    write_gridmap_bag(utm_map, path, layers=["R"])  # replaces the bag
    assert list(read_gridmap_bag(path)[0].layers) == ["R"]


def test_export_map_writes_everything(tmp_path, utm_map):
    cells = utm_map.cells_at([E0 + 12.0], [N0])
    fuse_cell_probabilities(utm_map, cells, [0.1, 0.1, 0.8], 0.3, group="far", t=5.0)
    for name in list(utm_map.layers):  # keep the PNG count (and the test time) small
        if name.startswith(("p_", "far_p_", "far_last", "sigma", "last")):
            utm_map.drop_layer(name)
    paths = export_map(utm_map, tmp_path / "out", name="run1", gridmap_bag=True)
    assert paths["geotiff"].name == "run1.tif"
    assert paths["geotiff_class"].name == "run1_class.tif"
    assert paths["geotiff_far_class"].name == "run1_far_class.tif"
    assert paths["gridmap_bag"].name == "run1_gridmap"
    pngs = {k for k in paths if k.startswith("png_")}
    assert pngs == {f"png_{n}" for n in utm_map.layers if utm_map.info(n).kind != "internal"}
    assert all(p.exists() for p in paths.values())
    with rasterio.open(paths["geotiff_far_class"]) as ds:
        assert ds.descriptions == ("far_class",) and ds.read(1).min() == 2


def test_export_of_an_empty_map(tmp_path):
    with pytest.warns(EmptyMapWarning):
        g = fuse_traverse(table([], 0.0, 0.0, 1e-4), np.zeros((0, 3)), NAMES)
    paths = export_map(g, tmp_path, png=False)
    with rasterio.open(paths["geotiff"]) as ds:
        assert np.all(np.isnan(ds.read(1))) and ds.overviews(1)
    with rasterio.open(paths["geotiff_class"]) as ds:
        assert np.all(ds.read(1) == 255)


@pytest.mark.parametrize(
    ("blocksize", "shape", "side"),
    [
        ("auto", (30, 18000), 64),
        ("auto", (100, 900), 128),
        ("auto", (300, 20), 64),
        ("auto", (400, 500), 256),
        (512, (30, 18000), 512),
    ],
)
def test_tile_side_fits_a_narrow_strip(blocksize, shape, side):
    assert block_side(blocksize, shape) == side


def test_a_long_strip_is_written_in_small_tiles(tmp_path, utm_map):
    path = write_values_geotiff(utm_map, tmp_path / "m.tif")
    with rasterio.open(path) as ds:
        want = block_side("auto", ds.shape)
        assert ds.block_shapes[0] == (want, want)
        assert want < 256 or min(ds.shape) >= 256
    pinned = write_values_geotiff(utm_map, tmp_path / "p.tif", profile={"blocksize": 256})
    with rasterio.open(pinned) as ds, rasterio.open(path) as auto:
        assert ds.block_shapes[0] == (256, 256)
        np.testing.assert_array_equal(ds.read(), auto.read())
