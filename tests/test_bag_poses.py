"""rough-map import with poses from PoseStamped, /tf or NavSatFix, and a CRS or an origin."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rough_map.cli.main import main
from rough_map.errors import FileFormatError, InputError
from rough_map.io.rosbag import (
    POINTCLOUD2,
    TF_MESSAGE,
    import_bag,
    odometry_message,
    pointcloud2_message,
    ros_typestore,
    tf_message,
    write_bag,
)
from rough_map.io.rosbag.poses import NAVSATFIX, POSE_STAMPED, POSE_WITH_COVARIANCE
from rough_map.io.traverse import load_traverse

T0 = 1_700_000_000 * 10**9
SPEED = np.array([1.0, 0.5, 0.0])  # m/s
YAW = math.atan2(0.5, 1.0)  # heading of the straight drive, rad
CLOUD_TIMES = [0.25, 0.75, 1.25]
STORE = ros_typestore()


def _ns(t: float) -> int:
    return T0 + round(t * 1e9)


def _clouds() -> list[tuple[str, str, int, Any]]:
    rng = np.random.default_rng(0)
    return [("/points", POINTCLOUD2, _ns(t), pointcloud2_message(
        STORE, rng.uniform(-3, 3, (10, 3)), _ns(t), "base_link")) for t in CLOUD_TIMES]  # fmt: skip


def _pose(t: float, *, covariance: bool = False) -> Any:
    odo = odometry_message(STORE, _ns(t), SPEED * t, [0.0, 0.0, YAW], frame_id="map")
    if covariance:
        return STORE.types[POSE_WITH_COVARIANCE](header=odo.header, pose=odo.pose)
    return STORE.types[POSE_STAMPED](header=odo.header, pose=odo.pose.pose)


@pytest.mark.parametrize("covariance", [False, True])
def test_poses_from_a_pose_topic(tmp_path: Path, covariance: bool) -> None:
    kind = POSE_WITH_COVARIANCE if covariance else POSE_STAMPED
    msgs = [("/pose", kind, _ns(i * 0.1), _pose(i * 0.1, covariance=covariance)) for i in range(21)]
    bag = write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")
    trav = import_bag(bag, tmp_path / "out", "/points", "/pose")
    assert len(trav) == 3
    for t, frame in zip(CLOUD_TIMES, trav.frames, strict=True):
        np.testing.assert_allclose([frame.pose.x, frame.pose.y], SPEED[:2] * t, atol=1e-9)
        assert frame.pose.yaw == pytest.approx(YAW, abs=1e-9)
    assert trav.spec.metadata["source"]["world_frame"] == "map"


def test_poses_from_the_tf_tree(tmp_path: Path) -> None:
    """map -> odom (fixed offset, 2 Hz) -> base_link (moving, 10 Hz): the chain, composed."""
    offset = np.array([10.0, -5.0, 0.0])

    def tf(t: float, parent: str, child: str, xyz: Any, yaw: float) -> Any:
        return (
            "/tf",
            TF_MESSAGE,
            _ns(t),
            tf_message(STORE, _ns(t), parent, child, xyz, [0, 0, yaw]),
        )

    msgs = [tf(i * 0.5, "map", "odom", offset, 0.3) for i in range(5)]
    msgs += [tf(i * 0.1, "odom", "base_link", SPEED * i * 0.1, YAW) for i in range(21)]
    bag = write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")
    trav = import_bag(bag, tmp_path / "out", "/points", "/tf")
    rot = Rotation.from_euler("z", 0.3)
    for t, frame in zip(CLOUD_TIMES, trav.frames, strict=True):
        expect = offset + rot.apply(SPEED * t)
        np.testing.assert_allclose([frame.pose.x, frame.pose.y], expect[:2], atol=1e-9)
        assert frame.pose.yaw == pytest.approx(0.3 + YAW, abs=1e-9)
    assert trav.spec.metadata["source"]["world_frame"] == "map"
    with pytest.raises(FileFormatError, match="no transform to the vehicle frame 'chassis'"):
        import_bag(bag, tmp_path / "other", "/points", "/tf", vehicle_frame="chassis")


def _fix(t: float, lat: float, lon: float, status: int = 0) -> Any:
    t_ = STORE.types
    header = odometry_message(STORE, _ns(t), [0, 0, 0], [0, 0, 0], frame_id="gps").header
    return t_[NAVSATFIX](
        header=header,
        status=t_["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
        latitude=lat, longitude=lon, altitude=50.0,
        position_covariance=np.zeros(9), position_covariance_type=0,
    )  # fmt: skip


def _gnss_bag(tmp_path: Path) -> Path:
    """A drive north-east at 1.118 m/s from 45 N, 9 E, GNSS at 10 Hz, one fix without a fix."""
    m_per_deg_lat = 111_132.0
    m_per_deg_lon = 111_320.0 * math.cos(math.radians(45.0))
    msgs = []
    for i in range(21):
        t = i * 0.1
        east, north = SPEED[:2] * t
        msgs.append(("/fix", NAVSATFIX, _ns(t), _fix(t, 45.0 + north / m_per_deg_lat,
                                                      9.0 + east / m_per_deg_lon)))  # fmt: skip
    msgs.append(("/fix", NAVSATFIX, _ns(1.05), _fix(1.05, 0.0, 0.0, status=-1)))
    return write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")


def test_poses_from_gnss_in_a_local_frame_at_the_first_fix(tmp_path: Path, caplog) -> None:
    trav = import_bag(_gnss_bag(tmp_path), tmp_path / "out", "/points", "/fix")
    crs = trav.spec.crs
    assert crs.code == "local" and crs.origin is not None
    assert (crs.origin.lat, crs.origin.lon) == pytest.approx((45.0, 9.0))
    assert "1 NavSatFix messages on /fix without a fix skipped" in caplog.text
    for t, frame in zip(CLOUD_TIMES, trav.frames, strict=True):
        np.testing.assert_allclose([frame.pose.x, frame.pose.y], SPEED[:2] * t, atol=0.01)
        assert frame.pose.yaw == pytest.approx(YAW, abs=0.01)  # the direction of travel


def test_poses_from_gnss_in_utm(tmp_path: Path) -> None:
    out = tmp_path / "out"
    code = main(["-q", "import", str(_gnss_bag(tmp_path)), "--points-topic", "/points",
                 "--pose-topic", "/fix", "--crs", "EPSG:32632", "--out", str(out)])  # fmt: skip
    assert code == 0
    trav = load_traverse(out)
    assert trav.spec.crs.code == "EPSG:32632"
    x0, y0 = trav.frames[0].pose.x, trav.frames[0].pose.y
    assert 400_000 < x0 < 600_000 and 4_900_000 < y0 < 5_100_000  # 45 N, 9 E in zone 32
    dx, dy = trav.frames[2].pose.x - x0, trav.frames[2].pose.y - y0
    assert math.hypot(dx, dy) == pytest.approx(1.118, rel=0.01)  # 1 s of driving


def test_an_origin_georeferences_odometry(tmp_path: Path) -> None:
    msgs = [("/odom", "nav_msgs/msg/Odometry", _ns(i * 0.1), odometry_message(
        STORE, _ns(i * 0.1), SPEED * i * 0.1, [0, 0, YAW])) for i in range(21)]  # fmt: skip
    bag = write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")
    out = tmp_path / "out"
    assert main(["-q", "import", str(bag), "--points-topic", "/points", "--odom-topic",
                 "/odom", "--origin", "40.35,18.17,12", "--out", str(out)]) == 0  # fmt: skip
    crs = load_traverse(out).spec.crs
    assert crs.origin is not None and (crs.origin.lat, crs.origin.lon, crs.origin.alt) == (
        40.35, 18.17, 12.0)  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--origin", "95,0"], "out of range"),
        (["--origin", "north"], "LAT,LON"),
        (["--crs", "UTM33"], "'local' or EPSG"),
        (["--crs", "EPSG:32633", "--origin", "40,18"], "--origin places a local frame"),
        (["--crs", "EPSG:4326"], "not a projected CRS in metres"),
        (["--pose-topic", "/points"], "not a pose topic: '/points' carries"),
    ],
)
def test_bad_crs_origin_and_pose_topics(tmp_path: Path, capsys, args, message) -> None:
    bag = _gnss_bag(tmp_path)
    base = ["import", str(bag), "--points-topic", "/points", "--out", str(tmp_path / "o")]
    if "--pose-topic" not in args:
        base += ["--pose-topic", "/fix"]
    code = main([*base, *args])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_a_geographic_crs_is_refused_for_any_pose_source(tmp_path: Path) -> None:
    msgs = [("/pose", POSE_STAMPED, _ns(i * 0.1), _pose(i * 0.1)) for i in range(21)]
    bag = write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")
    with pytest.raises(InputError, match="not a projected CRS in metres"):
        import_bag(bag, tmp_path / "out", "/points", "/pose", crs="EPSG:4326")


def test_import_replaces_its_outputs_as_a_set(tmp_path: Path, capsys) -> None:
    """One --out rule: an existing folder has the traverse replaced, the user's files kept,
    the clouds of the old run that this one does not write dropped."""
    msgs = [("/pose", POSE_STAMPED, _ns(i * 0.1), _pose(i * 0.1)) for i in range(21)]
    bag = write_bag(tmp_path / "bag", sorted(msgs + _clouds(), key=lambda m: m[2]), "mcap")
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    args = ["import", str(bag), "--points-topic", "/points", "--pose-topic", "/pose",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    assert main([*args, "--every", "2"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == str(out / "traverse.json")
    assert (out / "notes.txt").read_text() == "mine"
    assert len(load_traverse(out)) == 2 and len(list((out / "clouds").iterdir())) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "run"]  # no staging left
