"""The tiled map's fusion and its tiles on disk (rough_map.map.tiles, and the patch
footprints of rough_map.map.grid_geometry): the same bits as fusing in one grid, files
written only when a tile changed."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rough_map.errors import InputError
from rough_map.map import (
    GridGeometry,
    GridMap,
    fuse_patch,
    init_layers,
    patch_cells,
    update_estimates,
)
from rough_map.map.grid_geometry import lattice_patch_cells, patch_bounds, patch_corners
from rough_map.map.tiles import TiledMap, by_tile, read_tile, used_window, write_tile
from rough_map.patch import PatchSpec

NAMES = ("concrete", "dirt_road", "gravel")


def _poses(n: int, seed: int) -> list[tuple[float, float, float]]:
    """Poses on and off the lattice, at headings of every kind (right angles too)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        x, y = (float(v) for v in rng.uniform(-40.0, 40.0, 2))
        if i % 3 == 0:
            x, y = round(x, 1), round(y, 1)
        if i % 11 == 0:
            x, y = 0.0, 0.0
        yaw = [float(rng.uniform(-7.0, 7.0)), 0.0, math.pi / 2, math.pi, -math.pi / 2][i % 5]
        out.append((x, y, yaw))
    return out


@pytest.mark.parametrize(
    ("spec", "resolution"),
    [
        (PatchSpec(ahead=2.3, size=1.3), 0.1),
        (PatchSpec(ahead=1.0, size=0.3, spacing=0.01, lateral=-0.3), 0.25),
        (PatchSpec(ahead=0.0, size=0.1, spacing=0.005, lateral=0.5), 0.3),
    ],
)
def test_lattice_cells_are_patch_cells_on_the_covering_map(spec, resolution) -> None:
    """Bit for bit what patch_cells gives on GridGeometry.covering of the patch's corners,
    offset to the lattice, with the same bounds (the sign of a zero too)."""
    for x, y, yaw in _poses(600, 1):
        corners = patch_corners(x, y, yaw, spec)
        bounds = (*corners.min(axis=0), *corners.max(axis=0))
        geo = GridGeometry.covering(bounds, resolution)
        cells = patch_cells(geo, x, y, yaw, spec)
        got, rows, cols = lattice_patch_cells(x, y, yaw, spec, resolution)
        assert got == tuple(float(v) for v in bounds)
        assert [math.copysign(1, v) for v in got] == [math.copysign(1, v) for v in bounds]
        assert got == patch_bounds(x, y, yaw, spec)
        r0, c0 = math.floor(bounds[1] / resolution), math.floor(bounds[0] / resolution)
        assert rows.tolist() == (cells[:, 0] + r0).tolist()
        assert cols.tolist() == (cells[:, 1] + c0).tolist()


def test_patch_bounds_take_signed_zeros_as_numpy_does() -> None:
    """A corner at x = -0.0 and another at 0.0: the minimum numpy's reduction gives."""
    spec = PatchSpec(ahead=1.0, size=2.0)  # corners at u = 0 and 2, v = -1 and 1
    for x in (0.0, -0.0):
        corners = patch_corners(x, 0.0, 0.0, spec)
        got = patch_bounds(x, 0.0, 0.0, spec)
        want = (*corners.min(axis=0), *corners.max(axis=0))
        assert [math.copysign(1, v) for v in got] == [math.copysign(1, v) for v in want]


def _drive(n: int, seed: int):
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.1, n))
    x = np.concatenate([[0.3], 0.3 + np.cumsum(0.25 * np.cos(yaw[:-1]))])
    y = np.concatenate([[-0.4], -0.4 + np.cumsum(0.25 * np.sin(yaw[:-1]))])
    R = 10 ** rng.uniform(-5, -3, n)
    probs = rng.dirichlet(np.ones(len(NAMES)), n)
    probs[rng.random(n) < 0.1] = np.nan
    levels = rng.integers(0, 3, n).astype(float)
    levels[rng.random(n) < 0.2] = np.nan
    return x, y, yaw, R, rng.uniform(1.5, 3, n), probs, levels


def test_tiled_fusion_is_the_one_grid_fusion_bit_for_bit(tmp_path: Path) -> None:
    """Two passes (roughness and time, then classes and levels, counted once) through small
    tiles that go to disk and come back, against fusing in one grid."""
    spec = PatchSpec(ahead=1.0, size=1.3)
    x, y, yaw, R, w, probs, levels = _drive(80, 3)
    tiles = TiledMap(0.1, NAMES, spec=spec, tile_cells=8, spill_dir=tmp_path / "t")
    ref = GridMap(GridGeometry.covering((-10.0, -20.0, 30.0, 20.0), 0.1))
    init_layers(ref, NAMES)
    first = {"sigma_R": 1e-5, "sigma_w": 0.1}
    for i in range(len(x)):
        obs = {"t": 0.5 * i, "R": R[i], "w": w[i], **first}
        tiles.add_frame(x[i], y[i], yaw[i], obs)
        fuse_patch(ref, x[i], y[i], yaw[i], spec=spec, grow=False, update=False, **obs)
        tiles.evict(x[i], y[i], 0.5)
    assert tiles.in_memory() < len(tiles.keys())
    for i in range(len(x)):
        p = probs[i] if np.all(np.isfinite(probs[i])) else None
        obs = {"probs": p, "level": levels[i], "count": False}
        tiles.add_frame(x[i], y[i], yaw[i], obs)
        fuse_patch(ref, x[i], y[i], yaw[i], spec=spec, grow=False, update=False, **obs)
        tiles.evict(x[i], y[i], 0.5)
    got = tiles.window(ref.geometry.bounds)
    update_estimates(ref)
    assert got.shape == ref.shape
    for name in got.layers:
        if name != "elevation":
            assert np.array_equal(got[name], ref[name], equal_nan=True), name
    assert np.isfinite(got["R"]).sum() > 100 and np.isfinite(got["class"]).sum() > 100
    tiles.close()


def test_a_tile_read_and_left_alone_is_not_written_again(tmp_path: Path) -> None:
    spec = PatchSpec(ahead=1.0, size=1.3)
    folder = tmp_path / "t"
    tiles = TiledMap(0.1, NAMES, spec=spec, tile_cells=64, spill_dir=folder)
    tiles.add_frame(3.0, 3.0, 0.0, {"t": 1.0, "R": 1e-4, "w": 2.0})
    assert tiles.evict(100.0, 100.0, 1.0) == 1
    (path,) = folder.iterdir()
    before = path.stat().st_mtime_ns, path.read_bytes()
    merged = tiles.merged()  # reads the tile back, changes nothing
    assert np.nanmax(merged["count"]) == 1.0
    assert (path.stat().st_mtime_ns, path.read_bytes()) == before
    tiles.add_frame(3.0, 3.0, 0.0, {"probs": [0.2, 0.3, 0.5], "count": False})
    tiles.evict(100.0, 100.0, 1.0)
    assert path.read_bytes() != before[1]  # changed: written again
    again = tiles.merged()
    assert again["p_gravel"][np.isfinite(again["p_gravel"])].max() > 0.4
    tiles.close()
    assert not folder.exists() or not any(folder.iterdir())


def test_tile_file_round_trip_keeps_what_holds_data(tmp_path: Path) -> None:
    geo = GridGeometry(0.1, (0.0, 0.0), (8, 8))
    grid = GridMap(geo)
    for name, fill in (("count", 0.0), ("last_seen", math.nan), ("sum_w", 0.0), ("v", 0.0)):
        grid.add_layer(name, units="1", fill=fill, kind="internal")
    path = tmp_path / "a.tile"
    assert not write_tile(path, grid) and not path.exists()  # nothing to keep
    assert used_window(grid) is None
    grid["count"][2:4, 5] = 1.0
    grid["last_seen"][2:4, 5] = 7.5
    grid["sum_w"][3, 6] = -2.0
    assert used_window(grid) == (2, 4, 5, 7)
    assert write_tile(path, grid)
    back = GridMap(geo)
    for name in grid.layers:
        back.add_layer_as(name, grid.info(name))
    read_tile(path, back)
    for name in grid.layers:
        assert np.array_equal(back[name], grid[name], equal_nan=True), name


def test_cells_by_tile_keep_their_order() -> None:
    rows = np.array([-1, 0, -1, 5, 0, 40, -30], dtype=np.int64)
    cols = np.array([7, 8, 9, 3, -1, 2, 60], dtype=np.int64)
    groups = by_tile(rows, cols, 8)
    assert [g[0] for g in groups] == sorted(
        {(r // 8, c // 8) for r, c in zip(rows, cols, strict=True)}
    )
    back = set()
    for (tr, tc), sel, r, c in groups:
        assert np.all((r >= 0) & (r < 8) & (c >= 0) & (c < 8))
        back |= {(int(a) + tr * 8, int(b) + tc * 8) for a, b in zip(r, c, strict=True)}
        assert np.array_equal(rows[sel], r + tr * 8)
    assert back == set(zip(rows.tolist(), cols.tolist(), strict=True))
    (one,) = by_tile(rows[:1], cols[:1], 8)
    assert one[0] == (-1, 0) and one[2].tolist() == [7] and one[3].tolist() == [7]


def test_bad_observations_leave_the_tiles_alone(tmp_path: Path) -> None:
    tiles = TiledMap(0.1, NAMES, tile_cells=16, spill_dir=tmp_path / "t")
    with pytest.raises(InputError, match="pose must be finite"):
        tiles.add_frame(math.nan, 0.0, 0.0, {"R": 1e-4, "w": 2.0})
    with pytest.raises(InputError, match="probs must have shape"):
        tiles.add_frame(0.0, 0.0, 0.0, {"R": 1e-4, "w": 2.0, "probs": [0.5, 0.5]})
    with pytest.raises(InputError, match="level must be an index"):
        tiles.add_frame(0.0, 0.0, 0.0, {"level": 1.5})
    assert tiles.keys() == []
    no_classes = TiledMap(0.1, tile_cells=16, spill_dir=tmp_path / "u")
    with pytest.raises(InputError, match="no class_names"):
        no_classes.add_frame(0.0, 0.0, 0.0, {"probs": [1.0]})
