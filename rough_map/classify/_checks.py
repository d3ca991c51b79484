"""Checks of a loaded :class:`~rough_map.classify.TerrainModel`, so that ``predict`` cannot
fail later on a malformed file.

skops rebuilds objects of trusted types from whatever attributes a file gives them, without
running their constructors. :func:`check_loaded_model` checks the structure that predict
relies on (types, shapes, finiteness, index ranges of the trees, which compiled code reads
without bounds checks) and then runs a trial prediction on a small synthetic feature matrix;
any failure is a one-line :class:`~rough_map.errors.ModelError` naming the file.

The crash the node checks prevent: scikit-learn's compiled tree walk follows a child index
beyond the tree's nodes without a bounds check, and a forest so rebuilt by skops dies in
``predict`` (SIGSEGV; ``tests/test_library_crashes.py``), as would the trial prediction. The
other checks turn late exceptions into one line at load.
"""

from __future__ import annotations

import itertools
import math
from numbers import Real
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._bounded import brief
from rough_map.classify.model import MODES
from rough_map.classify.spectral import INPUT_SCALARS
from rough_map.classify.training import CLASSIFIERS
from rough_map.errors import ModelError
from rough_map.limits import LIMITS
from rough_map.patch import Extraction

__all__ = ["check_loaded_model"]

_MAX_RATE = 1e6  # 1/m, switch rates of the path filter


class _Bad(Exception):
    """One failed check (turned into a ModelError naming the file)."""


def _qualname(obj: Any) -> str:
    return f"{type(obj).__module__}.{type(obj).__name__}"


def _is(obj: Any, *names: str) -> None:
    if _qualname(obj) not in names:
        raise _Bad(f"expected {' or '.join(names)}, got {_qualname(obj)!r:.80}")


def _array(obj: Any, name: str, ndim: int, *, kind: str = "f", finite: bool = True) -> np.ndarray:
    if not isinstance(obj, np.ndarray) or obj.ndim != ndim or obj.dtype.kind not in kind:
        shape = getattr(obj, "shape", None)
        raise _Bad(
            f"{name} must be a {ndim}-d array of kind {kind!r}; got {_qualname(obj)} {shape}"
        )
    if finite and obj.dtype.kind == "f" and not np.all(np.isfinite(obj)):
        raise _Bad(f"{name} holds non-finite values")
    return obj


def _number(value: Any, name: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, Real | np.floating | np.integer):
        raise _Bad(f"{name} must be a number; got {type(value).__name__}")
    if not (math.isfinite(float(value)) and low <= float(value) <= high):
        raise _Bad(f"{name} = {value!r:.40} outside [{low:g}, {high:g}]")
    return float(value)


def _labels(obj: Any, name: str) -> list[str]:
    if (
        not isinstance(obj, np.ndarray)
        or obj.ndim != 1
        or not 2 <= len(obj) <= LIMITS.model_classes
    ):
        raise _Bad(f"{name} must be a 1-d array of 2 to {LIMITS.model_classes} class names")
    values = list(obj)
    if not all(isinstance(v, str) for v in values):
        raise _Bad(f"{name} must hold strings")
    if any(b <= a for a, b in itertools.pairwise(values)):
        raise _Bad(f"{name} must be sorted and distinct")
    return values


def _check_terrain(model: Any) -> None:
    """The TerrainModel's own fitted attributes."""

    if model.kind not in CLASSIFIERS or model.mode not in MODES:
        raise _Bad(f"kind {model.kind!r:.30} or mode {model.mode!r:.30} unknown")
    _labels(model.classes_, "classes_")
    omega = _array(model.omega_, "omega_", 1)
    if not 2 <= len(omega) <= LIMITS.model_bins or omega[0] <= 0 or np.any(np.diff(omega) <= 0):
        raise _Bad("omega_ must be 2 or more increasing positive wavenumbers")
    names, thresholds = model.level_names_, model.level_thresholds_
    if not (
        isinstance(names, tuple | list)
        and 2 <= len(names) <= 100
        and all(isinstance(n, str) for n in names)
        and isinstance(thresholds, tuple | list)
        and len(thresholds) == len(names) - 1
    ):
        raise _Bad("level_names_ / level_thresholds_ malformed")
    values = [_number(t, "level_thresholds_", 0.0) for t in thresholds]
    if any(b <= a for a, b in itertools.pairwise(values)):
        raise _Bad("level_thresholds_ must increase")
    for name in ("cv_report_", "training_", "extraction_"):
        if not isinstance(getattr(model, name), dict):
            raise _Bad(f"{name} must be a dict")
    try:
        Extraction.from_dict(model.extraction_)
    except Exception as err:
        raise _Bad(f"extraction_ invalid ({brief(err, 60)})") from None
    if (model.filter_ is None) != (model.evidence_per_m_ is None):
        raise _Bad("filter_ and evidence_per_m_ must both be set or both None")
    if model.evidence_per_m_ is not None:
        _number(model.evidence_per_m_, "evidence_per_m_", 1e-12)


def _check_filter(flt: Any, classes: np.ndarray) -> None:
    _is(flt, "rough_map.filter.path_filter.PathFilter")
    flt._check_params()
    got = _labels(flt.classes_, "filter_.classes_")
    if got != list(classes):
        raise _Bad("filter_.classes_ differ from the model's classes_")
    k = len(got)
    if flt.n_features_in_ != k:
        raise _Bad(f"filter_.n_features_in_ must be {k}")
    gen = _array(flt.generator_, "filter_.generator_", 2)
    if gen.shape != (k, k):
        raise _Bad(f"filter_.generator_ must be {k} x {k}; got {gen.shape}")
    off = gen[~np.eye(k, dtype=bool)]
    if np.any(off < 0) or np.any(np.abs(gen) > _MAX_RATE):
        raise _Bad("filter_.generator_ must have rates in [0, 1e6] 1/m off the diagonal")
    if np.any(np.abs(gen.sum(axis=1)) > 1e-9 * max(1.0, float(np.abs(gen).max()))):
        raise _Bad("filter_.generator_ rows must sum to 0")
    prior = _array(flt.class_prior_, "filter_.class_prior_", 1)
    if prior.shape != (k,) or np.any(prior < 0) or abs(prior.sum() - 1) > 1e-6:
        raise _Bad("filter_.class_prior_ must be K probabilities summing to 1")
    _number(flt.emission_weight_, "filter_.emission_weight_", 1e-12, 1.0)


def _check_defects(defects: Any) -> None:
    _is(defects, "rough_map.filter.defects.IsolatedSpikes")
    fields = ("ratio", "window", "max_length", "margin")
    if set(vars(defects)) != set(fields):
        raise _Bad("defects has other fields than IsolatedSpikes'")
    type(defects)(**{f: getattr(defects, f) for f in fields})  # its own checks


def _check_novelty(score: Any, n_features: int) -> None:
    """The novelty score's class means, precisions and threshold (sizes and finiteness)."""
    _is(score, "rough_map.classify.novelty.ClassDistance")
    means = _array(score.means_, "novelty_.means_", 2)
    precisions = _array(score.precisions_, "novelty_.precisions_", 3)
    k, d = means.shape
    if k != len(_labels(score.classes_, "novelty_.classes_")) or precisions.shape != (k, d, d):
        raise _Bad(f"novelty_ arrays disagree: means {means.shape}, precisions {precisions.shape}")
    if d != n_features:
        raise _Bad(f"novelty_ has {d} features for a classifier of {n_features!r:.20}")
    _number(score.threshold_, "novelty_.threshold_", 1e-12)
    _number(score.quantile, "novelty_.quantile", 0.5, 1.0)


def _check_nodes(
    left: Any, right: Any, feature: Any, leaf: Any, n_features: int, name: str
) -> None:
    """Tree nodes: children after their parent and in range, features in range."""
    n = len(left)
    idx = np.arange(n)
    inner = ~leaf
    if n == 0 or not (len(right) == len(feature) == len(leaf) == n):
        raise _Bad(f"{name}: node arrays of different lengths")
    for child in (left, right):
        if np.any(inner & ((child <= idx) | (child >= n))):
            raise _Bad(f"{name}: child index out of range")
    if np.any(inner & ((feature < 0) | (feature >= n_features))):
        raise _Bad(f"{name}: feature index out of range")


def _check_forest(est: Any, n_features: int, n_classes: int) -> None:
    trees = est.estimators_
    if not isinstance(trees, list) or not 1 <= len(trees) <= 10_000:
        raise _Bad("forest estimators_ must be a list of 1 to 10000 trees")
    for i, tree in enumerate(trees):
        _is(tree, "sklearn.tree._classes.DecisionTreeClassifier")
        t = tree.tree_
        _is(t, "sklearn.tree._tree.Tree")
        left, right = np.asarray(t.children_left), np.asarray(t.children_right)
        if t.n_features != n_features or list(t.n_classes) != [n_classes] or t.n_outputs != 1:
            raise _Bad(f"tree {i}: n_features/n_classes/n_outputs inconsistent")
        _check_nodes(left, right, np.asarray(t.feature), left == -1, n_features, f"tree {i}")
        value = np.asarray(t.value)
        if value.shape != (len(left), 1, n_classes) or not np.all(np.isfinite(value)):
            raise _Bad(f"tree {i}: value array malformed")
        if not np.all(np.isfinite(np.asarray(t.threshold))):
            raise _Bad(f"tree {i}: non-finite threshold")


def _check_hgb(est: Any, n_features: int, n_classes: int) -> None:
    per_iter = 1 if n_classes == 2 else n_classes
    if est.n_trees_per_iteration_ != per_iter:
        raise _Bad("hgb n_trees_per_iteration_ inconsistent with the classes")
    base = _array(est._baseline_prediction, "hgb _baseline_prediction", 2)
    if base.shape != (1, per_iter):
        raise _Bad("hgb _baseline_prediction has the wrong shape")
    preds = est._predictors
    if not isinstance(preds, list) or not 1 <= len(preds) <= 100_000:
        raise _Bad("hgb _predictors must be a non-empty list")
    if est.is_categorical_ is not None or getattr(est, "_preprocessor", None) is not None:
        raise _Bad("hgb with categorical features is not a rough_map model")
    for i, trees in enumerate(preds):
        if not isinstance(trees, list) or len(trees) != per_iter:
            raise _Bad(f"hgb iteration {i}: wrong number of trees")
        for tree in trees:
            _is(tree, "sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor")
            nodes = tree.nodes
            if not isinstance(nodes, np.ndarray) or nodes.ndim != 1 or nodes.dtype.names is None:
                raise _Bad(f"hgb iteration {i}: nodes malformed")
            from sklearn.ensemble._hist_gradient_boosting.common import PREDICTOR_RECORD_DTYPE

            if nodes.dtype != PREDICTOR_RECORD_DTYPE or np.any(nodes["is_categorical"]):
                raise _Bad(f"hgb iteration {i}: nodes of the wrong type")
            leaf = nodes["is_leaf"].astype(bool)
            _check_nodes(
                nodes["left"], nodes["right"], nodes["feature_idx"], leaf, n_features, "hgb"
            )
            if not np.all(np.isfinite(nodes["value"])):
                raise _Bad(f"hgb iteration {i}: non-finite leaf value")


def _check_estimator(est: Any, kind: str, n_features: int, n_classes: int) -> None:
    if getattr(est, "n_features_in_", None) != n_features:
        raise _Bad(f"base estimator n_features_in_ must be {n_features}")
    if kind == "logistic":
        _is(est, "sklearn.linear_model._logistic.LogisticRegression")
        rows = 1 if n_classes == 2 else n_classes
        coef = _array(est.coef_, "coef_", 2)
        intercept = _array(est.intercept_, "intercept_", 1)
        if coef.shape != (rows, n_features) or intercept.shape != (rows,):
            raise _Bad(f"coef_ {coef.shape} / intercept_ {intercept.shape} inconsistent")
    elif kind == "forest":
        _is(est, "sklearn.ensemble._forest.RandomForestClassifier")
        if est.verbose or not (est.n_jobs is None or isinstance(est.n_jobs, int)):
            raise _Bad("forest verbose/n_jobs not as trained")
        _check_forest(est, n_features, n_classes)
    else:
        _is(
            est,
            "sklearn.ensemble._hist_gradient_boosting.gradient_boosting.HistGradientBoostingClassifier",
        )
        if est.verbose:
            raise _Bad("hgb verbose not as trained")
        _check_hgb(est, n_features, n_classes)


def _check_classifier(model: Any) -> int:
    """The pipeline; returns the width of its input."""

    pipe = model.classifier_
    _is(pipe, "sklearn.pipeline.Pipeline")
    steps = pipe.steps
    if not isinstance(steps, list) or [s[0] for s in steps] != ["features", "scale", "classifier"]:
        raise _Bad("classifier_ must be the pipeline features, scale, classifier")
    feats, scale, calib = (s[1] for s in steps)
    _is(feats, "rough_map.classify.spectral.SpectralFeatures")
    width = len(INPUT_SCALARS) + len(model.omega_)
    if tuple(feats.scalars) != INPUT_SCALARS or feats.n_features_in_ != width:
        raise _Bad(f"features step expects {feats.n_features_in_!r:.20} columns, not {width}")
    omega = _array(feats.omega_, "features.omega_", 1)
    if omega.shape != model.omega_.shape or not np.allclose(omega, model.omega_, rtol=1e-6):
        raise _Bad("features.omega_ differ from the model's omega_")
    band = _array(feats.band_, "features.band_", 1, kind="iu")
    if band.shape != omega.shape or band.min() < -1 or band.max() >= len(omega):
        raise _Bad("features.band_ malformed")
    names = feats.feature_names_out_
    if (
        not isinstance(names, np.ndarray)
        or names.ndim != 1
        or not 1 <= len(names) <= LIMITS.model_features
    ):
        raise _Bad("features.feature_names_out_ malformed")
    n = len(names)
    _is(scale, "sklearn.preprocessing._data.StandardScaler")
    if scale.n_features_in_ != n:
        raise _Bad(f"scale step expects {scale.n_features_in_!r:.20} features, not {n}")
    for attr in ("mean_", "scale_", "var_"):
        value = getattr(scale, attr)
        if value is not None and _array(value, f"scale.{attr}", 1).shape != (n,):
            raise _Bad(f"scale.{attr} must have {n} values")
    if scale.scale_ is not None and np.any(scale.scale_ <= 0):
        raise _Bad("scale.scale_ must be positive")
    _is(calib, "sklearn.calibration.CalibratedClassifierCV")
    cls = _labels(calib.classes_, "classifier.classes_")
    if not set(cls) <= set(model.classes_) or calib.n_features_in_ != n:
        raise _Bad("classifier classes_ or n_features_in_ inconsistent with the model")
    fitted = calib.calibrated_classifiers_
    if not isinstance(fitted, list) or not 1 <= len(fitted) <= 100:
        raise _Bad("calibrated_classifiers_ must be a list of 1 to 100")
    for one in fitted:
        _is(one, "sklearn.calibration._CalibratedClassifier")
        _check_estimator(one.estimator, model.kind, n, len(cls))
        if not isinstance(one.calibrators, list) or not 1 <= len(one.calibrators) <= len(cls):
            raise _Bad("calibrators malformed")
        for c in one.calibrators:
            _is(
                c,
                "sklearn.calibration._TemperatureScaling",
                "sklearn.calibration._SigmoidCalibration",
            )
    return width


def _trial_features(width: int, omega: np.ndarray) -> np.ndarray:
    """Six plausible frames: scalar columns then log10 PSD, from smooth to rough ground."""
    rows = []
    for log_r in (-7.0, -6.0, -5.0, -4.5, -4.0, -3.0):
        r = 10.0**log_r
        scalars = [r, 2.0, 0.2 * r, 0.1, 1e-3 * 10 ** (log_r / 2 + 2.5), r, 2.1, 0.1, 1e-10]
        psd = log_r - 2.0 * np.log10(omega)
        rows.append(np.concatenate([scalars, psd]))
    X = np.array(rows)
    if X.shape[1] != width:  # pragma: no cover - guarded by _check_classifier
        raise _Bad("trial feature matrix has the wrong width")
    return X


def _trial(model: Any, width: int) -> None:
    """Run predict's steps on synthetic frames; any exception or a bad output is refused."""

    X = _trial_features(width, model.omega_)
    clf = model.classifier_
    proba = np.asarray(clf.predict_proba(X), dtype=float)
    k = len(clf.classes_)
    if proba.shape != (len(X), k) or not np.all(np.isfinite(proba)):
        raise _Bad(f"trial predict_proba gave shape {proba.shape} or non-finite values")
    if np.any(proba < -1e-9) or np.any(np.abs(proba.sum(axis=1) - 1) > 1e-6):
        raise _Bad("trial predict_proba gave rows that are not probabilities")
    classes = model.classes_
    raw = np.zeros((len(X), len(classes)))
    raw[:, np.searchsorted(classes, clf.classes_)] = proba
    distance = np.arange(len(X), dtype=float) * 0.5
    valid = np.ones(len(X), dtype=bool)
    if model.filter_ is not None:
        for mode in MODES:
            filtered, labels = model._filter(raw, distance, valid, mode)
            if filtered.shape != raw.shape or not np.all(np.isfinite(filtered)):
                raise _Bad(f"trial path filter ({mode}) gave a bad result")
            if len(labels) != len(X):
                raise _Bad(f"trial path filter ({mode}) gave {len(labels)} classes")
    if getattr(model, "novelty_", None) is not None:
        score = np.asarray(model.novelty_.novelty(clf[:-1].transform(X)), dtype=float)
        if score.shape != (len(X),) or np.any(score < 0):
            raise _Bad("trial novelty score gave a bad result")
    if model.defects is not None:
        flags = np.asarray(model.defects(X[:, 0], distance))
        if flags.shape != (len(X),):
            raise _Bad("trial defect detector gave a bad result")


def check_loaded_model(model: Any, where: Path) -> None:
    """Raise :class:`ModelError` unless a loaded TerrainModel is well formed and predicts.

    Parameters
    ----------
    model : TerrainModel
        As rebuilt by skops (its type and ``format_`` already checked).
    where : Path
        The model file, for messages.
    """
    try:
        _check_terrain(model)
        width = _check_classifier(model)
        if model.filter_ is not None:
            _check_filter(model.filter_, model.classes_)
        if model.defects is not None:
            _check_defects(model.defects)
        if getattr(model, "novelty_", None) is not None:
            _check_novelty(model.novelty_, model.classifier_.named_steps["scale"].n_features_in_)
    except _Bad as err:
        raise ModelError(f"{where}: malformed model: {err!s:.150}") from None
    except Exception as err:  # missing attributes, wrong types, ...
        raise ModelError(f"{where}: malformed model ({brief(err)})") from None
    try:
        with np.errstate(all="ignore"):
            _trial(model, width)
    except _Bad as err:
        raise ModelError(f"{where}: fails a trial prediction: {err!s:.150}") from None
    except Exception as err:  # whatever the rebuilt objects raise
        raise ModelError(f"{where}: fails a trial prediction ({brief(err)})") from None
