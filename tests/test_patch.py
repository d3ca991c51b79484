"""Patch of interest: cropping, gridding, tilt (paper Eq. 11, section 5.3), noise floor."""

import math

import numpy as np
import pytest

from rough_map.errors import InputError, PatchError
from rough_map.geometry import rotation_matrix
from rough_map.patch import (
    Extraction,
    PatchSpec,
    compensate_tilt,
    extract_patch,
    grid_points,
)
from rough_map.psd import patch_roughness


def test_eq11_matrix():
    phi, theta = math.radians(4.0), math.radians(3.0)  # pitch, roll
    c, s = math.cos, math.sin
    eq11 = np.array(
        [
            [c(phi), s(phi) * s(theta), s(phi) * c(theta)],
            [0, c(theta), -s(theta)],
            [-s(phi), c(phi) * s(theta), c(phi) * c(theta)],
        ]
    )
    np.testing.assert_allclose(rotation_matrix(roll=theta, pitch=phi), eq11, atol=1e-15)


@pytest.mark.parametrize("angles", [(0.3, -0.2, 2.9), (-1.2, 0.7, -0.4), (0.0, 1.5, 3.1)])
def test_rotation_matrix_is_extrinsic_xyz_euler(angles):
    """The written-out matrix is scipy's Rotation.from_euler("xyz", ...)."""
    from scipy.spatial.transform import Rotation

    expected = Rotation.from_euler("xyz", angles).as_matrix()
    np.testing.assert_allclose(rotation_matrix(*angles), expected, atol=1e-15)


def test_grid_means_and_geometry():
    spec = PatchSpec(ahead=1.0, size=0.064, spacing=0.008)  # 8 x 8 cells
    assert spec.n == 8
    pts = np.array(
        [
            [spec.x0 + 0.004, spec.y0 + 0.004, 1.0],  # cell [0, 0]
            [spec.x0 + 0.005, spec.y0 + 0.003, 3.0],  # cell [0, 0]
            [spec.x0 + 0.028, spec.y0 + 0.012, 5.0],  # row 1 (y), column 3 (x)
            [spec.x0 - 0.001, 0.0, 9.0],  # just outside (near edge)
            [5.0, 5.0, 9.0],  # far outside
        ]
    )
    g = grid_points(pts, spec, min_points=1)
    assert g.heights[0, 0] == pytest.approx(2.0)
    assert g.heights[1, 3] == pytest.approx(5.0)
    assert g.counts.sum() == 3 and g.n_points == 3
    assert np.isnan(g.heights[2, 2])


def test_non_finite_points_are_ignored():
    spec = PatchSpec(size=0.064)
    pts = np.array(
        [
            [1.0, 0.0, 0.1],
            [np.nan, 0.0, 5.0],
            [1.0, np.nan, 5.0],
            [1.0, 0.0, np.nan],
            [np.inf, 0.0, 1.0],
            [1.0, 0.001, 0.3],
        ]
    )
    g = grid_points(pts, spec, min_points=1)
    assert g.n_points == 2
    assert np.nanmax(g.heights) == pytest.approx(0.2)


def test_point_noise_is_estimated_on_a_sloped_surface(dense_cloud):
    pts = dense_cloud("concrete", noise=0.0005)
    pts[:, 2] += 0.1 * pts[:, 0]  # a 10 % slope
    g = grid_points(pts)
    assert g.point_noise == pytest.approx(0.0005, rel=0.15)
    expected_floor = g.point_noise**2 * np.mean(1 / g.counts[g.counts > 0]) * 0.008 / math.pi
    assert g.noise_psd == pytest.approx(expected_floor)
    assert g.gridding == "cell_mean"


def test_dense_cloud_recovers_the_surface(dense_cloud):
    r = patch_roughness(grid_points(dense_cloud("gravel")).heights, 0.008, gridding="cell_mean")
    assert 128e-6 < r.R < 512e-6  # ISO E
    assert r.w == pytest.approx(-2.4, abs=0.15)


@pytest.mark.parametrize("surface", ["compact_soil", "ploughed_soil"])
@pytest.mark.parametrize(("roll_deg", "pitch_deg"), [(3.0, 0.0), (3.1, 4.46)])
def test_tilt_is_a_small_effect_and_compensation_removes_it(
    dense_cloud, surface, roll_deg, pitch_deg
):
    """Paper section 5.3: R and w change by < 8 % uncompensated; ~0 once compensated.

    Tilting the view shears the surface (x moves by -pitch * z) and shifts the patch by a
    few mm; grid_points levels the patch on its own plane, which removes the shear. R,
    extrapolated to 1 rad/m, is the more sensitive of the two, as in the paper.
    """
    roll, pitch = math.radians(roll_deg), math.radians(pitch_deg)
    err_r, err_w = [], []
    for seed in range(6):
        world = dense_cloud(surface, n_points=400_000, noise=0.0002, seed=seed)
        vehicle = world @ rotation_matrix(roll, pitch)  # the same points from a tilted rover
        truth = patch_roughness(grid_points(world).heights, 0.008, gridding="cell_mean")
        raw = patch_roughness(grid_points(vehicle).heights, 0.008, gridding="cell_mean")
        comp = patch_roughness(
            grid_points(vehicle, roll=roll, pitch=pitch).heights, 0.008, gridding="cell_mean"
        )
        err_r.append(abs(raw.R / truth.R - 1))
        err_w.append(abs(raw.w / truth.w - 1))
        assert comp.R == pytest.approx(truth.R, rel=1e-3)
        assert comp.w == pytest.approx(truth.w, rel=1e-3)
    assert np.mean(err_r) < 0.08
    assert np.mean(err_w) < 0.08
    np.testing.assert_allclose(compensate_tilt(vehicle, roll, pitch), world, atol=1e-12)
    same = extract_patch(vehicle, roll=roll, pitch=pitch)
    np.testing.assert_allclose(same.heights, grid_points(world).heights, atol=1e-9)


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((0, 3)), "empty"),
        (np.zeros((10, 2)), r"shape \(N, 3\)"),
        (np.zeros(30), r"shape \(N, 3\)"),
        (np.full((10, 3), np.nan), "NaN"),
        ([["a", "b", "c"]], "numeric"),
    ],
)
def test_bad_clouds(points, match):
    with pytest.raises(InputError, match=match):
        grid_points(points)


def test_too_few_points_in_the_patch():
    pts = np.random.default_rng(0).uniform(-5, -4, (1000, 3))  # all behind the vehicle
    with pytest.raises(PatchError, match="vehicle frame"):
        grid_points(pts)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"spacing": 0.0}, "spacing"),
        ({"size": -1.0}, "size"),
        ({"ahead": float("nan")}, "ahead"),
        ({"size": 0.02}, "at least 8"),
    ],
)
def test_bad_specs(kwargs, match):
    with pytest.raises(InputError, match=match):
        PatchSpec(**kwargs)


def test_bad_angles():
    with pytest.raises(InputError, match="roll"):
        compensate_tilt(np.zeros((3, 3)), float("nan"), 0.0)
    with pytest.raises(InputError, match="pitch"):
        grid_points(np.zeros((3, 3)), pitch=4.0)


@pytest.mark.parametrize("width", [1.2, 20.0])
def test_a_tilted_patch_is_levelled_however_wide_the_cloud(width: float) -> None:
    """The patch's plane comes from a subsample of the cloud; when the cloud is a wide scan
    with a fraction of a per cent of its points over the patch, from a denser one."""
    rng = np.random.default_rng(3)
    n = 200_000
    x = rng.uniform(1.0 - width / 2, 1.0 + width / 2, n)
    y = rng.uniform(-width / 2, width / 2, n)
    z = math.tan(math.radians(5.0)) * x + rng.normal(0.0, 0.002, n)
    grid = grid_points(np.column_stack([x, y, z]), min_points=100)
    assert grid.level_angle == pytest.approx(math.radians(5.0), abs=math.radians(0.05))
    flat = grid_points(np.column_stack([x, y, z - math.tan(math.radians(5.0)) * x]))
    assert flat.level_angle == 0.0


@pytest.mark.parametrize("per_cell", [3.0, 6.0, 12.0, 40.0])
def test_point_noise_of_a_tilted_plane_at_any_density(per_cell):
    """Known answer: white noise of 0.3 mm on a tilted plane, at densities that pool every
    4th row of cells (under 8 points per cell) or every 8th: within 5 % of 0.3 mm (the
    centroid correction's gradient, from noisy neighbouring means, adds about 1/(12 k) of
    the variance, which the cell value carries too)."""
    spec = PatchSpec()
    rng = np.random.default_rng(int(per_cell))
    count = int(per_cell * spec.n**2)
    x = rng.uniform(spec.x0, spec.x0 + spec.n * spec.spacing, count)
    y = rng.uniform(spec.y0, spec.y0 + spec.n * spec.spacing, count)
    z = 0.05 * x - 0.03 * y + rng.normal(0.0, 3e-4, count)
    g = grid_points(np.column_stack([x, y, z]), spec, level=False)
    assert g.point_noise == pytest.approx(3e-4, rel=0.05)


def test_wide_rows_grid_a_plane_at_their_cell_centres():
    """Cells 8 mm along and 32 mm across: each cell's mean is referred to its centre with
    the gradient along and across, so a tilted plane reads its height at every centre to
    within what the gradient of the neighbouring means misses."""
    spec = PatchSpec(row_spacing=0.032)
    rng = np.random.default_rng(0)
    x = spec.x0 + spec.n * spec.spacing * rng.random(60_000)
    y = spec.y0 + spec.rows * spec.row_step * rng.random(60_000)
    grid = grid_points(np.column_stack([x, y, 0.03 * x - 0.05 * y + 0.2]), spec, level=False)
    assert grid.heights.shape == (spec.rows, spec.n) == (28, 112)
    cx = spec.x0 + (np.arange(spec.n) + 0.5) * spec.spacing
    cy = spec.y0 + (np.arange(spec.rows) + 0.5) * spec.row_step
    plane = 0.03 * cx[None, :] - 0.05 * cy[:, None] + 0.2
    inner = (slice(1, -1), slice(1, -1))  # the edges take one-sided gradients
    err = np.abs(grid.heights - plane)[inner]
    # the plain cell means sit at their points' centroid: 74 um off on median, 0.4 mm at
    # most; referred with the gradient of the neighbouring means, 4 um and 43 um
    assert np.median(err) < 1e-5 and err.max() < 1e-4
    assert grid.point_noise < 1e-4


def test_row_spacing_is_checked_and_square_cells_have_one_spelling():
    assert PatchSpec(row_spacing=0.008) == PatchSpec()
    spec = PatchSpec(row_spacing=0.016)
    assert (spec.rows, spec.n, spec.row_step) == (56, 112, 0.016)
    assert spec.corners()[2] == pytest.approx([1.448, 0.448])
    with pytest.raises(InputError, match=r"row_spacing=0.5 m\); need 3"):
        PatchSpec(row_spacing=0.5)
    with pytest.raises(InputError, match="row_spacing"):
        PatchSpec(row_spacing=-0.01)
    ex = Extraction(patch=spec)
    assert ex.to_dict()["row_spacing"] == 0.016
    assert Extraction.from_dict(ex.to_dict()) == ex
    assert "row_spacing" not in Extraction().to_dict()  # models of square cells unchanged
