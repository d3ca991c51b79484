"""``rough-map score``: maps scored against a surveyed class raster (issue 13, part 3).

The simulator's truth goes through the same path as a user's: ``rough-map simulate`` writes
``world_truth.tif``, and scoring the written map against it gives the accuracy that
``rough-map map --json`` reports from the world in memory.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.transform import Affine
from rasterio.warp import calculate_default_transform, reproject

from rough_map.cli.main import main
from rough_map.errors import FileFormatError, InputError
from rough_map.evaluation.score import LayerPrediction, observed_mask, score_cells
from rough_map.evaluation.score_files import score_map_dir
from rough_map.io.truth import TiledWorld, TiledWorldWriter
from rough_map.io.truth_raster import read_class_names, write_truth_geotiff
from rough_map.types import HeightField


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 6 m mixed course simulated and mapped with the CLI; the map's --json figures."""
    root = tmp_path_factory.mktemp("score")
    run, out = root / "run", root / "map"
    argv = ["-q", "simulate", "--out", run, "--course", "mixed", "--length", "6",
            "--no-images", "--seed", "3"]  # fmt: skip
    assert main([str(a) for a in argv]) == 0
    return {"run": run, "map": out, "truth": run / "world_truth.tif"}


@pytest.fixture(scope="module")
def map_json(mapped: dict) -> dict:
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["-q", "map", str(mapped["run"]), "--out", str(mapped["map"]), "--no-png",
                     "--json"])  # fmt: skip
    assert code == 0
    return json.loads(buf.getvalue())


def _rewrite(src: Path, dst: Path, fn=None, **profile) -> Path:
    """Copy a GeoTIFF, the data through ``fn`` and the profile updated."""
    with rasterio.open(src) as ds:
        data, prof, tags = ds.read(1), ds.profile, ds.tags(1)
    if fn is not None:
        data = fn(data)
    prof.update(profile)
    prof.update(dtype=data.dtype)
    with rasterio.open(dst, "w", **prof) as ds:
        ds.write(data, 1)
        ds.update_tags(1, **tags)
    return dst


def _sidecar(tif: Path, names: dict[int, str]) -> None:
    tif.with_name(f"{tif.stem}.classes.json").write_text(json.dumps(names))


# ------------------------------------------------------------------- round trip


def test_simulator_truth_scores_as_the_map_evaluation(mapped: dict, map_json: dict) -> None:
    with rasterio.open(mapped["truth"]) as ds:
        assert ds.dtypes[0] == "uint8" and ds.nodata == 255 and ds.crs is not None
        assert abs(ds.res[0] - 0.002) < 1e-12
    names = read_class_names(mapped["truth"])
    assert names[1] == "dirt_road"  # the world's order, not the map's
    score = score_map_dir(mapped["map"], mapped["truth"])
    assert score.near_field_accuracy == map_json["near_class_accuracy"]
    near = score.layers["class"]
    assert near.correct == np.trace(near.confusion[:, :-1])
    assert near.labelled == near.confusion[:, :-1].sum()
    assert near.cells == score.scored_cells == near.confusion.sum()
    # per distance: the bins add up to the whole, and the near field lies near the path
    assert sum(b["labelled"] for b in near.bins) == near.labelled
    assert sum(b["correct"] for b in near.bins) == near.correct
    assert near.bins[0]["labelled"] > near.labelled / 2
    assert near.abstained == 0 and near.abstention_rate == 0.0  # observed cells all labelled
    assert score.map_only == () and score.truth_only == ()


def test_mode_resampling_is_close_to_nearest(mapped: dict) -> None:
    a = score_map_dir(mapped["map"], mapped["truth"]).near_field_accuracy
    b = score_map_dir(mapped["map"], mapped["truth"], resampling="mode").near_field_accuracy
    assert abs(a - b) < 0.05


@pytest.mark.filterwarnings("ignore:Use `@` matmul:PendingDeprecationWarning")  # rasterio's
@pytest.mark.parametrize("crs", ["EPSG:32634", "EPSG:4326"])
def test_truth_in_another_crs_and_resolution(mapped: dict, tmp_path: Path, crs: str) -> None:
    """UTM 34N (the course lies in zone 33) or lon/lat, 2x coarser: the same within 0.02."""
    dst = tmp_path / "utm.tif"
    with rasterio.open(mapped["truth"]) as src:
        transform, w, h = calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds, dst_width=src.width // 2,
            dst_height=src.height // 2)  # fmt: skip
        data = np.full((h, w), 255, dtype=np.uint8)
        reproject(rasterio.band(src, 1), data, dst_transform=transform, dst_crs=crs,
                  src_nodata=255, dst_nodata=255, resampling=Resampling.nearest)  # fmt: skip
        prof = src.profile | {"crs": CRS.from_string(crs), "transform": transform, "width": w,
                              "height": h}  # fmt: skip
        tags = src.tags(1)
    with rasterio.open(dst, "w", **prof) as ds:
        ds.write(data, 1)
        ds.update_tags(1, **tags)
    base = score_map_dir(mapped["map"], mapped["truth"])
    moved = score_map_dir(mapped["map"], dst)
    assert abs(moved.near_field_accuracy - base.near_field_accuracy) < 0.02
    assert abs(moved.scored_cells - base.scored_cells) <= 0.02 * base.scored_cells


# ------------------------------------------------------------------- class names


def test_renamed_and_reordered_codes_give_the_same_score(mapped: dict, tmp_path: Path) -> None:
    names = read_class_names(mapped["truth"])
    perm = {0: 7, 1: 3, 2: 0, 3: 12, 4: 1}  # old value -> new value
    lut = np.full(256, 99, dtype=np.uint8)
    for old, new in perm.items():
        lut[old] = new
    tif = _rewrite(mapped["truth"], tmp_path / "survey.tif", lambda d: lut[d], nodata=99)
    _sidecar(tif, {perm[v]: n.replace("_", " ").title() for v, n in names.items() if v in perm})
    base = score_map_dir(mapped["map"], mapped["truth"])
    other = score_map_dir(mapped["map"], tif)
    assert other.near_field_accuracy == base.near_field_accuracy
    np.testing.assert_array_equal(other.layers["class"].confusion, base.layers["class"].confusion)

    # a CSV sidecar (value,name) reads the same
    tif.with_name("survey.classes.json").unlink()
    rows = "".join(f"{perm[v]},{n}\n" for v, n in names.items() if v in perm)
    tif.with_name("survey.classes.csv").write_text("value,name\n" + rows)
    assert score_map_dir(mapped["map"], tif).near_field_accuracy == base.near_field_accuracy


def test_classes_only_in_the_truth_or_only_in_the_map_are_reported(
    mapped: dict, tmp_path: Path
) -> None:
    # the survey knows concrete, dirt road and "water" (on the gravel), nothing else
    tif = _rewrite(mapped["truth"], tmp_path / "water.tif")
    _sidecar(tif, {0: "concrete", 1: "dirt_road", 2: "water"})
    score = score_map_dir(mapped["map"], tif)
    assert score.truth_only == ("water",)
    assert set(score.map_only) == {"compact_soil", "gravel", "ploughed_soil"}
    base = score_map_dir(mapped["map"], mapped["truth"]).layers["class"]
    near = score.layers["class"]
    water = score.true_classes.index("water")
    gravel = score.map_classes.index("gravel")
    # every gravel cell the map found is now counted wrong, in the row "water"
    assert near.confusion[water, gravel] == base.confusion[3, 3] > 0
    assert near.correct == base.correct - base.confusion[3, 3]
    assert "classes of the truth not in the map: water" in score.to_text()


def test_gdal_category_names_in_aux_xml(mapped: dict, tmp_path: Path) -> None:
    tif = _rewrite(mapped["truth"], tmp_path / "cat.tif")
    with rasterio.open(tif, "r+") as ds:
        ds.update_tags(1, **{k: "" for k in ds.tags(1)})  # GDAL removes empty items
    categories = ["Concrete", "dirt-road", "gravel", "compact soil", "ploughed_soil"]
    cats = "".join(f"<Category>{n}</Category>" for n in categories)
    tif.with_name("cat.tif.aux.xml").write_text(
        f'<PAMDataset><PAMRasterBand band="1"><CategoryNames>{cats}</CategoryNames>'
        "</PAMRasterBand></PAMDataset>"
    )
    names = read_class_names(tif)
    assert names[0] == "Concrete" and names[1] == "dirt-road"
    base = score_map_dir(mapped["map"], mapped["truth"])
    assert score_map_dir(mapped["map"], tif).near_field_accuracy == base.near_field_accuracy


# ------------------------------------------------------------------- abstention


def test_abstention_is_observed_cells_left_unknown() -> None:
    truth = np.array([0, 0, 1, 1, 1, -1, 0, 1])
    values = np.array([0, -1, 1, 0, -1, 0, -1, -1])
    observed = np.array([1, 1, 1, 1, 1, 1, 1, 0], dtype=bool)
    names = ("gravel", "concrete")
    dist = np.array([0.1, 0.2, 0.3, 0.7, 1.5, 0.1, 2.5, 9.0])
    s = score_cells({"far_class": LayerPrediction(values, names, observed)}, truth,
                    {0: "Gravel", 1: "concrete", 255: "unknown"}, distance=dist,
                    bins=(0.5, 1.0, 2.0))  # fmt: skip
    far = s.layers["far_class"]
    # scored: 7 cells with truth; labelled 3 (2 right); observed 6, of them 3 unknown
    assert (far.cells, far.labelled, far.correct) == (7, 3, 2)
    assert (far.observed, far.abstained) == (6, 3) and far.abstention_rate == 0.5
    assert s.far_field_accuracy == pytest.approx(2 / 3) and math.isnan(s.near_field_accuracy)
    assert [b["cells"] for b in far.bins] == [3, 1, 1, 2]
    assert [b["abstained"] for b in far.bins] == [1, 0, 1, 1]
    assert far.confusion.tolist() == [[1, 0, 2], [1, 1, 2]]


def test_observed_cells_from_count_or_confidence_bands() -> None:
    bands = {"far_count": np.array([0.0, 2.0, np.nan]), "far_confidence": np.array(
        [np.nan, np.nan, 0.3])}  # fmt: skip
    seen = observed_mask("far_class", bands.get)
    assert seen is not None and seen.tolist() == [False, True, True]
    assert observed_mask("class", bands.get) is None


# ------------------------------------------------------------------- writing the truth


def test_tiled_world_truth_geotiff_equals_the_whole(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    classes = rng.integers(0, 3, (5, 11)).astype(np.int8)
    heights = np.zeros((5, 11), dtype=np.float32)
    whole = HeightField(heights, 0.01, (1.0, 2.0), classes, ("a", "b", "c"))
    with TiledWorldWriter(tmp_path / "w.npz", (5, 11), 0.01, (1.0, 2.0), ("a", "b", "c"),
                          tile_columns=4) as writer:  # fmt: skip
        writer.append(0, heights, classes)
    crs = CRS.from_epsg(32633)
    a = write_truth_geotiff(whole, tmp_path / "a.tif", crs)
    b = write_truth_geotiff(TiledWorld(tmp_path / "w.npz"), tmp_path / "b.tif", crs)
    with rasterio.open(a) as da, rasterio.open(b) as db:
        np.testing.assert_array_equal(da.read(1), db.read(1))
        np.testing.assert_array_equal(da.read(1), classes[::-1])  # north-up
        assert da.transform.c == pytest.approx(0.995) and da.transform.f == pytest.approx(2.045)
    assert read_class_names(a) == {0: "a", 1: "b", 2: "c"}


# ------------------------------------------------------------------- bad input


def test_bad_truth_files(mapped: dict, tmp_path: Path) -> None:
    m, truth = mapped["map"], mapped["truth"]
    with pytest.raises(FileFormatError, match=r"nothere\.tif: no such file"):
        score_map_dir(m, tmp_path / "nothere.tif")
    with pytest.raises(FileFormatError, match=r"nocrs\.tif \[crs\]: no CRS"):
        score_map_dir(m, _rewrite(truth, tmp_path / "nocrs.tif", crs=None))
    far = _rewrite(truth, tmp_path / "far.tif")
    with rasterio.open(far, "r+") as ds:
        t = ds.transform
        ds.transform = Affine(t.a, t.b, t.c + 1e6, t.d, t.e, t.f)
    with pytest.raises(FileFormatError, match=r"far\.tif \[extent\]: .*no overlap"):
        score_map_dir(m, far)
    floats = _rewrite(truth, tmp_path / "float.tif", lambda d: d.astype(np.float32))
    with pytest.raises(FileFormatError, match=r"float\.tif \[dtype\]: band 1 is float32"):
        score_map_dir(m, floats)
    unnamed = _rewrite(truth, tmp_path / "unnamed.tif")
    _sidecar(unnamed, {0: "concrete", 1: "dirt_road"})
    with pytest.raises(FileFormatError, match=r"unnamed\.tif \[class names\]: class values \[2\]"):
        score_map_dir(m, unnamed)
    foreign = _rewrite(truth, tmp_path / "foreign.tif")
    _sidecar(foreign, {i: f"crop_{i}" for i in range(5)})
    with pytest.raises(InputError, match=r"no class of the truth .* is a class of the map"):
        score_map_dir(m, foreign)
    nameless = _rewrite(truth, tmp_path / "nameless.tif")
    with rasterio.open(nameless, "r+") as ds:
        ds.update_tags(1, **{k: "" for k in ds.tags(1)})
    with pytest.raises(FileFormatError, match=r"nameless\.tif \[class names\]: no class names"):
        score_map_dir(m, nameless)
    with pytest.raises(FileFormatError, match="no such map folder"):
        score_map_dir(tmp_path / "nomap", truth)
    with pytest.raises(FileFormatError, match="not a `rough-map map` folder"):
        score_map_dir(tmp_path, truth)


# ------------------------------------------------------------------- CLI


def test_cli_score_table_json_and_one_line_errors(
    mapped: dict, map_json: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["score", str(mapped["map"]), "--truth", str(mapped["truth"])]) == 0
    out, err = capsys.readouterr()
    assert "class confusion matrix (cells)" in out and "by distance from the path" in out
    assert err.startswith("near-field accuracy")

    argv = ["score", str(mapped["map"]), "--truth", str(mapped["truth"]), "--json",
            "--max-distance", "1", "--bins", "0.25,0.5"]  # fmt: skip
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    near = data["layers"]["class"]
    assert [b["hi_m"] for b in near["by_distance_m"]][:2] == [0.25, 0.5]
    assert all(b["lo_m"] < 1.0 for b in near["by_distance_m"])
    assert near["confusion"]["columns_map"][-1] == "unknown"
    assert data["near_field_accuracy"] == near["accuracy"] and data["far_field_accuracy"] is None

    floats = _rewrite(mapped["truth"], tmp_path / "float.tif", lambda d: d.astype(np.float32))
    for argv, message in [
        (["--truth", str(floats)], "float.tif [dtype]: band 1 is float32"),
        (["--truth", str(tmp_path / "typo.tif")], "no such file or folder"),
        (["--truth", str(mapped["truth"]), "--bins", "1,0.5"], "increasing positive distances"),
    ]:
        assert main(["score", str(mapped["map"]), *argv]) == 2
        out, err = capsys.readouterr()
        assert out == "" and err.count("\n") == 1 and "Traceback" not in err, err
        assert err.startswith("rough-map score: error: ") and message in err, err


def test_every_class_layer_of_the_folder_is_scored(mapped: dict, tmp_path: Path) -> None:
    """A far_class file (near-to-far) is read like the class file; without a far_count
    band, every scored cell counts as observed by it."""
    import shutil

    folder = tmp_path / "map"
    shutil.copytree(mapped["map"], folder)
    with rasterio.open(folder / "map_class.tif") as ds:
        data, prof, tags = ds.read(1), ds.profile, ds.tags(1)
    prof.update(driver="GTiff")
    with rasterio.open(folder / "map_far_class.tif", "w", **prof) as ds:
        ds.write(data, 1)
        ds.update_tags(1, **(tags | {"layer": "far_class"}))
    score = score_map_dir(folder, mapped["truth"])
    near, far = score.layers["class"], score.layers["far_class"]
    assert score.far_field_accuracy == score.near_field_accuracy
    assert far.observed == far.cells and far.abstained == far.cells - far.labelled
    assert near.observed == near.labelled  # the count band: cells seen
    assert "far_class confusion matrix (cells)" in score.to_text()


def test_truth_in_a_local_frame(tmp_path: Path) -> None:
    """A truth in rough_map's local engineering CRS lies in the map's local frame; it
    cannot be placed on a georeferenced map."""
    from rough_map.config import LOCAL_WKT
    from rough_map.evaluation.score_files import resample_truth

    local = CRS.from_wkt(LOCAL_WKT)
    classes = np.zeros((50, 100), dtype=np.int8)
    classes[:, 50:] = 1  # x >= 0.5 m
    world = HeightField(np.zeros((50, 100), np.float32), 0.01, (0.005, 0.005), classes,
                        ("gravel", "concrete"))  # fmt: skip
    tif = write_truth_geotiff(world, tmp_path / "local.tif", local)
    grid = Affine(0.1, 0.0, 0.3, 0.0, -0.1, 0.5)  # 5 x 10 cells of 0.1 m from x = 0.3 m
    values, names = resample_truth(tif, (5, 10), grid, local)
    assert values[0].tolist() == [0, 0, 1, 1, 1, 1, 1, -1, -1, -1]
    assert names == {0: "gravel", 1: "concrete"}
    with pytest.raises(FileFormatError, match=r"local\.tif \[crs\]: a local .*CRS cannot"):
        resample_truth(tif, (5, 10), grid, CRS.from_epsg(32633))


def test_simulate_can_skip_the_truth_geotiff(tmp_path: Path) -> None:
    argv = ["-q", "simulate", "--out", tmp_path / "sim", "--length", "2", "--no-images",
            "--points-per-cell", "2", "--no-truth-geotiff"]  # fmt: skip
    assert main([str(a) for a in argv]) == 0
    assert (tmp_path / "sim" / "world_truth.npz").is_file()
    assert not (tmp_path / "sim" / "world_truth.tif").exists()
