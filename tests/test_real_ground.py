"""Random clouds of ground outside the Gaussian power-law family read like its exact grid.

The 1 cm grids of ``surfaces.real_like_surface`` (paving blocks with a characteristic scale,
boulders with steep sides, a power law smoothed over 4 mm as stereo smooths), read between
their nodes bilinearly, are sampled at random points with 0.3 mm of noise; each cloud's
reading (``spacing auto``, as ``rough-map features CLOUD`` reads it) is compared with the
same surface sampled exactly on the 8 mm grid and read with ``gridding="point"``. The
figure of issue 29 is 0.3 in median |ln R| and 0.1 in median |dw|; where it is not met yet,
the test is an expected failure that says what it measures.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
from surfaces import bilinear, real_like_surface

from rough_map.errors import PatchError
from rough_map.features import cloud_roughness
from rough_map.patch import Extraction, PatchSpec
from rough_map.psd import patch_roughness

SPEC = PatchSpec()
NOISE = 0.0003  # m
#: Window origins (m) on the 3 m grids: 12 patches per surface, on two surfaces.
ORIGINS = [(ox, oy) for ox in (0.1, 0.7, 1.3, 1.9) for oy in (0.1, 1.0, 1.9)]


@cache
def readings(kind: str, per_cell: float) -> np.ndarray:
    """(ln(R / R_exact), w - w_exact) of every window that was read, shape (windows, 2)."""
    rng = np.random.default_rng(int(per_cell * 10) + len(kind))
    centres = (np.arange(SPEC.n) + 0.5) * SPEC.spacing
    x, y = np.meshgrid(centres, centres)
    side = SPEC.n * SPEC.spacing
    out = []
    for seed in (0, 1):
        grid = real_like_surface(kind, seed)
        for ox, oy in ORIGINS:
            ref = patch_roughness(bilinear(grid, ox + x, oy + y), SPEC.spacing)
            count = rng.poisson(per_cell * (1.1 * side / SPEC.spacing) ** 2)
            px = rng.uniform(-0.05 * side, 1.05 * side, count)
            py = rng.uniform(-0.05 * side, 1.05 * side, count)
            pz = bilinear(grid, ox + px, oy + py) + NOISE * rng.standard_normal(count)
            cloud = np.column_stack([px + SPEC.x0, py + SPEC.y0, pz])
            try:
                _, r = cloud_roughness(cloud, Extraction(auto_spacing=True))
            except PatchError:
                continue
            out.append((math.log(r.R / ref.R), r.w - ref.w))
    return np.array(out)


def _check(kind: str, per_cell: float) -> None:
    got = readings(kind, per_cell)
    assert len(got) == 2 * len(ORIGINS), "every window is read"
    assert np.median(np.abs(got[:, 0])) <= 0.3
    assert np.median(np.abs(got[:, 1])) <= 0.1


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "per_cell"), [("blocks", 12), ("blocks", 4), ("boulders", 12)])
def test_clouds_of_real_like_ground_read_like_its_exact_grid(kind: str, per_cell: float) -> None:
    """Measured: blocks 0.27 / 0.13 and boulders 0.14 in median |ln R| at 12 / 4 / 12
    points per cell."""
    _check(kind, per_cell)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 29: not met yet (see the module's text)")
@pytest.mark.parametrize(
    ("kind", "per_cell"),
    [
        # -0.81 in ln R: the noise floor leaves out the cells of the boulders' flanks as
        # outliers (pooling every cell reads -0.35, but lets stereo mismatches into the
        # floor: gravel's stereo R then 1.29 x the truth, test_stereo)
        ("boulders", 4),
        ("smooth", 12),  # -1.70: the top half of the band is 1-20 % of the noise floor
        ("smooth", 4),
        ("blocks", 1),  # -2.3: the coarser grid's band, on a curved spectrum
        ("boulders", 1),
    ],
)
def test_where_real_like_ground_does_not_read_like_its_grid_yet(kind: str, per_cell: float) -> None:
    _check(kind, per_cell)
