"""A cloud on a regular lattice (a height map exported as points) is read on that lattice.

Re-binned onto the 8 mm cells, a 1 cm lattice leaves one cell in five empty in a fixed
pattern; read on its own nodes it is the exact grid of the surface. The surfaces are the
1 cm grids of ``surfaces.real_like_surface``: paving blocks, boulders with steep sides and
a smoothed (stereo-like) power law, none of them a Gaussian power law.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from surfaces import GRID_STEP, real_like_surface

from rough_map.errors import InputError
from rough_map.features import cloud_roughness, frame_features
from rough_map.patch import (
    Extraction,
    Lattice,
    PatchSpec,
    find_lattice,
    grid_lattice,
    lattice_patch,
)
from rough_map.psd import patch_roughness

AUTO = Extraction(auto_spacing=True)
NODES = 100  # nodes per side of a window: 1 m, over the 0.896 m patch


def lattice_cloud(
    grid: np.ndarray,
    corner: tuple[int, int],
    origin: tuple[float, float],
    missing: float = 0.02,
    step: float = GRID_STEP,
    seed: int = 0,
) -> tuple[np.ndarray, float, float]:
    """The window of ``grid`` from node ``corner`` as a cloud on its lattice, node (0, 0)
    at ``origin`` (m, vehicle frame), with a share ``missing`` of the nodes left out;
    returns the cloud and the origin."""
    r0, c0 = corner
    sub = grid[r0 : r0 + NODES, c0 : c0 + NODES]
    x, y = np.meshgrid(origin[0] + np.arange(NODES) * step, origin[1] + np.arange(NODES) * step)
    pts = np.column_stack([x.ravel(), y.ravel(), sub.ravel()])
    keep = np.random.default_rng(seed).random(len(pts)) >= missing
    return pts[keep], origin[0], origin[1]


def exact_on_lattice(grid, corner, origin, spec: PatchSpec, step: float = GRID_STEP):
    """``patch_roughness`` of the exact grid of the window's nodes under ``spec``."""
    r0, c0 = corner
    sub = grid[r0 : r0 + NODES, c0 : c0 + NODES]
    centres = (np.arange(spec.n) + 0.5) * spec.spacing
    ix = np.rint((spec.x0 + centres - origin[0]) / step).astype(int)
    iy = np.rint((spec.y0 + centres - origin[1]) / step).astype(int)
    return patch_roughness(sub[np.ix_(iy, ix)], step)


CORNERS = [(r, c) for r in (10, 100, 190) for c in (20, 110, 195)]


@pytest.mark.parametrize("kind", ["blocks", "boulders", "smooth"])
def test_every_window_of_a_height_grid_reads_like_its_exact_grid(kind: str) -> None:
    """All windows are read, and within 0.15 in median |ln R| and 0.05 in median |dw| of
    the exact grid at the lattice's spacing (the 2 % of missing nodes are gap-filled)."""
    grid = real_like_surface(kind, seed=3)
    rng = np.random.default_rng(7)
    dl, dw = [], []
    for corner in CORNERS:
        origin = (
            0.5 + rng.uniform(-0.6, 0.4) * GRID_STEP,
            -0.5 + rng.uniform(-0.5, 0.5) * GRID_STEP,
        )
        pts, *_ = lattice_cloud(grid, corner, origin, seed=corner[0] + corner[1])
        patch, rough = cloud_roughness(pts, AUTO)
        assert patch.gridding == "point"
        assert patch.spec.spacing == pytest.approx(GRID_STEP, rel=1e-6)
        assert patch.spec.n == 90
        ref = exact_on_lattice(grid, corner, origin, patch.spec)
        dl.append(math.log(rough.R / ref.R))
        dw.append(rough.w - ref.w)
    assert np.median(np.abs(dl)) <= 0.15
    assert np.median(np.abs(dw)) <= 0.05


def test_an_untouched_lattice_reads_exactly_its_grid() -> None:
    grid = real_like_surface("blocks", seed=1)
    origin = (0.5123, -0.4977)
    pts, *_ = lattice_cloud(grid, (50, 50), origin, missing=0.0)
    patch, rough = cloud_roughness(pts, AUTO)
    ref = exact_on_lattice(grid, (50, 50), origin, patch.spec)
    assert patch.fill_fraction == 1.0
    assert rough.R == pytest.approx(ref.R, rel=1e-9)
    assert rough.w == pytest.approx(ref.w, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    step=st.floats(0.005, 0.03),
    ox=st.floats(-10.0, 10.0),
    oy=st.floats(-10.0, 10.0),
)
def test_the_lattice_is_found_at_any_step_and_origin(step: float, ox: float, oy: float) -> None:
    spec = PatchSpec()
    nx = int(1.2 / step)
    # nodes ox + k step covering the patch square
    kx = np.arange(nx) + math.floor((spec.x0 - 0.1 - ox) / step)
    ky = np.arange(nx) + math.floor((spec.y0 - 0.1 - oy) / step)
    x, y = np.meshgrid(ox + kx * step, oy + ky * step)
    z = 0.001 * np.sin(7 * x) * np.cos(5 * y)
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    found = find_lattice(pts, spec)
    if step > 8 * spec.spacing or step < 0.5 * spec.spacing:
        assert found is None
        return
    assert found is not None
    assert found.step_x == pytest.approx(step, rel=1e-6)
    assert found.step_y == pytest.approx(step, rel=1e-6)
    on = lattice_patch(spec, found)
    # every node over the patch is the centre of one cell
    grid = grid_lattice(pts, spec, found)
    assert on.spacing == pytest.approx(step)
    assert grid.counts.max() == 1
    assert grid.fill_fraction == 1.0
    assert abs(on.ahead - spec.ahead) <= 0.5 * step + 1e-9


def test_random_and_rotated_clouds_are_not_lattices() -> None:
    rng = np.random.default_rng(0)
    spec = PatchSpec()
    pts = np.column_stack(
        [rng.uniform(0.5, 1.5, 50_000), rng.uniform(-0.5, 0.5, 50_000), rng.normal(0, 1e-3, 50_000)]
    )
    assert find_lattice(pts, spec) is None
    x, y = np.meshgrid(np.arange(-60, 60) * 0.01, np.arange(-60, 60) * 0.01)
    a = math.radians(20)
    xr, yr = 1.0 + x * math.cos(a) - y * math.sin(a), x * math.sin(a) + y * math.cos(a)
    rotated = np.column_stack([xr.ravel(), yr.ravel(), np.zeros(xr.size)])
    assert find_lattice(rotated, spec) is None
    # a rectangular lattice is not taken as square cells
    x, y = np.meshgrid(np.arange(40, 160) * 0.01, np.arange(-30, 30) * 0.02)
    rect = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    assert find_lattice(rect, spec) is None


def test_a_fixed_spacing_reads_the_lattice_on_its_nodes_too() -> None:
    """A fixed 8 mm step (a terrain model's) re-binning a 1 cm lattice leaves one cell in
    five empty and every profile refused: the lattice is read on its nodes instead."""
    grid = real_like_surface("blocks", seed=2)
    pts, *_ = lattice_cloud(grid, (40, 40), (0.5, -0.5))
    patch, rough = cloud_roughness(pts, Extraction())
    assert patch.gridding == "point"
    assert patch.spec.spacing == pytest.approx(GRID_STEP)
    assert rough.n_profiles == 90


def test_frames_of_a_lattice_are_read_on_it() -> None:
    grid = real_like_surface("boulders", seed=2)
    pts, *_ = lattice_cloud(grid, (60, 60), (0.503, -0.497))
    row, omega, psd = frame_features(pts, AUTO)
    assert row["valid"], row["reason"]
    assert omega is not None and psd is not None
    assert omega[-1] == pytest.approx(math.pi / GRID_STEP, rel=1e-6)
    assert math.isnan(row["noise_psd"])


def test_find_lattice_refuses_bad_input() -> None:
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        find_lattice(np.zeros((10, 2)), PatchSpec())
    with pytest.raises(InputError, match="spec must be a PatchSpec"):
        find_lattice(np.zeros((10, 3)), "patch")  # type: ignore[arg-type]
    assert find_lattice(np.zeros((10, 3)), PatchSpec()) is None
    assert isinstance(Lattice(0.01, 0.01, 0.0, 0.0), Lattice)


def test_features_of_a_lattice_cloud_say_so(tmp_path, capsys) -> None:
    from rough_map.cli.main import main

    grid = real_like_surface("blocks", seed=4)
    pts, *_ = lattice_cloud(grid, (30, 30), (0.5, -0.5))
    path = tmp_path / "lattice.npy"
    np.save(path, pts)
    assert main(["features", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["gridding"] == "point"
    assert out["spacing"] == pytest.approx(GRID_STEP)
    assert out["band_rad_per_m"][1] == pytest.approx(math.pi / GRID_STEP, rel=1e-6)
