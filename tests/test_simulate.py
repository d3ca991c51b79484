"""The simulator and the features pipeline along a traverse (issue: traverses in)."""

import json
import math

import numpy as np
import pytest

from rough_map.cli.main import main
from rough_map.io.traverse import load_traverse
from rough_map.pipeline import read_features, traverse_features, write_features
from rough_map.simulate.course import SensorSpec, load_world, simulate
from rough_map.simulate.world import build_world, course_layout, drive

SPARSE = SensorSpec(points_per_cell=8.0)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "mixed"
    simulate(out, "mixed", length=24.0, seed=11, images=False, sensor=SPARSE)
    return out


@pytest.fixture(scope="module")
def mixed_features(mixed):
    return traverse_features(mixed)


def test_traverse_validates_and_holds_the_truth(mixed):
    trav = load_traverse(mixed)
    trav.validate_files()
    assert len(trav) > 50
    assert np.all(np.diff(trav.times()) > 0)
    assert {f.label for f in trav.frames} == {"concrete", "dirt_road", "gravel"}
    world = load_world(mixed / trav.spec.height_field)
    assert world.heights.shape[1] * world.spacing > 24.0
    assert world.class_names[int(world.classes[0, 0])] == "concrete"
    meta = trav.spec.metadata
    assert meta["defects"][0]["kind"] == "manhole"
    cloud = trav.load_cloud(0)
    assert cloud.shape[1] == 3 and len(cloud) > 50_000
    # the rover rolls and pitches with the ground under its wheels
    poses = trav.poses()
    assert np.ptp(poses[:, 4]) > 0 or np.ptp(poses[:, 5]) > 0


def test_features_separate_the_surfaces_as_in_the_paper(mixed_features):
    f = mixed_features
    assert f.valid.all()
    # Averages along each stretch, as the paper reports them (geometric mean of R).
    med = {lab: np.mean(np.log(f["R"][f["label"] == lab])) for lab in set(f["label"])}
    wm = {lab: np.mean(f["w"][f["label"] == lab]) for lab in set(f["label"])}
    assert med["concrete"] < med["dirt_road"] < med["gravel"]
    assert math.exp(med["concrete"]) < 64e-6  # near ISO C, below the D centre
    assert 16e-6 < math.exp(med["dirt_road"]) < 256e-6  # near D
    assert math.exp(med["gravel"]) > 64e-6  # near E
    assert wm["concrete"] == pytest.approx(-2.0, abs=0.15)
    assert wm["gravel"] == pytest.approx(-2.4, abs=0.15)
    assert wm["concrete"] > wm["dirt_road"] > wm["gravel"]


def test_the_manhole_is_a_spike(mixed, mixed_features):
    f = mixed_features
    trav = load_traverse(mixed)
    x_manhole = trav.spec.metadata["defects"][0]["x"]
    concrete = f["label"] == "concrete"
    near = concrete & (np.abs(f["x"] + 1.0 - x_manhole) < 0.6)  # patch centre 1 m ahead
    far = concrete & (np.abs(f["x"] + 1.0 - x_manhole) > 1.5)
    assert near.any() and far.any()
    assert f["R"][near].max() > 5 * np.median(f["R"][far])


def test_default_model_maps_the_mixed_course(mixed, mixed_features):
    """Issue 5: >= 0.9 class accuracy over the near-field map cells on simulated truth,
    with the manhole flagged as an isolated defect rather than mapped as rough ground."""
    from rough_map.cli.map import default_model
    from rough_map.workflow import analyse, map_accuracy

    trav = load_traverse(mixed)
    result = analyse(trav, default_model(), features=mixed_features, near_far=False)
    world = load_world(mixed / trav.spec.height_field)
    assert map_accuracy(result.map, world) >= 0.9
    f, pred = mixed_features, result.prediction
    x_manhole = trav.spec.metadata["defects"][0]["x"]
    on_it = np.abs(f["x"] + 1.0 - x_manhole) < 0.3  # patch centre over the cover
    assert pred.defect[on_it].all() and pred.defect.sum() <= 12
    assert np.all(pred.filtered_class[on_it] == "concrete")


def test_map_and_report_commands_on_the_mixed_course(mixed, tmp_path, capsys):
    """`rough-map map` (GeoTIFFs, tables, accuracy against the truth) and `rough-map report`
    (the paper's figures and index.html) on a simulated traverse, end to end."""
    import rasterio

    code = main(["-q", "map", str(mixed), "--out", str(tmp_path / "map"), "--no-png", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["near_class_accuracy"] >= 0.9
    with rasterio.open(summary["outputs"]["geotiff_class"]) as ds:
        assert ds.descriptions == ("class",) and ds.colormap(1) and ds.overviews(1)
    with open(summary["outputs"]["labels"]) as fh:
        header = fh.readline().strip().split(",")
    assert {"raw_class", "filtered_class", "level", "defect"} <= set(header)
    assert main(["-q", "report", str(mixed), "--out", str(tmp_path / "report")]) == 0
    report = tmp_path / "report"
    html = (report / "index.html").read_text()
    for fig in ("fig_path.png", "fig_psd_profile.png", "fig_classes.png", "fig_map_class.png"):
        assert (report / fig).stat().st_size > 10_000 and fig in html


def test_map_of_a_traverse_without_a_valid_patch_is_all_nodata(tmp_path, capsys):
    """Every cloud too sparse for a patch: exit 0, an all-nodata map, a warning line."""
    import rasterio

    (tmp_path / "clouds").mkdir()
    frames = []
    for i in range(4):
        np.save(tmp_path / "clouds" / f"{i}.npy", np.zeros((30, 3), dtype=np.float32))
        frames.append({"t": 0.5 * i, "pose": {"x": 0.25 * i, "y": 0.0, "yaw": 0.0},
                       "cloud": f"clouds/{i}.npy"})  # fmt: skip
    (tmp_path / "traverse.json").write_text(
        json.dumps({"schema_version": "1.0", "name": "sparse", "frames": frames})
    )
    assert main(["map", str(tmp_path), "--out", str(tmp_path / "map"), "--no-png"]) == 0
    err = capsys.readouterr().err
    assert "EmptyMapWarning: none of the 4 frames has a valid patch" in err
    assert "Traceback" not in err and "warnings.warn" not in err
    with rasterio.open(tmp_path / "map" / "map.tif") as ds:
        assert np.isnan(ds.read(1)).all()


def test_reverse_course_gives_the_surfaces_in_reverse(tmp_path):
    segs, defects = course_layout("mixed-reverse", 30.0)
    assert [s.surface for s in segs] == ["gravel", "dirt_road", "concrete"]
    assert segs[-1].start <= defects[0].x <= segs[-1].end
    out = tmp_path / "rev"
    simulate(out, "mixed-reverse", length=6.0, seed=3, images=False, sensor=SPARSE)
    labels = [f.label for f in load_traverse(out).frames]
    firsts = list(dict.fromkeys(labels))
    assert firsts == ["gravel", "dirt_road", "concrete"]


def test_feature_table_round_trip(tmp_path, mixed_features):
    path = write_features(mixed_features, tmp_path / "f.csv")
    back = read_features(path)
    assert back.name == mixed_features.name
    np.testing.assert_allclose(back.omega, mixed_features.omega, rtol=1e-9)
    for c in ("t", "x", "R", "w", "sigma_R"):
        np.testing.assert_allclose(back[c], mixed_features[c], rtol=1e-8, equal_nan=True)
    assert list(back["label"]) == list(mixed_features["label"])
    np.testing.assert_array_equal(back.valid, mixed_features.valid)
    np.testing.assert_allclose(back.log_psd, mixed_features.log_psd, rtol=1e-8)


def test_parquet_round_trip(tmp_path, mixed_features):
    pytest.importorskip("pyarrow")
    back = read_features(write_features(mixed_features, tmp_path / "f.parquet"))
    np.testing.assert_allclose(back["R"], mixed_features["R"], rtol=1e-12)


def test_bad_frames_are_invalid_not_fatal(tmp_path, mixed):
    trav = load_traverse(mixed)
    doc = trav.spec.model_dump(mode="json", exclude_none=True)
    doc["frames"] = doc["frames"][:3]
    np.save(tmp_path / "far.npy", np.random.default_rng(0).uniform(5, 6, (5000, 3)))
    np.save(tmp_path / "nan.npy", np.full((100, 3), np.nan))
    doc["frames"][1]["cloud"] = "far.npy"
    doc["frames"][2]["cloud"] = "nan.npy"
    (tmp_path / "clouds").symlink_to(mixed / "clouds")
    (tmp_path / "world_truth.npz").symlink_to(mixed / "world_truth.npz")
    (tmp_path / "traverse.json").write_text(json.dumps(doc))
    f = traverse_features(tmp_path)
    assert list(f.valid) == [True, False, False]
    assert "too few points" in f["reason"][1]
    assert f["reason"][2]


def test_cli_features_on_a_traverse(tmp_path, mixed, capsys):
    out = tmp_path / "feat.csv"
    assert main(["features", str(mixed), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["frames"] == len(load_traverse(mixed))
    assert set(doc["summary"]) == {"concrete", "dirt_road", "gravel"}
    assert read_features(out).valid.all()
    assert main(["features", str(mixed)]) == 2
    assert "--out" in capsys.readouterr().err


def test_world_and_drive_are_seeded():
    segs, defects = course_layout("compact", 6.0)
    a = build_world(segs, defects, seed=4, width=1.5)
    b = build_world(segs, defects, seed=4, width=1.5)
    np.testing.assert_array_equal(a.heights, b.heights)
    pa = drive(a, 0.0, 4.0, seed=1)
    np.testing.assert_array_equal(pa, drive(b, 0.0, 4.0, seed=1))
    assert pa[1, 0] == pytest.approx(0.5)  # 2 Hz
    assert pa[1, 1] == pytest.approx(0.25)  # 0.5 m/s


def test_random_course_has_all_classes():
    segs, _ = course_layout("random", 200.0, seed=1)
    assert {s.surface for s in segs} == {
        "concrete",
        "dirt_road",
        "gravel",
        "compact_soil",
        "ploughed_soil",
    }
    assert segs[-1].end == pytest.approx(200.0)


def test_bad_simulator_input(tmp_path, mixed):
    from rough_map.errors import InputError

    with pytest.raises(InputError, match="unknown course"):
        simulate(tmp_path / "x", "moon")
    with pytest.raises(InputError, match="already holds a traverse"):
        simulate(mixed, "mixed", length=4.0, images=False)
    with pytest.raises(InputError, match="length"):
        course_layout("mixed", 0.5)
