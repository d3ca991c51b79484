"""Fusing patches into map layers (rough_map.map.fusion)."""

import math
import warnings

import numpy as np
import pytest

from rough_map.errors import InputError
from rough_map.features import FeatureTable
from rough_map.map import (
    EmptyMapWarning,
    GridGeometry,
    GridMap,
    apply_levels,
    fuse_cell_probabilities,
    fuse_patch,
    fuse_traverse,
    init_layers,
    patch_cells,
    patch_corners,
)
from rough_map.patch import PatchSpec

NAMES = ("concrete", "dirt_road", "gravel")


def table(x, y, yaw, *, t=None, R=1e-4, w=2.0, sigma_R=2e-5, sigma_w=0.1, valid=True):
    """A FeatureTable with the columns the map reads (scalars broadcast)."""
    x = np.asarray(x, float)
    n = x.size
    full = lambda v: np.broadcast_to(np.asarray(v, float), (n,)).copy()  # noqa: E731
    cols = {
        "frame": np.arange(n),
        "t": full(np.arange(n) * 0.5 if t is None else t),
        "x": x,
        "y": full(y),
        "yaw": full(yaw),
        "R": full(R),
        "w": full(w),
        "sigma_R": full(sigma_R),
        "sigma_w": full(sigma_w),
        "valid": np.broadcast_to(np.asarray(valid, bool), (n,)).copy(),
    }
    return FeatureTable(cols, np.zeros(0), np.zeros((n, 0)), "test")


def drive(n=30, seed=0):
    """A curving drive at 0.25 m per frame, random roughness and class probabilities."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0, 0.08, n))
    x = np.concatenate([[0], np.cumsum(0.25 * np.cos(yaw[:-1]))]) + 100.0
    y = np.concatenate([[0], np.cumsum(0.25 * np.sin(yaw[:-1]))]) - 50.0
    R = 10 ** rng.uniform(-5, -3, n)
    valid = rng.random(n) > 0.1
    ft = table(
        x,
        y,
        yaw,
        R=R,
        w=rng.uniform(1.5, 3, n),
        sigma_R=R * rng.uniform(0.1, 0.3, n),
        sigma_w=rng.uniform(0.05, 0.2, n),
        valid=valid,
        t=np.arange(n) * 0.5,
    )
    probs = rng.dirichlet(np.ones(3), n)
    probs[~valid] = np.nan
    levels = rng.integers(0, 3, n).astype(float)
    return ft, probs, levels


# -- footprints -----------------------------------------------------------------------------


@pytest.mark.parametrize("yaw", [0.0, 0.7, math.pi / 2, -2.5])
def test_footprint_is_the_oriented_patch(yaw):
    spec = PatchSpec()
    geo = GridGeometry.covering((-3, -3, 3, 3), 0.05)
    cells = patch_cells(geo, 0.4, -0.2, yaw, spec)
    xc, yc = geo.cell_center(cells[:, 0], cells[:, 1])
    centre = (0.4 + math.cos(yaw), -0.2 + math.sin(yaw))
    # every cell centre inside the square, about the right number of cells
    u = (xc - centre[0]) * math.cos(yaw) + (yc - centre[1]) * math.sin(yaw)
    v = -(xc - centre[0]) * math.sin(yaw) + (yc - centre[1]) * math.cos(yaw)
    assert np.all(np.abs(u) <= spec.size / 2) and np.all(np.abs(v) <= spec.size / 2)
    assert len(cells) == pytest.approx((spec.size / 0.05) ** 2, rel=0.1)
    assert math.hypot(xc.mean() - centre[0], yc.mean() - centre[1]) < geo.resolution / 2
    corners = patch_corners(0.4, -0.2, yaw, spec)
    np.testing.assert_allclose(corners.mean(axis=0), centre, atol=1e-12)


def test_patch_smaller_than_a_cell_fills_the_cell_of_its_centre():
    geo = GridGeometry.covering((-5, -5, 5, 5), 2.0)
    cells = patch_cells(geo, 0.1, 0.1, 0.3, PatchSpec(size=0.5, spacing=0.05))
    assert len(cells) == 1
    r, c = geo.cell_of(0.1 + math.cos(0.3), 0.1 + math.sin(0.3))
    assert cells.tolist() == [[int(r), int(c)]]


# -- what the layers hold -------------------------------------------------------------------


def test_log_mean_R_mean_w_and_their_sigmas():
    g = GridMap(GridGeometry.covering((-1, -2, 4, 2), 0.1))
    init_layers(g, NAMES)
    fuse_patch(g, 0.0, 0.0, 0.0, t=1.0, R=1e-5, w=2.0, sigma_R=2e-6, sigma_w=0.1)
    fuse_patch(g, 0.3, 0.0, 0.0, t=3.0, R=1e-3, w=3.0, sigma_R=4e-4, sigma_w=0.3)
    both = g["count"] == 2
    assert both.sum() > 30
    np.testing.assert_allclose(g["R"][both], 1e-4)  # geometric mean
    np.testing.assert_allclose(g["w"][both], 2.5)
    var_ln = (math.log(1e-3 / 1e-5) / 2) ** 2
    expect = 1e-4 * math.sqrt((0.2**2 + 0.4**2) / 2 + var_ln)
    np.testing.assert_allclose(g["sigma_R"][both], expect)
    np.testing.assert_allclose(g["sigma_w"][both], math.sqrt((0.01 + 0.09) / 2 + 0.25))
    np.testing.assert_array_equal(g["last_seen"][both], 3.0)
    one = g["count"] == 1
    assert np.all(np.isclose(g["R"][one], 1e-5) | np.isclose(g["R"][one], 1e-3))
    never = g["count"] == 0
    for name in ("R", "w", "sigma_R", "sigma_w", "last_seen", "class", "level"):
        assert np.all(np.isnan(g[name][never])), name


def test_the_band_rms_layer_is_the_log_mean_of_the_patches_band_rms():
    """roughness_rms, the layer added as one entry of FUSED_LAYERS: in cells two patches
    cover, the geometric mean of their band rms (m); a patch without one adds nothing."""
    g = GridMap(GridGeometry.covering((-1, -2, 4, 2), 0.1))
    init_layers(g, ())
    fuse_patch(g, 0.0, 0.0, 0.0, R=1e-5, w=2.0, band_rms=0.001)
    fuse_patch(g, 0.3, 0.0, 0.0, R=1e-3, w=3.0, band_rms=0.004)
    fuse_patch(g, 0.3, 0.0, 0.0, R=1e-3, w=3.0, band_rms=math.nan)
    both = (g["n_roughness_rms"] == 2) & (g["count"] == 3)
    assert both.sum() > 30
    np.testing.assert_allclose(g["roughness_rms"][both], 0.002)
    assert g.info("roughness_rms").units == "m" and g.info("n_roughness_rms").kind == "internal"
    assert np.isnan(g["roughness_rms"][g["count"] == 0]).all()
    with pytest.raises(InputError, match=r"unknown observation fields \['rms'\]"):
        fuse_patch(g, 0.0, 0.0, 0.0, rms=0.001)


def test_a_traverse_map_fuses_the_band_rms_column():
    ft, _, _ = drive()
    rms = np.random.default_rng(3).uniform(0.001, 0.01, len(ft))
    ft = FeatureTable({**ft.columns, "band_rms": rms}, ft.omega, ft.log_psd, ft.name)
    g = fuse_traverse(ft, spec=PatchSpec())
    seen = g["count"] > 0
    lo, hi = rms[ft.valid].min(), rms[ft.valid].max()
    values = g["roughness_rms"][seen]
    assert np.isfinite(values).all() and values.min() >= lo * 0.999 and values.max() <= hi * 1.001


def test_dirichlet_class_fusion():
    g = GridMap(GridGeometry.covering((-1, -2, 4, 2), 0.1))
    init_layers(g, NAMES, prior=1.5)
    for p in ([0.6, 0.3, 0.1], [0.2, 0.7, 0.1], [0.5, 0.4, 0.1]):
        fuse_patch(g, 0.0, 0.0, 0.0, probs=p)
    cells = g["count"] == 3
    expect = (np.array([1.3, 1.4, 0.3]) + 0.5) / (3 + 1.5)
    for k, c in enumerate(NAMES):
        np.testing.assert_allclose(g[f"p_{c}"][cells], expect[k])
    assert np.all(g["class"][cells] == 1)
    total = sum(g[f"p_{c}"] for c in NAMES)
    np.testing.assert_allclose(total[cells], 1.0)
    assert np.all(np.isnan(g["class"][g["count"] == 0]))


def test_far_field_has_its_own_layers_and_lower_weight():
    g = GridMap(GridGeometry.covering((-1, -2, 4, 2), 0.1))
    init_layers(g, NAMES)
    fuse_patch(g, 0.0, 0.0, 0.0, t=2.0, probs=[0.9, 0.05, 0.05])
    near = {n: g[n].copy() for n in g.layers}
    mask = np.zeros(g.shape, bool)
    mask[5:10, 30:40] = True
    fuse_cell_probabilities(g, mask, [0.0, 0.0, 1.0], 0.25, group="far", t=9.0)
    fuse_cell_probabilities(g, mask, [0.0, 0.0, 1.0], 0.25, group="far", t=7.0)
    for n, v in near.items():  # the near field is untouched
        np.testing.assert_array_equal(g[n], v, err_msg=n)
    assert np.all(g["far_count"][mask] == 2) and np.all(g["far_count"][~mask] == 0)
    assert np.all(g["far_last_seen"][mask] == 9.0)
    assert np.all(g["far_class"][mask] == 2) and np.all(np.isnan(g["far_class"][~mask]))
    # weight 0.5 in total against a prior of 1: far_p = (1/3 + 0.5) / 1.5
    np.testing.assert_allclose(g["far_p_gravel"][mask], (1 / 3 + 0.5) / 1.5)
    # integer (row, col) cells, one probability row per cell
    cells = np.array([[0, 0], [0, 0], [1, 2]])
    fuse_cell_probabilities(g, cells, np.eye(3), [1.0, 1.0, 2.0], group="far")
    assert g["far_count"][0, 0] == 2 and g["far_class"][1, 2] == 2
    np.testing.assert_allclose(g["far_p_concrete"][0, 0], (1 / 3 + 1) / 3)


def test_bad_cells_and_probabilities():
    g = GridMap(GridGeometry.covering((-1, -1, 1, 1), 0.1))
    init_layers(g, NAMES)
    with pytest.raises(InputError, match=r"use grid\.cells_at"):
        fuse_cell_probabilities(g, np.array([[0.5, 0.2]]), [1, 0, 0])
    with pytest.raises(InputError, match="mask must have the map's shape"):
        fuse_cell_probabilities(g, np.ones((3, 3), bool), [1, 0, 0])
    with pytest.raises(InputError, match="outside the map"):
        fuse_cell_probabilities(g, np.array([[0, 999]]), [1, 0, 0])
    with pytest.raises(InputError, match=r"probs must have shape \(1, 3\)"):
        fuse_cell_probabilities(g, np.array([[0, 0]]), [1, 0])
    with pytest.raises(InputError, match=">= 0"):
        fuse_cell_probabilities(g, np.array([[0, 0]]), [1, -1, 0])
    with pytest.raises(InputError, match="group must be one of"):
        fuse_cell_probabilities(g, np.array([[0, 0]]), [1, 0, 0], group="mid")
    with pytest.raises(InputError, match="weight must be finite"):
        fuse_cell_probabilities(g, np.array([[0, 0]]), [1, 0, 0], -1.0)
    with pytest.raises(InputError, match="differ from the map's"):
        init_layers(g, ("a", "b", "c"))


def test_levels_by_majority_or_from_R():
    ft = table([0.0, 0.1, 0.2], 0.0, 0.0, R=[1e-5, 1e-4, 2e-3])
    g = fuse_traverse(ft, levels=[0, 2, 2])
    assert np.nanmax(g["level"]) == 2 and set(np.unique(g["level"][g["count"] == 3])) == {2}
    # a tie between low and high goes to high
    g = fuse_traverse(ft, levels=np.array(["low", "high", ""], dtype=object))
    both = g["count"] == 3
    assert np.all(g["level"][both] == 2)
    # a function of the fused R: indices or names
    g = fuse_traverse(ft, levels=lambda R: np.searchsorted([3.2e-5, 5.12e-4], R))
    assert np.all(g["level"][both] == 1) and np.all(np.isnan(g["level"][g["count"] == 0]))
    apply_levels(g, lambda R: np.where(R > 0, "high", ""))
    assert np.all(g["level"][both] == 2)
    with pytest.raises(InputError, match="unknown level names"):
        fuse_traverse(ft, levels=["low", "bumpy", "high"])
    with pytest.raises(InputError, match="levels must have shape"):
        fuse_traverse(ft, levels=[0, 1])


# -- invariances ----------------------------------------------------------------------------


def test_fusion_is_order_independent():
    ft, probs, levels = drive()
    ref = fuse_traverse(ft, probs, NAMES, levels)
    perm = np.random.default_rng(3).permutation(len(ft))
    shuffled = table(
        *(ft[k][perm] for k in ("x", "y", "yaw")),
        t=ft["t"][perm],
        R=ft["R"][perm],
        w=ft["w"][perm],
        sigma_R=ft["sigma_R"][perm],
        sigma_w=ft["sigma_w"][perm],
        valid=ft["valid"][perm],
    )
    other = fuse_traverse(shuffled, probs[perm], NAMES, levels[perm])
    assert other.geometry == ref.geometry and other.layers == ref.layers
    for name in ref.layers:
        np.testing.assert_allclose(
            other[name], ref[name], rtol=1e-12, atol=1e-300, equal_nan=True, err_msg=name
        )
    assert np.array_equal(other["last_seen"], ref["last_seen"], equal_nan=True)


def test_incremental_fusion_with_growth_is_order_independent():
    ft, probs, _ = drive(n=24, seed=5)
    maps = []
    for order in (np.arange(24), np.arange(24)[::-1], np.random.default_rng(1).permutation(24)):
        g = GridMap(GridGeometry(0.1, (100.0, -50.0), (1, 1)))
        init_layers(g, NAMES)
        for i in order:
            if ft.valid[i]:
                fuse_patch(
                    g,
                    ft["x"][i],
                    ft["y"][i],
                    ft["yaw"][i],
                    t=ft["t"][i],
                    R=ft["R"][i],
                    w=ft["w"][i],
                    sigma_R=ft["sigma_R"][i],
                    sigma_w=ft["sigma_w"][i],
                    probs=probs[i],
                    margin=0.5,
                )
        maps.append(g)
    # compare on the world lattice: the maps may differ in extent, never in alignment
    ref = maps[0]
    for g in maps[1:]:
        xc, yc = ref.geometry.xy()
        rows, cols = g.geometry.cell_of(*np.meshgrid(xc, yc))
        inside = g.geometry.inside(rows, cols)
        assert np.all(inside[ref["count"] > 0])
        for name in ("R", "w", "sigma_R", "sigma_w", "count", "last_seen", "class", "p_gravel"):
            np.testing.assert_allclose(
                g[name][rows[inside], cols[inside]],
                ref[name][inside],
                rtol=1e-12,
                equal_nan=True,
                err_msg=name,
            )


def test_translation_moves_the_map():
    ft, probs, levels = drive(n=12)
    a = fuse_traverse(ft, probs, NAMES, levels, resolution=0.1)
    shifted = table(
        ft["x"] + 3.0,
        ft["y"] - 2.0,
        ft["yaw"],
        t=ft["t"],
        R=ft["R"],
        w=ft["w"],
        sigma_R=ft["sigma_R"],
        sigma_w=ft["sigma_w"],
        valid=ft["valid"],
    )
    b = fuse_traverse(shifted, probs, NAMES, levels, resolution=0.1)
    np.testing.assert_allclose(
        np.array(b.geometry.origin) - a.geometry.origin, (3.0, -2.0), atol=1e-9
    )
    # the same cells, up to a cell centre landing on a patch edge after the shift
    mismatch = np.isfinite(a["R"]) != np.isfinite(b["R"])
    assert mismatch.sum() <= 0.02 * np.isfinite(a["R"]).sum()


# -- empty traverses ------------------------------------------------------------------------


def test_empty_traverse_gives_an_all_nodata_map():
    with pytest.warns(EmptyMapWarning, match="no frames"):
        g = fuse_traverse(table([], 0.0, 0.0), np.zeros((0, 3)), NAMES)
    assert g.shape[0] >= 1 and g.shape[1] >= 1
    for name in ("R", "w", "sigma_R", "sigma_w", "level", "class", "p_gravel", "last_seen"):
        assert np.all(np.isnan(g[name])), name
    assert np.all(g["count"] == 0)


def test_all_invalid_traverse_gives_an_all_nodata_map_over_the_track():
    ft = table(np.arange(10) * 0.25, 1.0, 0.0, R=math.nan, valid=False)
    with pytest.warns(EmptyMapWarning, match="none of the 10 frames"):
        g = fuse_traverse(ft, np.full((10, 3), np.nan), NAMES, levels=np.full(10, np.nan))
    x0, y0, x1, y1 = g.geometry.bounds
    assert x0 <= 0.5 and x1 >= 2.25 + 1.45 and y0 <= 0.55 and y1 >= 1.45
    for name in ("R", "w", "sigma_R", "sigma_w", "level", "class", "p_concrete"):
        assert np.all(np.isnan(g[name])), name


def test_valid_traverse_does_not_warn():
    ft, probs, levels = drive(n=8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = fuse_traverse(ft, probs, NAMES, levels)
    assert np.nanmax(g["count"]) >= 3
    assert g.attrs["class_names"] == NAMES and g.attrs["track"].shape == (8, 2)


def test_bad_traverse_inputs():
    ft, probs, _ = drive(n=8)
    with pytest.raises(InputError, match=r"class_probs must have shape"):
        fuse_traverse(ft, probs[:, :2], NAMES)
    with pytest.raises(InputError, match="resolution must be a positive"):
        fuse_traverse(ft, probs, NAMES, resolution=-1)
    with pytest.raises(InputError, match="pose must be finite"):
        fuse_patch(GridMap(GridGeometry(0.1)), math.nan, 0.0, 0.0)


# -- a simulated traverse -------------------------------------------------------------------


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from rough_map.features import traverse_features
    from rough_map.io.truth import load_world
    from rough_map.simulate.course import SensorSpec, simulate

    out = tmp_path_factory.mktemp("sim") / "mixed"
    # 4 mm world cells: half the simulation time of the 2 mm default; the class map and
    # the poses (all this test reads) do not depend on it
    simulate(
        out,
        "mixed",
        length=8,
        images=False,
        sensor=SensorSpec(points_per_cell=6),
        world_spacing=0.004,
    )
    return traverse_features(out), load_world(out / "world_truth.npz"), out


def test_simulated_map_class_matches_the_world(simulated):
    from rough_map.io.traverse import load_traverse

    features, world, folder = simulated
    names = world.class_names
    truth_frames = np.array([names.index(lab) for lab in features["label"]])
    # a noisy classifier: 75 % on its answer, which is wrong for 15 % of the frames
    rng = np.random.default_rng(0)
    answer = truth_frames.copy()
    wrong = rng.random(answer.size) < 0.15
    answer[wrong] = rng.integers(0, len(names), wrong.sum())
    probs = np.full((answer.size, len(names)), 0.25 / (len(names) - 1))
    probs[np.arange(answer.size), answer] = 0.75
    g = fuse_traverse(features, probs, names, resolution=0.1, crs=load_traverse(folder).spec.crs)
    assert g.crs.origin is not None
    seen = g["count"] > 0
    assert seen.sum() > 300
    xc, yc = g.geometry.xy()
    X, Y = np.meshgrid(xc, yc)
    j = np.clip(np.round((X - world.origin[0]) / world.spacing).astype(int), 0, world.shape[1] - 1)
    i = np.clip(np.round((Y - world.origin[1]) / world.spacing).astype(int), 0, world.shape[0] - 1)
    truth = world.classes[i, j]
    accuracy = np.mean(g["class"][seen] == truth[seen])
    assert accuracy > 0.85
    assert accuracy > np.mean(answer == truth_frames)  # fusing overlapping patches helps
    assert np.all(np.isfinite(g["R"][seen])) and np.all(np.isnan(g["R"][~seen]))
