"""The terrain model: classifier, path filter, defect detector and roughness levels.

:class:`TerrainModel` is a scikit-learn estimator composed like scikit-learn's: the path
filter and the defect detector are components given to it (``path_filter``, ``defects``),
duck typed, so that this layer does not depend on :mod:`rough_map.filter`, which sits above
it. The configuration that ships (the classifier of :func:`make_classifier` with a
:class:`rough_map.filter.PathFilter` and :class:`rough_map.filter.IsolatedSpikes`) is built
by :func:`rough_map.filter.make_terrain_model`.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator, clone

from rough_map import errors
from rough_map.classify._rows import row_width, warn_other_rows
from rough_map.classify.crossval import (
    cross_validated_report,
    filtered_held_out,
    scored_frames,
)
from rough_map.classify.evidence import (
    choose_evidence_per_m,
    emission_log_likelihood,
    frame_steps,
)
from rough_map.classify.levels import RoughnessLevels, roughness_level
from rough_map.classify.novelty import ClassDistance, held_out_distances
from rough_map.classify.spectral import INPUT_SCALARS, feature_matrix
from rough_map.classify.training import (
    CLASSIFIERS,
    EXCLUDED_FEATURES,
    ClassifierRecipe,
    Folds,
    TrainingFrames,
    held_out_posteriors,
    labels_of,
    training_hash,
    traverse_folds,
)
from rough_map.classify.validation import check_components, check_fitted, model_failures
from rough_map.patch import Extraction

log = logging.getLogger(__name__)

__all__ = ["MODEL_FORMAT", "MODES", "TerrainModel", "TerrainPrediction"]

#: Identifies the object layout of :class:`TerrainModel`; a loaded model must match it.
#: 2: the path filter and the defect detector are components (``path_filter``, ``defects``).
MODEL_FORMAT = "rough_map.TerrainModel/2"

#: Filter modes of :meth:`TerrainModel.predict`.
MODES = ("forward", "smooth", "viterbi")


@dataclass(frozen=True, eq=False)
class TerrainPrediction:
    """Per-frame output of :meth:`TerrainModel.predict`.

    Attributes
    ----------
    classes : ndarray of str, shape (K,)
        Class names, the columns of the probabilities.
    valid : ndarray of bool, shape (n,)
        Frames with a valid patch (the others get no raw class, and a predict step only in
        the filter).
    raw_proba : ndarray, shape (n, K)
        Calibrated classifier posteriors; NaN rows for invalid frames.
    filtered_proba : ndarray, shape (n, K)
        Posteriors after the path filter (forward filter or smoother, per ``mode``).
    raw_class : ndarray of str, shape (n,)
        Argmax of ``raw_proba``; ``""`` for invalid frames.
    filtered_class : ndarray of str, shape (n,)
        Argmax of ``filtered_proba``, or the Viterbi path when ``mode == "viterbi"``;
        ``""`` for invalid frames (the filter carries its belief over them, but they were
        not read).
    level : ndarray of str, shape (n,)
        Roughness level from R; ``""`` for invalid frames.
    distance : ndarray, shape (n,)
        Distance travelled along the path in m.
    mode : str
        Filter mode used.
    novelty : ndarray, shape (n,)
        How unlike every trained class the frame's ground is (dimensionless, >= 0; the
        model's :class:`~rough_map.classify.novelty.ClassDistance`): above 1 the frame is
        :attr:`novel`. NaN for invalid frames and for a model without the score.
    defect : ndarray of bool, shape (n,)
        Frames that see an isolated defect (a short spike of R,
        the model's ``defects`` detector): the filter gives them a predict step
        only, so that a manhole does not turn the ground around it into rough terrain.
        Their raw class and roughness stay as measured. All False in ``"forward"`` mode
        or when the model has no ``defects`` detector.
    """

    classes: NDArray[np.object_]
    valid: NDArray[np.bool_]
    raw_proba: NDArray[np.float64]
    filtered_proba: NDArray[np.float64]
    raw_class: NDArray[np.object_]
    filtered_class: NDArray[np.object_]
    level: NDArray[np.object_]
    distance: NDArray[np.float64]
    mode: str
    defect: NDArray[np.bool_] | None = None
    novelty: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if self.defect is None:
            object.__setattr__(self, "defect", np.zeros(len(self.valid), dtype=bool))
        if self.novelty is None:
            object.__setattr__(self, "novelty", np.full(len(self.valid), np.nan))

    @property
    def novel(self) -> NDArray[np.bool_]:
        """Frames whose ground is unlike every class the model was trained on (novelty
        above 1): their class is the nearest one, not a match."""
        with np.errstate(invalid="ignore"):
            return np.asarray(np.asarray(self.novelty, dtype=float) > 1.0, dtype=bool)

    @property
    def raw_confidence(self) -> NDArray[np.float64]:
        """Probability of the raw class (NaN for invalid frames)."""
        with np.errstate(invalid="ignore"):
            return np.where(
                self.valid, np.nanmax(np.nan_to_num(self.raw_proba, nan=-1.0), 1), np.nan
            )

    @property
    def filtered_confidence(self) -> NDArray[np.float64]:
        """Filtered probability of the filtered class (NaN for invalid frames)."""
        idx = np.minimum(np.searchsorted(self.classes, self.filtered_class), len(self.classes) - 1)
        picked = self.filtered_proba[np.arange(len(idx)), idx]
        return np.where(self.valid, picked, np.nan)


class TerrainModel(BaseEstimator):
    """Terrain class and roughness level along a traverse: everything a model file holds.

    ``fit`` takes labelled feature tables (one per traverse), cross-validates the classifier
    with whole traverses as folds, fits it on all frames, and fits the path filter on the
    held-out posteriors (so that its evidence per metre matches what the classifier does on
    unseen ground). ``predict`` gives, for every frame of a table, the raw and the filtered
    class with their probabilities, the frames of isolated defects and the roughness level.

    The path filter and the defect detector are components, as scikit-learn composes
    estimators; :func:`rough_map.filter.make_terrain_model` builds the configuration that
    ships. Without them (``None``, the default) there is no smoothing along the path: the
    filtered class is the raw one.

    Parameters
    ----------
    kind : {"logistic", "hgb", "forest"}, default "logistic"
        Base classifier (see :func:`make_classifier`).
    mode : {"forward", "smooth", "viterbi"}, default "smooth"
        Filter mode used by :meth:`predict` unless it is given one: ``"forward"`` is the
        online filter (each frame sees only the frames before it), ``"smooth"`` the
        forward-backward smoother and ``"viterbi"`` the most probable class sequence, for
        recorded traverses. The fitted path filter runs in this mode (its own ``mode`` is
        set to it).
    level_names : tuple of str, default ("low", "medium", "high")
        Roughness levels, smoothest first (paper section 5.5).
    level_thresholds : tuple of float, optional
        Upper bounds on R in m^3/rad of all but the last level; default the ISO 8608 C/D
        and E/F boundaries (see :class:`RoughnessLevels`).
    cv : int, default 5
        Cross-validation folds (whole traverses; fewer if there are fewer traverses).
    evidence_per_m : float or "auto", default "auto"
        Weight of the classifier's evidence per metre travelled, 1/m (see
        :func:`emission_log_likelihood`). "auto" takes the value of
        :data:`EVIDENCE_GRID` with the best filtered macro-F1 on the held-out posteriors
        (:func:`~rough_map.classify.evidence.choose_evidence_per_m`).
    exclude : tuple of str, default EXCLUDED_FEATURES
        Features of :class:`SpectralFeatures` the classifier does not see.
    level_jitter : float, default 0.4
        Standard deviation in log10 units of the random scaling of the terrain in the
        training copies (:func:`jitter_levels`); 0 trains on the frames as they are.
    waviness_jitter : float, default 0.05
        Standard deviation of the random shift of w in the training copies.
    jitter_copies : int, default 3
        Jittered copies of every training frame.
    path_filter : estimator or None, default None
        The path filter, cloned in ``fit`` and fitted on the log likelihoods of
        :func:`emission_log_likelihood` (a :class:`rough_map.filter.PathFilter` with
        ``inputs="log_likelihood"``): anything with ``fit(X, y, distance=, groups=)``,
        ``predict`` and ``predict_proba`` taking ``(X, distance=, groups=, valid=)``, and a
        ``mode`` parameter. None: no smoothing.
    defects : callable or None, default None
        Detector of isolated defects, ``defects(R, distance) -> bool per frame`` with R in
        m^3/rad and distance in m (a :class:`rough_map.filter.IsolatedSpikes`): in
        ``"smooth"`` and ``"viterbi"`` modes the filter does not take the class of those
        frames. None: no test.
    extraction : Extraction or dict, optional
        How the feature tables were computed (:class:`rough_map.patch.Extraction`: patch
        geometry in m, tilt, estimator), stored (as ``Extraction.to_dict``) so that
        ``classify`` and ``evaluate`` compute features the same way. Default the paper's.
    random_state : int, default 0
        Seed of the classifier and of the jitter.

    Attributes
    ----------
    classes_ : ndarray of str
        Terrain classes, from the training labels.
    classifier_ : sklearn.pipeline.Pipeline
        The fitted pipeline of :func:`make_classifier`.
    filter_ : estimator or None
        The fitted path filter (a clone of ``path_filter``), fed by
        :func:`emission_log_likelihood`.
    evidence_per_m_ : float or None
        Evidence per metre travelled of the filter's emissions, 1/m (None without a filter).
    omega_ : ndarray
        Wavenumbers in rad/m of the spectrum the model expects.
    level_names_ : tuple of str
        Roughness levels.
    level_thresholds_ : tuple of float
        Their upper thresholds on R in m^3/rad.
    extraction_ : dict
        Feature extraction settings (``Extraction.to_dict``).
    cv_report_ : dict
        Cross-validated metrics (see :meth:`fit`).
    training_ : dict
        Traverses, frame counts and :func:`training_hash` of the training data.
    novelty_ : ClassDistance or None
        The novelty score (:mod:`rough_map.classify.novelty`), its threshold set from the
        held-out folds; None in a model saved without it.
    format_ : str
        :data:`MODEL_FORMAT`.
    """

    def __init__(
        self,
        kind: str = "logistic",
        mode: str = "smooth",
        level_names: tuple[str, ...] = ("low", "medium", "high"),
        level_thresholds: tuple[float, ...] | None = None,
        cv: int = 5,
        evidence_per_m: float | str = "auto",
        exclude: tuple[str, ...] = EXCLUDED_FEATURES,
        level_jitter: float = 0.4,
        waviness_jitter: float = 0.05,
        jitter_copies: int = 3,
        path_filter: Any = None,
        defects: Any = None,
        extraction: dict[str, Any] | None = None,
        random_state: int = 0,
    ) -> None:
        self.kind = kind
        self.mode = mode
        self.level_names = level_names
        self.level_thresholds = level_thresholds
        self.cv = cv
        self.evidence_per_m = evidence_per_m
        self.exclude = exclude
        self.level_jitter = level_jitter
        self.waviness_jitter = waviness_jitter
        self.jitter_copies = jitter_copies
        self.path_filter = path_filter
        self.defects = defects
        self.extraction = extraction
        self.random_state = random_state

    # ---------------------------------------------------------------- fit

    def _check_params(self) -> RoughnessLevels:
        """Raise InputError on bad parameters; the roughness levels."""
        if self.kind not in CLASSIFIERS:
            raise errors.InputError(f"kind must be one of {CLASSIFIERS}; got {self.kind!r}")
        if self.mode not in MODES:
            raise errors.InputError(f"mode must be forward, smooth or viterbi; got {self.mode!r}")
        per_m = self.evidence_per_m
        if not (
            per_m == "auto" or (isinstance(per_m, Real) and math.isfinite(per_m) and per_m > 0)
        ):
            raise errors.InputError(
                f"evidence_per_m must be 'auto' or a positive number (1/m); got {per_m!r}"
            )
        if not (isinstance(self.cv, Integral) and self.cv >= 2):
            raise errors.InputError(f"cv must be an integer >= 2; got {self.cv!r}")
        for name in ("level_jitter", "waviness_jitter"):
            value = getattr(self, name)
            if not (isinstance(value, Real) and math.isfinite(value) and value >= 0):
                raise errors.InputError(f"{name} must be >= 0; got {value!r}")
        if not (isinstance(self.jitter_copies, Integral) and self.jitter_copies >= 0):
            raise errors.InputError(
                f"jitter_copies must be an integer >= 0; got {self.jitter_copies!r}"
            )
        check_components(self.path_filter, self.defects)
        names = tuple(str(n) for n in self.level_names)
        thresholds = (
            tuple(float(v) for v in RoughnessLevels().values())
            if self.level_thresholds is None
            else tuple(float(v) for v in self.level_thresholds)
        )
        return RoughnessLevels(levels=names, thresholds=thresholds)

    def fit(self, X: Sequence[Any], y: None = None) -> TerrainModel:
        """Train on labelled traverses.

        Frames without a label are left out; frames without a valid patch train the
        switching model of the filter but not the classifier.

        Parameters
        ----------
        X : sequence of FeatureTable
            One per traverse, computed with one patch geometry, with ``label`` set.
        y : None
            The labels are the tables' ``label`` column.

        Returns
        -------
        TerrainModel
            ``self``, fitted. ``cv_report_`` holds the cross-validated metrics: ``scheme``,
            ``n_splits``, ``frames``, and under ``raw`` and ``filtered`` the ``accuracy``,
            ``macro_f1`` and ``f1`` per class, plus ``per_fold`` results.

        Raises
        ------
        InputError
            No traverses, a traverse without labels, fewer than two classes, mixed patch
            geometries, bad parameters, or ``y`` given.
        """
        if y is not None:
            raise errors.InputError(
                "TerrainModel.fit takes its labels from the tables' 'label' column; y must be None"
            )
        levels = self._check_params()
        tables = list(X)
        frames = TrainingFrames.from_tables(tables)
        jitter = self.level_jitter > 0 or self.waviness_jitter > 0
        recipe = ClassifierRecipe(
            kind=self.kind,
            omega=frames.omega,
            exclude=tuple(self.exclude),
            random_state=self.random_state,
            level_jitter=float(self.level_jitter),
            waviness_jitter=float(self.waviness_jitter),
            copies=int(self.jitter_copies) if jitter else 0,
        )
        rng = np.random.default_rng(self.random_state)
        folds = traverse_folds(frames.traverse, self.cv)
        held_out = held_out_posteriors(recipe, frames, folds, rng)
        v = frames.valid
        self.classifier_ = recipe.fit(frames.X[v], frames.y[v], folds.groups[v], rng)
        self.novelty_ = fit_novelty(self.classifier_, frames.X, frames.y, v, folds.splits)
        steps = frame_steps(frames.distance, folds.groups)
        self.filter_, self.evidence_per_m_ = self._fit_filter(frames, folds, held_out, steps)
        filtered = filtered_held_out(
            self.filter_, held_out, frames, folds, steps, self.evidence_per_m_
        )
        self.cv_report_ = cross_validated_report(held_out, filtered, frames, folds, self.mode)
        self.classes_ = np.unique(frames.y)
        self.omega_ = frames.omega
        self.level_names_ = levels.levels
        self.level_thresholds_ = tuple(float(t) for t in levels.values())
        self.extraction_ = Extraction.from_dict(self.extraction).to_dict()
        self.training_ = _training_summary(tables, frames)
        self.format_ = MODEL_FORMAT
        log.info(
            "cross-validated (%s): raw macro-F1 %.3f, filtered macro-F1 %.3f on %d frames",
            self.cv_report_["scheme"],
            self.cv_report_["raw"]["macro_f1"],
            self.cv_report_["filtered"]["macro_f1"],
            self.cv_report_["frames"],
        )
        return self

    def _fit_filter(
        self,
        frames: TrainingFrames,
        folds: Folds,
        held_out: NDArray[np.float64],
        steps: NDArray[np.float64],
    ) -> tuple[Any, float | None]:
        """The fitted path filter and its evidence per metre (None, None without a filter).

        The switching model and the class prior come from the labels, the evidence per
        metre from the held-out posteriors. The classifier is trained with balanced class
        weights, so its posteriors are likelihoods up to a constant: how often each class
        was driven in the training traverses is an accident of the courses, and the
        filter's switching model is where prior knowledge of the path belongs.
        """
        if self.path_filter is None:
            return None, None
        flt = clone(self.path_filter).set_params(mode=self.mode)
        d, g = frames.distance, folds.groups
        flt.fit(emission_log_likelihood(held_out, steps, 1.0), frames.y, distance=d, groups=g)
        if self.evidence_per_m != "auto":
            return flt, float(self.evidence_per_m)
        scored = scored_frames(held_out)
        per_m = choose_evidence_per_m(
            flt, held_out, steps, frames.y, distance=d, groups=g, scored=scored
        )
        return flt, per_m

    # ---------------------------------------------------------------- predict

    def _check_fitted(self) -> None:
        check_fitted(self, "classifier_", "this TerrainModel is not fitted; call fit() first")

    @property
    def levels_(self) -> RoughnessLevels:
        """The roughness levels of the model, as :class:`RoughnessLevels`."""
        self._check_fitted()
        return RoughnessLevels(levels=self.level_names_, thresholds=self.level_thresholds_)

    @property
    def feature_names(self) -> list[str]:
        """Names of the features the classifier sees (see :data:`FEATURE_DOC`)."""
        self._check_fitted()
        return [str(n) for n in self.classifier_.named_steps["features"].get_feature_names_out()]

    def check_labels(self, labels: ArrayLike, where: str = "the data") -> None:
        """Raise :class:`~rough_map.errors.ModelError` if labels hold classes the model lacks.

        Parameters
        ----------
        labels : array_like of str
            Labels; ``""`` (unlabelled) is ignored.
        where : str
            What to name in the message (e.g. the traverse).
        """
        self._check_fitted()
        lab = np.asarray(labels, dtype=object)
        unknown = sorted({str(v) for v in lab[lab != ""]} - {str(c) for c in self.classes_})
        if unknown:
            raise errors.ModelError(
                f"{where} has labels the model does not know: {unknown}; it was trained on "
                f"{[str(c) for c in self.classes_]}"
            )

    def predict(self, table: Any, *, mode: str | None = None) -> TerrainPrediction:
        """Raw and filtered class, their probabilities, and the roughness level per frame.

        Parameters
        ----------
        table : FeatureTable
            Features of one traverse, computed as :meth:`reading` says.
        mode : {"forward", "smooth", "viterbi"}, optional
            Filter mode; default the model's ``mode``.

        Returns
        -------
        TerrainPrediction

        Raises
        ------
        ModelError
            The table's spectrum has other wavenumbers than the model's (another patch).
        """
        self._check_fitted()
        mode = self.mode if mode is None else mode
        if mode not in MODES:
            raise errors.InputError(f"mode must be forward, smooth or viterbi; got {mode!r}")
        X, valid = self._rows(table)
        raw = self._proba(X, valid)
        raw_class = np.full(len(raw), "", dtype=object)
        if valid.any():
            raw_class[valid] = self.classes_[np.argmax(raw[valid], axis=1)]
        distance = np.asarray(table.distance(), dtype=float)
        defect = self._defects(table, valid, distance, mode)
        if self.filter_ is None:
            filtered, filtered_class = raw.copy(), raw_class.copy()
        else:
            filtered, filtered_class = self._filter(raw, distance, valid & ~defect, mode)
        # A frame that was not read gets no class (the filter only carries its belief over it)
        filtered_class = np.where(valid, filtered_class, "").astype(object)
        level = roughness_level(
            np.where(valid, table.columns["R"], np.nan), self.level_names_, self.level_thresholds_
        )
        return TerrainPrediction(
            classes=self.classes_.astype(object),
            valid=valid,
            raw_proba=raw,
            filtered_proba=filtered,
            raw_class=raw_class,
            filtered_class=filtered_class,
            level=level,
            distance=distance,
            mode=mode,
            defect=defect,
            novelty=_logged_novelty(table.name, self._novelty(X, valid), valid),
        )

    def reading(self) -> Extraction:
        """How the frames this model classifies are read: its ``extraction_``, with the
        step chosen for each traverse's density from the model's own up
        (:meth:`rough_map.patch.Extraction.any_density`); :meth:`raw_proba` maps a coarser
        grid's spectrum onto the model's wavenumbers."""
        self._check_fitted()
        return Extraction.from_dict(self.extraction_).any_density()

    def raw_proba(self, table: Any) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The classifier's class probabilities per frame, before the path filter.

        Parameters
        ----------
        table : FeatureTable
            Features computed with the model's patch (:meth:`reading`): at its step, or a
            coarser one for a sparse traverse, whose spectrum is mapped onto the model's
            wavenumbers (:func:`rough_map.classify.on_model_grid`).

        Returns
        -------
        proba : ndarray, shape (n_frames, K)
            Over ``classes_``; NaN rows for frames without a valid measurement.
        valid : ndarray of bool, shape (n_frames,)
            Frames with one.

        Raises
        ------
        ModelError
            The table's wavenumbers are not on the model's patch (another patch size).
        """
        self._check_fitted()
        X, valid = self._rows(table)
        return self._proba(X, valid), valid

    def frame_scores(
        self, table: Any
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
        """:meth:`raw_proba` and :meth:`novelty` of each frame from one pass over its
        features: ``(proba, valid, novelty)``."""
        self._check_fitted()
        X, valid = self._rows(table)
        return self._proba(X, valid), valid, self._novelty(X, valid)

    def novelty(self, table: Any) -> NDArray[np.float64]:
        """How unlike every trained class each frame's ground is (see
        :attr:`TerrainPrediction.novelty`; NaN for invalid frames, or all NaN for a model
        saved without the score)."""
        self._check_fitted()
        return self._novelty(*self._rows(table))

    def _rows(self, table: Any) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The input rows of the classifier (the table's spectrum on the model's
        wavenumbers) and the frames with a valid measurement."""
        self._check_fitted()
        warn_other_rows(self.training_, table)
        X, _ = feature_matrix(table, omega=self.omega_)
        if len(table.omega) != self.omega_.size and len(X):
            log.info(
                "%s: spectrum read to %.0f rad/m (a %.1f mm grid), mapped onto the model's "
                "%d wavenumbers to %.0f rad/m",
                table.name,
                float(table.omega[-1]),
                1e3 * math.pi / float(table.omega[-1]),
                self.omega_.size,
                float(self.omega_[-1]),
            )
        n_scalars = len(INPUT_SCALARS)
        valid = (
            np.asarray(table.valid, dtype=bool)
            & np.isfinite(X[:, :n_scalars]).all(axis=1)
            & np.isfinite(X[:, n_scalars:]).any(axis=1)
        )
        return X, valid

    def _proba(self, X: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
        raw = np.full((len(X), len(self.classes_)), np.nan)
        if valid.any():
            cols = np.searchsorted(self.classes_, self.classifier_.classes_)
            raw[valid] = 0.0
            with model_failures(self, "classifier"):
                raw[np.ix_(valid, cols)] = self.classifier_.predict_proba(X[valid])
        return raw

    def _novelty(self, X: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
        out = np.full(len(X), np.nan)
        score = getattr(self, "novelty_", None)
        if score is not None and valid.any():
            with model_failures(self, "novelty score"):
                out[valid] = score.novelty(self.classifier_[:-1].transform(X[valid]))
        return out

    def _filter(
        self,
        raw: NDArray[np.float64],
        distance: NDArray[np.float64],
        evidence: NDArray[np.bool_],
        mode: str,
    ) -> tuple[NDArray[np.float64], NDArray[np.object_]]:
        """Filtered posteriors and class per frame; frames not in ``evidence`` get a predict
        step only."""
        if self.evidence_per_m_ is None:
            raise errors.ModelError("this TerrainModel has a path filter but no evidence_per_m_")
        flt = copy.copy(self.filter_)
        flt.set_params(mode=mode)
        ll = emission_log_likelihood(raw, frame_steps(distance), self.evidence_per_m_)
        with model_failures(self, "path filter"):
            filtered = flt.predict_proba(ll, distance=distance, valid=evidence)
            if mode == "viterbi":
                filtered_class = flt.predict(ll, distance=distance, valid=evidence).astype(object)
            else:
                filtered_class = self.classes_[np.argmax(filtered, axis=1)].astype(object)
        return filtered, filtered_class

    def _defects(
        self, table: Any, valid: NDArray[np.bool_], distance: NDArray[np.float64], mode: str
    ) -> NDArray[np.bool_]:
        """Frames of an isolated defect (recorded traverses only: the test looks ahead)."""
        none = np.zeros(len(valid), dtype=bool)
        if self.defects is None or mode == "forward" or not valid.any():
            return none
        if not np.all(np.isfinite(distance)):
            log.warning("%s: poses not all finite; isolated defects not looked for", table.name)
            return none
        R = np.where(valid, np.asarray(table.columns["R"], dtype=float), np.nan)
        with model_failures(self, "defect detector"):
            defect = np.asarray(self.defects(R, distance), dtype=bool)
        if defect.any():
            log.info(
                "%s: %d frame(s) see an isolated defect (%r); the filter does not take their class",
                table.name,
                int(defect.sum()),
                self.defects,
            )
        return defect


#: Share of a traverse's valid frames above which its novel frames are a warning, not news:
#: about 1 % of the frames of trained ground are above 1 by construction.
_NOVEL_WARNING_SHARE = 0.1


def _logged_novelty(
    name: str, novelty: NDArray[np.float64], valid: NDArray[np.bool_]
) -> NDArray[np.float64]:
    with np.errstate(invalid="ignore"):
        n_novel = int(np.sum(novelty > 1))
    if n_novel:
        share = n_novel / max(int(valid.sum()), 1)
        level = logging.WARNING if share > _NOVEL_WARNING_SHARE else logging.INFO
        log.log(
            level,
            "%s: %d of %d frames (%.0f %%) look unlike every class the model was trained on "
            "(novelty above 1): their class is the nearest one, not a match",
            name,
            n_novel,
            int(valid.sum()),
            100 * share,
        )
    return novelty


def fit_novelty(
    classifier: Any,
    X: NDArray[np.float64],
    y: NDArray[Any],
    valid: NDArray[np.bool_],
    splits: list[tuple[NDArray[np.intp], NDArray[np.intp]]],
) -> ClassDistance:
    """The novelty score of a fitted classifier pipeline on its training rows.

    The distances are taken in the pipeline's features after scaling (everything but its
    last step). Each fold's frames are scored by a :class:`ClassDistance` fitted on the
    other folds, which sets the threshold; the score is then fitted on every valid frame.
    """
    transform = classifier[:-1]
    Z = np.full((len(X), len(transform.get_feature_names_out())), np.nan)
    Z[valid] = transform.transform(X[valid])
    held_out = held_out_distances(Z, y, splits)
    return ClassDistance().fit(Z[valid], y[valid]).calibrate(held_out)


def _training_summary(tables: Sequence[Any], frames: TrainingFrames) -> dict[str, Any]:
    """Traverses, frame counts and :func:`training_hash` of the training data."""
    return {
        "sha256": training_hash(tables),
        "traverses": [
            {
                "name": str(t.name),
                "frames": int(len(t)),
                "labelled": int((labels_of(t) != "").sum()),
                "valid": int(np.sum(t.valid)),
                "row_spacing_m": row_width(t),
            }
            for t in tables
        ],
        "class_frames": {str(c): int(np.sum(frames.y == c)) for c in np.unique(frames.y)},
    }
