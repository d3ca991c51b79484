"""`rough-map batch`: many traverses, one map; the same bytes locally, on processes and on a
Dask cluster; resumable."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from rough_map import batch as batch_mod
from rough_map.cli.main import main
from rough_map.errors import InputError
from rough_map.map.tiles import TiledMap


@pytest.fixture(scope="module")
def second_traverse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rough_map.simulate.course import SensorSpec, simulate

    out = tmp_path_factory.mktemp("sim") / "compact"
    simulate(out, "compact", length=3.0, seed=2, images=False, sensor=SensorSpec(points_per_cell=2))
    return out


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _assert_same(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    for name in fa:
        assert fa[name] == fb[name], name


@pytest.fixture(scope="module")
def serial(small_traverse: Path, second_traverse: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("batch") / "serial"
    args = ["-q", "batch", str(small_traverse), str(second_traverse), "--out", str(out)]
    assert main(args) == 0
    return out


def test_batch_layout_and_fusion(serial: Path, small_traverse: Path) -> None:
    names = sorted(p.name for p in serial.iterdir() if p.is_dir())
    assert names == ["sim-compact-seed2", "sim-mixed-seed1"]
    for name in names:
        assert (serial / name / "map.tif").is_file()
        assert (serial / name / "map_state.npz").is_file()
    assert (serial / "map.tif").is_file() and (serial / "map_class.tif").is_file()
    assert (serial / "map_R.png").is_file()
    total = 0.0
    for name in names:
        state = serial / name / "map_state.npz"
        tiles = TiledMap.open_saved(state)
        tiles.add_saved(state)
        total += tiles.merged()["count"].sum()
        tiles.close()
    marker = json.loads((serial / "batch.json").read_text())
    assert marker["traverses"] == ["sim-mixed-seed1", "sim-compact-seed2"]
    import rasterio

    with rasterio.open(serial / "map.tif") as src:
        bands = list(src.descriptions)
        count = src.read(bands.index("count") + 1)
    assert count.sum() == pytest.approx(total)  # every patch of both traverses is in it
    for path in serial.rglob("*"):  # no absolute path in any output
        if path.suffix in (".json", ".csv"):
            assert str(serial) not in path.read_text() and "/tmp" not in path.read_text()


def test_batch_on_two_processes_is_identical(serial, small_traverse, second_traverse, tmp_path):
    out = tmp_path / "j2"
    assert main(["-q", "batch", str(small_traverse), str(second_traverse), "--out", str(out),
                 "-j", "2"]) == 0  # fmt: skip
    _assert_same(serial, out)


def test_batch_resumes(serial, small_traverse, second_traverse, tmp_path) -> None:
    out = tmp_path / "resume"
    shutil.copytree(serial, out)
    # a run killed before the second traverse was done left only the first one
    shutil.rmtree(out / "sim-compact-seed2")
    (out / ".sim-compact-seed2.1234abcd.partial").mkdir()  # half-written leftovers
    result = batch_mod.run_batch([small_traverse, second_traverse], out)
    assert result.skipped == ["sim-mixed-seed1"] and result.mapped == ["sim-compact-seed2"]
    assert not (out / ".sim-compact-seed2.1234abcd.partial").exists()  # cleaned up
    again = batch_mod.run_batch([small_traverse, second_traverse], out)
    assert again.mapped == [] and len(again.skipped) == 2
    _assert_same(serial, out)
    # other settings: done again
    other = batch_mod.run_batch([small_traverse], out, resolution=0.2, png=False)
    assert other.mapped == ["sim-mixed-seed1"]


def test_batch_refuses_two_traverses_of_one_name(small_traverse, tmp_path) -> None:
    with pytest.raises(InputError, match="two traverses are named 'sim-mixed-seed1'"):
        batch_mod.run_batch([small_traverse, small_traverse / "traverse.json"], tmp_path)


def test_batch_unreachable_scheduler(small_traverse, tmp_path) -> None:
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        batch_mod.run_batch([small_traverse], tmp_path / "o", scheduler="tcp://127.0.0.1:9")


@pytest.mark.slow
def test_batch_on_a_dask_cluster(serial, small_traverse, second_traverse, tmp_path, monkeypatch):
    """A local cluster of a scheduler and two worker processes gives the same bytes; the
    traverses are mapped on the workers (in this process mapping is made to fail)."""
    distributed = pytest.importorskip("distributed")

    def not_here(job):
        raise AssertionError("mapped in the client, not on a worker")

    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        monkeypatch.setattr(batch_mod, "map_traverse_files", not_here)
        out = tmp_path / "dask"
        result = batch_mod.run_batch(
            [small_traverse, second_traverse], out, scheduler=cluster.scheduler_address
        )
    assert sorted(result.mapped) == ["sim-compact-seed2", "sim-mixed-seed1"]
    _assert_same(serial, out)
    import rasterio

    with rasterio.open(out / "sim-mixed-seed1" / "map.tif") as src:
        assert np.isfinite(src.read(1, masked=True).filled(np.nan)).any()


@pytest.mark.slow
def test_the_readme_scheduler_listens_only_where_it_is_told(tmp_path) -> None:
    """The README's `dask scheduler` names the address of its dashboard as well as its own:
    run so on 127.0.0.1, every socket it listens on is there (by default the dashboard
    listens on every interface)."""
    import re
    import shutil
    import subprocess
    import sys
    import time
    from pathlib import Path

    psutil = pytest.importorskip("psutil")
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    (line,) = [x for x in readme.splitlines() if x.startswith("dask scheduler ")]
    host = re.search(r"--host (\S+)", line).group(1)
    assert re.search(rf"--dashboard-address {re.escape(host)}:\d+", line), line
    dask = shutil.which("dask", path=str(Path(sys.executable).parent))
    if dask is None:
        pytest.skip("dask.distributed (the cluster extra) is not installed")
    proc = subprocess.Popen(
        [
            dask,
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--dashboard-address",
            "127.0.0.1:0",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=tmp_path,
    )
    try:
        listening: list = []
        for _ in range(100):
            conns = psutil.Process(proc.pid).net_connections(kind="inet")
            listening = [c for c in conns if c.status == psutil.CONN_LISTEN]
            if len(listening) >= 2:  # the scheduler and its dashboard
                break
            time.sleep(0.2)
        assert len(listening) >= 2, listening
        assert {c.laddr.ip for c in listening} == {"127.0.0.1"}, listening
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_a_batch_for_a_vehicle_has_the_fused_speed_advice_and_costmap(
    serial, small_traverse, second_traverse, tmp_path
) -> None:
    """--vehicle as map takes it: each traverse's outputs and the fused map get v_max (from
    the fused R and w), v_max_95 and the costmap; the same vehicle resumes, another vehicle
    or none maps again, and without one the costmap is gone."""
    import rasterio

    from rough_map.vehicle import SpeedTable, load_vehicle

    out = tmp_path / "drive"
    shutil.copytree(serial, out)
    args = ["-q", "batch", str(small_traverse), str(second_traverse), "--out", str(out)]
    assert main([*args, "--vehicle", "tractor", "--no-png"]) == 0
    for folder in (out, out / "sim-mixed-seed1"):
        assert (folder / "map_costmap.pgm").is_file() and (folder / "map_costmap.yaml").is_file()
    with rasterio.open(out / "map.tif") as src:
        names = list(src.descriptions)
        layer = {n: src.read(names.index(n) + 1) for n in ("R", "w", "v_max", "v_max_95")}
    marker = json.loads((out / "sim-mixed-seed1" / "batch.json").read_text())
    band = tuple(marker["summary"]["band_rad_m"])
    expected = SpeedTable(load_vehicle("tractor"), band).v_max(layer["R"], layer["w"])
    assert np.allclose(layer["v_max"], expected, equal_nan=True, rtol=1e-5)
    seen = np.isfinite(layer["v_max"])
    assert seen.any() and (layer["v_max_95"][seen] <= layer["v_max"][seen] + 1e-6).all()
    again = batch_mod.run_batch(
        [small_traverse, second_traverse], out, png=False, vehicle=load_vehicle("tractor")
    )
    assert again.mapped == []
    car = batch_mod.run_batch([small_traverse], out, png=False, vehicle=load_vehicle("car"))
    assert car.mapped == ["sim-mixed-seed1"]
    assert main([*args, "--no-png"]) == 0
    assert not (out / "map_costmap.pgm").exists()
    with pytest.raises(InputError, match="speed gives the responses of a vehicle"):
        batch_mod.run_batch([small_traverse], out, speed=2.0)
