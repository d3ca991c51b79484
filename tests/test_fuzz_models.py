"""Fuzzing of model files: mutated ``.skops`` archives re-signed with a matching card (as
someone holding both files could), mutated ``schema.json`` and arrays inside the zip, and
mutated cards. Loading gives a TerrainModel that predicts, or a one-line ModelError."""

from __future__ import annotations

import copy
import hashlib
import io
import json
import random
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fuzzing import FUZZ, SEEDS, assert_bounded, mutate, write_case
from hypothesis import given
from test_classify import random_segments, synthetic_table

from rough_map.classify import load_terrain_model, read_card
from rough_map.errors import ModelError
from rough_map.resources import model_base

pytestmark = pytest.mark.fuzz

BASE = model_base("default")
SKOPS = BASE.with_name("default.skops").read_bytes()
CARD: dict[str, Any] = json.loads(BASE.with_name("default.card.json").read_text())

with zipfile.ZipFile(io.BytesIO(SKOPS)) as _zf:
    MEMBERS = {info.filename: _zf.read(info) for info in _zf.infolist()}
SCHEMA = json.loads(MEMBERS["schema.json"])

#: Values a mutated schema node may take.
_HOSTILE: list[Any] = [None, True, 0, -1, 2**64, 1e308, float("nan"), "", "x" * 300, [], {},
                       [[[[]]]], "\"nan\"", "1e999", "(", "[1,", "__import__('os')",
                       "builtins", "numpy", "sklearn.tree._tree.Tree", "ObjectNode", "DictNode",
                       "NdArrayNode", "JsonNode", "ListNode", "TupleNode"]  # fmt: skip


@pytest.fixture(scope="module")
def table():
    rng = np.random.default_rng(3)
    return synthetic_table(rng, random_segments(rng, 6.0), name="fuzz", invalid_every=5)


def zip_members(members: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return out.getvalue()


def write_pair(factory: pytest.TempPathFactory, data: bytes, card: Any = None) -> Path:
    """``m.skops`` holding ``data`` and a card re-signed with its sha256."""
    path = write_case(factory, "m.skops", data)
    signed = dict(CARD, model_file="m.skops", sha256=hashlib.sha256(data).hexdigest())
    text = json.dumps(signed if card is None else card, allow_nan=True)
    path.with_name("m.card.json").write_text(text)
    return path.with_suffix("")


def load_and_predict(name: Path, table: Any) -> Any:
    model = load_terrain_model(name)
    for mode in ("forward", "smooth", "viterbi"):
        pred = model.predict(table, mode=mode)
        assert pred.filtered_proba.shape == (len(table), len(model.classes_))
    return model


def _spots(node: Any, out: list[tuple[Any, Any]]) -> list[tuple[Any, Any]]:
    """Every (container, key) of a JSON tree."""
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, value in items:
        out.append((node, key))
        _spots(value, out)
    return out


def mutate_node(tree: Any, rng: random.Random) -> Any:
    """A copy of the schema with one to three of its nodes changed."""
    tree = copy.deepcopy(tree)
    for _ in range(rng.choice((1, 1, 2, 3))):
        spots = _spots(tree, [])
        parent, key = rng.choice(spots)
        kind = rng.randrange(5)
        if kind == 0 and isinstance(parent, dict):
            del parent[key]
        elif kind == 1:  # a value from elsewhere in the schema
            other, okey = rng.choice(spots)
            parent[key] = copy.deepcopy(other[okey])
        elif kind == 2 and isinstance(parent[key], str) and parent[key][:1] not in '"[{':
            # a JSON-encoded scalar gets a hostile number
            parent[key] = rng.choice(["1e999", "-1", "0", "NaN", "9" * 40, '""', "[]"])
        else:
            parent[key] = rng.choice(_HOSTILE)
    return tree


@FUZZ
@given(seed=SEEDS)
def test_resigned_model_bytes(tmp_path_factory, table, seed) -> None:
    name = write_pair(tmp_path_factory, mutate(SKOPS, seed))
    assert_bounded(load_and_predict, name, table)


@FUZZ
@given(seed=SEEDS)
def test_resigned_schema_values(tmp_path_factory, table, seed) -> None:
    schema = mutate_node(SCHEMA, random.Random(seed))
    members = dict(MEMBERS, **{"schema.json": json.dumps(schema).encode()})
    name = write_pair(tmp_path_factory, zip_members(members))
    assert_bounded(load_and_predict, name, table)


@FUZZ
@given(seed=SEEDS)
def test_resigned_schema_text(tmp_path_factory, table, seed) -> None:
    members = dict(MEMBERS, **{"schema.json": mutate(MEMBERS["schema.json"], seed)})
    name = write_pair(tmp_path_factory, zip_members(members))
    assert_bounded(load_and_predict, name, table)


@FUZZ
@given(seed=SEEDS)
def test_resigned_arrays(tmp_path_factory, table, seed) -> None:
    rng = random.Random(seed)
    arrays = sorted(n for n in MEMBERS if n.endswith(".npy"))
    members = dict(MEMBERS)
    for member in rng.sample(arrays, rng.choice((1, 1, 2))):
        members[member] = mutate(members[member], rng.randrange(2**32))
    name = write_pair(tmp_path_factory, zip_members(members))
    assert_bounded(load_and_predict, name, table)


@FUZZ
@given(seed=SEEDS)
def test_mutated_card(tmp_path_factory, seed) -> None:
    path = write_case(tmp_path_factory, "m.skops", SKOPS)
    card = dict(CARD, model_file="m.skops")
    path.with_name("m.card.json").write_bytes(mutate(json.dumps(card).encode(), seed))
    assert_bounded(read_card, path)
    assert_bounded(load_terrain_model, path.with_suffix(""))


# ----------------------------------------------------------------------- regressions


def _schema_with(edit: Any) -> bytes:
    schema = copy.deepcopy(SCHEMA)
    edit(schema)
    return zip_members(dict(MEMBERS, **{"schema.json": json.dumps(schema).encode()}))


def _attrs(schema: dict) -> dict:
    return schema["content"]["content"]


def test_regression_corrupt_zip_message_is_short(tmp_path_factory) -> None:
    data = SKOPS[:200] + bytes(30_000) + SKOPS[200:]
    err = assert_bounded(load_terrain_model, write_pair(tmp_path_factory, data))
    assert isinstance(err, ModelError)


def test_regression_zip_bomb(tmp_path_factory) -> None:
    data = zip_members(dict(MEMBERS, **{"big.npy": bytes(4 * 2**20)}))
    with pytest.raises(ModelError, match="zip bomb"):
        load_terrain_model(write_pair(tmp_path_factory, data))


def test_regression_deep_schema(tmp_path_factory) -> None:
    data = zip_members(dict(MEMBERS, **{"schema.json": b"[" * 5000 + b"]" * 5000}))
    with pytest.raises(ModelError, match="nested 5000 deep"):
        load_terrain_model(write_pair(tmp_path_factory, data))


def test_regression_npy_declaring_more_than_it_holds(tmp_path_factory) -> None:
    name = next(n for n in MEMBERS if n.endswith(".npy"))
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False,
                                               "shape": (2**40,)})  # fmt: skip
    data = zip_members(dict(MEMBERS, **{name: buf.getvalue() + bytes(64)}))
    with pytest.raises(ModelError, match="declares 8796093022208 bytes"):
        load_terrain_model(write_pair(tmp_path_factory, data))


def test_regression_bad_classes_fail_the_checks(tmp_path_factory) -> None:
    def edit(schema: dict) -> None:
        _attrs(schema)["mode"]["content"] = '"sideways"'

    with pytest.raises(ModelError, match="malformed model: kind 'logistic' or mode 'sideways'"):
        load_terrain_model(write_pair(tmp_path_factory, _schema_with(edit)))


def test_regression_filter_generator(tmp_path_factory) -> None:
    import skops.io as sio

    model = load_terrain_model("default")
    model.filter_.generator_ = model.filter_.generator_ + 0.5
    path = tmp_path_factory.mktemp("gen") / "m.skops"
    sio.dump(model, path)
    with pytest.raises(ModelError, match="generator_ rows must sum to 0"):
        load_terrain_model(write_pair(tmp_path_factory, path.read_bytes()))


def test_regression_card_without_sha(tmp_path_factory) -> None:
    card = {k: v for k, v in CARD.items() if k != "sha256"}
    name = write_pair(tmp_path_factory, SKOPS, card=card)
    with pytest.raises(ModelError, match="no sha256"):
        load_terrain_model(name)


def test_regression_untrusted_type_still_refused(tmp_path_factory) -> None:
    def edit(schema: dict) -> None:
        _attrs(schema)["defects"]["__module__"] = "os"
        _attrs(schema)["defects"]["__class__"] = "system"

    with pytest.raises(ModelError, match="refusing to load types rough_map does not trust: 'os"):
        load_terrain_model(write_pair(tmp_path_factory, _schema_with(edit)))


def test_regression_many_references_to_one_array(tmp_path_factory) -> None:
    big = max((n for n in MEMBERS if n.endswith(".npy")), key=lambda n: len(MEMBERS[n]))
    node = {"__class__": "ndarray", "__module__": "numpy", "__loader__": "NdArrayNode",
            "type": "numpy", "file": big}  # fmt: skip
    copies = [dict(node, __id__=i) for i in range(4000)]

    def edit(schema: dict) -> None:
        junk = {"__class__": "list", "__module__": "builtins", "__loader__": "ListNode"}
        _attrs(schema)["junk"] = dict(junk, content=copies, __id__=-1)

    with pytest.raises(ModelError, match=r"refers to \d+ bytes of arrays"):
        load_terrain_model(write_pair(tmp_path_factory, _schema_with(edit)))


def _with_trees(kind: str) -> Any:
    """The default model with a small tree ensemble as its base classifier."""
    from sklearn.ensemble import HistGradientBoostingClassifier, RandomForestClassifier

    model = load_terrain_model("default")
    calib = model.classifier_.named_steps["classifier"]
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, calib.n_features_in_))
    y = calib.classes_[np.arange(200) % len(calib.classes_)]
    if kind == "forest":
        base: Any = RandomForestClassifier(n_estimators=3, random_state=0).fit(X, y)
    else:
        base = HistGradientBoostingClassifier(max_iter=3).fit(X, y)
    calib.calibrated_classifiers_[0].estimator = base
    model.kind = kind
    return model, base


@pytest.mark.parametrize("kind", ["forest", "hgb"])
def test_tree_models_load_and_out_of_range_nodes_are_refused(tmp_path_factory, table, kind):
    import skops.io as sio

    model, base = _with_trees(kind)
    path = tmp_path_factory.mktemp("trees") / "m.skops"
    sio.dump(model, path)
    loaded = load_and_predict(write_pair(tmp_path_factory, path.read_bytes()), table)
    assert loaded.kind == kind
    if kind == "forest":  # compiled code follows these indices without bounds checks
        base.estimators_[1].tree_.children_right[0] = 10**6
    else:
        base._predictors[1][0].nodes["left"][0] = 10**6
    sio.dump(model, path)
    with pytest.raises(ModelError, match=r"malformed model: .*child index out of range"):
        load_terrain_model(write_pair(tmp_path_factory, path.read_bytes()))


@pytest.fixture(scope="module")
def tree_members(tmp_path_factory) -> dict[str, dict[str, bytes]]:
    """The members of the forest and boosting variants of the default model."""
    import skops.io as sio

    out = {}
    for kind in ("forest", "hgb"):
        path = tmp_path_factory.mktemp("trees") / f"{kind}.skops"
        sio.dump(_with_trees(kind)[0], path)
        with zipfile.ZipFile(path) as zf:
            out[kind] = {info.filename: zf.read(info) for info in zf.infolist()}
    return out


@FUZZ
@given(seed=SEEDS)
def test_resigned_tree_arrays(tmp_path_factory, table, tree_members, seed) -> None:
    rng = random.Random(seed)
    members = dict(tree_members[rng.choice(("forest", "hgb"))])
    arrays = sorted(n for n in members if n.endswith(".npy"))
    for member in rng.sample(arrays, rng.choice((1, 1, 2))):
        members[member] = mutate(members[member], rng.randrange(2**32))
    name = write_pair(tmp_path_factory, zip_members(members))
    assert_bounded(load_and_predict, name, table)
