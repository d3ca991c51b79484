"""Grid geometry, layers, growth and the grid_map conversion (rough_map.map.grid)."""

import math

import numpy as np
import pytest

from rough_map.config import Crs, GeodeticOrigin
from rough_map.errors import InputError
from rough_map.map import (
    GridGeometry,
    GridMap,
    LayerInfo,
    from_grid_map,
    to_grid_map,
)


def ramp_map(shape=(7, 12), res=0.25, origin=(-1.0, 2.5)) -> GridMap:
    """A map whose layer ``xy`` is 1000 x + y at each cell centre (unique per cell)."""
    g = GridMap(GridGeometry(res, origin, shape, Crs.from_any("EPSG:32633"), "utm"))
    xc, yc = g.geometry.xy()
    g.add_layer("xy", units="m", description="1000 x + y", data=1000 * xc[None, :] + yc[:, None])
    g.add_layer("count", units="1", fill=0.0)
    return g


# -- geometry --------------------------------------------------------------------------------


def test_cell_centres_rows_go_north_columns_east():
    geo = GridGeometry(0.5, (10.0, -4.0), (3, 4))
    x, y = geo.xy()
    np.testing.assert_allclose(x, [10.25, 10.75, 11.25, 11.75])
    np.testing.assert_allclose(y, [-3.75, -3.25, -2.75])
    assert geo.bounds == (10.0, -4.0, 12.0, -2.5)
    assert geo.center == (11.0, -3.25)
    rows, cols = geo.cell_of([10.1, 11.9, 9.9], [-3.9, -2.6, -3.1])
    assert rows.tolist() == [0, 2, 1] and cols.tolist() == [0, 3, -1]
    assert geo.inside(rows, cols).tolist() == [True, True, False]
    cx, cy = geo.cell_center(rows[:2], cols[:2])
    np.testing.assert_allclose(cx, [10.25, 11.75])
    np.testing.assert_allclose(cy, [-3.75, -2.75])


def test_covering_is_on_the_lattice_and_covers():
    geo = GridGeometry.covering((1.23, -0.71, 4.56, 2.02), 0.1, margin=0.5)
    k = np.array(geo.origin) / 0.1
    np.testing.assert_allclose(k, np.round(k), atol=1e-9)
    x0, y0, x1, y1 = geo.bounds
    assert x0 <= 1.23 - 0.5 and y0 <= -0.71 - 0.5 and x1 >= 4.56 + 0.5 and y1 >= 2.02 + 0.5
    assert x1 - x0 < 4.56 - 1.23 + 1.0 + 0.2  # not more than one cell of slack per side


def test_geotransform_is_north_up():
    geo = GridGeometry(0.2, (3.0, 5.0), (10, 20))
    assert geo.transform().to_gdal() == (3.0, 0.2, 0.0, 7.0, 0.0, -0.2)
    # the south-west corner of the map is the bottom-left corner of the north-up raster
    assert geo.transform() @ (0, 10) == pytest.approx((3.0, 5.0))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"resolution": 0.0}, "resolution must be a positive"),
        ({"resolution": 0.1, "origin": (math.nan, 0.0)}, "origin must be finite"),
        ({"resolution": 0.1, "shape": (-1, 3)}, "shape must be"),
        ({"resolution": 0.1, "crs": "WGS84"}, "crs must be .local., .EPSG:<code>."),
    ],
)
def test_bad_geometry(kwargs, match):
    with pytest.raises(InputError, match=match):
        GridGeometry(**kwargs)


# -- CRS ------------------------------------------------------------------------------------


def test_crs_from_traverse_spec_and_shorthands():
    local = Crs.from_any(Crs(code="local", origin=GeodeticOrigin(lat=40.35, lon=18.17, alt=5)))
    assert local.code == "local" and local.origin == GeodeticOrigin(lat=40.35, lon=18.17, alt=5)
    proj = local.proj_string()
    assert proj is not None and "+proj=tmerc" in proj and "+lat_0=40.35" in proj
    assert "+lon_0=18.17" in proj and "+k=1" in proj and "+ellps=WGS84" in proj
    assert Crs.from_any(32633).epsg == 32633
    assert Crs.from_any("epsg:32633").proj_string() == "EPSG:32633"
    assert Crs.from_any(None).proj_string() is None
    with pytest.raises(InputError, match="only meaningful with crs 'local'"):
        Crs.from_any({"code": "EPSG:32633", "origin": {"lat": 1.0, "lon": 2.0, "alt": 3.0}})


# -- layers ---------------------------------------------------------------------------------


def test_layers_have_units_and_check_shapes():
    g = GridMap(GridGeometry(0.1, (0, 0), (4, 5)))
    arr = g.add_layer("R", units="m^3/rad", description="overall energy")
    assert arr.shape == (4, 5) and np.all(np.isnan(arr))
    assert g.units("R") == "m^3/rad" and g.info("R") == LayerInfo("m^3/rad", "overall energy")
    g["R"] = 2.0
    assert np.all(g["R"] == 2.0)
    with pytest.raises(InputError, match="exists already"):
        g.add_layer("R", units="1")
    with pytest.raises(InputError, match="do not fit a map of shape"):
        g["R"] = np.zeros((5, 4))
    with pytest.raises(InputError, match="no layer 'nope'"):
        g["nope"]
    g.drop_layer("R")
    assert g.layers == ()


def test_layers_made_together_are_as_if_made_one_by_one():
    """``add_layers_as`` (the tiles' blank layers, in one block) against ``add_layer_as``."""
    infos = [
        ("count", LayerInfo("1", "patches", 0.0, "internal")),
        ("R", LayerInfo("m^3/rad", "overall energy")),
        ("class", LayerInfo("1", "", math.nan, "class", ("a", "b"))),
    ]
    geometry = GridGeometry(0.1, (0, 0), (3, 4))
    one, block = GridMap(geometry), GridMap(geometry)
    for name, info in infos:
        one.add_layer_as(name, info)
    block.add_layers_as(infos)
    assert block.layers == one.layers
    for name, _ in infos:
        assert block.info(name) == one.info(name)
        assert np.array_equal(block[name], one[name], equal_nan=True)
    block["count"][1, 2] += 5.0  # each layer is its own array
    assert block["count"].sum() == 5.0 and np.isnan(block["R"]).all()
    with pytest.raises(InputError, match="layer 'R' exists already"):
        block.add_layers_as([("R", infos[1][1])])
    with pytest.raises(InputError, match="layer 'x' exists already"):
        GridMap(GridGeometry(0.1, (0, 0), (3, 4))).add_layers_as([("x", infos[0][1])] * 2)
    with pytest.raises(InputError, match=r"\(name, LayerInfo\) pairs, got ''"):
        block.add_layers_as([("", infos[0][1])])


def test_height_field_view_samples_cell_centres():
    g = ramp_map()
    hf = g.to_height_field("xy")
    xc, yc = g.geometry.xy()
    v = hf.sample(np.array([xc[3]]), np.array([yc[5]]))
    assert v[0] == pytest.approx(1000 * xc[3] + yc[5])


# -- growth ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bounds",
    [
        (-5.0, 3.0, -4.0, 3.5),
        (1.0, -3.0, 1.5, -2.0),
        (4.0, 3.0, 9.0, 3.2),
        (0.0, 5.0, 0.5, 9.0),
        (-3.0, -3.0, 8.0, 8.0),
    ],
)
def test_map_grows_keeping_world_positions(bounds):
    g = ramp_map()
    old = g.copy()
    g["count"][2, 3] = 5.0
    di, dj = g.ensure_covers(bounds, margin=0.3)
    geo = g.geometry
    assert geo.contains(bounds)
    # still on the lattice of the original map
    k = (np.array(geo.origin) - np.array(old.geometry.origin)) / geo.resolution
    np.testing.assert_allclose(k, np.round(k), atol=1e-9)
    assert (di, dj) == (-round(k[1]), -round(k[0]))
    rows, cols = old.shape
    np.testing.assert_array_equal(g["xy"][di : di + rows, dj : dj + cols], old["xy"])
    assert g["count"][2 + di, 3 + dj] == 5.0
    # new cells hold each layer's fill value
    new = np.ones(g.shape, bool)
    new[di : di + rows, dj : dj + cols] = False
    assert np.all(np.isnan(g["xy"][new])) and np.all(g["count"][new] == 0)
    # values still sit at the same world positions
    xc, yc = geo.xy()
    ok = np.isfinite(g["xy"])
    np.testing.assert_allclose(g["xy"][ok], (1000 * xc[None, :] + yc[:, None])[ok])


def test_no_growth_inside():
    g = ramp_map()
    shape = g.shape
    assert g.ensure_covers((0.0, 3.0, 0.5, 3.5)) == (0, 0)
    assert g.shape == shape


def test_cells_at_grows_or_refuses():
    g = ramp_map()
    with pytest.raises(InputError, match="outside the map"):
        g.cells_at([20.0], [20.0], grow=False)
    cells = g.cells_at([20.0, -1.0], [20.0, 2.6])
    x, y = g.geometry.cell_center(cells[:, 0], cells[:, 1])
    np.testing.assert_allclose(x, [20.0, -1.0], atol=g.resolution / 2)
    np.testing.assert_allclose(y, [20.0, 2.6], atol=g.resolution / 2)


# -- grid_map conventions -------------------------------------------------------------------


def test_grid_map_index_convention():
    g = ramp_map()
    gm = to_grid_map(g)
    nx, ny = gm.size
    assert gm.layers["xy"].shape == (nx, ny) == (g.shape[1], g.shape[0])
    assert gm.position == g.geometry.center and gm.length == g.geometry.length
    assert gm.frame_id == "utm"
    xc, yc = g.geometry.xy()
    # (0, 0) is the cell with the largest x and largest y
    assert gm.layers["xy"][0, 0] == 1000 * xc[-1] + yc[-1]
    # grid_map's getIndexFromPosition: index = floor((position + length / 2 - p) / res)
    rng = np.random.default_rng(1)
    x0, y0, x1, y1 = g.geometry.bounds
    for px, py in zip(rng.uniform(x0, x1, 50), rng.uniform(y0, y1, 50), strict=True):
        r = math.floor((gm.position[0] + gm.length[0] / 2 - px) / gm.resolution)
        c = math.floor((gm.position[1] + gm.length[1] / 2 - py) / gm.resolution)
        i, j = g.geometry.cell_of(px, py)
        assert gm.layers["xy"][r, c] == g["xy"][i, j]
    # row index increases along -x, column index along -y
    assert np.all(np.diff(gm.layers["xy"], axis=0) < -100)
    assert np.all((np.diff(gm.layers["xy"], axis=1) < 0) & (np.diff(gm.layers["xy"], axis=1) > -1))


def test_grid_map_round_trip():
    g = ramp_map()
    g.add_layer("hidden", units="1", fill=0.0, kind="internal")
    gm = to_grid_map(g)
    assert "hidden" not in gm.layers and set(gm.layers) == {"xy", "count"}
    back = from_grid_map(gm, crs=g.crs, info={"xy": g.info("xy")})
    assert back.geometry.shape == g.shape
    np.testing.assert_allclose(back.geometry.origin, g.geometry.origin, atol=1e-12)
    assert back.resolution == g.resolution and back.crs == g.crs
    np.testing.assert_array_equal(back["xy"], g["xy"])
    assert back.units("xy") == "m"


def test_from_grid_map_rejects_wrong_shapes():
    gm = to_grid_map(ramp_map())
    gm.layers["xy"] = gm.layers["xy"].T
    with pytest.raises(InputError, match="grid_map size"):
        from_grid_map(gm)


def test_add_at_adds_into_the_layers_through_copies_and_growth():
    """``add_at`` (a patch's sums into a tile) on block layers, layers of their own, a
    pickled copy and a grown map: the same as adding layer by layer."""
    import pickle

    infos = [(n, LayerInfo("1", "", 0.0, "internal")) for n in ("count", "sum_w", "n")]
    grid = GridMap(GridGeometry(0.1, (0, 0), (3, 4)))
    grid.add_layers_as(infos)
    grid.add_layer("extra", units="1", fill=0.0)
    cells = np.array([0, 5, 11])
    sums = [("count", 1.0), ("sum_w", -2.5), ("extra", 3.0), ("absent", 9.0)]
    for g in (grid, pickle.loads(pickle.dumps(grid)), grid.copy()):
        g.add_at(cells, sums)
        for name, value in sums[:3]:
            flat = g[name].reshape(-1)
            assert np.all(flat[cells] == value) and np.count_nonzero(flat) == 3, name
        assert not g["n"].any()
    grid.add_at(cells, [("n", 1.0), ("n", 2.0)])  # a name twice: both values
    assert np.all(grid["n"].reshape(-1)[cells] == 3.0)
    grid.drop_layer("sum_w")
    grid.ensure_covers((0.0, 0.0, 1.0, 1.0), margin=0.0)
    grid.add_at(np.array([0]), [("count", 1.0), ("sum_w", 1.0)])
    assert grid["count"].sum() == 4.0 and "sum_w" not in grid
