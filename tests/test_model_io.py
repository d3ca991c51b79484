"""rough_map.classify.persistence: skops files with trusted types, sha256 in the card,
clear refusals."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import skops.io as sio
from sklearn.linear_model import LogisticRegression
from test_classify import random_segments, synthetic_table

from rough_map.classify import (
    TRUSTED_TYPES,
    TerrainModel,
    load_terrain_model,
    model_paths,
    read_card,
    save_terrain_model,
    sha256_file,
)
from rough_map.errors import ModelError
from rough_map.filter import make_terrain_model

ROOT = Path(__file__).resolve().parents[1]

#: Set when an object of :class:`Trap` is rebuilt: loading must never get that far.
SPRUNG: list[str] = []


class Trap:
    """A foreign type whose rebuilding would run code."""

    def __setstate__(self, state: dict) -> None:
        SPRUNG.append("setstate")
        self.__dict__.update(state)


@pytest.fixture(scope="module")
def tables():
    rng = np.random.default_rng(21)
    train = [synthetic_table(rng, random_segments(rng, 60.0), name=f"t{i}") for i in range(2)]
    test = synthetic_table(rng, random_segments(rng, 40.0), name="held-out", invalid_every=7)
    return train, test


@pytest.fixture(scope="module")
def model(tables) -> TerrainModel:
    return make_terrain_model(cv=2, evidence_per_m=1.5, level_jitter=0.0).fit(tables[0])


@pytest.fixture
def saved(model, tmp_path) -> tuple[Path, Path]:
    return save_terrain_model(model, tmp_path / "models" / "m", card_extra={"command": "test"})


def test_round_trip(model, tables, saved) -> None:
    model_file, card_file = saved
    assert model_file.name == "m.skops" and card_file.name == "m.card.json"
    loaded = load_terrain_model(model_file.with_suffix(""))
    _, test = tables
    a, b = model.predict(test), loaded.predict(test)
    np.testing.assert_array_equal(a.raw_class, b.raw_class)
    np.testing.assert_array_equal(a.filtered_class, b.filtered_class)
    np.testing.assert_allclose(a.filtered_proba, b.filtered_proba)
    np.testing.assert_allclose(a.raw_proba, b.raw_proba, equal_nan=True)
    assert loaded.cv_report_ == model.cv_report_
    assert loaded.levels_ == model.levels_


def test_card(model, saved) -> None:
    model_file, card_file = saved
    card = read_card(card_file)
    assert card["sha256"] == sha256_file(model_file)
    assert card["classes"] == [str(c) for c in model.classes_]
    assert list(card["features"]["derived"]) == model.feature_names
    assert all(card["features"]["derived"].values())  # every feature documented
    assert len(card["training_data"]["sha256"]) == 64
    assert [t["name"] for t in card["training_data"]["traverses"]] == ["t0", "t1"]
    cv = card["cross_validation"]
    assert cv["scheme"].startswith("GroupKFold")
    for part in ("raw", "filtered"):
        assert 0.0 <= cv[part]["macro_f1"] <= 1.0
    assert {"numpy", "scipy", "scikit-learn", "skops", "python"} <= set(card["versions"])
    assert card["command"] == "test"
    assert card["roughness_levels"]["levels"] == ["low", "medium", "high"]


def test_only_trusted_types_in_the_file(saved) -> None:
    untrusted = sio.get_untrusted_types(file=saved[0])
    assert set(untrusted) <= set(TRUSTED_TYPES)
    # the components are in the file: the path filter and the defect detector
    assert {
        "rough_map.filter.path_filter.PathFilter",
        "rough_map.filter.defects.IsolatedSpikes",
        "rough_map.classify.model.TerrainModel",
    } <= set(untrusted)


def test_trusted_types_name_the_classes_where_they_are_defined() -> None:
    import importlib

    for name in TRUSTED_TYPES:
        module, _, attr = name.rpartition(".")
        cls = getattr(importlib.import_module(module), attr)
        assert f"{cls.__module__}.{cls.__qualname__}" == name


def test_model_without_components_round_trips(tables, tmp_path) -> None:
    """path_filter=None: no smoothing; the card says so."""
    plain = TerrainModel(cv=2, level_jitter=0.0).fit(tables[0])
    model_file, card_file = save_terrain_model(plain, tmp_path / "plain")
    loaded = load_terrain_model(model_file)
    pred = loaded.predict(tables[1])
    np.testing.assert_array_equal(pred.filtered_class, pred.raw_class)
    card = read_card(card_file)
    assert card["filter"]["evidence_per_m"] is None and card["filter"]["defect_ratio"] is None


def test_model_paths() -> None:
    for name in ("models/x", "models/x.skops", "models/x.card.json"):
        assert model_paths(name) == (Path("models/x.skops"), Path("models/x.card.json"))


def test_tampered_file_is_refused(saved) -> None:
    model_file, _ = saved
    data = bytearray(model_file.read_bytes())
    data[len(data) // 2] ^= 0xFF
    model_file.write_bytes(bytes(data))
    with pytest.raises(
        ModelError, match=r"is not the [0-9a-f]{16}\.\.\. of .*altered or replaced"
    ) as e:
        load_terrain_model(model_file)
    assert len(str(e.value)) - len(str(model_file)) <= 150  # fuzz seed 23: 207 chars


def _with_card(path: Path, like: Path) -> None:
    """A card for ``path`` copied from a genuine one, with the right sha256."""
    card = json.loads(like.read_text())
    card["sha256"] = sha256_file(path)
    model_paths(path)[1].write_text(json.dumps(card))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda p: p.write_bytes(b"not a zip at all"), "not a skops model file"),
        (
            lambda p: zipfile.ZipFile(p, "w").writestr("hello.txt", "hi"),
            "not a skops model file",
        ),
        (lambda p: sio.dump(LogisticRegression(), p), "not a rough_map TerrainModel"),
        (lambda p: sio.dump({"model": Trap()}, p), "refusing to load types"),
    ],
    ids=["bytes", "zip", "sklearn", "foreign-type"],
)
def test_foreign_files_are_refused(tmp_path, saved, make, match) -> None:
    path = tmp_path / "foreign.skops"
    make(path)
    _with_card(path, saved[1])
    SPRUNG.clear()
    with pytest.raises(ModelError, match=match):
        load_terrain_model(path)
    assert not SPRUNG  # nothing from the file was run


def test_missing_file_and_card(tmp_path, saved, caplog) -> None:
    with pytest.raises(ModelError, match="no such model file"):
        load_terrain_model(tmp_path / "nothing")
    model_file, card_file = saved
    card_file.unlink()
    with pytest.raises(ModelError, match="no model card"):
        load_terrain_model(model_file)
    assert isinstance(load_terrain_model(model_file, verify=False), TerrainModel)
    assert "integrity is not checked" in caplog.text


def test_other_model_format_is_refused(model, tmp_path) -> None:
    old = model.format_
    model.format_ = "rough_map.TerrainModel/0"
    try:
        path, _ = save_terrain_model(model, tmp_path / "old")
    finally:
        model.format_ = old
    with pytest.raises(ModelError, match="retrain it"):
        load_terrain_model(path)


def test_unfitted_model_is_not_saved(tmp_path) -> None:
    with pytest.raises(ModelError, match="fitted TerrainModel"):
        save_terrain_model(TerrainModel(), tmp_path / "x")


def test_shipped_default_model() -> None:
    """models/default.skops loads, matches its card, and was trained on five classes."""
    model = load_terrain_model(ROOT / "models" / "default")
    card = read_card(ROOT / "models" / "default")
    assert list(model.classes_) == card["classes"]
    assert set(card["classes"]) == {
        "concrete", "dirt_road", "gravel", "compact_soil", "ploughed_soil",
    }  # fmt: skip
    assert card["size_bytes"] < 5e6
    assert card["command"].startswith("rough-map train")
    # the reproduction recipe names the training data the shipped model was fitted on
    recipe = (ROOT / "rough_map" / "cli" / "train.py").read_text()
    assert f"``{card['training_data']['sha256'][:8]}...``" in recipe
