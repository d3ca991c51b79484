"""Long simulated worlds: built tile by tile, joined seamlessly, written and read in tiles."""

import filecmp
import math
import tracemalloc

import numpy as np
import pytest

from rough_map.errors import FileFormatError, InputError
from rough_map.evaluation.near_far import world_class
from rough_map.evaluation.truth import map_accuracy, truth_accuracy
from rough_map.io.traverse import load_traverse
from rough_map.io.truth import (
    HEIGHT_STEP,
    TiledWorld,
    TiledWorldWriter,
    load_world,
    open_world,
    traverse_truth,
)
from rough_map.map.grid import GridMap
from rough_map.map.grid_geometry import GridGeometry
from rough_map.simulate.course import SensorSpec, simulate
from rough_map.simulate.world import CLASS_NAMES, Segment, build_world, course_layout
from rough_map.simulate.world_tiles import WorldTiles, cross_fade

SPARSE = SensorSpec(points_per_cell=3.0)
#: A small world: 4 mm cells, 1.5 m wide.
SMALL = dict(spacing=0.004, width=1.5)
#: The same through simulate().
SIM = dict(images=False, sensor=SPARSE, world_spacing=0.004, width=1.5)


def test_a_world_of_one_tile_is_the_world_built_whole():
    segs, defects = course_layout("mixed", 9.0)
    whole = build_world(segs, defects, seed=3, **SMALL)
    tiles = WorldTiles(segs, defects, seed=3, tile_length=20.0, **SMALL)
    assert tiles.n_tiles == 1
    got = tiles.whole()
    np.testing.assert_array_equal(got.heights, whole.heights.astype(np.float32))
    np.testing.assert_array_equal(got.classes, whole.classes)
    assert (got.spacing, got.origin, got.class_names) == (0.004, whole.origin, CLASS_NAMES)


def test_tiles_join_without_a_step_and_keep_the_variance():
    """Across a join the heights about their local level keep the surface's variance
    (cos/sin weights of two independent tiles); a linear cross-fade would lose half of it
    in the middle. Neither the level nor the slope jumps."""
    segs = [Segment("gravel", 0.0, 30.0)]
    tiles = WorldTiles(
        segs, seed=1, tile_length=2.0, overlap=0.25, envelope_sigma=0.0, spacing=0.004, width=1.0
    )
    h = tiles.whole().heights.astype(np.float64)
    ov = tiles.overlap
    joins = tiles.edges[1:-1]
    assert len(joins) >= 10

    def spread(cols):  # std of the heights about each row's mean over the columns
        z = h[:, cols]
        return float(np.sqrt(np.mean((z - z.mean(axis=1, keepdims=True)) ** 2)))

    middle = np.mean([spread(slice(e - 8, e + 8)) for e in joins])
    inside = np.mean([spread(slice(e + ov + 20, e + ov + 36)) for e in joins])
    assert middle == pytest.approx(inside, rel=0.15)
    # the steps between columns are no larger across the joins than inside the tiles
    step = np.abs(np.diff(h, axis=1)).mean(axis=0)
    zone = np.zeros(step.size, dtype=bool)
    for e in joins:
        zone[e - ov - 2 : e + ov + 2] = True
    assert step[zone].max() < 1.3 * step[~zone].max()
    assert step[zone].mean() == pytest.approx(step[~zone].mean(), rel=0.15)

    # the rule itself: independent unit fields keep unit variance, the levels join linearly
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((4000, 200)) + 5.0, rng.standard_normal((4000, 200)) - 5.0
    faded = cross_fade(a, b).astype(np.float64)
    assert np.allclose(faded.std(axis=0), 1.0, atol=0.05)
    assert np.allclose(faded.mean(axis=0), 5.0 - 10.0 * (np.arange(200) + 0.5) / 200, atol=0.05)


def test_long_worlds_are_deterministic_and_read_the_same_in_any_window():
    segs, defects = course_layout("mixed", 15.0)
    kw = dict(seed=7, tile_length=1.5, overlap=0.25, **SMALL)
    whole = WorldTiles(segs, defects, **kw).whole()
    np.testing.assert_array_equal(whole.heights, WorldTiles(segs, defects, **kw).whole().heights)
    other = WorldTiles(segs, defects, **{**kw, "seed": 8}).whole()
    assert not np.allclose(other.heights, whole.heights)
    # windows moving along the course, with blocks released behind them, read the same cells
    tiles = WorldTiles(segs, defects, **kw)
    for x in np.arange(-2.0, 17.0, 0.7):
        win = tiles.window(x, x + 1.3)
        c0 = round((win.origin[0] - whole.origin[0]) / whole.spacing)
        np.testing.assert_array_equal(win.heights, whole.heights[:, c0 : c0 + win.heights.shape[1]])
        tiles.release(x - 0.1)
    with pytest.raises(InputError, match="released"):
        tiles.window(0.0, 1.0)
    # the manhole is carved whole into one tile, clear of every cross-fade
    (manhole,) = defects
    j = round((manhole.x - whole.origin[0]) / whole.spacing)
    near = [e for e in tiles.edges if abs(e - j) < int(0.6 / 0.004) + tiles.overlap + 2]
    assert not near
    i = round((manhole.y - whole.origin[1]) / whole.spacing)
    assert whole.heights[i, j] < np.median(whole.heights[i, j - 200 : j - 100]) - 0.01


def test_building_a_long_world_holds_a_few_tiles():
    """Memory holds a few tiles however long the world: a 40 m world streamed in windows
    (its finished blocks passed on, as to a truth writer) peaks as a 10 m one does."""
    segs_short = [Segment("compact_soil", 0.0, 10.0)]
    segs_long = [Segment("compact_soil", 0.0, 40.0)]

    def peak(segs):
        seen = []
        tiles = WorldTiles(
            segs,
            seed=1,
            tile_length=1.0,
            overlap=0.2,
            spacing=0.004,
            width=1.0,
            sink=lambda c, h, k: seen.append(h.shape[1]),
        )
        tracemalloc.start()
        x = segs[0].start
        while x < segs[-1].end:
            tiles.window(x, x + 2.0)
            tiles.release(x)
            x += 0.5
        tiles.finish()
        top = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert sum(seen) == tiles.shape[1]
        return top, tiles.shape[0] * tiles.shape[1] * 8

    short, _ = peak(segs_short)
    long, whole_bytes = peak(segs_long)
    assert long < 1.3 * short and long < 0.5 * whole_bytes


def test_one_tile_through_the_tiled_drive_gives_the_traverse_built_whole(tmp_path):
    """The tiled path (windows, runs of frames, the tiled truth) with one tile: the same
    frames as the world built whole, up to the float32 heights."""
    a = load_traverse(simulate(tmp_path / "a", "mixed", length=7.0, seed=5, **SIM))
    b = load_traverse(
        simulate(
            tmp_path / "b", "mixed", length=7.0, seed=5, whole_length=1.0, tile_length=30.0, **SIM
        )
    )
    assert len(a) == len(b) > 20
    np.testing.assert_allclose(b.poses(), a.poses(), atol=1e-7)
    assert [f.label for f in b.frames] == [f.label for f in a.frames]
    for i in (0, len(a) // 2, len(a) - 1):
        np.testing.assert_allclose(b.load_cloud(i), a.load_cloud(i), atol=1e-6)
    wa, wb = load_world(a.resolve("world_truth.npz")), open_world(b.resolve("world_truth.npz"))
    assert isinstance(wa.heights, np.ndarray) and isinstance(wb, TiledWorld)
    assert wa.heights.dtype == np.float32 and wa.classes.dtype == np.int8
    full = wb.load()
    np.testing.assert_allclose(full.heights, wa.heights, atol=2 * HEIGHT_STEP)
    np.testing.assert_array_equal(full.classes, wa.classes)


def _simulate_tiled(out):
    """A 12 m mixed course built in 2 m tiles, its truth in tiles of 1000 columns."""
    import rough_map.io.truth as truth

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(truth, "TILE_COLUMNS", 1000)  # several truth tiles on a small world
        simulate(out, "mixed", length=12.0, seed=2, whole_length=5.0, tile_length=2.0, **SIM)
    return out


@pytest.fixture(scope="module")
def tiled(tmp_path_factory):
    return _simulate_tiled(tmp_path_factory.mktemp("sim") / "tiled")


def test_a_tiled_traverse_is_deterministic(tiled, tmp_path):
    again = _simulate_tiled(tmp_path / "again")
    names = ["traverse.json", "world_truth.npz"] + [f"clouds/{i:06d}.npy" for i in range(0, 40, 7)]
    match, mismatch, errors = filecmp.cmpfiles(tiled, again, names, shallow=False)
    assert mismatch == [] and errors == [] and len(match) == len(names)


def test_the_tiled_truth_reads_in_windows_and_scores_maps(tiled):
    trav = load_traverse(tiled)
    trav.validate_files()
    world = traverse_truth(trav)
    assert isinstance(world, TiledWorld) and world.n_tiles >= 4
    whole = load_world(tiled / "world_truth.npz")
    assert whole.heights.shape == world.shape and whole.heights.dtype == np.float32
    win = world.window(3.0, 5.5)
    c0 = round((win.origin[0] - whole.origin[0]) / whole.spacing)
    np.testing.assert_array_equal(win.heights, whole.heights[:, c0 : c0 + win.heights.shape[1]])
    np.testing.assert_array_equal(win.classes, whole.classes[:, c0 : c0 + win.heights.shape[1]])
    # every frame's label is the truth's class at its patch centre
    poses = trav.poses()
    centre_x = poses[:, 0] + np.cos(poses[:, 5])
    centre_y = poses[:, 1] + np.sin(poses[:, 5])
    names = np.asarray(world.class_names)[world_class(world, centre_x, centre_y)]
    assert list(names) == [f.label for f in trav.frames]
    # the evaluations read the tiled world as the whole one
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-4, 16, 5000), rng.uniform(-1, 1, 5000)
    np.testing.assert_array_equal(world_class(world, x, y), world_class(whole, x, y))
    assert (world_class(world, x, y) == -1).any()  # beyond the ends and the sides
    grid = GridMap(GridGeometry.covering((-1.0, -0.7, 13.0, 0.7), 0.1))
    truth_class = world_class(whole, *grid.geometry.cell_center(*np.indices(grid.shape)))
    guess = np.where(np.arange(grid.shape[1])[None, :] % 3 == 0, 0, truth_class).astype(float)
    grid.add_layer("class", units="", kind="class", categories=CLASS_NAMES, data=guess)
    acc = map_accuracy(grid, world)
    assert acc == map_accuracy(grid, whole) and 0.5 < acc < 1.0
    assert truth_accuracy(grid, world) == {"near_class_accuracy": acc}


def test_tiled_world_file_round_trip(tmp_path):
    """Tiles of any block sizes, int16 steps over each tile's relief (float32 for a wide
    one), classes per column or per cell, the finite flags; a file left incomplete is
    not written."""
    rng = np.random.default_rng(1)
    ny, nx = 30, 250
    heights = rng.uniform(-0.05, 0.05, (ny, nx))
    heights[:, 200:] *= 30.0  # a 3 m relief: the last tile stays float32
    heights[3, 210] = np.nan
    classes = np.broadcast_to((np.arange(nx) // 60 % 5)[None, :], (ny, nx)).copy()
    classes[0, :] = 4
    path = tmp_path / "w.npz"
    with TiledWorldWriter(path, (ny, nx), 0.01, (-1.0, -0.15), CLASS_NAMES, tile_columns=100) as w:
        c = 0
        for n in (7, 93, 40, 110):
            w.append(c, heights[:, c : c + n], classes[:, c : c + n])
            c += n
    world = open_world(path)
    assert isinstance(world, TiledWorld)
    assert world.tile_columns.tolist() == [0, 100, 200, 250]
    back = world.load()
    assert back.heights.dtype == np.float32 and back.classes.dtype == np.int8
    np.testing.assert_array_equal(back.classes, classes)
    for k0, k1 in ((0, 100), (100, 200)):
        step = np.ptp(heights[:, k0:k1]) / 65534
        assert np.abs(back.heights[:, k0:k1] - heights[:, k0:k1]).max() <= step / 2 + 1e-7
    np.testing.assert_array_equal(back.heights[:, 200:], heights[:, 200:].astype(np.float32))
    rows, cols = np.array([3, 3, 0, 5]), np.array([210, 209, 17, 120])
    got, finite = world.lookup(rows, cols)
    assert got.tolist() == classes[rows, cols].tolist() and finite.tolist() == [0, 1, 1, 1]
    assert world_class(world, [1.10, 1.09], [-0.12, -0.12]).tolist() == [-1, classes[3, 209]]
    np.testing.assert_array_equal(load_world(path).heights, back.heights)

    with pytest.raises(InputError, match=r"expected columns from 7 .* got 5 from 8"):
        with TiledWorldWriter(tmp_path / "bad.npz", (ny, nx), 0.01, (0, 0), CLASS_NAMES) as w:
            w.append(0, heights[:, :7], classes[0, :7])
            w.append(8, heights[:, 8:13], classes[0, 8:13])
    with pytest.raises(InputError, match="7 of the world's 250 columns written"):
        with TiledWorldWriter(tmp_path / "bad.npz", (ny, nx), 0.01, (0, 0), CLASS_NAMES) as w:
            w.append(0, heights[:, :7], classes[0, :7])
    assert not any(tmp_path.glob("*bad*"))
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match=r"cut\.npz: not a rough_map world file"):
        open_world(tmp_path / "cut.npz")


def test_tiles_refuse_bad_lengths():
    segs = [Segment("concrete", 0.0, 10.0)]
    with pytest.raises(InputError, match=r"tile_length must be at least 4 overlaps"):
        WorldTiles(segs, tile_length=1.0, overlap=0.5)
    with pytest.raises(InputError, match=r"overlap must be a length in m >= 0"):
        WorldTiles(segs, overlap=-1.0)
    with pytest.raises(InputError, match=r"tile_length .* got nan"):
        WorldTiles(segs, tile_length=math.nan)


def test_the_truth_geotiff_of_a_tiled_world_holds_one_tile_at_a_time(tmp_path):
    """`simulate` writes world_truth.tif from the tiled truth: four times the tiles, about
    the same memory (holding them all took 1 GB for a 1 km course)."""
    import rasterio

    from rough_map.io.truth_raster import write_truth_geotiff

    def peak(n_tiles: int) -> tuple[int, int]:
        ny, cols = 200, 500
        path = tmp_path / f"w{n_tiles}.npz"
        with TiledWorldWriter(
            path, (ny, n_tiles * cols), 0.01, (0.0, 0.0), CLASS_NAMES, tile_columns=cols
        ) as w:
            for k in range(n_tiles):
                heights = np.zeros((ny, cols))
                w.append(k * cols, heights, np.full((ny, cols), k % 5, dtype=np.int8))
        world = open_world(path)
        tracemalloc.start()
        out = write_truth_geotiff(world, tmp_path / f"t{n_tiles}.tif", "EPSG:32632")
        top = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        with rasterio.open(out) as ds:
            band = ds.read(1)
        assert band.shape == (ny, n_tiles * cols)
        assert band[0, ::cols].tolist() == [k % 5 for k in range(n_tiles)]
        return top, ny * cols

    short, tile_bytes = peak(4)
    long, _ = peak(16)
    assert long < short + 3 * tile_bytes, (short, long)
