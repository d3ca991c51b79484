"""``rough-map train``, ``classify`` and ``evaluate`` on small simulated traverses.

The traverses are written in the minimal traverse form (frames with only t, pose, cloud and
label: no IMU, no images), as an independent data set would be, from short courses over
all five surfaces at the paper's speeds of 0.3, 0.5 and 0.7 m/s.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import accuracy_score, confusion_matrix, f1_score

from rough_map.cli.main import main
from rough_map.config import TraverseSpec
from rough_map.features import read_features, traverse_features, write_features
from rough_map.io.traverse import save_traverse
from rough_map.simulate.course import SensorSpec, sense_cloud
from rough_map.simulate.world import Segment, build_world, drive

ROOT = Path(__file__).resolve().parents[1]
SEGMENT_M = 3.0


def make_traverse(
    out: Path, surfaces: list[str], *, speed: float, seed: int, points_per_cell: float = 4.0
) -> Path:
    """A minimal traverse (t, pose, cloud, label per frame) over ``surfaces``, 3 m each."""
    (out / "clouds").mkdir(parents=True)
    segments = [Segment(s, i * SEGMENT_M, (i + 1) * SEGMENT_M) for i, s in enumerate(surfaces)]
    world = build_world(segments, width=1.4, seed=seed, lead=1.6)
    sensor = SensorSpec(points_per_cell=points_per_cell, half_extent=0.47)
    poses = drive(world, 0.0, segments[-1].end - sensor.ahead - 0.5, speed=speed, seed=seed)
    rng = np.random.default_rng(seed)
    frames = []
    for i, (t, x, y, z, roll, pitch, yaw) in enumerate(poses):
        cloud = sense_cloud(world, np.array([x, y, z, roll, pitch, yaw]), sensor, rng)
        np.save(out / "clouds" / f"{i:06d}.npy", cloud)
        ahead = x + sensor.ahead * math.cos(yaw)  # the class under the patch centre
        label = next((s.surface for s in segments if ahead < s.end), segments[-1].surface)
        frames.append(
            {
                "t": float(t),
                "pose": {"x": float(x), "y": float(y), "yaw": float(yaw)},
                "cloud": f"clouds/{i:06d}.npy",
                "label": label,
            }
        )
    spec = TraverseSpec.model_validate(
        {"schema_version": "1.0", "name": out.name, "crs": "local", "frames": frames}
    )
    return save_traverse(spec, out).parent


ALL = ["concrete", "gravel", "dirt_road", "ploughed_soil", "compact_soil"]


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict[str, Path]:
    """Two training traverses (0.5 and 0.4 m/s) and three unseen ones at 0.3/0.5/0.7 m/s,
    with the features of the unseen ones as tables (so that each is computed once)."""
    root = tmp_path_factory.mktemp("sim")
    paths = {
        "train_a": make_traverse(root / "train_a", ALL, speed=0.5, seed=11),
        "train_b": make_traverse(root / "train_b", ALL[::-1], speed=0.4, seed=12),
        "v03": make_traverse(root / "v03", ["gravel", "concrete", "ploughed_soil"], speed=0.3,
                             seed=21),
        "v05": make_traverse(root / "v05", ["compact_soil", "dirt_road", "gravel"], speed=0.5,
                             seed=22),
        "v07": make_traverse(root / "v07", ["dirt_road", "ploughed_soil", "concrete",
                                            "compact_soil"], speed=0.7, seed=23),
    }  # fmt: skip
    for key in ("v03", "v05", "v07"):
        paths[f"{key}_csv"] = write_features(traverse_features(paths[key]), root / f"{key}.csv")
    return paths


def run(capsys, *argv: object) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def trained(sim, tmp_path_factory) -> Path:
    """``rough-map train`` on the two training traverse folders."""
    out = tmp_path_factory.mktemp("models") / "sim"
    code = main(["-q", "train", str(sim["train_a"]), str(sim["train_b"]), "--out", str(out),
                 "--cv", "2"])  # fmt: skip
    assert code == 0
    return out


def read_labels(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([r[k] for r in rows], dtype=object) for k in rows[0]}


def test_train_parser_knows_the_classifiers() -> None:
    from rough_map import classify
    from rough_map.cli import train

    assert train.CLASSIFIERS == classify.CLASSIFIERS


def test_train_writes_model_and_card(trained) -> None:
    card = json.loads(trained.with_name("sim.card.json").read_text())
    assert card["classes"] == sorted(ALL)
    assert card["cross_validation"]["scheme"].startswith("GroupKFold")
    assert card["training_data"]["traverses"][0]["name"] == "train_a"
    assert {"level", "slope", "curvature"} <= set(card["features"]["derived"])
    # the novelty score is fitted with every model, its threshold from the held-out folds
    assert card["novelty"]["quantile"] == 0.99 and card["novelty"]["threshold"] > 0
    # The command as typed, -q before the command name included.
    assert card["command"].startswith("rough-map -q train ") and card["command"].endswith("--cv 2")


def test_evaluate_json_and_plot(sim, trained, tmp_path, capsys) -> None:
    png = tmp_path / "cm.png"
    code, out, err = run(capsys, "evaluate", sim["v03_csv"], sim["v05_csv"], sim["v07_csv"],
                         "--model", trained, "--json", "--plot", png)  # fmt: skip
    assert code == 0, err
    result = json.loads(out)
    for part in ("raw", "filtered"):
        for key in ("classes", "confusion_matrix", "accuracy", "macro_f1"):
            assert key in result[part]
    # Two 15 m training traverses at 4 points per cell: better than chance (0.2), no more.
    # With so little data the filter can lock onto a stretch the classifier gets wrong;
    # that filtering helps a properly trained model is checked on the shipped model below.
    assert result["raw"]["macro_f1"] > 0.4
    assert result["filtered"]["macro_f1"] > 0.4
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "scored" in err


def test_evaluate_matches_sklearn_on_classify_output(sim, trained, tmp_path, capsys) -> None:
    truth, raw, filtered = [], [], []
    for key in ("v03", "v05", "v07"):
        out_csv = tmp_path / f"{key}.labels.csv"
        code, _, err = run(capsys, "classify", sim[f"{key}_csv"], "--model", trained,
                           "--out", out_csv)  # fmt: skip
        assert code == 0, err
        rows = read_labels(out_csv)
        assert set(rows) >= {"raw_class", "raw_p", "filtered_class", "filtered_p"}
        valid = rows["valid"] == "true"
        novelty = rows["novelty"][valid].astype(float)
        assert np.all(novelty >= 0)
        assert (rows["novel"][valid] == np.where(novelty > 1, "true", "false")).all()
        assert (rows["novelty"][~valid] == "").all()
        scored = valid & (rows["label"] != "")
        truth.append(rows["label"][scored])
        raw.append(rows["raw_class"][scored])
        filtered.append(rows["filtered_class"][scored])
        proba = rows["filtered_p"].astype(float)
        assert np.all((proba > 0) & (proba <= 1))
    y, r, f = (np.concatenate(v).astype(str) for v in (truth, raw, filtered))
    code, out, _ = run(capsys, "evaluate", sim["v03_csv"], sim["v05_csv"], sim["v07_csv"],
                       "--model", trained, "--json")  # fmt: skip
    result = json.loads(out)
    # raw and filtered: one class list (all true or predicted classes, sorted); the
    # macro-F1 over the classes present in the truth
    classes = sorted(set(y) | set(r) | set(f))
    truth_classes = sorted(set(y))
    assert result["scored_classes"] == truth_classes
    for part, pred in (("raw", r), ("filtered", f)):
        got = result[part]
        assert got["classes"] == classes and got["scored_classes"] == truth_classes
        assert got["accuracy"] == pytest.approx(accuracy_score(y, pred))
        assert got["macro_f1"] == pytest.approx(
            f1_score(y, pred, labels=truth_classes, average="macro")
        )
        assert got["confusion_matrix"] == confusion_matrix(y, pred, labels=got["classes"]).tolist()
        per_class = f1_score(y, pred, labels=got["classes"], average=None)
        assert list(got["f1"].values()) == pytest.approx(list(per_class))


def test_evaluate_a_traverse_folder(sim, trained, capsys) -> None:
    """From the clouds of a minimal traverse, as in ``rough-map evaluate TRAVERSE``."""
    code, out, err = run(capsys, "evaluate", sim["v07"], "--model", trained)
    assert code == 0, err
    assert "confusion matrix (row-normalised)" in out and "macro-F1" in out
    # the text says which classes the macro-F1 averages: v07's four surfaces
    truth = ", ".join(sorted(["dirt_road", "ploughed_soil", "concrete", "compact_soil"]))
    assert f"over the 4 true classes ({truth})" in out


def test_macro_f1_averages_the_true_classes_only() -> None:
    """A hand-computed case: 'c' is predicted once but never true.

    a: TP 2, FP 1 (a b taken for a), FN 1 (an a taken for c): P = R = F1 = 2/3.
    b: TP 1, FP 0, FN 1: P = 1, R = 1/2, F1 = 2/3.  c: F1 0, not averaged.
    Macro-F1 over the true classes a, b: 2/3 (over a, b, c it would be 4/9).
    """
    from rough_map.evaluation.metrics import scores

    s = scores(["a", "a", "a", "b", "b"], ["a", "a", "c", "b", "a"])
    assert s["scored_classes"] == ["a", "b"] and s["classes"] == ["a", "b", "c"]
    assert s["f1"] == pytest.approx({"a": 2 / 3, "b": 2 / 3, "c": 0.0})
    assert s["macro_f1"] == pytest.approx(2 / 3)
    assert s["accuracy"] == pytest.approx(3 / 5)
    # a given class list orders the matrix (raw and filtered share one); it must hold them all
    s = scores(["a", "b"], ["b", "b"], classes=["b", "a", "c"])
    assert s["classes"] == ["b", "a", "c"] and s["confusion_matrix"][1] == [1, 0, 0]
    from rough_map import errors

    with pytest.raises(errors.InputError, match=r"lack the scored classes \['c'\]"):
        scores(["a", "b"], ["c", "b"], classes=["a", "b"])


def test_raw_and_filtered_confusion_matrices_share_their_classes(sim) -> None:
    """The shipped model on v05: whatever raw and filtered predict, one class list."""
    from rough_map.classify import load_terrain_model
    from rough_map.evaluation import evaluate_model

    model = load_terrain_model(ROOT / "models" / "default")
    table = read_features(sim["v05_csv"])
    result = evaluate_model(model, [table])
    pred = model.predict(table)
    ok = pred.valid & (table.columns["label"] != "")
    expect = sorted(
        set(table.columns["label"][ok]) | set(pred.raw_class[ok]) | set(pred.filtered_class[ok])
    )
    assert result["raw"]["classes"] == result["filtered"]["classes"] == expect
    assert result["scored_classes"] == sorted(set(table.columns["label"][ok]))
    n = len(expect)
    for part in ("raw", "filtered"):
        assert np.asarray(result[part]["confusion_matrix"]).shape == (n, n)


def test_unlabelled_and_invalid_frames_are_counted(sim, trained, tmp_path, capsys) -> None:
    table = read_features(sim["v05_csv"])
    label = np.array(table.columns["label"], dtype=object)
    label[:3] = ""
    valid = np.array(table.columns["valid"], dtype=bool)
    valid[5:9] = False
    log_psd = np.array(table.log_psd)
    log_psd[5:9] = np.nan
    table = table.replace(label=label, valid=valid, log_psd=log_psd)
    path = write_features(table, tmp_path / "holes.csv")
    code, out, _ = run(capsys, "evaluate", path, "--model", trained, "--json")
    assert code == 0
    frames = json.loads(out)["frames"]
    assert frames["unlabelled"] == 3 and frames["invalid"] == 4
    assert frames["scored"] == len(table) - 7
    labels = tmp_path / "holes.labels.csv"
    assert run(capsys, "classify", path, "--model", trained, "--out", labels)[0] == 0
    rows = read_labels(labels)
    assert list(rows["raw_class"][5:9]) == [""] * 4  # no raw class without a valid patch
    assert list(rows["filtered_class"][5:9]) == [""] * 4  # nor a filtered one (issue 29)
    assert all(rows["filtered_class"][9:] != "")


def test_train_refuses_traverses_without_labels(sim, tmp_path, capsys) -> None:
    spec = json.loads((sim["train_a"] / "traverse.json").read_text())
    for frame in spec["frames"]:
        frame.pop("label", None)
    out = tmp_path / "unlabelled"
    out.mkdir()
    (out / "clouds").symlink_to(sim["train_a"] / "clouds")
    (out / "traverse.json").write_text(json.dumps({**spec, "name": "unlabelled"}))
    code, _, err = run(capsys, "train", out, "--out", tmp_path / "m")
    assert code == 2
    assert "no labelled frames" in err and "unlabelled" in err


def test_evaluate_refuses_unknown_classes(sim, trained, tmp_path, capsys) -> None:
    table = read_features(sim["v05_csv"])
    label = np.array(table.columns["label"], dtype=object)
    label[:4] = "sand"
    path = write_features(table.replace(label=label), tmp_path / "sand.csv")
    code, _, err = run(capsys, "evaluate", path, "--model", trained)
    assert code == 2
    assert "'sand'" in err and "does not know" in err


def test_evaluate_refuses_a_model_from_elsewhere(sim, tmp_path, capsys) -> None:
    fake = tmp_path / "fake.skops"
    fake.write_bytes(b"PK\x03\x04 definitely not a model")
    code, _, err = run(capsys, "evaluate", sim["v05_csv"], "--model", fake)
    assert code == 2 and "no model card" in err
    card = json.loads(Path(str(ROOT / "models" / "default.card.json")).read_text())
    from rough_map.classify import sha256_file

    card["sha256"] = sha256_file(fake)
    tmp_path.joinpath("fake.card.json").write_text(json.dumps(card))
    code, _, err = run(capsys, "classify", sim["v05_csv"], "--model", fake,
                       "--out", tmp_path / "x.csv")  # fmt: skip
    assert code == 2 and "not a skops model file" in err


def test_default_model_generalises_to_unseen_traverses(sim) -> None:
    """The shipped model on other seeds, the speeds 0.3/0.5/0.7 m/s and a sparser sensor."""
    from rough_map.classify import load_terrain_model
    from rough_map.evaluation import evaluate_model

    model = load_terrain_model(ROOT / "models" / "default")
    tables = [read_features(sim[f"{k}_csv"]) for k in ("v03", "v05", "v07")]
    result = evaluate_model(model, tables)
    assert result["raw"]["macro_f1"] >= 0.7
    assert result["filtered"]["macro_f1"] >= result["raw"]["macro_f1"]


def test_tables_need_their_metadata_file(sim, trained, tmp_path, capsys) -> None:
    """A features CSV copied without its .csv.json: one line naming the missing file."""
    import shutil

    lone = Path(shutil.copy(sim["v05_csv"], tmp_path / "v05.csv"))
    for argv in (
        ("train", lone, "--out", tmp_path / "m"),
        ("classify", lone, "--model", trained, "--out", tmp_path / "l.csv"),
        ("evaluate", lone, "--model", trained),
    ):
        code, out, err = run(capsys, *argv)
        assert code == 2 and out == ""
        assert err.count("\n") == 1, err
        assert f"{lone}: its metadata file v05.csv.json is missing" in err
    shutil.copy(sim["v05_csv"].with_name("v05.csv.json"), tmp_path / "v05.csv.json")
    code, out, err = run(capsys, "classify", lone, "--model", trained, "--out",
                         tmp_path / "l.csv", "-q")  # fmt: skip
    assert code == 0 and err == ""
    assert read_labels(tmp_path / "l.csv")["frame"].size == len(read_features(lone))


def test_train_does_not_replace_a_model_without_force(sim, trained, capsys) -> None:
    """One --out rule: a trained model is replaced only with --force, and the refusal comes
    before any feature is computed (issue 30)."""
    model_file = trained.with_suffix(".skops")
    before = model_file.read_bytes()
    code = main(["train", str(sim["train_a"]), str(sim["train_b"]), "--out", str(trained)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1
    assert "exists: train does not replace a model without --force" in err
    assert model_file.read_bytes() == before
    code = main(["-q", "train", str(sim["train_a"]), str(sim["train_b"]), "--out", str(trained),
                 "--cv", "2", "--force"])  # fmt: skip
    assert code == 0 and model_file.exists()


def test_user_models_live_in_the_user_models_folder(sim, trained, capsys, tmp_path) -> None:
    """A bare --out name goes to $ROUGH_MAP_MODELS (the tests' own folder), and --model takes
    it back by name; a model of one's own is refused in the package's models/ (issue 30)."""
    import shutil

    from rough_map.cli.train import model_target
    from rough_map.resources import model_base, user_models_dir

    folder = user_models_dir()
    assert "user_models" in str(folder)  # tests/conftest.py keeps it out of the home folder
    assert model_target(Path("mine")) == folder / "mine" and folder.is_dir()
    assert model_target(tmp_path / "m") == tmp_path / "m"
    for suffix in (".skops", ".card.json"):
        shutil.copy(trained.with_name(trained.name + suffix), folder / f"mine{suffix}")
    code, _, err = run(capsys, "classify", sim["v05"], "--model", "mine", "--out",
                         tmp_path / "l.csv", "-q")  # fmt: skip
    assert code == 0 and err == "" and (tmp_path / "l.csv").exists()
    package = model_base().parent / "mine"
    code, _, err = run(capsys, "train", sim["train_a"], "--out", package)
    assert code == 2 and len(err.splitlines()) == 1
    assert "models/ holds only the shipped models" in err and "--out mine" in err
    assert not package.with_suffix(".skops").exists()
    code, _, err = run(capsys, "classify", sim["v05"], "--model", "nobody", "--out",
                       tmp_path / "x.csv")  # fmt: skip
    assert code != 0 and str(folder) in err
