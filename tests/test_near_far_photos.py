"""Near-to-far on real ground photographs (scikit-image's CC0 brick, gravel, grass and moon
surface), laid out on flat worlds of our own and seen by the test rig's left camera
(:mod:`rough_map.simulate.photo_ground`).

The near labels are those a path filter gives: they lag a change of ground by two frames,
and one frame mid-way carries a wrong class (an error of the geometric classifier). Every
world tried must pass, in colour (the photos tinted per class) and in grey (the photos as
they are, brightness matched, where the looks of the classes overlap).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_near_far import PATCH, TILE, scaled_calibration

from rough_map.evaluation.near_far import far_field_accuracy
from rough_map.evaluation.near_far_path import path_band_accuracy
from rough_map.near_far import FarPrediction, NearToFar, run_traverse, settled
from rough_map.simulate.photo_ground import (
    PHOTOS,
    PhotoGround,
    drive_straight,
    photo_world,
    true_near_labels,
    write_photo_traverse,
)
from rough_map.types import HeightField

#: Class order along the path of each world (indices into PHOTOS).
ORDERS = ((0, 1, 2, 3), (2, 0, 3, 1), (3, 2, 1, 0), (1, 3, 0, 2))
#: Frames the near labels lag a change of ground by.
LAG = 2


def path_labels(world: HeightField, poses: np.ndarray) -> list[str | None]:
    """The true near labels, lagging by LAG frames, with one wrong frame mid-way."""
    truth = true_near_labels(world, poses)
    labels = [truth[max(0, i - LAG)] for i in range(len(truth))]
    k = len(labels) // 2 + 3
    labels[k] = PHOTOS[(PHOTOS.index(str(labels[k])) + 1) % len(PHOTOS)]
    return labels


def run_world(
    tmp: Path, w: int, color: bool, segment: float
) -> tuple[list[FarPrediction], HeightField, np.ndarray, list[str | None]]:
    world = photo_world(ORDERS[w], segment=segment, seed=w)
    poses = drive_straight(len(ORDERS[w]) * segment - 1.5, seed=w)
    labels = path_labels(world, poses)
    ground = PhotoGround(color=color)
    traverse = write_photo_traverse(
        tmp / f"w{w}_{color}", world, poses, scaled_calibration(), ground, labels
    )
    predictions = run_traverse(
        traverse, labels, patch=PATCH, classes=PHOTOS, tile_px=TILE, settle=3
    )
    return predictions, world, poses, labels


def check_worlds(tmp: Path, segment: float) -> None:
    labelled = {}
    for color in (True, False):
        for w in range(len(ORDERS)):
            predictions, world, poses, labels = run_world(tmp, w, color, segment)
            table = far_field_accuracy(predictions, world)
            report = table.to_dict()
            band = path_band_accuracy(predictions, world, poses, labels, PATCH)
            labelled[color, w] = int(table.n.sum())
            assert 0.0 < report["abstained_fraction"] <= 1.0
            if color:
                # far-field accuracy over the cells it labels, in every world
                assert table.n.sum() > 1000, w
                assert table.overall() >= 0.85, (w, report)
                # on the path band, at least the nearest-near-field-cell baseline
                assert band.n > 100, w
                assert band.accuracy >= band.baseline_accuracy, (w, band)
            elif table.n.sum():
                # grey: looks overlap; what it labels stays right, by abstaining
                assert table.overall() >= 0.8, (w, report)
    for w in range(len(ORDERS)):
        # ... rather than labelling more area wrongly than in colour
        assert labelled[False, w] < labelled[True, w]


def test_near_far_on_ground_photographs(tmp_path: Path) -> None:
    """Four worlds of 3 m segments, in colour and in grey (about 15 s)."""
    check_worlds(tmp_path, segment=3.0)


@pytest.mark.slow
def test_near_far_on_ground_photographs_long_segments(tmp_path: Path) -> None:
    """The same with 5 m segments: more of the far field is checked and labelled."""
    check_worlds(tmp_path, segment=5.0)


def test_settled_labels_skip_changes_defects_and_doubt() -> None:
    labels = ["a"] * 5 + ["b"] * 6 + [None, "b", "a", "b", "b", "b", "b"]
    ok = settled(labels, 2)
    assert ok.tolist() == [
        True, True, True, False, False,  # a, then a change within two frames
        False, False, True, True, True, True,  # b (an unknown frame is no change)
        False, False, False, False, False,  # unknown, and an isolated "a" with its neighbours
        True, True,
    ]  # fmt: skip
    assert settled(labels, 0).sum() == 17  # every known label
    defect = np.zeros(len(labels), bool)
    defect[8] = True
    assert not settled(labels, 2, defect=defect)[6:11].any()
    posterior = np.full(len(labels), 0.9)
    posterior[0] = 0.5
    assert settled(labels, 0, 0.8, posterior).tolist()[:2] == [False, True]
    # probability rows: the class is the argmax, the posterior its share
    rows = [np.array([0.7, 0.3])] * 3
    assert settled(rows, 1, 0.8).tolist() == [False, False, False]
    assert settled(rows, 1, 0.6).tolist() == [True, True, True]


def test_calibrated_model_abstains_until_checked(tmp_path: Path) -> None:
    """Until far predictions of two classes were checked by the near field, the model
    labels nothing; with ``calibrate=False`` the looks alone label the far field."""
    world = photo_world(ORDERS[0], segment=3.0, seed=0)
    poses = drive_straight(2.0, seed=0)  # brick only
    labels = true_near_labels(world, poses)
    traverse = write_photo_traverse(
        tmp_path / "brick", world, poses, scaled_calibration(), PhotoGround(), labels
    )
    model = NearToFar(PHOTOS, PATCH, tile_px=TILE)
    calibrated = run_traverse(traverse, labels, model=model)
    assert sum(len(p) for p in calibrated) == 0
    assert sum(len(p.abstained) for p in calibrated) > 1000
    raw = run_traverse(traverse, labels, patch=PATCH, classes=PHOTOS, tile_px=TILE,
                       calibrate=False)  # fmt: skip
    assert sum(len(p) for p in raw) > 1000
