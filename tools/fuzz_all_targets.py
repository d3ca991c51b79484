"""Base inputs and fuzz targets of :mod:`fuzz_all`: every reader and entry point of rough_map.

The bases (``fuzz_all_bases.py``) hold one valid input of each kind (a simulated 2 m
traverse, its bags in the three storages, clouds in every format, configs, a features
table, a map folder, the shipped model...). A :class:`Target` names a part of that folder
(the files it copies into each case), which of its files may be mutated and how, and the
call that reads the case. Library targets with hostile arguments (``lib_*``) build their
arguments from the seed instead.
"""

from __future__ import annotations

import random
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import fuzz_all_mutators as mut

ROOT = Path(__file__).resolve().parents[1]
RM = [sys.executable, "-m", "rough_map"]


@dataclass
class Target:
    """One entry point: ``src`` (a file or folder under the bases) is copied to the case
    folder, one of ``mutable`` (paths relative to the copy; "." for ``src`` itself) is
    mutated as ``kinds`` says, and ``call`` reads the copy."""

    name: str
    src: str | None
    mutable: list[str]
    call: Callable[..., Any]
    kinds: dict[str, str] = field(default_factory=dict)


def _traverse(root: Path) -> Any:
    from rough_map.io.traverse import load_traverse
    from rough_map.io.truth import traverse_truth

    t = load_traverse(root)
    t.validate_files()
    traverse_truth(t)
    for i in range(min(len(t.spec.frames), 4)):
        if t.spec.frames[i].cloud is not None:
            t.load_cloud(i)
            t.load_cloud(i, frame="world")
    return t


def _traverse_features(root: Path) -> Any:
    from rough_map.features import traverse_features

    return traverse_features(root)


def _read_cloud(path: Path) -> Any:
    from rough_map.io.pointcloud import read_cloud

    return read_cloud(path)


def _read_las(path: Path) -> Any:
    from rough_map.io.las import read_las

    return read_las(path)


def _calibration(root: Path, rng: random.Random) -> Any:
    from rough_map.config import StereoCalibration
    from rough_map.stereo.rectify import load_calibration

    which = rng.randrange(4)
    if which == 0:
        return StereoCalibration.from_file(root / "stereo_calibration.yaml")
    if which == 1:
        return StereoCalibration.from_camera_info(root / "left.yaml", root / "right.yaml")
    if which == 2:
        return StereoCalibration.from_opencv(root / "opencv.yaml")
    return load_calibration(
        rng.choice(
            (
                [root / "left.yaml", root / "right.yaml"],
                root / "opencv.yaml",
                root / "stereo_calibration.yaml",
            )
        )
    )


def _configs(root: Path, rng: random.Random) -> Any:
    from rough_map.classify.levels import load_roughness_levels
    from rough_map.config import load_mapping
    from rough_map.filter.roughness import load_roughness_smoother
    from rough_map.near_far.settings import load_near_far_settings
    from rough_map.stereo.settings import StereoConfig

    calls = [
        lambda: load_roughness_levels(root / "roughness_levels.yaml"),
        lambda: load_near_far_settings(root / "near_far.yaml"),
        lambda: load_roughness_smoother(root / "roughness_smoothing.yaml"),
        lambda: StereoConfig.from_file(root / "stereo.yaml"),
        lambda: load_mapping(root / rng.choice(("stereo.yaml", "near_far.yaml"))),
    ]
    return [c() for c in calls]


def _world(path: Path) -> Any:
    from rough_map.io.truth import load_world, open_world

    w = open_world(path)
    return load_world(path), w


def _features(root: Path) -> Any:
    from rough_map.features import read_features

    return read_features(root / "features.csv")


def _parquet(path: Path) -> Any:
    from rough_map.features import read_features

    return read_features(path)


def _predict(root: Path) -> Any:
    from rough_map.classify.persistence import load_terrain_model
    from rough_map.features import read_features

    model = load_terrain_model(ROOT / "models" / "default")
    return model.predict(read_features(root / "features.csv"))


def _model(root: Path, rng: random.Random) -> Any:
    from rough_map.classify.persistence import load_terrain_model, read_card

    read_card(root / "default")
    return load_terrain_model(root / "default", verify=rng.random() < 0.5)


def _truth(path: Path) -> Any:
    from rough_map.io.truth_raster import read_class_names

    return read_class_names(path)


def _map_dir(root: Path) -> Any:
    from rough_map.evaluation.score_files import read_map_dir
    from rough_map.map.state import iter_state_tiles, read_state_meta

    state = root / "map_state.npz"
    meta = read_state_meta(state) if state.exists() else None
    tiles = list(iter_state_tiles(state, 128)) if state.exists() else None
    return read_map_dir(root), meta, tiles


def _gridmap(root: Path) -> Any:
    from rough_map.export.gridmap_msg import read_gridmap_bag

    bags = [p for p in root.iterdir() if p.is_dir()] or [root]
    return [read_gridmap_bag(b) for b in bags]


def _bag(path: Path) -> Any:
    from rough_map.io.rosbag.importer import import_bag
    from rough_map.io.rosbag.reader import inspect_bag

    info = inspect_bag(path)
    t = import_bag(path, path.parent / "imported", "/points", "/odom", imu_topic="/imu")
    return info, t


def _kitti(path: Path) -> Any:
    from rough_map.io.pointcloud import read_kitti_poses

    return read_kitti_poses(path)


def _image(path: Path) -> Any:
    from rough_map.io.images import read_image
    from rough_map.near_far.tiles import read_bgr

    return read_image(path), read_bgr(path)


# --------------------------------------------------------------------------- library targets


def _lib_psd(_: Path, rng: random.Random) -> Any:
    import numpy as np

    from rough_map import psd

    good = np.random.default_rng(rng.getrandbits(32)).normal(0, 1e-3, (64, 112))
    heights = mut.hostile_array(rng, good) if rng.random() < 0.7 else good
    kw: dict[str, Any] = {}
    for name, make in (
        (
            "window",
            lambda: rng.choice(("hann", "", "boxcar", "kaiser", "bogus", None, 3, ("tukey", 0.5))),
        ),
        ("nperseg", lambda: mut.hostile_int(rng, 32)),
        ("noverlap", lambda: mut.hostile_int(rng, 16)),
        ("noise_psd", lambda: mut.hostile_scalar(rng, 1e-9)),
        ("max_gap", lambda: mut.hostile_scalar(rng, 0.05)),
        ("max_gap_fraction", lambda: mut.hostile_scalar(rng, 0.2)),
        ("omega0", lambda: mut.hostile_scalar(rng, 1.0)),
        ("waviness", lambda: mut.hostile_scalar(rng, 2.0)),
        ("min_profiles", lambda: mut.hostile_int(rng, 3)),
        ("method", lambda: rng.choice(("unbiased", "paper", "x", None))),
        ("gridding", lambda: rng.choice(("point", "cell", "", None))),
    ):
        if rng.random() < 0.3:
            kw[name] = make()
    spacing = mut.hostile_scalar(rng, 0.008) if rng.random() < 0.4 else 0.008
    fn = rng.choice(("patch_roughness", "profile_psd", "fill_gaps", "patch_roughness_batch"))
    if fn == "fill_gaps":
        kw = {k: v for k, v in kw.items() if k in ("max_gap", "max_gap_fraction")}
    elif fn == "profile_psd":
        kw = {
            k: v
            for k, v in kw.items()
            if k in ("window", "nperseg", "noverlap", "max_gap", "max_gap_fraction")
        }
    elif fn == "patch_roughness_batch" and isinstance(heights, np.ndarray) and heights.ndim == 2:
        heights = np.stack([heights, heights])
    return getattr(psd, fn)(heights, spacing, **kw)


def _lib_patch(_: Path, rng: random.Random) -> Any:
    import numpy as np

    from rough_map import patch
    from rough_map.features import cloud_roughness, frame_features

    g = np.random.default_rng(rng.getrandbits(32))
    good = np.column_stack(
        [g.uniform(0.55, 1.45, 6000), g.uniform(-0.45, 0.45, 6000), g.normal(0, 2e-3, 6000)]
    )
    points = mut.hostile_array(rng, good) if rng.random() < 0.7 else good
    try:
        spec = patch.PatchSpec(
            ahead=mut.hostile_scalar(rng, 1.0) if rng.random() < 0.2 else 1.0,
            size=mut.hostile_scalar(rng, 0.896) if rng.random() < 0.2 else 0.896,
            spacing=mut.hostile_scalar(rng, 0.008) if rng.random() < 0.2 else 0.016,
            lateral=mut.hostile_scalar(rng, 0.0) if rng.random() < 0.1 else 0.0,
        )
    except Exception:
        raise
    roll = mut.hostile_scalar(rng, 0.01) if rng.random() < 0.3 else None
    pitch = mut.hostile_scalar(rng, 0.01) if rng.random() < 0.3 else None
    min_points = mut.hostile_int(rng, 100) if rng.random() < 0.2 else 100
    fn = rng.randrange(8)
    if fn == 0:
        return patch.extract_patch(points, spec, roll=roll, pitch=pitch, min_points=min_points)
    if fn == 1:
        return patch.grid_points(points, spec, roll=roll, pitch=pitch, min_points=min_points)
    if fn == 2:
        return patch.points_in_patch(points, spec)
    if fn == 3:
        return patch.compensate_tilt(
            points, mut.hostile_scalar(rng, 0.01), mut.hostile_scalar(rng, 0.01)
        )
    if fn == 4:
        return patch.check_points(points)
    if fn == 5:
        return patch.auto_spacing(mut.hostile_int(rng, 5000), spec)
    if fn == 6:
        return cloud_roughness(points, spec, roll=roll, pitch=pitch, min_points=min_points)
    return frame_features(points, spec, roll=roll, pitch=pitch, min_points=min_points)


# --------------------------------------------------------------------------- the targets


def _file(fn: Callable[[Path], Any]) -> Callable[[Path, random.Random], Any]:
    return lambda root, rng: fn(root)


def targets(bases: Path) -> list[Target]:
    """Every target whose base exists under ``bases``."""
    out: list[Target] = []
    kinds = {
        ".npy": "npy",
        ".npz": "zip",
        ".csv": "text",
        ".xyz": "text",
        ".txt": "text",
        ".ply": "header",
        ".pcd": "header",
        ".las": "las",
        ".laz": "las",
        ".json": "json",
        ".yaml": "yaml",
        ".png": "png",
        ".skops": "zip",
    }
    for p in sorted((bases / "clouds").glob("*")):
        out.append(
            Target(
                f"read_cloud{p.suffix}" + ("_ascii" if p.stem == "ascii" else ""),
                f"clouds/{p.name}",
                ["."],
                _file(_read_cloud),
                {".": kinds.get(p.suffix, "bytes")},
            )
        )
    for suffix in (".las", ".laz"):
        if (bases / "clouds" / f"cloud{suffix}").exists():
            out.append(
                Target(
                    f"read_las{suffix}",
                    f"clouds/cloud{suffix}",
                    ["."],
                    _file(_read_las),
                    {".": "las"},
                )
            )
    out += [
        Target("read_kitti_poses", "poses.txt", ["."], _file(_kitti), {".": "text"}),
        Target("read_image.png", "image.png", ["."], _file(_image), {".": "png"}),
        Target("read_image.jpg", "image.jpg", ["."], _file(_image)),
        Target(
            "load_traverse",
            "trav",
            [
                "traverse.json",
                "traverse.json",
                "traverse.json",
                "clouds/000000.npy",
                "world_truth.npz",
            ],
            _file(_traverse),
            {"traverse.json": "json", "clouds/000000.npy": "npy", "world_truth.npz": "zip"},
        ),
        Target(
            "load_traverse_yaml",
            "trav_yaml",
            ["traverse.yaml", "traverse.yaml", "clouds/000000.npy"],
            _file(_traverse),
            {"traverse.yaml": "yaml", "clouds/000000.npy": "npy"},
        ),
        Target(
            "traverse_features",
            "trav",
            ["traverse.json", "clouds/000001.npy"],
            _file(_traverse_features),
            {"traverse.json": "json", "clouds/000001.npy": "npy"},
        ),
        Target(
            "calibration",
            "configs",
            ["stereo_calibration.yaml", "left.yaml", "right.yaml", "opencv.yaml"],
            _calibration,
            {
                k: "yaml"
                for k in ("stereo_calibration.yaml", "left.yaml", "right.yaml", "opencv.yaml")
            },
        ),
        Target(
            "config_files",
            "configs",
            ["roughness_levels.yaml", "near_far.yaml", "roughness_smoothing.yaml", "stereo.yaml"],
            _configs,
            {
                k: "yaml"
                for k in (
                    "roughness_levels.yaml",
                    "near_far.yaml",
                    "roughness_smoothing.yaml",
                    "stereo.yaml",
                )
            },
        ),
        Target("load_world", "world.npz", ["."], _file(_world), {".": "zip"}),
        Target(
            "read_features",
            "features",
            ["features.csv", "features.csv.json"],
            _file(_features),
            {"features.csv": "text", "features.csv.json": "json"},
        ),
        Target("read_features.parquet", "features/features.parquet", ["."], _file(_parquet)),
        Target(
            "model_predict",
            "features8",
            ["features.csv", "features.csv.json"],
            _file(_predict),
            {"features.csv": "text", "features.csv.json": "json"},
        ),
        Target(
            "load_terrain_model",
            "model",
            ["default.skops", "default.card.json"],
            _model,
            {"default.skops": "zip", "default.card.json": "json"},
        ),
        Target("read_class_names", "truth.tif", ["."], _file(_truth)),
        Target("read_map_dir", "map", _map_files(bases), _file(_map_dir), {"map_state.npz": "zip"}),
        Target(
            "read_gridmap_bag",
            "map",
            _gridmap_files(bases),
            _file(_gridmap),
            {f: "yaml" for f in _gridmap_files(bases) if f.endswith(".yaml")},
        ),
        Target("lib_psd", None, [], _lib_psd),
        Target("lib_patch", None, [], _lib_patch),
    ]
    for name in ("mcap", "sqlite3", "ros1.bag"):
        src = bases / "bags" / name
        if not src.exists():
            continue
        files = (
            ["."]
            if src.is_file()
            else [p.relative_to(src).as_posix() for p in sorted(src.iterdir())]
        )
        main = [f for f in files if not f.endswith(".yaml")]
        out.append(
            Target(
                f"bag_{name.split('.')[0]}",
                f"bags/{name}",
                main * 3 + files,
                _file(_bag),
                {f: "yaml" for f in files if f.endswith(".yaml")},
            )
        )
    return [t for t in out if t.src is None or (bases / t.src).exists()]


def _map_files(bases: Path) -> list[str]:
    root = bases / "map"
    if not root.exists():
        return []
    return [
        p.name
        for p in sorted(root.iterdir())
        if p.is_file() and p.suffix in (".tif", ".npz", ".json", ".csv")
    ]


def _gridmap_files(bases: Path) -> list[str]:
    root = bases / "map"
    if not root.exists():
        return []
    return [
        p.relative_to(root).as_posix() for d in root.iterdir() if d.is_dir() for p in d.iterdir()
    ]


# --------------------------------------------------------------------------- CLI sample


def cli_cases(bases: Path) -> list[tuple[str, str, list[str], str]]:
    """``(name, src, argv, mutable)``: ``{case}`` in argv is the case copy of ``src``, ``{out}``
    a fresh output path; ``mutable`` the file of the copy that is mutated."""
    rm = ["features", "{case}"]
    return [
        ("cli_features_cloud", "cli/cloud.ply", rm, "."),
        ("cli_features_cloud_npy", "trav/clouds/000000.npy", rm, "."),
        (
            "cli_features_traverse",
            "trav",
            ["features", "{case}", "--out", "{out}/f.csv"],
            "traverse.json",
        ),
        ("cli_map", "trav", ["map", "{case}", "--out", "{out}", "--no-png"], "traverse.json"),
        ("cli_inspect", "bags/ros1.bag", ["inspect", "{case}"], "."),
        (
            "cli_import",
            "bags/mcap",
            [
                "import",
                "{case}",
                "--points-topic",
                "/points",
                "--odom-topic",
                "/odom",
                "--out",
                "{out}",
            ],
            "mcap.mcap",
        ),
        (
            "cli_classify",
            "model",
            [
                "classify",
                str(bases / "trav"),
                "--model",
                "{case}/default",
                "--out",
                "{out}/labels.csv",
            ],
            "default.skops",
        ),
        ("cli_score", "truth.tif", ["score", str(bases / "map"), "--truth", "{case}"], "."),
        (
            "cli_stereo",
            "stereo",
            [
                "stereo",
                "{case}/left.png",
                "{case}/right.png",
                "--calib",
                "{case}/calib.yaml",
                "--out",
                "{out}/p.ply",
            ],
            "calib.yaml",
        ),
    ]
