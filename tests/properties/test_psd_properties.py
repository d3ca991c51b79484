"""Invariants of the estimator (hypothesis): trends, scale, seeds, offsets."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rough_map import iso8608, psd
from rough_map.errors import PatchError
from rough_map.patch import grid_points
from rough_map.psd import patch_roughness

B = 0.008
seeds = st.integers(0, 2**16)


def _patch(seed, w=-2.3):
    return iso8608.synthesize_surface((64, 64), B, 64e-6, w, seed=seed)


@settings(max_examples=25, deadline=None)
@given(
    seed=seeds,
    offset=st.floats(-100, 100),
    slope=st.floats(-0.3, 0.3),
    lateral=st.floats(-0.3, 0.3),
)
def test_planes_do_not_change_the_estimate(seed, offset, slope, lateral):
    h = _patch(seed)
    x = np.arange(64) * B
    plane = offset + slope * x[None, :] + lateral * x[:, None]
    a, b = patch_roughness(h, B), patch_roughness(h + plane, B)
    assert math.isclose(a.R, b.R, rel_tol=1e-3)
    assert math.isclose(a.w, b.w, rel_tol=1e-3, abs_tol=1e-4)


@settings(max_examples=25, deadline=None)
@given(seed=seeds, k=st.floats(0.01, 100))
def test_scaling_heights_by_k_scales_R_by_k_squared(seed, k):
    h = _patch(seed)
    a, b = patch_roughness(h, B), patch_roughness(k * h, B)
    assert math.isclose(b.R, k * k * a.R, rel_tol=1e-4)
    assert math.isclose(a.w, b.w, rel_tol=1e-4, abs_tol=1e-5)
    assert math.isclose(b.rms, k * a.rms, rel_tol=1e-4)


@settings(max_examples=15, deadline=None)
@given(seed=seeds, w=st.floats(-3.0, -1.8))
def test_same_seed_same_answer(seed, w):
    a = patch_roughness(_patch(seed, w), B)
    b = patch_roughness(_patch(seed, w), B)
    assert a.R == b.R and a.w == b.w


@settings(max_examples=15, deadline=None)
@given(seed=seeds, dz=st.floats(-50, 50), dy=st.floats(-0.004, 0.004))
def test_cloud_translation_in_z_is_invisible(seed, dz, dy):
    rng = np.random.default_rng(seed)
    pts = np.column_stack(
        [
            rng.uniform(0.5, 1.5, 60_000),
            rng.uniform(-0.5, 0.5, 60_000),
            rng.normal(0, 0.003, 60_000),
        ]
    )
    a = grid_points(pts)
    b = grid_points(pts + [0.0, 0.0, dz])
    np.testing.assert_allclose(b.heights - dz, a.heights, atol=1e-9)
    np.testing.assert_array_equal(a.counts, b.counts)


def _same(a, b) -> bool:
    """Two outcomes equal to the last bit (PatchErrors by their message)."""
    if isinstance(a, PatchError) or isinstance(b, PatchError):
        return type(a) is type(b) and str(a) == str(b)
    fields = ("R", "w", "sigma_R", "sigma_w", "se_lnR", "se_w", "rms", "fit_residual")
    return all(getattr(a, f) == getattr(b, f) for f in fields) and np.array_equal(a.psd, b.psd)


@settings(max_examples=15, deadline=None)
@given(
    seeds=st.lists(seeds, min_size=1, max_size=9),
    holes=st.floats(0.0, 0.3),
    subtract=st.booleans(),
    split=st.integers(1, 8),
)
def test_a_patch_reads_the_same_alone_or_in_any_batch(seeds, holes, subtract, split):
    """patch_roughness_each gives each patch the numbers patch_roughness gives it alone, to
    the last bit, whatever it is stacked with (gaps, dropped profiles, own noise floors,
    refusals): frames measured in a traverse's chunks and one at a time agree."""
    rng = np.random.default_rng(seeds[0])
    stack = np.stack([_patch(s, w=-2.0 - 0.1 * (s % 8)) for s in seeds])
    stack[rng.random(stack.shape) < holes * rng.random((len(seeds), 1, 1))] = np.nan
    floors = 10.0 ** rng.uniform(-12, -7, len(seeds))
    options = {"subtract_noise": subtract, "gridding": "cell_mean"}
    batch = psd.patch_roughness_each(stack, B, noise_psd=floors, **options)
    alone = []
    for h, floor in zip(stack, floors, strict=True):
        try:
            alone.append(patch_roughness(h, B, noise_psd=float(floor), **options))
        except PatchError as exc:
            alone.append(exc)
    assert all(_same(a, b) for a, b in zip(batch, alone, strict=True))
    halves = [
        *psd.patch_roughness_each(stack[:split], B, noise_psd=floors[:split], **options),
        *psd.patch_roughness_each(stack[split:], B, noise_psd=floors[split:], **options),
    ]
    assert all(_same(a, b) for a, b in zip(batch, halves, strict=True))
