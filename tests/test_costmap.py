"""Speed advice along the path and on the map, and the costmap a navigation stack loads
(`features`/`map --vehicle`, rough_map.export.costmap): the map_server files read back as
map_server reads them (size, origin, thresholds, unknown never free), the OccupancyGrid in the
MCAP bag reads back with rosbags to the same values, and bad options get one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml

from rough_map.features import read_features
from rough_map.vehicle import load_vehicle


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rough_map", *args], capture_output=True, text=True, timeout=900
    )


def _map_server(yaml_path: Path) -> np.ndarray:
    """The occupancy values (0-100, -1 unknown) map_server gives for a map YAML and its PGM,
    read as map_server reads them (Nav2's modes), rows from the image's bottom (the origin)."""
    meta = yaml.safe_load(yaml_path.read_text(encoding="utf-8"))
    data = (yaml_path.parent / meta["image"]).read_bytes()
    magic, size, maxval, body = data.split(b"\n", 3)
    assert magic == b"P5" and maxval == b"255"
    width, height = (int(v) for v in size.split())
    pixels = np.frombuffer(body, dtype=np.uint8, count=width * height).reshape(height, width)
    pixels = pixels[::-1].astype(float)
    if meta["negate"]:
        pixels = 255 - pixels
    if meta["mode"] == "raw":
        return np.where(pixels > 100, -1, pixels).astype(np.int8)
    p = (255 - pixels) / 255
    occ = np.full(p.shape, -1, dtype=np.int8)
    occ[p > meta["occupied_thresh"]] = 100
    occ[p < meta["free_thresh"]] = 0
    return occ


@pytest.fixture(scope="module")
def mapped(small_traverse: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("costmap") / "map"
    proc = _run(
        "map", str(small_traverse), "--out", str(out), "--vehicle", "tractor", "--speed", "3",
        "--gridmap-bag", "--no-png", "-q",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out


def _v_max_layer(out: Path) -> tuple[np.ndarray, rasterio.Affine]:
    with rasterio.open(out / "map.tif") as ds:
        band = list(ds.descriptions).index("v_max") + 1
        return ds.read(band, masked=True).filled(np.nan)[::-1].astype(float), ds.transform


def test_the_costmap_loads_as_map_server_loads_it(mapped: Path) -> None:
    meta = yaml.safe_load((mapped / "map_costmap.yaml").read_text())
    assert set(meta) == {
        "image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh", "mode",
    }  # fmt: skip
    v_max, transform = _v_max_layer(mapped)  # rows from the south, as the costmap's
    cost = _map_server(mapped / "map_costmap.yaml")
    assert cost.shape == v_max.shape
    assert meta["resolution"] == pytest.approx(transform.a)
    south = transform.f + transform.e * v_max.shape[0]
    assert meta["origin"] == pytest.approx([transform.c, south, 0.0])
    top = load_vehicle("tractor").limits.top_speed
    known = np.isfinite(v_max)
    assert (cost[~known] == -1).all()  # unknown is unknown, never free
    expected = np.clip(np.rint(100 * (1 - v_max[known] / top)), 0, 100)
    assert np.array_equal(cost[known], expected.astype(np.int8))
    assert known.any() and (cost[known] < 100).any()


def test_the_bag_holds_the_same_costs_as_an_occupancy_grid(mapped: Path) -> None:
    from rosbags.highlevel import AnyReader

    from rough_map.export.gridmap_msg import COSTMAP_TOPIC, grid_map_typestore

    with AnyReader([mapped / "map_gridmap"], default_typestore=grid_map_typestore()) as bag:
        conns = [c for c in bag.connections if c.topic == COSTMAP_TOPIC]
        assert [c.msgtype for c in conns] == ["nav_msgs/msg/OccupancyGrid"]
        (msg,) = [bag.deserialize(raw, c.msgtype) for c, _, raw in bag.messages(conns)]
    cost = _map_server(mapped / "map_costmap.yaml")
    assert (msg.info.height, msg.info.width) == cost.shape
    assert np.array_equal(np.asarray(msg.data).reshape(cost.shape), cost)
    meta = yaml.safe_load((mapped / "map_costmap.yaml").read_text())
    assert msg.info.origin.position.x == pytest.approx(meta["origin"][0])
    assert msg.info.resolution == pytest.approx(meta["resolution"])


def test_the_map_and_its_features_carry_the_speed_advice(mapped: Path) -> None:
    feats = read_features(mapped / "features.csv")
    ok = feats.valid
    top = load_vehicle("tractor").limits.top_speed
    assert ok.any() and np.all((feats["v_max"][ok] > 0) & (feats["v_max"][ok] <= top))
    assert np.all(feats["v_max_95"][ok] <= feats["v_max"][ok] + 1e-9)
    assert np.all(np.isfinite(feats["weighted_acceleration"][ok]))
    assert np.isnan(feats["v_max"][~ok]).all()


def test_trinary_costs_follow_the_thresholds(small_traverse: Path, tmp_path: Path) -> None:
    out = tmp_path / "m"
    proc = _run(
        "map", str(small_traverse), "--out", str(out), "--vehicle", "rover", "--no-png", "-q",
        "--costmap-mode", "trinary", "--lethal-speed", "0.5",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    meta = yaml.safe_load((out / "map_costmap.yaml").read_text())
    assert meta["mode"] == "trinary"
    v_max, _ = _v_max_layer(out)
    occ = _map_server(out / "map_costmap.yaml")
    top = load_vehicle("rover").limits.top_speed
    cost = np.clip(np.rint(100 * (1 - v_max / top)), 0, 100)
    cost[v_max <= 0.5] = 100
    known = np.isfinite(v_max)
    assert (occ[~known] == -1).all()
    assert (occ[known & (cost > 100 * meta["occupied_thresh"] + 0.5)] == 100).all()
    assert (occ[known & (cost < 100 * meta["free_thresh"] - 0.5)] == 0).all()


def test_speed_advice_options_say_what_is_wrong(small_traverse: Path, tmp_path: Path) -> None:
    for args, message in (
        (["--speed", "2"], "--speed gives the responses of a --vehicle"),
        (["--vehicle", "car", "--speed", "99"], "above the car's 36 m/s"),
        (["--vehicle", "hovercraft"], "neither a vehicle file nor a preset"),
    ):
        proc = _run("features", str(small_traverse), "--out", str(tmp_path / "f.csv"), *args)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode != 0 and len(lines) == 1 and message in lines[0], proc.stderr
    proc = _run(
        "map", str(small_traverse), "--out", str(tmp_path / "m"), "--vehicle", "car",
        "--lethal-class", "lava", "--no-png", "-q",
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1, proc.stderr
    assert "--lethal-class 'lava' is not a class of the model" in lines[0]


def test_features_json_names_the_vehicle(small_traverse: Path, tmp_path: Path) -> None:
    out = tmp_path / "f.csv"
    proc = _run("features", str(small_traverse), "--out", str(out), "--vehicle", "car", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["frames"] == len(read_features(out))
    assert "car: v_max median" in proc.stderr


def test_one_cloud_gets_its_speed_advice_and_the_band_it_covers(small_traverse: Path) -> None:
    cloud = sorted((small_traverse / "clouds").iterdir())[0]
    proc = _run("features", str(cloud), "--vehicle", "car", "--speed", "10", "--json")
    assert proc.returncode == 0, proc.stderr
    advice = json.loads(proc.stdout)["speed_advice"]
    assert advice["vehicle"] == "car" and 0 <= advice["v_max_95_m_s"] <= advice["v_max_m_s"]
    at = advice["at_speed"]
    lo, hi = at["band_hz"]  # the band 7-392 rad/m at 10 m/s: 11-625 Hz
    assert lo == pytest.approx(10 * 7.0 / (2 * np.pi), rel=0.05) and hi > 500
    assert at["resonances_outside_band"] == ["body"]  # 1.2 Hz below it, 11 Hz wheel inside
    assert at["weighted_acceleration_m_s2"] > 0 and at["dynamic_load_ratio"] > 0


def test_the_map_at_a_speed_has_the_response_layers(mapped: Path) -> None:
    with rasterio.open(mapped / "map.tif") as ds:
        names = list(ds.descriptions)
        assert {"v_max", "weighted_acceleration", "suspension_travel"} <= set(names)
        acc = ds.read(names.index("weighted_acceleration") + 1, masked=True)
        v = ds.read(names.index("v_max") + 1, masked=True)
    assert np.array_equal(np.ma.getmaskarray(acc), np.ma.getmaskarray(v))
    assert (acc.compressed() > 0).all()


def test_the_maps_95_percent_speed_is_at_most_its_v_max_and_below_it_where_spread(
    mapped: Path,
) -> None:
    """v_max_95 from each cell's sigma_R and sigma_w: never above v_max, below it where the
    cell's R or w has a spread and v_max is under the top speed."""
    with rasterio.open(mapped / "map.tif") as ds:
        names = list(ds.descriptions)
        v = ds.read(names.index("v_max") + 1, masked=True)
        sure = ds.read(names.index("v_max_95") + 1, masked=True)
        spread = ds.read(names.index("sigma_w") + 1, masked=True)
    assert np.array_equal(np.ma.getmaskarray(v), np.ma.getmaskarray(sure))
    assert (sure.compressed() <= v.compressed() + 1e-6).all()
    slowed = (~np.ma.getmaskarray(spread)) & (spread.filled(0) > 0) & (v.filled(0) > 0.01)
    assert slowed.any() and (sure[slowed] < v[slowed]).mean() > 0.9
