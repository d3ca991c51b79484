"""Near-to-far: projection, the online appearance model, far-field accuracy, bad input."""

from __future__ import annotations

import copy
import functools
import math

import cv2
import numpy as np
import pytest
from sklearn.base import clone
from sklearn.utils.estimator_checks import (
    check_do_not_raise_errors_in_init_or_set_params,
    check_get_params_invariance,
    check_no_attributes_set_in_init,
    check_set_params,
    estimator_checks_generator,
)

from rough_map.config import StereoCalibration, TraverseSpec
from rough_map.errors import InputError, NotFittedError
from rough_map.evaluation.near_far import area_coverage, far_field_accuracy, world_class
from rough_map.geometry import ground_to_pixel, pixel_to_ground, pose_matrix
from rough_map.io.traverse import Traverse, save_traverse
from rough_map.near_far import (
    FarPrediction,
    LooksClassifier,
    NearToFar,
    run_traverse,
    tile_features,
)
from rough_map.patch import Extraction, PatchSpec
from rough_map.simulate.world import CLASS_NAMES, build_world, course_layout, drive
from rough_map.types import HeightField

#: Image scale of the test rig: a quarter of the XB3-like rig renders 16x faster, and tiles of
#: 8 px then cover the ground of the full rig's 32 px tiles.
SCALE = 0.25
TILE = 8
#: The near field: the default extraction's patch (0.552-1.448 m ahead, 0.896 m wide).
PATCH = Extraction()


def scaled_calibration(scale: float = SCALE) -> StereoCalibration:
    """The XB3-like rig with its images resized by ``scale`` (same field of view)."""
    full = StereoCalibration.xb3_default()
    return StereoCalibration(
        fx=full.fx * scale,
        fy=full.fy * scale,
        cx=(full.cx + 0.5) * scale - 0.5,
        cy=(full.cy + 0.5) * scale - 0.5,
        width=round(full.width * scale),
        height=round(full.height * scale),
        baseline=full.baseline,
        camera_to_vehicle=full.camera_to_vehicle,
    )


@pytest.fixture(scope="module")
def course(tmp_path_factory: pytest.TempPathFactory) -> tuple[Traverse, HeightField]:
    """A short mixed course (concrete, dirt road, gravel, 2.5 m each), one colour image pair
    every 0.5 m, rendered at a quarter of the rig's resolution (about 10 s)."""
    from rough_map.simulate.render import render_stereo
    from rough_map.simulate.textures import TextureSet

    out = tmp_path_factory.mktemp("near_far_course")
    (out / "left").mkdir()
    (out / "right").mkdir()
    calib = scaled_calibration()
    segments, defects = course_layout("mixed", 7.5, seed=3)
    world = build_world(segments, defects, spacing=0.008, seed=3, width=3.0)
    poses = drive(world, segments[0].start, segments[-1].end - 1.5, seed=3)
    textures = TextureSet(seed=3)
    frames = []
    for i, (t, x, y, z, roll, pitch, yaw) in enumerate(poses[::2]):
        left, right, _ = render_stereo(
            world, (x, y, z, roll, pitch, yaw), calib, textures, seed=i, color=True
        )
        cv2.imwrite(str(out / f"left/{i:03d}.png"), left)
        cv2.imwrite(str(out / f"right/{i:03d}.png"), right)
        col = round((x + math.cos(yaw) - world.origin[0]) / world.spacing)
        row = round((y + math.sin(yaw) - world.origin[1]) / world.spacing)
        frames.append(
            {
                "t": t,
                "pose": {"x": x, "y": y, "z": z, "roll": roll, "pitch": pitch, "yaw": yaw},
                "left": f"left/{i:03d}.png",
                "right": f"right/{i:03d}.png",
                "label": world.class_names[world.classes[row, col]],
            }
        )
    spec = TraverseSpec.model_validate(
        {"schema_version": "1.0", "name": "nf", "calibration": calib.model_dump(), "frames": frames}
    )
    save_traverse(spec, out)
    return Traverse.from_spec(spec, out), world


@pytest.fixture(scope="module")
def predictions(course: tuple[Traverse, HeightField]) -> list[FarPrediction]:
    traverse, _ = course
    return run_traverse(traverse, traverse.labels(), patch=PATCH, classes=CLASS_NAMES, tile_px=TILE)


def read(traverse: Traverse, i: int) -> np.ndarray:
    return cv2.imread(str(traverse.resolve(traverse.frames[i].left)), cv2.IMREAD_COLOR)


# ------------------------------------------------------------------------------ projection


def test_projection_round_trip_flat_ground() -> None:
    calib = StereoCalibration.xb3_default()
    rng = np.random.default_rng(0)
    pose = np.array([3.0, -1.0, 0.2, 0.03, -0.02, 0.7])
    transform = pose_matrix(pose)
    # World points on the vehicle's ground plane, 0.5-4 m ahead.
    vehicle = np.column_stack(
        [rng.uniform(0.5, 3.0, 200), rng.uniform(-1.0, 1.0, 200), np.zeros(200)]
    )
    world = vehicle @ transform[:3, :3].T + transform[:3, 3]
    # ... into the image and back onto the ground, and back to the world.
    back_vehicle = (world - transform[:3, 3]) @ transform[:3, :3]
    u, v = ground_to_pixel(calib, back_vehicle)
    inside = (u >= 0) & (u < calib.width) & (v >= 0) & (v < calib.height)
    assert inside.mean() > 0.5
    ground = pixel_to_ground(calib, u[inside], v[inside])
    back_world = ground @ transform[:3, :3].T + transform[:3, 3]
    assert np.max(np.linalg.norm(back_world - world[inside], axis=1)) < 0.01


def test_pixel_to_ground_matches_the_renderer_on_flat_ground() -> None:
    """Ray-cast depth of a flat world against the pinhole/plane intersection."""
    from rough_map.simulate.render import render_stereo

    calib = scaled_calibration()
    world = HeightField(np.zeros((600, 600)), 0.01, origin=(-1.0, -3.0))
    pose = (0.3, 0.1, 0.0, 0.0, 0.0, 0.2)
    _, _, depth = render_stereo(world, pose, calib, color=False, noise_sigma=0, psf_sigma=0)
    v, u = np.mgrid[0 : calib.height : 7, 0 : calib.width : 7]
    z = depth[v, u]
    ok = np.isfinite(z)
    cam = np.stack([(u - calib.cx) / calib.fx * z, (v - calib.cy) / calib.fy * z, z], axis=-1)[ok]
    transform = np.asarray(calib.camera_to_vehicle)
    truth = cam @ transform[:3, :3].T + transform[:3, 3]
    ground = pixel_to_ground(calib, u[ok], v[ok])
    assert np.max(np.linalg.norm(ground - truth, axis=1)) < 0.02  # m, a few cm


def test_pixel_above_horizon_gives_nan() -> None:
    calib = StereoCalibration.xb3_default()
    tilted = np.asarray(calib.camera_to_vehicle)
    # A camera looking straight ahead: the top half of the image sees the sky.
    level = StereoCalibration(
        **{**calib.model_dump(), "camera_to_vehicle": _level_camera(tilted).tolist()}
    )
    ground = pixel_to_ground(level, [640.0, 640.0], [100.0, 900.0])
    assert np.all(np.isnan(ground[0]))
    assert np.all(np.isfinite(ground[1]))


def _level_camera(transform: np.ndarray) -> np.ndarray:
    out = transform.copy()
    out[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return out


# ------------------------------------------------------------------------------ features, model


def _flat_image(calib: StereoCalibration, bgr: tuple[int, int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = np.empty((calib.height, calib.width, 3))
    image[:] = bgr
    image += rng.normal(0, 4.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


GREY, BROWN = (140, 143, 146), (105, 140, 170)


def test_tile_features_shape_and_colour() -> None:
    calib = scaled_calibration()
    features = tile_features(_flat_image(calib, BROWN, 0), TILE)
    assert features.shape == ((calib.height // TILE) * (calib.width // TILE), 6)
    lab = cv2.cvtColor(np.float32([[BROWN]]) / 255.0, cv2.COLOR_BGR2Lab)[0, 0]
    assert np.allclose(features[:, :3].mean(axis=0), lab, atol=0.5)
    # Noise of 4 grey levels: L* std about 1.5.
    assert 0.0 < np.exp(features[:, 3]).mean() < 3.0


def test_learns_looks_and_flags_unfamiliar_ones() -> None:
    calib = scaled_calibration()
    pose = np.zeros(6)
    # the looks alone: the calibrated model abstains until far predictions were checked
    model = NearToFar(CLASS_NAMES, PATCH, tile_px=TILE, min_confidence=0.0, calibrate=False)
    for seed in range(3):
        model.update(_flat_image(calib, GREY, seed), calib, pose, "concrete")
    grey = model.predict(_flat_image(calib, GREY, 10), calib, pose)
    assert len(grey) > 100
    assert np.all(grey.label == "concrete")
    assert grey.confidence.min() > 0.99
    # A colour never learnt is unknown (uniform), not the nearest known class ...
    brown = model.predict(_flat_image(calib, BROWN, 11), calib, pose)
    assert len(brown) == len(grey)
    assert np.allclose(brown.proba, 1.0 / len(CLASS_NAMES))
    # ... and left out with the default min_confidence.
    model.min_confidence = 0.5
    assert len(model.predict(_flat_image(calib, BROWN, 11), calib, pose)) == 0
    assert len(model.predict(_flat_image(calib, GREY, 10), calib, pose)) == len(grey)
    # One wrong label does not overturn three right ones, and is not used alone.
    model.update(_flat_image(calib, GREY, 12), calib, pose, "gravel")
    assert np.all(model.predict(_flat_image(calib, GREY, 13), calib, pose).label == "concrete")
    # Probabilities as the near label: 0.9 dirt road, twice -> the brown look is dirt road.
    p = np.array([0.0, 0.9, 0.1, 0.0, 0.0])
    for seed in (14, 15, 16):
        model.update(_flat_image(calib, BROWN, seed), calib, pose, p)
    brown = model.predict(_flat_image(calib, BROWN, 17), calib, pose)
    assert np.all(brown.label == "dirt_road")


def test_predictions_are_ground_cells_beyond_the_near_field() -> None:
    calib = scaled_calibration()
    pose = np.array([10.0, 5.0, 0.0, 0.0, 0.0, math.pi / 2])  # heading north (+y)
    model = NearToFar(
        CLASS_NAMES, PATCH, tile_px=TILE, max_range=3.0, ground_step=0.2, calibrate=False
    )
    for seed in range(2):
        model.update(_flat_image(calib, GREY, seed), calib, pose, "concrete")
    pred = model.predict(_flat_image(calib, GREY, 5), calib, pose, t=1.5, frame=7)
    assert (pred.t, pred.frame) == (1.5, 7)
    assert pred.proba.shape == (len(pred), len(CLASS_NAMES))
    assert np.allclose(pred.proba.sum(axis=1), 1.0)
    assert pred.distance.max() <= 3.0
    assert np.all(pred.ahead > 0)
    in_patch = (np.abs(pred.ahead - 1.0) <= 0.45) & (np.abs(pred.lateral) <= 0.45)
    assert not in_patch.any()
    # World = pose applied to (ahead, lateral): heading +y, so ahead runs along +y.
    assert np.allclose(pred.x, 10.0 - pred.lateral, atol=1e-6)
    assert np.allclose(pred.y, 5.0 + pred.ahead, atol=1e-6)
    # Cell centres on the 0.2 m lattice, one prediction per cell.
    for coord in (pred.x, pred.y):
        k = coord / 0.2 - 0.5
        assert np.allclose(k, np.rint(k), atol=1e-6)
    assert len({(round(x, 3), round(y, 3)) for x, y in zip(pred.x, pred.y, strict=True)}) == len(
        pred
    )


def test_the_near_field_is_the_patch_of_the_labels() -> None:
    """Labels of a patch 1.5 m ahead teach the tiles that see 1.052-1.948 m, and the ground
    nearer than that (the default patch) becomes far field."""
    calib = scaled_calibration()
    pose = np.zeros(6)
    patch = PatchSpec(ahead=1.5)
    model = NearToFar(CLASS_NAMES, patch, tile_px=TILE, max_range=3.0, calibrate=False)
    for seed in range(2):
        model.update(_flat_image(calib, GREY, seed), calib, pose, "concrete")
    (x0, x1), (y0, y1) = model.near_field_.ahead, model.near_field_.lateral
    assert (x0, x1) == Extraction(patch=patch).near_range == pytest.approx((1.052, 1.948))
    assert (y0, y1) == pytest.approx((-0.448, 0.448))
    pred = model.predict(_flat_image(calib, GREY, 5), calib, pose)
    across = (pred.lateral >= y0) & (pred.lateral <= y1)
    assert not np.any(across & (pred.ahead >= x0) & (pred.ahead <= x1))
    assert np.any(across & (pred.ahead > 0.552) & (pred.ahead < 1.0))


# ------------------------------------------------------------------------------ scikit-learn


def test_near_to_far_is_a_clonable_estimator() -> None:
    """The constructor stores its arguments as given (checked at the first update); clone
    gives an unfitted copy with the same parameters."""
    model = NearToFar(CLASS_NAMES, PATCH, tile_px=32.7)
    assert model.tile_px == 32.7 and model.get_params()["patch"] is PATCH
    for check in (
        check_no_attributes_set_in_init,
        check_get_params_invariance,
        check_set_params,
        check_do_not_raise_errors_in_init_or_set_params,
    ):
        check("NearToFar", model)
    calib = scaled_calibration()
    fitted = NearToFar(CLASS_NAMES, PATCH, tile_px=TILE)
    fitted.update(_flat_image(calib, GREY, 0), calib, np.zeros(6), "concrete")
    assert fitted.classes_ == tuple(CLASS_NAMES) and fitted.n_updates_ == 1
    assert fitted.near_field_.ahead == PATCH.near_range
    copied = clone(fitted)
    assert copied.get_params() == fitted.get_params()
    assert not hasattr(copied, "looks_") and not hasattr(copied, "classes_")
    with pytest.raises(NotFittedError, match="update"):
        copied.predict(_flat_image(calib, GREY, 1), calib, np.zeros(6))


def _shipped_appearance() -> LooksClassifier:
    """The appearance model in the configuration NearToFar ships with."""
    params = NearToFar(CLASS_NAMES, PATCH).get_params()
    return LooksClassifier(**{k: params[k] for k in LooksClassifier().get_params()})


#: scikit-learn checks that cannot pass in the shipped configuration, and why.
_SIX_FEATURES = (
    "the shipped min_std has one floor per tile feature, so X must have the 6 tile "
    "features; this check's data have another number"
)
_EXPECTED_FAILURES = dict.fromkeys(
    (
        "check_classifier_data_not_an_array",
        "check_classifiers_classes",
        "check_classifiers_one_label",
        "check_dict_unchanged",
        "check_dont_overwrite_parameters",
        "check_dtype_object",
        "check_estimators_dtypes",
        "check_estimators_fit_returns_self",
        "check_estimators_nan_inf",
        "check_estimators_overwrite_params",
        "check_estimators_partial_fit_n_features",
        "check_estimators_pickle",
        "check_f_contiguous_array_estimator",
        "check_fit2d_1feature",
        "check_fit2d_1sample",
        "check_fit2d_predict1d",
        "check_fit_check_is_fitted",
        "check_fit_idempotent",
        "check_fit_score_takes_y",
        "check_methods_sample_order_invariance",
        "check_methods_subset_invariance",
        "check_n_features_in",
        "check_n_features_in_after_fitting",
        "check_pipeline_consistency",
        "check_positive_only_tag_during_fit",
        "check_readonly_memmap_input",
        "check_supervised_y_2d",
    ),
    _SIX_FEATURES,
)
_EXPECTED_FAILURES["check_classifiers_train"] = (
    _SIX_FEATURES + "; and one fit is one batch per class, while a look is used only after "
    "min_support=2 batches, so a single fit predicts uniformly"
)


def _check_params(configuration: str, estimator: LooksClassifier) -> list:
    out = []
    for est, check in estimator_checks_generator(estimator, legacy=True, mark=None):
        func = check.func if isinstance(check, functools.partial) else check
        keywords = check.keywords if isinstance(check, functools.partial) else {}
        name = func.__name__
        label = name + "".join(f"-{k}={v}" for k, v in keywords.items() if k != "estimator")
        reason = _EXPECTED_FAILURES.get(name) if configuration == "shipped" else None
        marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
        out.append(pytest.param(est, check, id=f"{configuration}-{label}", marks=marks))
    return out


@pytest.mark.parametrize(
    ("estimator", "check"),
    _check_params("shipped", _shipped_appearance())
    # One floor for all features and looks in use after one batch: the whole contract.
    + _check_params("general", LooksClassifier(min_std=0.1, min_support=1)),
)
def test_appearance_model_follows_scikit_learn_conventions(estimator, check) -> None:
    check(estimator)


def test_appearance_model_learns_batches() -> None:
    """Two batches per class put their looks in use; a third, far-off colour is unknown."""
    rng = np.random.default_rng(0)
    centres = {
        "grey": np.array([60.0, 0.0, 0.0, 1.0, -1.0, -1.0]),
        "brown": np.array([55.0, 5.0, 15.0, 1.0, -1.0, -1.0]),
    }
    model = LooksClassifier()
    for _ in range(2):
        x = np.concatenate([c + rng.normal(0, 0.3, (50, 6)) for c in centres.values()])
        model.partial_fit(x, np.repeat(list(centres), 50), classes=["brown", "grey"])
    assert model.n_updates_ == 4 and len(model.looks_.cls) == 2
    test = np.stack([centres["grey"], centres["brown"], [30.0, -20.0, 40.0, 1.0, -1.0, -1.0]])
    assert model.predict(test[:2]).tolist() == ["grey", "brown"]
    assert np.allclose(model.predict_proba(test[2:]), 0.5)
    assert model.familiarity(test[2:])[0] < 1e-6 < model.familiarity(test[:1])[0]
    with pytest.raises(InputError, match="min_std must be a positive number or 6"):
        LooksClassifier(min_std=(1.0, 2.0)).fit(test, ["a", "b", "a"])


# ------------------------------------------------------------------------------ simulated course


def test_online_model_improves_as_frames_arrive(course: tuple[Traverse, HeightField]) -> None:
    """Frame 4 sees concrete, dirt road and gravel; score it with the model after k frames:
    the share of its cells classified confidently and right, and the mean probability of the
    true class, grow as concrete (frames 0-3), dirt road (4-7) and gravel (8-) are learnt."""
    traverse, world = course
    calib = traverse.spec.calibration
    image, pose = read(traverse, 4), traverse.frames[4].pose
    model = NearToFar(
        CLASS_NAMES, PATCH, tile_px=TILE, recall=False, min_confidence=0.0, calibrate=False
    )
    good, p_true = [], []
    for i in range(len(traverse) - 1):
        model.update(read(traverse, i), calib, traverse.frames[i].pose, traverse.frames[i].label)
        if i in (1, 5, len(traverse) - 2):
            pred = copy.deepcopy(model).predict(image, calib, pose)
            truth = world_class(world, pred.x, pred.y)
            good.append(np.mean((pred.confidence >= 0.6) & (pred.label_index == truth)))
            p_true.append(pred.proba[np.arange(len(pred)), truth].mean())
    assert good[0] < good[1] < good[2]
    assert p_true[0] < p_true[1] < p_true[2]
    assert good[2] > 0.5


def test_far_field_accuracy_and_area(
    course: tuple[Traverse, HeightField], predictions: list[FarPrediction]
) -> None:
    traverse, world = course
    assert len(predictions) == len(traverse) - 1
    assert [p.frame for p in predictions] == list(range(1, len(traverse)))
    table = far_field_accuracy(predictions, world, threshold=0.6)
    assert table.edges.tolist() == [0, 1.5, 2, 3, 4, 5, 6, 8]
    assert table.n[:4].sum() > 500
    assert table.overall(max_distance=4.0) >= 0.8
    coverage = area_coverage(predictions, traverse.poses(), world, PATCH, threshold=0.6)
    # calibrated, it abstains until far predictions of two classes were checked: on this
    # short course (three new classes in 7.5 m) that halves the area ...
    assert coverage.ratio >= 1.5
    assert coverage.accuracy >= 0.8
    assert "| 2-3 |" in table.to_text()
    assert 0.2 < table.to_dict()["abstained_fraction"] < 1.0
    # ... which the looks alone cover three times over, as accurately here
    raw = run_traverse(
        traverse, traverse.labels(), patch=PATCH, classes=CLASS_NAMES, tile_px=TILE,
        calibrate=False,
    )  # fmt: skip
    coverage = area_coverage(raw, traverse.poses(), world, PATCH, threshold=0.6)
    assert coverage.ratio >= 3.0
    assert coverage.accuracy >= 0.8


def test_unknown_near_labels_are_not_learnt(course: tuple[Traverse, HeightField]) -> None:
    traverse, _ = course
    assert run_traverse(traverse, [""] * len(traverse), patch=PATCH, tile_px=TILE) == []
    labels: list[str | None] = [None] * len(traverse)
    labels[0] = "concrete"
    predictions = run_traverse(
        traverse, np.array(labels, dtype=object), patch=PATCH, classes=CLASS_NAMES, tile_px=TILE
    )
    assert len(predictions) == len(traverse) - 1


def test_no_peeking(course: tuple[Traverse, HeightField]) -> None:
    """The prediction of frame k does not depend on the labels of frames k and later."""
    traverse, _ = course
    labels = traverse.labels()
    k = 6
    changed = labels[:k] + ["ploughed_soil"] * (len(labels) - k)
    a = run_traverse(traverse, labels, patch=PATCH, classes=CLASS_NAMES, tile_px=TILE, every=2)
    b = run_traverse(traverse, changed, patch=PATCH, classes=CLASS_NAMES, tile_px=TILE, every=2)
    for pa, pb in zip(a, b, strict=True):
        if pa.frame is not None and pa.frame <= k:
            assert np.array_equal(pa.proba, pb.proba)


# ------------------------------------------------------------------------------ bad input


def test_bad_input_raises_input_error(course: tuple[Traverse, HeightField]) -> None:
    traverse, world = course
    calib = scaled_calibration()
    image = _flat_image(calib, GREY, 0)
    model = NearToFar(CLASS_NAMES, PATCH, tile_px=TILE)
    with pytest.raises(NotFittedError, match="update"):
        model.predict(image, calib, np.zeros(6))
    with pytest.raises(InputError, match="calibration is for 320x240"):
        model.update(np.zeros((480, 640, 3), np.uint8), calib, np.zeros(6), "concrete")
    with pytest.raises(InputError, match="unknown class label 'asphalt'"):
        model.update(image, calib, np.zeros(6), "asphalt")
    with pytest.raises(InputError, match="unknown class label"):
        model.update(image, calib, np.zeros(6), 7)
    with pytest.raises(InputError, match="5 non-negative"):
        model.update(image, calib, np.zeros(6), [0.5, 0.5])
    with pytest.raises(InputError, match="BGR"):
        model.update(image[..., 0], calib, np.zeros(6), "concrete")
    with pytest.raises(InputError, match="pose"):
        model.update(image, calib, np.zeros(5), "concrete")
    # The parameters are checked at the first update (the constructor only stores them).
    with pytest.raises(InputError, match="max_range"):
        NearToFar(CLASS_NAMES, PATCH, max_range=1.0).update(image, calib, np.zeros(6), 0)
    with pytest.raises(InputError, match="distinct"):
        NearToFar(["a", "a"], PATCH).update(image, calib, np.zeros(6), 0)
    with pytest.raises(InputError, match="tile_px must be an integer"):
        NearToFar(CLASS_NAMES, PATCH, tile_px=8.5).update(image, calib, np.zeros(6), 0)
    with pytest.raises(InputError, match="min_std must be"):
        NearToFar(CLASS_NAMES, PATCH, tile_px=TILE, min_std=(1.0,)).update(
            image, calib, np.zeros(6), 0
        )
    with pytest.raises(InputError, match="patch must be a PatchSpec"):
        NearToFar(CLASS_NAMES, (0.55, 1.45)).update(image, calib, np.zeros(6), 0)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="near_labels has 2 entries"):
        run_traverse(traverse, ["concrete", "gravel"], patch=PATCH)
    with pytest.raises(InputError, match="needs the patch"):
        run_traverse(traverse, traverse.labels())
    with pytest.raises(InputError, match="need classes"):
        run_traverse(traverse, [0] * len(traverse), patch=PATCH)
    with pytest.raises(InputError, match="bins"):
        far_field_accuracy([], world, bins=(2.0, 1.0))
    with pytest.raises(InputError, match="proba"):
        FarPrediction(*(np.zeros(3),) * 5, proba=np.zeros((3, 2)), classes=("a", "b", "c"))
