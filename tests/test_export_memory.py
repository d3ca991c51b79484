"""Export of long maps with little memory (rough_map.export): the GeoTIFFs are written a few
tiles at a time through a file on disk, yet hold what writing every band at once gives; the
PNGs free each figure before the next one."""

import gc

import numpy as np
import pytest
import rasterio
from rasterio.enums import Resampling
from rasterio.io import MemoryFile
from rasterio.shutil import copy as rio_copy

from rough_map.config import Crs
from rough_map.export import geotiff
from rough_map.export.geotiff import (
    class_colours,
    class_layers,
    overview_factors,
    value_layers,
    write_class_geotiff,
    write_values_geotiff,
)
from rough_map.export.layout import data_view
from rough_map.export.png import layer_figure, write_pngs
from rough_map.map.grid import GridMap
from rough_map.map.grid_geometry import GridGeometry

NAMES = ("concrete", "dirt_road", "gravel")


def strip(shape: tuple[int, int], seed: int = 0) -> GridMap:
    """A map of random values with holes (NaN) and an empty corner, three value layers, a
    count and a class layer."""
    rng = np.random.default_rng(seed)
    geo = GridGeometry(0.1, (500_000.0, 4_470_000.0), shape, Crs(code="EPSG:32633"), "map")
    g = GridMap(geo, attrs={"name": "strip", "class_names": NAMES})
    holes = rng.random(shape) < 0.3
    holes[: shape[0] // 3, : shape[1] // 4] = True
    for name in ("R", "w", "sigma_R"):
        g.add_layer(name, units="1", data=np.where(holes, np.nan, rng.lognormal(size=shape)))
    g.add_layer("count", units="1", fill=0.0, data=np.where(holes, 0, rng.integers(1, 9, shape)))
    classes = np.where(holes, np.nan, rng.integers(0, len(NAMES), shape))
    g.add_layer("class", units="1", kind="class", categories=NAMES, data=classes)
    return g


def all_at_once(grid: GridMap, path, layer: str | None = None) -> None:
    """The bands all at once through an in-memory GTiff, copied to a COG: how the files were
    first written (the reference of the data and overviews)."""
    if layer is None:
        bands = np.stack([np.flipud(grid[n]) for n in value_layers(grid)]).astype("float32")
        dtype, nodata, resampling, predictor = "float32", np.nan, Resampling.average, "YES"
    else:
        values = np.flipud(grid[layer])
        bands = np.where(np.isfinite(values), values, 255).astype("uint8")[None]
        dtype, nodata, resampling, predictor = "uint8", 255, Resampling.mode, "NO"
    with MemoryFile() as mem:
        with mem.open(
            driver="GTiff",
            width=grid.shape[1],
            height=grid.shape[0],
            count=len(bands),
            dtype=dtype,
            nodata=nodata,
            crs=grid.crs.rasterio(),
            transform=grid.geometry.transform(),
        ) as ds:
            ds.write(bands)
            if layer is not None:  # the colour table changes how GDAL computes overviews
                ds.write_colormap(1, class_colours(NAMES))
            ds.build_overviews(overview_factors(grid.shape), resampling)
        with mem.open() as src:
            rio_copy(
                src,
                path,
                driver="COG",
                BLOCKSIZE=256,
                COMPRESS="DEFLATE",
                PREDICTOR=predictor,
                OVERVIEWS="FORCE_USE_EXISTING",
            )


def assert_same_pixels(a, b) -> None:
    """Same bands at full resolution and at every overview level."""
    with rasterio.open(a) as ds:
        levels = len(ds.overviews(1))
        assert levels == len(overview_factors((ds.height, ds.width)))
    for level in [None, *range(levels)]:
        kw = {} if level is None else {"overview_level": level}
        with rasterio.open(a, **kw) as x, rasterio.open(b, **kw) as y:
            assert (x.count, x.shape) == (y.count, y.shape)
            np.testing.assert_array_equal(x.read(), y.read(), err_msg=f"level {level}")


@pytest.mark.parametrize("shape", [(20, 3000), (3000, 20), (300, 700)])
def test_written_in_small_windows_the_file_holds_all_bands_at_once(tmp_path, monkeypatch, shape):
    """Small windows (rows and columns; the long map lying east or north) give the pixels
    and overviews of all bands at once: a narrow map whose overviews shrink to one column
    too (GDAL computes those from the full image, which a band-interleaved intermediate
    file would change)."""
    monkeypatch.setattr(geotiff, "_CHUNK_BYTES", 50_000)
    g = strip(shape)
    chunks = geotiff._chunks(g.shape, geotiff._source_block(g.shape[1]), 4 * 4)
    assert len(chunks) > 4
    write_values_geotiff(g, tmp_path / "m.tif")
    all_at_once(g, tmp_path / "ref.tif")
    assert_same_pixels(tmp_path / "m.tif", tmp_path / "ref.tif")
    write_class_geotiff(g, tmp_path / "c.tif")
    all_at_once(g, tmp_path / "ref_c.tif", "class")
    assert_same_pixels(tmp_path / "c.tif", tmp_path / "ref_c.tif")
    # the intermediate file is gone; the class file has its category names and QGIS style
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "c.qml", "c.tif", "c.tif.aux.xml", "m.tif", "ref.tif", "ref_c.tif"]  # fmt: skip


def test_window_size_does_not_change_the_file(tmp_path, monkeypatch):
    g = strip((40, 1500), seed=3)
    write_values_geotiff(g, tmp_path / "one.tif")
    monkeypatch.setattr(geotiff, "_CHUNK_BYTES", 10_000)
    write_values_geotiff(g, tmp_path / "many.tif")
    assert (tmp_path / "one.tif").read_bytes() == (tmp_path / "many.tif").read_bytes()


def test_chunks_tile_the_map_once():
    # a 1.8 km strip of 13 float32 bands: one tile row is 15 MB, so windows of 16 rows and
    # 19 tiles (4864 columns)
    chunks = geotiff._chunks((30, 18027), (256, 16), 13 * 4)
    assert chunks[:2] == [(0, 16, 0, 4864), (0, 16, 4864, 9728)]
    assert len(chunks) == 8 and chunks[-1] == (16, 30, 14592, 18027)
    # a narrow map: whole rows, as many tile rows as fit
    assert geotiff._chunks((18027, 30), (32, 16), 52) == [
        (r0, min(18027, r0 + 2688), 0, 30) for r0 in range(0, 18027, 2688)
    ]
    assert geotiff._source_block(30) == (32, 16)
    assert geotiff._source_block(18027) == (256, 16)
    assert geotiff._source_block(1) == (16, 16)
    for shape, block, cell in [((5, 3), (16, 16), 4), ((700, 333), (256, 16), 60)]:
        covered = np.zeros(shape, int)
        for r0, r1, c0, c1 in geotiff._chunks(shape, block, cell):
            assert r0 % block[1] == 0 and c0 % block[0] == 0
            covered[r0:r1, c0:c1] += 1
        assert np.all(covered == 1)


def test_data_view_is_the_box_of_the_true_cells():
    rng = np.random.default_rng(1)
    extent = (10.0, 40.0, -5.0, 5.0)
    for _ in range(20):
        mask = rng.random((20, 60)) < rng.choice([0.0, 0.001, 0.05, 0.5])
        rows, cols = np.nonzero(mask)
        if rows.size == 0:
            assert data_view(mask, extent) == extent
            continue
        # the box of the true cells (0.5 m cells) before padding
        box = (10 + 0.5 * cols.min(), 10 + 0.5 * (cols.max() + 1))
        x0, x1, _, _ = data_view(mask, extent, margin=0.0)
        pad = 2 * 0.5
        least = 20 * 0.5
        if box[1] - box[0] + 2 * pad >= least:
            assert (x0, x1) == pytest.approx((max(10, box[0] - pad), min(40, box[1] + pad)))
        assert x0 <= box[0] and x1 >= box[1]


def test_pngs_free_their_figures_and_leave_the_map_alone(tmp_path):
    from matplotlib.figure import Figure

    g = strip((30, 400))
    before = {n: g[n].copy() for n in g.layers}
    gc.collect()
    figures = sum(isinstance(o, Figure) for o in gc.get_objects())
    paths = write_pngs(g, tmp_path, "m")
    assert set(paths) == set(g.layers)
    # no figure waits for the garbage collector (each would hold copies of its layer)
    assert sum(isinstance(o, Figure) for o in gc.get_objects()) == figures
    for n in g.layers:  # the layers drawn as they are (no copy) are not changed
        np.testing.assert_array_equal(g[n], before[n])
    assert class_layers(g) == ["class"]


@pytest.mark.parametrize("layer", ["R", "class", "count"])
@pytest.mark.parametrize("shape", [(30, 3000), (60, 500)])
def test_map_picture_is_that_of_the_coloured_cells(shape, layer):
    """The map is drawn by colouring the cell sampled for each pixel: the picture of
    colouring every cell first (what matplotlib does by itself for more cells than pixels,
    with two RGBA copies of the map)."""
    g = strip(shape, seed=2)
    fig = layer_figure(g, layer)
    fig.canvas.draw()
    sampled_first = np.asarray(fig.canvas.buffer_rgba()).copy()
    (image,) = fig.axes[0].get_images()
    assert image.get_interpolation_stage() == "data"
    image.set_interpolation_stage("rgba")
    fig.canvas.draw()
    np.testing.assert_array_equal(np.asarray(fig.canvas.buffer_rgba()), sampled_first)
