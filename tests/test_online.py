"""One pass per frame, the same result on any number of processes, and the streaming mapper."""

from __future__ import annotations

import gc
import importlib
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rough_map.classify import load_terrain_model
from rough_map.cli._common import start_up, unused_optional_imports
from rough_map.errors import FileFormatError, InputError, ModelError
from rough_map.features import FramePass, frame_jobs, iter_frames, traverse_features
from rough_map.features.frames import FrameJob, height_sample, process_frame, process_frames
from rough_map.features.traverse import start_frame_pass
from rough_map.io.model_files import model_paths
from rough_map.io.traverse import load_traverse
from rough_map.map import fuse_traverse
from rough_map.map.tiles import TiledMap
from rough_map.near_far import NearFarSettings
from rough_map.online import OnlineMapper
from rough_map.patch import Extraction
from rough_map.resources import model_base
from rough_map.workflow import AnalysisOptions, analyse, analyse_model_file, write_outputs


@pytest.fixture(scope="module")
def model():
    return load_terrain_model("default")


def _same_tables(a, b) -> None:
    for c in a.columns:
        x, y = a[c], b[c]
        if x.dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), c
        else:
            assert list(x) == list(y), c
    assert np.array_equal(a.log_psd, b.log_psd, equal_nan=True)


def test_features_identical_on_two_processes(small_traverse: Path) -> None:
    one = traverse_features(small_traverse, n_jobs=1)
    two = traverse_features(small_traverse, n_jobs=2)
    _same_tables(one, two)
    assert one.valid.sum() > 0


def test_chunks_measure_each_frame_as_it_reads_alone(small_traverse: Path, model) -> None:
    """A worker measures a chunk's patches in one batch; each frame's row and spectrum are
    those of the frame measured alone (as the online mapper does), to the last bit."""
    trav = load_traverse(small_traverse)
    jobs = frame_jobs(trav)
    settings = FramePass(Extraction.from_dict(model.extraction_), height_resolution=0.1)
    chunked = process_frames(jobs, settings)
    assert sum(bool(o.row["valid"]) for o in chunked) > 0
    for out in chunked:
        alone = process_frame(jobs[out.index], settings)
        assert out.row.keys() == alone.row.keys()
        for key, value in out.row.items():
            assert value == alone.row[key] or (value != value and alone.row[key] != alone.row[key])
        assert (out.psd is None) == (alone.psd is None)
        assert out.psd is None or np.array_equal(out.psd, alone.psd)


def test_frames_come_back_in_order_with_small_chunks(small_traverse: Path) -> None:
    trav = load_traverse(small_traverse)
    jobs = frame_jobs(trav)
    outs = list(iter_frames(jobs, FramePass(), n_jobs=2, chunk=2))
    assert [o.index for o in outs] == list(range(len(trav)))


@pytest.mark.parametrize("n_jobs", [0, -100, 1.5])
def test_bad_n_jobs(small_traverse: Path, n_jobs) -> None:
    with pytest.raises(InputError, match="n_jobs must be"):
        traverse_features(small_traverse, n_jobs=n_jobs)


def test_height_sample_lands_in_the_right_world_cell() -> None:
    """A flat cloud 1 m ahead at z = 0.2, seen from (10, -3, 0.5) heading north: world
    (10, -2), height 0.7, in lattice cell row floor(-2 / 0.1), col floor(10 / 0.1)."""
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(0.96, 0.99, 500), rng.uniform(-0.04, -0.01, 500), np.full(500, 0.2)]
    )
    job = FrameJob(0, 0.0, (10.0, -3.0, 0.5, 0.0, 0.0, math.pi / 2))
    h = height_sample(pts, job, 0.1, 20_000)
    assert h.rows.tolist() == [-21] and h.cols.tolist() == [100]
    assert h.counts.tolist() == [500.0]
    assert h.sums[0] / h.counts[0] == pytest.approx(0.7)


def test_map_is_the_table_fusion_with_spilled_tiles(small_traverse: Path, model) -> None:
    """The tiled, spilled map equals fusing the whole features table in one grid."""
    result = analyse(load_traverse(small_traverse), model, near_far=False)
    pred = result.prediction
    assert pred is not None
    names = tuple(str(c) for c in pred.classes)
    lv = {n: i for i, n in enumerate(model.level_names_)}
    levels = np.array([lv.get(str(v), np.nan) for v in pred.level], dtype=float)
    ref = fuse_traverse(
        result.features,
        pred.filtered_proba,
        names,
        levels,
        spec=result.extraction.patch,
        novelty=pred.novelty,
    )
    assert ref.shape == result.map.shape and ref.geometry.origin == result.map.geometry.origin
    estimates = [n for n in ref.layers if ref.info(n).kind != "internal"]
    assert sorted([*estimates, "elevation"]) == sorted(result.map.layers)
    for layer in estimates:
        assert np.array_equal(ref[layer], result.map[layer], equal_nan=True), layer
    assert np.isfinite(result.map["elevation"]).sum() > 10


@pytest.mark.parametrize("roughness", ["raw", "smoothed"])
def test_the_replay_grows_into_the_map(small_traverse: Path, model, roughness) -> None:
    """One window per valid frame, in time order; the map grows, and the last window reads
    what the final map reads over it (the replay fuses the same observations)."""
    result = analyse(load_traverse(small_traverse), model, near_far=False, roughness=roughness)
    assert result.mapper is not None
    updates = list(result.mapper.replay())
    assert len(updates) == int(result.features.valid.sum())
    times = [t for t, _ in updates]
    assert times == sorted(times)
    grid = result.map
    _, last = updates[-1]
    rows, cols = np.nonzero(np.isfinite(last["R"]))
    x0, y0 = last.geometry.origin
    res = last.resolution
    r, c = grid.cells_at(x0 + (cols + 0.5) * res, y0 + (rows + 0.5) * res, grow=False).T
    for layer in ("R", "w", "class", "level", "count", "p_gravel"):
        assert np.allclose(last[layer][rows, cols], grid[layer][r, c], equal_nan=True), layer
    # the first window knows less than the same cells do at the end
    first = updates[0][1]
    fx, fy = first.geometry.origin
    fr, fc = np.nonzero(np.isfinite(first["count"]) & (first["count"] > 0))
    gr, gc = grid.cells_at(fx + (fc + 0.5) * res, fy + (fr + 0.5) * res, grow=False).T
    assert np.all(first["count"][fr, fc] <= grid["count"][gr, gc])
    assert np.any(first["count"][fr, fc] < grid["count"][gr, gc])


def test_map_bag_has_one_gridmap_per_update(small_traverse: Path, model, tmp_path) -> None:
    from rough_map.export.gridmap_msg import read_gridmap_bag

    result = analyse(load_traverse(small_traverse), model, near_far=False)
    paths = write_outputs(result, tmp_path / "out", png=False, gridmap_bag=True)
    messages = read_gridmap_bag(paths["gridmap_bag"])
    valid = int(result.features.valid.sum())
    assert len(messages) == valid + 1  # each frame fused, then the whole map
    assert all(m.basic_layers == ("R",) for m in messages)
    assert "elevation" not in messages[0].layers and "elevation" in messages[-1].layers
    assert messages[-1].size == (result.map.shape[1], result.map.shape[0])


def test_small_tiles_and_window_change_nothing(small_traverse: Path, model, monkeypatch) -> None:
    ref = analyse(load_traverse(small_traverse), model, near_far=False).map
    init = OnlineMapper.__init__

    def tiny(self, *args, **kwargs):
        kwargs.update(window=0.3, tile_cells=8)
        init(self, *args, **kwargs)

    monkeypatch.setattr(OnlineMapper, "__init__", tiny)
    got = analyse(load_traverse(small_traverse), model, near_far=False, n_jobs=2).map
    assert sorted(got.layers) == sorted(ref.layers)
    for layer in ref.layers:
        assert np.array_equal(ref[layer], got[layer], equal_nan=True), layer


def test_online_mapper_frame_by_frame(small_traverse: Path, model, tmp_path: Path) -> None:
    trav = load_traverse(small_traverse)
    table = traverse_features(trav, model.extraction_)
    spill = tmp_path / "tiles"
    mapper = OnlineMapper(model, window=0.5, tile_cells=8, spill_dir=spill, name=trav.name)
    most = 0
    for i, frame in enumerate(trav.frames):
        imu = None if frame.imu is None else (frame.imu.roll, frame.imu.pitch)
        up = mapper.update(frame.pose, cloud=trav.load_cloud(i), imu=imu, t=frame.t)
        most = max(most, mapper.tiles.in_memory())
        assert up.index == i
        if not up.features["valid"]:
            continue
        assert up.features["R"] == table["R"][i]  # the same measurement as offline
        assert up.posterior is not None and up.posterior.sum() == pytest.approx(1.0)
        assert up.label in mapper.classes
        assert up.map is not None and np.isfinite(up.map["R"]).any()
        assert set(mapper.classes) <= {c[2:] for c in up.map.layers if c.startswith("p_")}
    assert most <= 9  # the tiles within 0.5 m of the vehicle, not the whole course
    assert any(spill.iterdir())  # the rest went to disk
    grid = mapper.finish()
    mapper.close()
    assert not spill.exists() or not any(spill.iterdir())
    offline = analyse(trav, model, near_far=False).map
    for layer in ("R", "w", "count", "sigma_R"):
        assert np.array_equal(grid[layer], offline[layer], equal_nan=True), layer


def test_online_mapper_refuses_a_stereo_pair_without_calibration(model) -> None:
    mapper = OnlineMapper(model)
    img = np.zeros((10, 10), dtype=np.uint8)
    with pytest.raises(InputError, match="calibration"):
        mapper.update((0, 0, 0, 0, 0, 0), left=img, right=img)
    mapper.finish()


def test_online_mapper_bad_window() -> None:
    with pytest.raises(InputError, match="window must be"):
        OnlineMapper(None, window=0.0)


def test_tiled_map_bad_tile_size() -> None:
    with pytest.raises(InputError, match="tile_cells"):
        TiledMap(0.1, tile_cells=2)


def test_map_state_round_trip_and_fusion(small_traverse: Path, model, tmp_path: Path) -> None:
    result = analyse(load_traverse(small_traverse), model, near_far=False)
    assert result.mapper is not None
    path = result.mapper.save_state(tmp_path / "s.npz")
    back = TiledMap.open_saved(path)
    assert back.add_saved(path) == {"name": result.traverse.name}
    again = back.merged()
    grid = result.map
    assert again.geometry == grid.geometry and sorted(again.layers) == sorted(grid.layers)
    for layer in grid.layers:
        assert np.array_equal(again[layer], grid[layer], equal_nan=True), layer
    # one map fused with itself: counts double, the estimates stay (same observations twice)
    back.add_saved(path)
    twice = back.merged()
    assert np.array_equal(twice["count"], 2 * grid["count"])
    seen = grid["count"] > 0
    assert np.allclose(twice["R"][seen], grid["R"][seen])
    assert np.allclose(twice["elevation"], grid["elevation"], equal_nan=True)
    back.close()


def test_map_state_rejects_other_files(small_traverse: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(FileFormatError, match=r"bad\.npz.*not a readable map state"):
        TiledMap.open_saved(bad)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FileFormatError, match=r"junk\.npz.*not a readable map state"):
        TiledMap(0.1).add_saved(tmp_path / "junk.npz")
    result = analyse(load_traverse(small_traverse), None, near_far=False, resolution=0.2)
    assert result.mapper is not None
    state = result.mapper.save_state(tmp_path / "coarse.npz")
    with pytest.raises(InputError, match=r"coarse\.npz: a map of 0\.2 m cells"):
        TiledMap(0.1).add_saved(state)


@pytest.mark.parametrize("by_name", [False, True])
def test_outputs_identical_for_any_jobs(
    small_traverse: Path, model, tmp_path: Path, by_name: bool
) -> None:
    """By name, ``-j 2`` starts the frames from the model's card before the model loads."""
    trav = load_traverse(small_traverse)
    for n in (1, 2):
        options = AnalysisOptions(near_far=False, n_jobs=n)
        if by_name:
            result = analyse_model_file(trav, "default", options)
        else:
            result = analyse(trav, model, options)
        write_outputs(result, tmp_path / f"j{n}", png=False)
    names = sorted(p.name for p in (tmp_path / "j1").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "j2").iterdir())
    for name in names:
        assert (tmp_path / "j1" / name).read_bytes() == (tmp_path / "j2" / name).read_bytes(), name


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_cli_rejects_bad_jobs(small_traverse: Path, tmp_path: Path, capsys, value: str) -> None:
    from rough_map.cli.main import main

    assert main(["map", str(small_traverse), "--out", str(tmp_path / "m"), "-j", value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "-j/--jobs" in err[0] and value in err[0]


def test_state_keeps_the_far_field(imaged_traverse: Path, model, tmp_path: Path) -> None:
    """Near-to-far predictions fused into the map travel in its state, whole: a batch of
    this one traverse has every far-field prediction of its map."""
    # every label, uncalibrated: settled and calibrated, near-to-far abstains on this short
    # course (7 images, the class changing every 2 m)
    settings = NearFarSettings(calibrate=False, settle_frames=0)
    result = analyse(
        load_traverse(imaged_traverse), model, near_far=True, near_far_settings=settings
    )
    assert result.mapper is not None and "far_count" in result.map
    state = result.mapper.save_state(tmp_path / "s.npz")
    tiles = TiledMap.open_saved(state)
    tiles.add_saved(state)
    again = tiles.merged()
    tiles.close()
    assert again["far_count"].sum() == result.map["far_count"].sum() > 0
    assert again["count"].sum() == result.map["count"].sum()
    seen = np.isfinite(again["far_class"])
    assert seen.sum() == np.isfinite(result.map["far_class"]).sum()


def test_a_started_pass_gives_the_frames_in_order_and_stops_early(small_traverse: Path) -> None:
    jobs = frame_jobs(load_traverse(small_traverse))
    alone = [o.row for o in iter_frames(jobs, FramePass(), chunk=2)]
    primed = [o.row for o in iter_frames(jobs, FramePass(), n_jobs=2, chunk=2, prime=5)]
    assert len(primed) == len(alone)
    for a, b in zip(primed, alone, strict=True):  # NaN from another process is another NaN
        assert a.keys() == b.keys()
        differ = [k for k in a if not (a[k] == b[k] or (a[k] != a[k] and b[k] != b[k]))]
        assert not differ, [(k, a[k], b[k]) for k in differ]
    stopped = iter_frames(jobs, FramePass(), n_jobs=2, chunk=2, prime=5)
    stopped.close()  # never read: the queued chunks are dropped, nothing waits
    with pytest.raises(InputError, match="prime"):
        iter_frames(jobs, FramePass(), prime=-1)


def test_a_pass_starts_early_only_from_a_card(small_traverse: Path, model, tmp_path) -> None:
    trav = load_traverse(small_traverse)
    assert start_frame_pass(trav, "default", resolution=0.1, n_jobs=1) is None
    assert start_frame_pass(trav, model, resolution=0.1, n_jobs=2) is None  # no card
    assert start_frame_pass(trav, tmp_path / "missing", resolution=0.1, n_jobs=2) is None
    stream = start_frame_pass(trav, "default", resolution=0.1, n_jobs=2)
    assert stream is not None
    stream.close()
    assert stream.settings.extraction == Extraction.from_dict(model.extraction_)


def test_a_card_that_lies_about_the_extraction_is_refused(small_traverse, tmp_path) -> None:
    """The card is not covered by the model's sha256: its extraction, which the frames
    start on, must be the model's."""
    model_file, card_file = model_paths(model_base())
    shutil.copy(model_file, tmp_path / "m.skops")
    card = json.loads(card_file.read_text(encoding="utf-8"))
    card["feature_extraction"]["spacing"] = 0.016
    (tmp_path / "m.card.json").write_text(json.dumps(card), encoding="utf-8")
    with pytest.raises(
        ModelError,
        match=r"m: the feature extraction on its card is not the "
        r"model's \(spacing 0\.016 against 0\.008\)",
    ):
        analyse_model_file(load_traverse(small_traverse), tmp_path / "m", AnalysisOptions(n_jobs=2))


def test_map_runs_without_pandas(small_traverse: Path, tmp_path: Path) -> None:
    """scikit-learn imports pandas, dask, pytest and rich when it can; `rough-map map`
    keeps them out (63 MB; 18 MB and 0.3 s for the other three)."""
    code = (
        "import sys; from rough_map.cli.main import main; "
        f"rc = main(['map', {str(small_traverse)!r}, '--out', {str(tmp_path / 'm')!r}, "
        "'-j', '2', '-q', '--no-png']); "
        "print(rc, *(m in sys.modules for m in ('pandas', 'dask', 'pytest', 'rich')))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.split()[-5:] == ["0", *["False"] * 4], done.stderr[-2000:]
    with unused_optional_imports("tabnanny"):
        with pytest.raises(ImportError):
            importlib.import_module("tabnanny")
    assert importlib.import_module("tabnanny").__name__ == "tabnanny"


def test_start_up_runs_without_the_collector_and_freezes_what_it_made() -> None:
    """`map`'s start-up: no collection walks the imports, and later ones skip them."""
    enabled, before = gc.isenabled(), gc.get_freeze_count()
    try:
        with start_up():
            assert not gc.isenabled()
            made = [[] for _ in range(1000)]
        assert gc.isenabled() == enabled
        assert gc.get_freeze_count() >= before + len(made)
        with pytest.raises(KeyError), start_up():
            raise KeyError("x")
        assert gc.isenabled() == enabled
    finally:
        gc.unfreeze()


def test_one_blas_thread_limits_blas_inside_the_block_only() -> None:
    from threadpoolctl import threadpool_info

    from rough_map._blas import one_blas_thread

    def blas() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas()
    assert before  # numpy's OpenBLAS at least
    for _ in range(2):  # the second time with the libraries found the first
        with one_blas_thread():
            assert set(blas()) == {1}
        assert blas() == before


def test_analyse_takes_one_input_form(small_traverse: Path, model) -> None:
    """A Traverse, a TerrainModel (or None) and one AnalysisOptions, whole or as keyword
    changes; paths, names and unknown options are refused in one line."""
    trav = load_traverse(small_traverse)
    with pytest.raises(InputError, match=r"analyse takes a Traverse .* got PosixPath"):
        analyse(small_traverse, model)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"analyse takes a TerrainModel or None .* got str"):
        analyse(trav, "default")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"analyse\(\) got unexpected keyword arguments \['far'\]"):
        analyse(trav, model, far=True)
    with pytest.raises(InputError, match=r"analyse\(\) options must be a rough_map\.workflow\.An"):
        analyse(trav, model, {"resolution": 0.2})  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"near_far must be 'auto', True or False; got 'yes'"):
        AnalysisOptions(near_far="yes")
    whole = analyse(trav, None, AnalysisOptions(near_far=False, resolution=0.2))
    changed = analyse(trav, None, AnalysisOptions(resolution=0.2), near_far=False)
    assert np.array_equal(whole.map["R"], changed.map["R"], equal_nan=True)
    whole.mapper.close()
    changed.mapper.close()
