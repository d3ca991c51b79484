"""Does a reading follow its power law, and does it describe its patch? (issue 29)

``centre_psd``, ``band_rms``, ``rms_ratio`` and ``curvature_z`` of
:class:`rough_map.psd.PatchRoughness` (:mod:`rough_map.psd._fit`), on power-law patches
(known answers) and on spectra that bend by a known amount.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from surfaces import power_law_field, real_like_surface

from rough_map.features import frame_features
from rough_map.patch import Extraction
from rough_map.psd import patch_roughness

B = 0.008


def power_law_patches(w: float) -> np.ndarray:
    return power_law_field(896, B, 1e-4, w, seed=int(-10 * w)).patches(112)


@pytest.mark.parametrize("w", [-2.0, -2.5, -3.0])
def test_power_law_patches_read_as_power_laws_that_describe_them(w: float) -> None:
    ratios, zs, centres = [], [], []
    for patch in power_law_patches(w):
        r = patch_roughness(patch, B)
        ratios.append(r.rms_ratio)
        zs.append(r.curvature_z)
        # the band's log centre: geometric mean of the first and last ordinate fitted
        om = r.omega[r.fit_mask]
        assert r.omega_centre == pytest.approx(math.sqrt(om[0] * om[-1]))
        centres.append(math.log(r.centre_psd / (1e-4 * r.omega_centre**w)))
        assert r.consistent
    assert 0.9 <= np.median(ratios) <= 1.1
    assert np.mean(np.abs(zs) <= 4.0) >= 0.9
    assert abs(np.median(zs)) <= 1.5
    # no extrapolation: the centre's PSD scatters far less than R itself
    assert np.median(np.abs(centres)) <= 0.1


def test_band_rms_is_the_power_over_the_band() -> None:
    """A power law's band rms is the integral of R Omega^w over the ordinates fitted."""
    w = -2.5
    vals = []
    for patch in power_law_patches(w):
        r = patch_roughness(patch, B)
        om = r.omega[r.fit_mask]
        d = r.omega[1] - r.omega[0]
        expected = math.sqrt(1e-4 * np.sum(om**w) * d)
        vals.append(math.log(r.band_rms / expected))
    assert abs(np.median(vals)) <= 0.1


def bent_patch(c: float, seed: int, w: float = -2.5, n: int = 112) -> np.ndarray:
    """Profiles whose PSD is ``R Omega^w exp(c (ln Omega - ln 60)^2)``, a log spectrum with
    the quadratic term ``c``, as a stack of independent rows."""
    rng = np.random.default_rng(seed)
    k = np.arange(1, 4 * n // 2 + 1)
    omega = 2 * np.pi * k / (4 * n * B)
    psd = 1e-4 * omega**w * np.exp(c * (np.log(omega) - math.log(60.0)) ** 2)
    amp = np.sqrt(psd * (omega[1] - omega[0]))  # one-sided: variance per bin
    phase = rng.uniform(0, 2 * np.pi, (n, k.size))
    coef = amp * rng.rayleigh(1.0, (n, k.size)) * np.exp(1j * phase)
    t = np.arange(4 * n) * B
    rows = (coef[:, :, None] * np.exp(1j * omega[None, :, None] * t[None, None, :])).real.sum(1)
    return rows[:, n : 2 * n]  # a window of a longer profile: not periodic in the patch


@pytest.mark.parametrize("c", [-0.4, 0.4])
def test_a_bent_spectrum_is_not_a_power_law(c: float) -> None:
    r = patch_roughness(bent_patch(c, seed=1), B)
    assert not r.power_law
    assert np.sign(r.curvature_z) == np.sign(c)
    assert r.curvature == pytest.approx(c, abs=0.2)


def test_a_straight_spectrum_of_the_same_make_is_one() -> None:
    zs = [patch_roughness(bent_patch(0.0, seed=s), B).curvature_z for s in range(6)]
    assert np.median(np.abs(zs)) <= 2.0


def test_a_patch_whose_power_is_a_few_profiles_fails_its_own_check() -> None:
    """A boulder under three of the patch's 112 profiles: their power is most of the
    patch's, the geometric mean of the profiles' fits far below it. The fit contradicts
    the patch; a frame refuses it and says why."""
    patch = power_law_patches(-2.5)[0].copy() * 0.05
    x = np.arange(112) * B
    patch[50:53] += 0.05 * np.exp(-(((x - 0.45) / 0.05) ** 2))
    r = patch_roughness(patch, B)
    assert r.rms_ratio < 0.5
    assert not r.consistent
    yy, xx = np.meshgrid(np.arange(112), np.arange(112), indexing="ij")
    pts = np.column_stack([0.552 + (xx.ravel() + 0.5) * B, -0.448 + (yy.ravel() + 0.5) * B])
    rng = np.random.default_rng(0)
    cloud = np.column_stack(
        [
            np.repeat(pts, 12, axis=0) + rng.uniform(-B / 2, B / 2, (pts.shape[0] * 12, 2)),
            np.repeat(patch.ravel(), 12),
        ]
    )
    row, omega, psd = frame_features(cloud, Extraction())
    assert not row["valid"]
    assert "contradicts its patch" in row["reason"]
    assert omega is None and psd is None


@pytest.mark.parametrize("kind", ["blocks", "boulders", "smooth"])
def test_readings_of_ground_outside_the_family_stay_in_their_ranges(kind: str) -> None:
    grid = real_like_surface(kind, seed=5)
    for r0 in (0, 100, 200):
        r = patch_roughness(grid[r0 : r0 + 90, 20:110], 0.01)
        assert 0.0 <= r.lateral_scale <= 5.0 or math.isnan(r.lateral_scale)
        assert r.band_rms > 0 and r.centre_psd > 0 and r.rms_ratio > 0
        assert 0.0 < r.omega_centre < math.pi / 0.01
        d = r.as_dict()
        assert isinstance(d["consistent"], bool) and isinstance(d["power_law"], bool)
