"""The simulator and the features pipeline along a traverse (issue: traverses in)."""

import json
import math

import numpy as np
import pytest

from rough_map.classify import load_terrain_model
from rough_map.cli.main import main
from rough_map.features import read_features, traverse_features, write_features
from rough_map.io.traverse import load_traverse
from rough_map.io.truth import load_world
from rough_map.simulate.course import SensorSpec, sense_cloud, simulate
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
    from rough_map.evaluation.truth import map_accuracy
    from rough_map.resources import model_base as default_model
    from rough_map.workflow import analyse

    trav = load_traverse(mixed)
    result = analyse(trav, load_terrain_model(default_model()), near_far=False)
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


def test_map_of_a_traverse_without_a_valid_patch_fails_with_the_reason(tmp_path, capsys):
    """Every cloud too sparse for a patch: exit 2, one line with the frames' reason, and
    nothing written (issue 30: an all-nodata map exited 0 before)."""
    (tmp_path / "clouds").mkdir()
    frames = []
    for i in range(4):
        np.save(tmp_path / "clouds" / f"{i}.npy", np.zeros((30, 3), dtype=np.float32))
        frames.append({"t": 0.5 * i, "pose": {"x": 0.25 * i, "y": 0.0, "yaw": 0.0},
                       "cloud": f"clouds/{i}.npy"})  # fmt: skip
    (tmp_path / "traverse.json").write_text(
        json.dumps({"schema_version": "1.0", "name": "sparse", "frames": frames})
    )
    assert main(["map", str(tmp_path), "--out", str(tmp_path / "map"), "--no-png"]) == 2
    err = capsys.readouterr().err
    line = err.strip().splitlines()[-1]
    assert line.startswith("rough-map map: error: sparse: none of its 4 frames has a valid patch")
    assert "4 like frame 0: too few points" in line and "Traceback" not in err
    assert not (tmp_path / "map").exists()


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
    f = traverse_features(load_traverse(tmp_path, allow_outside=[mixed]))  # clouds/ links there
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


def test_simulate_replaces_its_outputs_as_a_set(tmp_path, capsys):
    """One --out rule: simulating into an existing folder replaces the traverse as a set
    and keeps the user's files."""
    from rough_map.cli.main import main
    from rough_map.io.traverse import load_traverse

    out = tmp_path / "sim"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    base = ["-q", "simulate", "--out", str(out), "--length", "3", "--no-images"]
    assert main([*base, "--course", "mixed", "--seed", "1"]) == 0
    assert main([*base, "--course", "compact", "--seed", "2"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == str(out / "traverse.json")
    trav = load_traverse(out)
    assert trav.name == "sim-compact-seed2" and (out / "notes.txt").read_text() == "mine"
    assert {f.label for f in trav.frames} == {"compact_soil"}
    trav.validate_files()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]


def test_bad_simulator_input(tmp_path, mixed):
    from rough_map.errors import InputError

    with pytest.raises(InputError, match="unknown course"):
        simulate(tmp_path / "x", "moon")
    with pytest.raises(InputError, match="already holds a traverse"):
        simulate(mixed, "mixed", length=4.0, images=False)
    with pytest.raises(InputError, match="length"):
        course_layout("mixed", 0.5)


# -- what simulate writes: cropped clouds, a compact truth, optional .npz clouds -------------


def test_clouds_keep_the_square_around_the_patch_and_the_same_points():
    """The crop comes after every random draw: the points kept are those the whole
    footprint had, bit for bit, the random stream goes on as before, and the patch sees
    the same points."""
    from rough_map.features import frame_features
    from rough_map.patch import PatchSpec

    segs, defects = course_layout("compact", 4.0)
    world = build_world(segs, defects, seed=2, width=1.5)
    pose = drive(world, 0.0, 2.0, seed=1)[2, 1:]
    rng_full, rng_crop = np.random.default_rng(7), np.random.default_rng(7)
    full = sense_cloud(world, pose, SensorSpec(cloud_half_extent=None), rng_full)
    crop = sense_cloud(world, pose, SensorSpec(), rng_crop)
    assert rng_full.random() == rng_crop.random()
    keep = (np.abs(full[:, 0] - 1.0) <= 0.5) & (np.abs(full[:, 1]) <= 0.5)
    np.testing.assert_array_equal(crop, full[keep])
    assert crop.dtype == np.float32 and len(crop) < 0.86 * len(full)
    assert np.abs(full[:, 1]).max() > 0.54  # the sensor sees +-0.55 m
    a, _, _ = frame_features(full, PatchSpec(), roll=pose[3], pitch=pose[4])
    b, _, _ = frame_features(crop, PatchSpec(), roll=pose[3], pitch=pose[4])
    assert a["valid"] and a["n_points"] == b["n_points"]
    assert b["R"] == pytest.approx(a["R"], rel=0.02)


def test_compressed_traverse_reads_as_the_float_one(tmp_path):
    """--compress: .npz clouds of 16-bit columns, 15 um steps; every reader takes them and
    the features hardly move (a new draw of the sensor moves ln R by about 0.09)."""
    kw = dict(length=3.0, seed=5, images=False, sensor=SPARSE, world_spacing=0.004)
    plain = simulate(tmp_path / "plain", "compact", **kw).parent
    packed = simulate(tmp_path / "packed", "compact", compress=True, **kw).parent
    a, b = load_traverse(plain), load_traverse(packed)
    b.validate_files()
    assert all(f.cloud.endswith(".npz") for f in b.frames)
    meta = b.spec.metadata
    assert meta["cloud_storage"]["format"] == "npz"
    assert meta["cloud_extent"] == a.spec.metadata["cloud_extent"]
    assert meta["cloud_extent"]["x_m"] == [0.5, 1.5] and meta["cloud_extent"]["y_m"] == [-0.5, 0.5]
    for i in (0, len(a) - 1):
        ref = a.load_cloud(i)
        ref = ref[np.argsort(ref[:, 0], kind="stable")]  # stored sorted along x
        got = b.load_cloud(i)
        assert got.shape == ref.shape
        assert np.abs(got - ref).max(axis=0)[:2] == pytest.approx([0.5 / 65535] * 2, rel=0.01)
        assert np.abs(got - ref)[:, 2].max() < 1e-6
        assert b.cloud_path(i).stat().st_size < 0.45 * a.cloud_path(i).stat().st_size
    fa, fb = traverse_features(a), traverse_features(b)
    assert fb.valid.all()
    d = np.abs(np.log(fb["R"]) - np.log(fa["R"]))
    assert np.median(d) < 0.01 and d.max() < 0.05


def test_compressed_cloud_round_trip(tmp_path):
    from rough_map.errors import InputError
    from rough_map.io.pointcloud import read_cloud
    from rough_map.simulate.course import save_cloud_npz

    rng = np.random.default_rng(3)
    pts = rng.uniform([0.5, -0.5, -0.05], [1.5, 0.5, 0.05], (1000, 3))
    got = read_cloud(save_cloud_npz(tmp_path / "c.npz", pts))
    ref = pts[np.argsort(pts[:, 0])]
    step = np.ptp(pts, axis=0) / 65535
    assert np.all(np.abs(got - ref) <= step / 2 + 1e-12)
    with np.load(tmp_path / "c.npz") as d:
        assert d["x"].dtype == np.uint16 and float(d["x_scale"]) == pytest.approx(step[0])
    # a column wider than 65535 steps of 20 um is kept as float32
    pts[:, 0] *= 50
    got = read_cloud(save_cloud_npz(tmp_path / "wide.npz", pts))
    np.testing.assert_array_equal(np.sort(got[:, 0]), np.sort(pts[:, 0].astype(np.float32)))
    with pytest.raises(InputError, match=r"\(N, 3\) array .* got shape \(4, 2\)"):
        save_cloud_npz(tmp_path / "bad.npz", np.zeros((4, 2)))


def test_npz_cloud_reader(tmp_path):
    from rough_map.errors import FileFormatError
    from rough_map.io.pointcloud import read_cloud

    pts = np.arange(15.0).reshape(5, 3)
    np.savez(tmp_path / "points.npz", points=pts)
    np.testing.assert_array_equal(read_cloud(tmp_path / "points.npz"), pts)
    np.savez(tmp_path / "cols.npz", x=pts[:, 0], y=pts[:, 1].astype(np.float32), z=pts[:, 2])
    np.testing.assert_array_equal(read_cloud(tmp_path / "cols.npz"), pts)
    cases = {
        r"\[z\]: an \.npz cloud holds 'points' \(N x 3\) or columns x, y, z; this one "
        r"holds \['x', 'y'\]": dict(x=pts[:, 0], y=pts[:, 1]),
        r"\[shape\]: columns of different lengths: x 5, y 5, z 4": dict(
            x=pts[:, 0], y=pts[:, 1], z=pts[:4, 2]
        ),
        r"\[x\]: expected a 1-D numeric column; got shape \(5, 1\)": dict(
            x=pts[:, :1], y=pts[:, 1], z=pts[:, 2]
        ),
        r"\[y_scale\]: expected a number in m; got shape \(2,\)": dict(
            x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], y_scale=np.ones(2)
        ),
    }
    for i, (match, arrays) in enumerate(cases.items()):
        np.savez(tmp_path / f"bad{i}.npz", **arrays)
        with pytest.raises(FileFormatError, match=rf"bad{i}\.npz {match}"):
            read_cloud(tmp_path / f"bad{i}.npz")
    np.save(tmp_path / "array.npy", pts)
    (tmp_path / "array.npz").write_bytes((tmp_path / "array.npy").read_bytes())
    with pytest.raises(FileFormatError, match=r"array\.npz: this is an \.npy array, not an \.npz"):
        read_cloud(tmp_path / "array.npz")
    data = (tmp_path / "cols.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError, match=r"cut\.npz: not a readable \.npz archive \(trunc"):
        read_cloud(tmp_path / "cut.npz")


def test_world_truth_is_compact_and_round_trips(tmp_path):
    """Heights as int16 steps of relief / 65534 (at most 10 um), the class map deflated;
    a wider relief stays float32, and files of the older float32 layout still load. They
    read back as float32 heights (within half a step and float32's rounding) and an int8
    class map."""
    from rough_map.io.truth import HEIGHT_STEP, save_world
    from rough_map.types import HeightField

    rng = np.random.default_rng(0)
    heights = rng.uniform(-0.1, 0.2, (300, 400))
    classes = (np.arange(400)[None, :] // 100 + np.zeros((300, 1), int)) % 5
    names = ("a", "b", "c", "d", "e")
    world = HeightField(heights, 0.002, (-3.0, -0.3), classes, names)
    save_world(world, tmp_path / "w.npz")
    back = load_world(tmp_path / "w.npz")
    step = np.ptp(heights) / 65534
    assert back.heights.dtype == np.float32 and back.classes.dtype == np.int8
    assert np.abs(back.heights - heights).max() <= step / 2 + np.spacing(np.float32(0.2))
    np.testing.assert_array_equal(back.classes, classes)
    assert (back.spacing, back.origin, back.class_names) == (0.002, (-3.0, -0.3), names)
    with np.load(tmp_path / "w.npz") as d:
        assert d["heights"].dtype == np.int16
    size = (tmp_path / "w.npz").stat().st_size
    assert size < 2 * heights.size + 10_000  # the class map packs to almost nothing
    wide = HeightField(heights * 10, 0.002, (0.0, 0.0), classes, names)  # 3 m of relief
    assert np.ptp(wide.heights) / 65534 > HEIGHT_STEP
    save_world(wide, tmp_path / "wide.npz")
    np.testing.assert_array_equal(
        load_world(tmp_path / "wide.npz").heights, wide.heights.astype(np.float32)
    )
    np.savez(  # the layout written before heights were quantised
        tmp_path / "old.npz",
        heights=heights.astype(np.float32),
        classes=classes.astype(np.int8),
        spacing=0.002,
        origin=np.array([-3.0, -0.3]),
        class_names=np.asarray(names),
    )
    old = load_world(tmp_path / "old.npz")
    np.testing.assert_array_equal(old.heights, heights.astype(np.float32))
    np.testing.assert_array_equal(old.classes, classes)


def test_cli_simulate_compress_and_cloud_extent(tmp_path, capsys):
    out = tmp_path / "sim"
    args = ["-q", "simulate", "--out", str(out), "--course", "compact", "--length", "2.5"]
    args += ["--no-images", "--points-per-cell", "4", "--compress", "--cloud-extent", "0.55"]
    assert main(args) == 0
    trav = load_traverse(capsys.readouterr().out.strip())
    extent = trav.spec.metadata["cloud_extent"]
    assert extent["cropped"] is False and extent["x_m"] == [0.45, 1.55]
    assert trav.frames[0].cloud.endswith(".npz")
    assert np.abs(trav.load_cloud(0)[:, 1]).max() > 0.54
    assert main(["simulate", "--out", str(tmp_path / "x"), "--cloud-extent", "0"]) == 2
    assert "--cloud-extent" in capsys.readouterr().err
