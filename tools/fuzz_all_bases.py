"""Base inputs of :mod:`fuzz_all`: one valid input of every kind rough_map reads.

:func:`build_bases` writes, into one folder (about 40 s, 7 MB): a simulated 2 m traverse
(3 frames of 4000 points, a small world), its bag in ROS 1, ROS 2 sqlite3 and MCAP storage,
a cloud in every format, a KITTI poses file, images, a quarter-size stereo pair with its
calibration, the shipped configs plus CameraInfo and OpenCV calibrations, features tables
(at the traverse's spacing and at the model's 8 mm), a map folder with its state and
grid_map bag, and the shipped model.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RM = [sys.executable, "-m", "rough_map"]


def _run(argv: list[str]) -> None:
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, cwd=ROOT)


def build_bases(out: Path) -> None:
    """Write every base input under ``out`` (about 30 s, 6 MB)."""
    import numpy as np

    from rough_map.io.las import write_las
    from rough_map.io.pointcloud import write_cloud
    from rough_map.io.rosbag.example import write_example_bag
    from rough_map.io.truth import load_world, save_world
    from rough_map.types import HeightField

    out.mkdir(parents=True, exist_ok=True)
    sim = out / "sim"
    _run(
        [
            *RM,
            "-q",
            "simulate",
            "--out",
            str(sim),
            "--course",
            "mixed",
            "--length",
            "2",
            "--image-every",
            "2",
            "--points-per-cell",
            "2",
            "--seed",
            "1",
        ]
    )
    # The traverse: 3 frames of 4000 points each, no images, a small world.
    trav = out / "trav"
    (trav / "clouds").mkdir(parents=True)
    spec = json.loads((sim / "traverse.json").read_text())
    rng = np.random.default_rng(0)
    for f in spec["frames"]:
        pts = np.load(sim / f["cloud"])
        np.save(trav / f["cloud"], pts[rng.choice(len(pts), 4000, replace=False)])
        f.pop("left", None)
        f.pop("right", None)
    world = load_world(sim / "world_truth.npz")
    ny, nx = world.heights.shape
    small = HeightField(
        world.heights[: ny : max(1, ny // 60), : nx : max(1, nx // 60)],
        world.spacing * max(1, nx // 60),
        world.origin,
        None
        if world.classes is None
        else world.classes[: ny : max(1, ny // 60), : nx : max(1, nx // 60)],
        world.class_names,
    )
    save_world(small, trav / "world_truth.npz")
    (trav / "traverse.json").write_text(json.dumps(spec, indent=1))
    import yaml

    shutil.copytree(trav, out / "trav_yaml")
    (out / "trav_yaml" / "traverse.json").unlink()
    (out / "trav_yaml" / "traverse.yaml").write_text(yaml.safe_dump(spec))
    shutil.copy(sim / "world_truth.tif", out / "truth.tif")
    shutil.copy(trav / "world_truth.npz", out / "world.npz")
    # Clouds in every format.
    pts = np.load(trav / "clouds" / "000000.npy").astype(np.float64)[:1500]
    clouds = out / "clouds"
    clouds.mkdir()
    for suffix in (".npy", ".csv", ".xyz", ".txt", ".ply", ".pcd"):
        write_cloud(clouds / f"cloud{suffix}", pts)
    np.savez(clouds / "cloud.npz", points=pts)
    write_las(clouds / "cloud.las", pts)
    try:
        write_las(clouds / "cloud.laz", pts)
    except Exception as err:  # no LAZ backend
        print(f"no cloud.laz: {err}", file=sys.stderr)
    np.column_stack([pts, np.ones(len(pts))]).astype("<f4").tofile(clouds / "cloud.bin")
    (out / "cli").mkdir()  # dense enough for `rough-map features CLOUD`
    write_cloud(out / "cli" / "cloud.ply", np.load(trav / "clouds" / "000000.npy"))
    ply = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(pts[:300])}",
        "property float x",
        "property float y",
        "property float z",
        "end_header",
    ]
    ply += [f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in pts[:300]]
    (clouds / "ascii.ply").write_text("\n".join(ply) + "\n")
    poses = np.tile(np.eye(4)[:3].reshape(1, 12), (20, 1))
    poses[:, 3] = np.arange(20) * 0.5
    np.savetxt(out / "poses.txt", poses)
    # Images.
    import cv2

    img = np.asarray(cv2.imread(str(sim / "left" / "000000.png")))
    small_img = cv2.resize(img, (64, 48))
    cv2.imwrite(str(out / "image.png"), small_img)
    cv2.imwrite(str(out / "image.jpg"), small_img)
    # Stereo at a quarter size, with a calibration scaled to it.
    stereo = out / "stereo"
    stereo.mkdir()
    for side in ("left", "right"):
        im = np.asarray(cv2.imread(str(sim / side / "000000.png")))
        cv2.imwrite(str(stereo / f"{side}.png"), cv2.resize(im, (320, 240)))
    cal = dict(spec["calibration"])
    for k in ("fx", "fy", "cx", "cy"):
        cal[k] = cal[k] / 4
    cal["width"], cal["height"] = 320, 240
    (stereo / "calib.yaml").write_text(yaml.safe_dump(cal))
    # Configs and calibration files.
    configs = out / "configs"
    shutil.copytree(ROOT / "configs", configs)
    shutil.copy(ROOT / "tests" / "data" / "middlebury_motorcycle_left.yaml", configs / "left.yaml")
    shutil.copy(
        ROOT / "tests" / "data" / "middlebury_motorcycle_right.yaml", configs / "right.yaml"
    )
    f, b = 985.0, 0.24
    m = f"[{f}, 0., 639.5, 0., {f}, 479.5, 0., 0., 1.]"

    def mat(rows: int, cols: int, data: str) -> str:
        return f"!!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: {data}\n"

    (configs / "opencv.yaml").write_text(
        "%YAML:1.0\n---\n" + f"M1: {mat(3, 3, m)}D1: {mat(1, 5, '[0., 0., 0., 0., 0.]')}"
        f"M2: {mat(3, 3, m)}D2: {mat(1, 5, '[0., 0., 0., 0., 0.]')}"
        f"R: {mat(3, 3, '[1., 0., 0., 0., 1., 0., 0., 0., 1.]')}T: {mat(3, 1, f'[{-b}, 0., 0.]')}"
    )
    # Bags.
    bags = out / "bags"
    bags.mkdir()
    for storage, name in (("mcap", "mcap"), ("sqlite3", "sqlite3"), ("ros1", "ros1.bag")):
        write_example_bag(trav, bags / name, storage=storage)
    # Features table, map folder (with state and grid_map bag), model.
    (out / "features").mkdir()
    _run([*RM, "-q", "features", str(trav), "--out", str(out / "features" / "features.csv")])
    _run([*RM, "-q", "map", str(trav), "--out", str(out / "map"), "--state", "--gridmap-bag"])
    from rough_map.features import read_features, write_features

    table = read_features(out / "features" / "features.csv")
    write_features(table, out / "features" / "features.parquet")
    # At the shipped model's patch (8 mm), from the full clouds, for the model's predict.
    (out / "features8").mkdir()
    _run(
        [
            *RM,
            "-q",
            "features",
            str(sim),
            "--spacing",
            "0.008",
            "--points-from",
            "cloud",
            "--out",
            str(out / "features8" / "features.csv"),
        ]
    )
    shutil.copytree(ROOT / "models", out / "model")
    shutil.rmtree(sim)
    (out / "DONE").write_text("ok\n")
