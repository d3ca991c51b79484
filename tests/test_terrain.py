"""The named synthetic surfaces land where the paper puts them."""

import math

import numpy as np
import pytest

from rough_map import terrain
from rough_map.errors import InputError
from rough_map.iso8608 import iso_class
from rough_map.psd import patch_roughness, patch_roughness_batch

N, B = 112, 0.008


@pytest.mark.parametrize(
    ("name", "cls", "w"),
    [
        ("concrete", "C", -2.0),
        ("dirt_road", "D", -2.2),
        ("gravel", "E", -2.4),
        ("compact_soil", "E", -2.4),
        ("ploughed_soil", "F", -2.59),
    ],
)
def test_surfaces_match_the_paper(name, cls, w):
    stack = np.stack(
        [terrain.generate(name, (N, 3 * N), B, seed=s)[:, N : 2 * N] for s in range(12)]
    )
    est = patch_roughness_batch(stack, B)
    r = math.exp(np.mean([math.log(e.R) for e in est]))
    assert iso_class(r) == cls
    assert np.mean([e.w for e in est]) == pytest.approx(w, abs=0.08)


def test_generation_is_deterministic():
    a = terrain.generate("gravel", (64, 64), B, seed=1)
    np.testing.assert_array_equal(a, terrain.generate("gravel", (64, 64), B, seed=1))
    assert not np.array_equal(a, terrain.generate("gravel", (64, 64), B, seed=2))


def test_defects_make_a_spike():
    base = terrain.generate("concrete", (N, N), B, seed=3)
    plain = patch_roughness(base, B)
    centre = (N * B / 2, N * B / 2)
    for name, add in terrain.DEFECTS.items():
        r = patch_roughness(add(base, B, centre), B)
        assert r.rms > 2 * plain.rms, name


def test_unknown_surface():
    with pytest.raises(InputError, match="unknown surface"):
        terrain.generate("lava", (8, 8))
    assert terrain.surface_spec("ploughed").name == "ploughed_soil"
