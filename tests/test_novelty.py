"""The novelty score: ground unlike every trained class says so, trained ground does not.

Known answers on Gaussian classes (the share of new samples above 1 is the quantile's
complement; far samples read far above 1), the shipped model on simulated ground it never
saw and on real-like ground (paving blocks, boulders, smoothed ground, the CAPTIF
chipseal), the map's ``novel`` layer, round trips and tampered scores.
"""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from surfaces import bilinear, real_like_surface
from test_density import CAPTIF_STARTS, captif_cloud

from rough_map.classify import load_terrain_model, save_terrain_model
from rough_map.classify.novelty import ClassDistance, held_out_distances
from rough_map.errors import InputError, ModelError
from rough_map.features import frame_features
from rough_map.features.extract import feature_table
from rough_map.map import fuse_patch
from rough_map.map.grid import GridMap
from rough_map.map.grid_geometry import GridGeometry
from rough_map.map.layers import init_layers
from rough_map.patch import PatchSpec

SPEC = PatchSpec()


def _mixes(d: int, seed: int = 0) -> list[np.ndarray]:
    """The shapes of three Gaussian classes in d dimensions (each its own covariance)."""
    rng = np.random.default_rng(seed)
    return [rng.normal(size=(d, d)) / math.sqrt(d) + np.eye(d) for _ in range(3)]


def _classes(rng: np.random.Generator, n: int, d: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """n samples of each of the three classes of :func:`_mixes`, 6 apart."""
    rows = [rng.normal(size=(n, d)) @ m + 6.0 * k for k, m in enumerate(_mixes(d))]
    return np.vstack(rows), np.repeat(np.array(["a", "b", "c"]), n)


def test_the_held_out_quantile_is_the_share_of_new_samples_within_one() -> None:
    Z, y = _classes(np.random.default_rng(0), 3000)
    folds = np.arange(len(Z)) % 5
    splits = [(np.flatnonzero(folds != f), np.flatnonzero(folds == f)) for f in range(5)]
    score = ClassDistance(0.95).fit(Z, y).calibrate(held_out_distances(Z, y, splits, 0.95))
    fresh, _ = _classes(np.random.default_rng(1), 4000)
    assert np.mean(score.novelty(fresh) > 1) == pytest.approx(0.05, abs=0.012)
    far = fresh[:100] + 12.0 * np.array([1, -1, 1, -1, 1, -1])
    assert np.all(score.novelty(far) > 3)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), shift=st.floats(-50, 50), scale=st.floats(0.01, 100))
def test_the_score_is_the_same_in_any_units_and_origin(seed: int, shift: float, scale: float):
    """Mahalanobis distances do not change when every feature is scaled and shifted (the
    shrinkage target scales with them)."""
    rng = np.random.default_rng(seed)
    Z, y = _classes(rng, 200, d=4)
    probe = rng.normal(size=(50, 4)) * 4
    a = ClassDistance().fit(Z, y).distance(probe)
    b = ClassDistance().fit(Z * scale + shift, y).distance(probe * scale + shift)
    assert np.allclose(a, b, rtol=1e-6)


def test_bad_rows_are_refused_with_a_reason() -> None:
    with pytest.raises(InputError, match="quantile must be in"):
        ClassDistance(1.0).fit(np.zeros((4, 2)), ["a"] * 4)
    with pytest.raises(InputError, match="rows and labels differ"):
        ClassDistance().fit(np.zeros((4, 2)), ["a"] * 3)
    with pytest.raises(InputError, match="at least 2 frames"):
        ClassDistance().fit(np.full((4, 2), np.nan), ["a"] * 4)
    with pytest.raises(InputError, match="no held-out frame"):
        ClassDistance().fit(np.eye(3), ["a", "b", "a"]).calibrate([np.nan])


# ------------------------------------------------------------------ the shipped model


@cache
def _model():
    return load_terrain_model("default")


def _novelty(clouds: list[np.ndarray]) -> np.ndarray:
    """The shipped model's novelty of each cloud read (the patch ahead), as classify reads."""
    model = _model()
    results = [frame_features(c, model.reading()) for c in clouds]
    omega = next(r[1] for r in results if r[1] is not None)
    table = feature_table([r[0] for r in results], [r[2] for r in results], omega, SPEC, "t")
    novelty = model.novelty(table)
    return novelty[np.isfinite(novelty)]


def _real_like_clouds(kind: str, per_cell: float) -> list[np.ndarray]:
    rng = np.random.default_rng(len(kind) + int(per_cell))
    side = SPEC.n * SPEC.spacing
    clouds = []
    for seed in (0, 1):
        grid = real_like_surface(kind, seed)
        for ox, oy in ((0.1, 0.1), (0.7, 1.0), (1.3, 1.9), (1.9, 0.1), (0.4, 1.6), (1.6, 1.0)):
            n = rng.poisson(per_cell * (1.1 * side / SPEC.spacing) ** 2)
            px = rng.uniform(-0.05 * side, 1.05 * side, n)
            py = rng.uniform(-0.05 * side, 1.05 * side, n)
            pz = bilinear(grid, ox + px, oy + py) + 0.0003 * rng.standard_normal(n)
            clouds.append(np.column_stack([px + SPEC.x0, py + SPEC.y0, pz]))
    return clouds


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["blocks", "boulders", "smooth"])
@pytest.mark.parametrize("per_cell", [12, 4])
def test_real_like_ground_is_unlike_every_trained_class(kind: str, per_cell: float) -> None:
    """Measured: every window of the three kinds at 12 and 4 points per cell reads above 1
    (medians 1.35-1.99)."""
    novelty = _novelty(_real_like_clouds(kind, per_cell))
    assert len(novelty) >= 10
    assert np.mean(novelty > 1) >= 0.9


def test_real_chipseal_is_unlike_every_trained_class() -> None:
    """The CAPTIF scan (real road texture) reads 4.5-5.5."""
    novelty = _novelty([captif_cloud(s, 4, seed=i) for i, s in enumerate(CAPTIF_STARTS)])
    assert len(novelty) >= 3 and np.all(novelty > 2)


@pytest.mark.parametrize("per_cell", [1, 3, 40])
def test_trained_ground_at_other_densities_is_rarely_novel(tmp_path: Path, per_cell) -> None:
    """A simulated course the model never saw (another seed, and densities outside the
    training's 6-20 points per cell): measured 2-4 of 115 frames above 1."""
    from rough_map.features import feature_tables
    from rough_map.io.traverse import load_traverse
    from rough_map.simulate.course import SensorSpec, simulate

    out = tmp_path / "course"
    simulate(
        out,
        "random",
        length=12.0,
        seed=7,
        images=False,
        sensor=SensorSpec(points_per_cell=per_cell),
    )
    model = _model()
    (table,) = feature_tables([load_traverse(out)], model.reading())
    pred = model.predict(table)
    scored = np.isfinite(pred.novelty)
    assert scored.sum() == pred.valid.sum() > 30
    assert np.mean(pred.novel[scored]) <= 0.1


# ------------------------------------------------------------------ files and the map


def test_the_shipped_card_describes_the_score() -> None:
    from rough_map.classify import read_card
    from rough_map.resources import model_base

    whole = read_card(model_base("default"))
    card = whole["novelty"]
    assert card["quantile"] == 0.99 and 1 < card["threshold"] < 3
    # fitted on this version's features of the training recipe, not the classifier's
    assert len(card["training_sha256"]) == 64
    assert card["training_sha256"] != whole["training_data"]["sha256"]


def test_a_saved_model_keeps_its_score_and_a_tampered_one_is_refused(tmp_path: Path) -> None:
    model = _model()
    save_terrain_model(model, tmp_path / "m")
    again = load_terrain_model(tmp_path / "m")
    probe = np.random.default_rng(0).normal(size=(20, len(model.novelty_.means_[0])))
    assert np.array_equal(again.novelty_.novelty(probe), model.novelty_.novelty(probe))
    import copy

    bad = copy.deepcopy(model)
    bad.novelty_.precisions_ = bad.novelty_.precisions_[:, :3, :3]
    save_terrain_model(bad, tmp_path / "bad")
    with pytest.raises(ModelError, match=r"bad\.skops: malformed model: novelty_ arrays disagree"):
        load_terrain_model(tmp_path / "bad")
    bad = copy.deepcopy(model)
    bad.novelty_.threshold_ = -1.0
    save_terrain_model(bad, tmp_path / "neg")
    with pytest.raises(ModelError, match=r"novelty_\.threshold_"):
        load_terrain_model(tmp_path / "neg")


def test_a_model_without_the_score_gives_no_novelty(small_traverse: Path) -> None:
    import copy

    from rough_map.features import feature_tables
    from rough_map.io.traverse import load_traverse

    model = copy.deepcopy(_model())
    model.novelty_ = None
    (table,) = feature_tables([load_traverse(small_traverse)], model.reading())
    pred = model.predict(table)
    assert np.isnan(pred.novelty).all() and not pred.novel.any()


def test_the_novel_layer_is_the_share_of_novel_patches() -> None:
    grid = GridMap(GridGeometry(origin=(0.0, -1.0), resolution=0.1, shape=(20, 40)))
    init_layers(grid, ("a", "b"))
    p = np.array([0.7, 0.3])
    for novelty in (0.5, 2.0, 3.0, math.nan):
        fuse_patch(grid, 0.0, 0.0, 0.0, R=1e-4, w=-2.0, probs=p, novelty=novelty, spec=SPEC)
    seen = grid["count"] > 0
    assert seen.any()
    assert np.allclose(grid["novel"][seen], 2 / 3)
    assert np.isnan(grid["novel"][~seen]).all()
