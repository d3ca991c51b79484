"""Near-to-far on simulated traverses: far-field accuracy by distance, area covered, speed.

Run ``python benchmarks/bench_near_far.py --traverse DIR [DIR ...]`` on traverse folders with
colour images and a ``world_truth.npz`` (``rough-map simulate --out DIR --course mixed
--length 12 --image-every 2 --seed 1``), or ``--simulate mixed`` to simulate one into a
temporary folder first (3-10 s a frame). The frames' true labels stand in for the geometric
classifier's near-field labels (``--flip 0.2`` replaces a share of them with another class
present on the course).

For each traverse it prints

* the accuracy table of :func:`rough_map.evaluation.near_far.far_field_accuracy`
  (predictions made with the model learnt from the earlier frames only), at ``--threshold``;
* the ground area (0.1 m grid, cells of the world only) covered by the near-field patches
  (the default extraction's patch, 0.552-1.448 m ahead),
  by near + confident far cells, and by near + every far cell in view (the ceiling the camera
  allows): the camera sees the ground from about 1.5 to 4 m ahead and the simulator's
  world is a 4 m wide strip (``--width``), which caps the ratio at about 4 when every
  frame or every second frame has images (a 36 m mixed course, seed 41, every second
  image: x3.9 at a far-field accuracy of 0.999, ceiling x4.05);
* baselines measured in the same run: the same model without the unfamiliarity gate and
  recall (``novelty_alpha=0, recall=False, min_support=1, min_confidence=0``: every far cell
  in view gets the nearest learnt class), and a tile-level comparison of this module's
  colour features with colour + texture features (uniform LBP histogram, P=8, R=1, and
  the mean gradient magnitude), both in a plain online Gaussian naive Bayes, on far tiles
  of classes already learnt;
* the time per frame: reading the image, tile features, predict, update (wall clock, the
  median over frames; the load average is printed because other processes slow it down).

``--photos`` instead runs :func:`rough_map.near_far.run_traverse` (labels settled over
3 frames) on flat worlds textured with scikit-image's CC0 ground photographs
(:mod:`rough_map.simulate.photo_ground`; brick, gravel, grass, moon), in colour and in grey,
with near labels lagging a change of ground by two frames and one wrong frame mid-way
(``tests/test_near_far_photos.py``), and prints per world the far-field accuracy over the
cells it labels, the share of cells in view it abstained on, and on the path band its
accuracy and that of the nearest-near-field-cell baseline on the same cells.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from rough_map import near_far as nf
from rough_map.evaluation.near_far import area_coverage, far_field_accuracy, world_class
from rough_map.geometry import pose_matrix
from rough_map.io.traverse import Traverse, load_traverse
from rough_map.io.truth import TRUTH_FILE, load_world
from rough_map.patch import Extraction
from rough_map.simulate.world import CLASS_NAMES
from rough_map.types import HeightField

#: The near field the labels describe: the patch of a model trained with the default
#: extraction.
PATCH = Extraction()


def simulate(course: str, length: float, image_every: int, seed: int, width: float) -> Path:
    """Simulate a traverse into a temporary folder; ``width`` (m) of the world strip."""
    from rough_map.simulate.course import simulate as simulate_course

    out = Path(tempfile.mkdtemp(prefix=f"near_far_{course}_")) / "traverse"
    simulate_course(
        out,
        course,
        length=length,
        image_every=image_every,
        seed=seed,
        world_spacing=0.004,
        width=width,
    )
    return out


def noisy_labels(labels: list[str | None], share: float, seed: int) -> list[str | None]:
    """Replace ``share`` of the labels by another class present on the course."""
    rng = np.random.default_rng(seed)
    present = sorted({x for x in labels if x is not None})
    out = []
    for label in labels:
        if label is not None and len(present) > 1 and rng.random() < share:
            label = str(rng.choice([c for c in present if c != label]))
        out.append(label)
    return out


def run(traverse: Traverse, labels: list[str | None], **kwargs: object) -> tuple[list, dict]:
    """run_traverse with a timing breakdown (s per frame, medians)."""
    calib = traverse.spec.calibration
    model = nf.NearToFar(CLASS_NAMES, PATCH, **kwargs)  # type: ignore[arg-type]
    times: dict[str, list[float]] = {"read": [], "features": [], "predict": [], "update": []}
    out = []
    for i, frame in enumerate(traverse.frames):
        if frame.left is None:
            continue
        t0 = time.perf_counter()
        image = cv2.imread(str(traverse.resolve(frame.left)), cv2.IMREAD_COLOR)
        t1 = time.perf_counter()
        tiles = nf.tile_features(image, model.tile_px)
        t2 = time.perf_counter()
        if hasattr(model, "looks_"):
            out.append(model.predict_tiles(tiles, calib, frame.pose, t=frame.t, frame=i))
            times["predict"].append(time.perf_counter() - t2)
        t3 = time.perf_counter()
        if labels[i] is not None:
            model.update_tiles(tiles, calib, labels[i], frame.pose)
            times["update"].append(time.perf_counter() - t3)
        times["read"].append(t1 - t0)
        times["features"].append(t2 - t1)
    return out, {k: statistics.median(v) for k, v in times.items() if v}


def texture_baseline(traverse: Traverse, world: HeightField, labels: list[str | None]) -> None:
    """Tile-level accuracy by distance: colour features against colour + texture features."""
    from skimage.feature import local_binary_pattern
    from sklearn.naive_bayes import GaussianNB

    calib = traverse.spec.calibration
    model = nf.NearToFar(CLASS_NAMES, PATCH)
    geometry = model.tile_geometry(calib)  # the same tiles as the model
    n_tiles = geometry.n_rows * geometry.n_cols
    edges = np.array([0.0, 1.5, 2.0, 3.0, 4.0])
    sets = {"colour (this module)": None, "colour + LBP + gradient": None}
    models = {name: GaussianNB() for name in sets}
    hits = {name: np.zeros(len(edges) - 1) for name in sets}
    count = np.zeros(len(edges) - 1)
    seen: set[int] = set()
    near = model.near_tiles(calib)
    for i, frame in enumerate(traverse.frames):
        if frame.left is None or labels[i] is None:
            continue
        image = cv2.imread(str(traverse.resolve(frame.left)), cv2.IMREAD_COLOR)
        colour = nf.tile_features(image, model.tile_px)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        codes = local_binary_pattern(gray, 8, 1, "uniform").astype(np.int64)
        t = model.tile_px
        codes = codes[: geometry.n_rows * t, : geometry.n_cols * t]
        tile_index = (np.arange(codes.shape[0]) // t)[:, None] * geometry.n_cols + (
            np.arange(codes.shape[1]) // t
        )[None, :]
        lbp = np.bincount((tile_index * 10 + codes).ravel(), minlength=n_tiles * 10)
        lbp = lbp.reshape(n_tiles, 10) / (t * t)
        grad = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
        grad = grad[: geometry.n_rows * t, : geometry.n_cols * t]
        grad = grad.reshape(geometry.n_rows, t, geometry.n_cols, t).mean(axis=(1, 3))
        texture = np.column_stack([colour, lbp, np.log(grad.reshape(-1, 1) + 1e-3)])
        features = {"colour (this module)": colour, "colour + LBP + gradient": texture}
        transform = pose_matrix(frame.pose)
        ground = geometry.ground @ transform[:3, :3].T + transform[:3, 3]
        ok = np.isfinite(geometry.distance)
        truth = np.full(n_tiles, -1)
        truth[ok] = world_class(world, ground[ok, 0], ground[ok, 1])
        evaluate = ok & ~near & (truth >= 0) & np.isin(truth, list(seen))
        b = np.searchsorted(edges, geometry.distance[evaluate], side="right") - 1
        inside = (b >= 0) & (b < len(count))
        if seen:
            np.add.at(count, b[inside], 1)
            for name, x in features.items():
                with np.errstate(divide="ignore"):  # log prior of classes not seen yet
                    pred = models[name].predict(x[evaluate])
                np.add.at(hits[name], b[inside], (pred == truth[evaluate])[inside])
        label = CLASS_NAMES.index(labels[i])
        for name, x in features.items():
            models[name].partial_fit(
                x[near], np.full(int(near.sum()), label), classes=np.arange(len(CLASS_NAMES))
            )
        seen.add(label)
    print("  tile accuracy on far tiles of learnt classes, plain Gaussian NB:")
    bins = " | ".join(f"{a:g}-{b:g} m" for a, b in itertools.pairwise(edges))
    print(f"  | features | {bins} |")
    for name in sets:
        acc = [f"{h / n:.3f}" if n else "-" for h, n in zip(hits[name], count, strict=True)]
        print(f"  | {name} | " + " | ".join(acc) + " |")


def report(path: Path, args: argparse.Namespace) -> None:
    traverse = load_traverse(path)
    world = load_world(path / TRUTH_FILE)
    labels = traverse.labels()
    if args.flip > 0:
        labels = noisy_labels(labels, args.flip, seed=0)
    n_images = sum(f.left is not None for f in traverse.frames)
    print(f"\n## {traverse.name}: {len(traverse)} frames, {n_images} with images ({path})")
    preds, times = run(traverse, labels, tile_px=args.tile)
    table = far_field_accuracy(preds, world, threshold=args.threshold)
    print(table.to_text())
    poses = traverse.poses()
    ours = area_coverage(preds, poses, world, PATCH, threshold=args.threshold)
    base_preds, _ = run(
        traverse,
        labels,
        tile_px=args.tile,
        novelty_alpha=0.0,
        recall=False,
        min_support=1,
        min_confidence=0.0,
        calibrate=False,
    )
    ceiling = area_coverage(base_preds, poses, world, PATCH, threshold=0.0)
    base = area_coverage(base_preds, poses, world, PATCH, threshold=args.threshold)
    base_table = far_field_accuracy(base_preds, world, threshold=args.threshold)
    print(
        f"\n  area (m^2, {ours.cell:g} m grid): near {ours.near_area:.2f}; near + far "
        f"(p >= {args.threshold:g}) {ours.total_area:.2f} = {ours.ratio:.2f} x, fused far "
        f"accuracy {ours.accuracy:.3f}, far accuracy <= 4 m {table.overall(4.0):.3f}"
    )
    print(f"  ceiling (every far cell in view): {ceiling.total_area:.2f} = {ceiling.ratio:.2f} x")
    print(
        f"  baseline without gate and recall: {base.total_area:.2f} = {base.ratio:.2f} x, fused "
        f"far accuracy {base.accuracy:.3f}, far accuracy <= 4 m {base_table.overall(4.0):.3f}"
    )
    print(
        "  time per frame (median, s): "
        + ", ".join(f"{k} {v:.3f}" for k, v in times.items())
        + f"; load average {os.getloadavg()[0]:.1f}"
    )
    if not args.no_texture:
        texture_baseline(traverse, world, labels)


def photos(segment: float, n_worlds: int) -> None:
    """Near-to-far on photo worlds (see the module notes)."""
    from rough_map.config import StereoCalibration
    from rough_map.evaluation.near_far_path import path_band_accuracy
    from rough_map.simulate import photo_ground as pg

    full = StereoCalibration.xb3_default()
    calib = StereoCalibration(  # a quarter of the rig: tiles of 8 px
        fx=full.fx / 4, fy=full.fy / 4, cx=(full.cx + 0.5) / 4 - 0.5,
        cy=(full.cy + 0.5) / 4 - 0.5, width=round(full.width / 4),
        height=round(full.height / 4), baseline=full.baseline,
        camera_to_vehicle=full.camera_to_vehicle,
    )  # fmt: skip
    orders = [(0, 1, 2, 3), (2, 0, 3, 1), (3, 2, 1, 0), (1, 3, 0, 2), (0, 2, 1, 3), (3, 1, 0, 2)]
    print(f"\n## photo worlds, {segment:g} m segments (far accuracy over labelled cells)")
    print("| world | look | labelled cells | far accuracy | abstained | <1.5 m | 1.5-2 m | 2-3 m "
          "| 3-4 m | path band cells | path band | baseline |")  # fmt: skip
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for w, order in enumerate(orders[:n_worlds]):
        for color in (True, False):
            world = pg.photo_world(order, segment=segment, seed=w)
            poses = pg.drive_straight(len(order) * segment - 1.5, seed=w)
            truth = pg.true_near_labels(world, poses)
            labels = [truth[max(0, i - 2)] for i in range(len(truth))]
            k = len(labels) // 2 + 3
            labels[k] = pg.PHOTOS[(pg.PHOTOS.index(str(labels[k])) + 1) % 4]
            out = Path(tempfile.mkdtemp(prefix="near_far_photo_")) / "traverse"
            trav = pg.write_photo_traverse(out, world, poses, calib, pg.PhotoGround(color=color),
                                           labels)  # fmt: skip
            preds = nf.run_traverse(trav, labels, patch=PATCH, classes=pg.PHOTOS, tile_px=8,
                                    settle=3)  # fmt: skip
            table = far_field_accuracy(preds, world)
            band = path_band_accuracy(preds, world, poses, labels, PATCH)
            d = table.to_dict()
            acc = " | ".join(f"{a:.3f}" if np.isfinite(a) else "-" for a in table.accuracy[:4])
            print(f"| {w} | {'colour' if color else 'grey'} | {table.n.sum()} | "
                  f"{table.overall():.3f} | {d['abstained_fraction']:.3f} | {acc} | {band.n} | "
                  f"{band.accuracy:.3f} | {band.baseline_accuracy:.3f} |")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--traverse", type=Path, nargs="*", default=[], metavar="DIR")
    parser.add_argument("--simulate", metavar="COURSE", help="simulate this course first")
    parser.add_argument("--length", type=float, default=12.0, metavar="M")
    parser.add_argument("--image-every", type=int, default=2, metavar="N")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--width",
        type=float,
        default=4.0,
        metavar="M",
        help="width of the simulated world in m (default 4, as `rough-map simulate`)",
    )
    parser.add_argument("--threshold", type=float, default=0.6)
    parser.add_argument("--tile", type=int, default=32, metavar="PX")
    parser.add_argument(
        "--flip",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of near labels replaced by another class",
    )
    parser.add_argument("--no-texture", action="store_true", help="skip the LBP baseline")
    parser.add_argument("--photos", action="store_true", help="run the photo worlds instead")
    parser.add_argument("--segment", type=float, default=3.0, metavar="M",
                        help="photo worlds: length of a class segment, m")  # fmt: skip
    parser.add_argument("--worlds", type=int, default=4, metavar="N")
    args = parser.parse_args()
    if args.photos:
        photos(args.segment, args.worlds)
        return
    paths = list(args.traverse)
    if args.simulate:
        start = time.perf_counter()
        paths.append(simulate(args.simulate, args.length, args.image_every, args.seed, args.width))
        print(f"simulated {args.simulate} in {time.perf_counter() - start:.0f} s")
    if not paths:
        parser.error("give --traverse DIR or --simulate COURSE")
    for path in paths:
        report(path, args)


if __name__ == "__main__":
    main()
