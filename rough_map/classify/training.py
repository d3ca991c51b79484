"""Training helpers of the terrain classifier: the pipeline, jittered copies, folds.

* :func:`make_classifier` is the pipeline ``SpectralFeatures -> StandardScaler -> calibrated
  classifier``; :class:`ClassifierRecipe` fits it on jittered copies of the training frames
  (:func:`jitter_levels`) with calibration folds that keep overlapping frames together
  (:func:`calibration_split`);
* :class:`TrainingFrames` stacks the labelled frames of the training traverses, and
  :func:`training_hash` identifies them;
* :func:`traverse_folds` and :func:`held_out_posteriors` cross-validate with whole
  traverses as folds.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map import errors
from rough_map.classify.spectral import INPUT_SCALARS, SpectralFeatures, feature_matrix

log = logging.getLogger(__name__)

__all__ = [
    "CLASSIFIERS",
    "EXCLUDED_FEATURES",
    "ClassifierRecipe",
    "Folds",
    "TrainingFrames",
    "calibration_split",
    "held_out_posteriors",
    "jitter_levels",
    "labels_of",
    "make_classifier",
    "training_hash",
    "traverse_folds",
]

#: Base classifiers :func:`make_classifier` knows; the first is the default.
CLASSIFIERS: tuple[str, ...] = ("logistic", "hgb", "forest")

#: Outputs of :class:`SpectralFeatures` that the default pipeline leaves out, because they
#: describe the sensor (or the renderer of a simulator) as much as the ground:
#:
#: * ``sigma_lnR``, ``sigma_w`` and ``fit_residual``, the scatter of the per-profile fits,
#:   grow with the point noise: three to four standard deviations between a 0.3 mm and a
#:   1.5 mm sensor on the same ground;
#: * ``log10_R`` is fitted up to the Nyquist wavenumber or to the noise floor, whichever
#:   comes first, so it moves with the sensor's noise and with how finely the ground is
#:   rendered (by up to a factor of 2 between simulated worlds at 4 mm and 2 mm on the same
#:   surfaces); ``level``, the same quantity over a fixed band up to 160 rad/m, carries it.
#:
#: ``w`` moves with the sensor too (by 0.1 between those worlds), but it is the paper's
#: best single separator of smooth surfaces (concrete w = -2.0 against dirt road -2.2 at
#: overlapping R), and the band-limited ``slope`` does not replace it: on 13 held-out
#: simulated traverses (other seeds, speeds, 2-20 points per cell, 0.3-2 mm noise) the
#: filtered accuracy is 0.92 without w (0.68 on the worst traverse) and 0.97 with it (0.93
#: on the worst). The model trains with w shifted at random (``waviness_jitter``) so that a
#: bias of a few hundredths costs little; a bias of 0.1 (a sensor that smooths the ground)
#: still costs about 0.1 of accuracy: train on that sensor's data.
EXCLUDED_FEATURES: tuple[str, ...] = ("sigma_lnR", "sigma_w", "fit_residual", "log10_R")


def jitter_levels(
    X: ArrayLike,
    sd: float,
    copies: int,
    rng: np.random.Generator,
    w_sd: float = 0.0,
) -> NDArray[np.float64]:
    """Copies of the rows of a :func:`feature_matrix` with the terrain scaled at random.

    Each copy multiplies the terrain's heights by ``10**(s/2)``, ``s ~ N(0, sd)``: R,
    sigma_R and R_lat by ``10**s``, rms by ``10**(s/2)`` and the log10 PSD shifts by ``s``;
    the sensor's noise floor stays. Used in training so that the classifier leans less on
    the level of the spectrum, which drifts along a uniform stretch by about a factor of 2
    (paper section 5.1, standard deviations of R) and between stretches by more than a few
    training traverses show.

    Parameters
    ----------
    X : array_like, shape (n, len(INPUT_SCALARS) + n_bins)
        Rows of :func:`feature_matrix`.
    sd : float
        Standard deviation of the scaling in log10 units (0.25: a factor of 1.8).
    copies : int
        Jittered copies per row.
    rng : numpy.random.Generator
    w_sd : float, default 0
        Standard deviation of a shift added to the fitted waviness ``w`` and ``w_lat``
        (dimensionless): w is fitted up to where the sensor's noise or resolution takes
        over, so another sensor moves it by a few hundredths to a tenth.

    Returns
    -------
    ndarray, shape (n * (copies + 1), n_features)
        Every row followed by its copies (so that a row's copies stay next to it).
    """
    X = np.asarray(X, dtype=float)
    out = np.repeat(X, copies + 1, axis=0)
    s = sd * rng.normal(size=len(out))
    s[:: copies + 1] = 0.0
    ns = len(INPUT_SCALARS)
    for name in ("R", "sigma_R", "R_lat"):
        out[:, INPUT_SCALARS.index(name)] *= 10.0**s
    out[:, INPUT_SCALARS.index("rms")] *= 10.0 ** (s / 2)
    out[:, ns:] += s[:, None]
    if w_sd > 0:
        dw = w_sd * rng.normal(size=len(out))
        dw[:: copies + 1] = 0.0
        for name in ("w", "w_lat"):
            out[:, INPUT_SCALARS.index(name)] += dw
    return out


def calibration_split(groups: ArrayLike, y: ArrayLike, n_splits: int = 3) -> Any:
    """Calibration folds that keep overlapping frames together and every class in training.

    Neighbouring frames of a traverse see overlapping patches, so folds that split a
    traverse at random leak: the calibration would see near-copies of its training frames
    and stay overconfident. The folds are therefore whole traverses (GroupKFold) when each
    fold leaves every class in its training part; otherwise (one traverse, or a class seen
    in a single traverse) the frames of each class are cut into ``n_splits`` contiguous
    runs, one per fold, so that only the frames at the ends of a run leak. A class with a
    single frame is never held out.

    Parameters
    ----------
    groups : array_like, shape (n_frames,)
        Traverse id per training frame, in the order of the rows passed to ``fit``.
    y : array_like, shape (n_frames,)
        Class per training frame.
    n_splits : int
        Folds (fewer if there are fewer traverses or frames).

    Returns
    -------
    sklearn.model_selection.PredefinedSplit
    """
    from sklearn.model_selection import GroupKFold, PredefinedSplit

    g = np.asarray(groups)
    labels = np.asarray(y)
    if g.shape != labels.shape or g.ndim != 1:
        raise errors.InputError(
            f"groups and y must be 1-D with one value per frame; got {g.shape} and {labels.shape}"
        )
    classes = np.unique(labels)
    fold = np.full(len(g), -1, dtype=np.intp)
    n_groups = len(np.unique(g))
    if n_groups >= 2:
        k = min(n_splits, n_groups)
        for i, (_, test) in enumerate(GroupKFold(k).split(g, groups=g)):
            fold[test] = i
        if all(len(np.unique(labels[fold != i])) == len(classes) for i in range(k)):
            return PredefinedSplit(fold)
        fold[:] = -1
    for c in classes:
        idx = np.flatnonzero(labels == c)
        if len(idx) < 2:
            continue
        k = min(n_splits, len(idx))
        fold[idx] = np.minimum(np.arange(len(idx)) * k // len(idx), k - 1)
    return PredefinedSplit(fold)


def make_classifier(
    kind: str = "logistic",
    *,
    omega: ArrayLike | None = None,
    cv: Any = 3,
    exclude: tuple[str, ...] = EXCLUDED_FEATURES,
    random_state: int | None = 0,
) -> Any:
    """The terrain classifier: ``SpectralFeatures -> StandardScaler -> calibrated classifier``.

    Parameters
    ----------
    kind : {"logistic", "hgb", "forest"}
        Base classifier: multinomial logistic regression (default), histogram gradient
        boosting, or a random forest. On held-out simulated traverses with other seeds,
        speeds and sensors the linear model generalises best (raw macro-F1 0.85 against
        0.80 for boosting and 0.78 for the forest): the classes differ mostly by smooth
        shifts of level, slope and shape of the spectrum, and the trees learn the
        particulars of the training sensors.
    omega : array_like, optional
        Wavenumbers in rad/m of the spectrum columns (``FeatureTable.omega``).
    cv : int or cross-validation splitter, default 3
        Folds of the calibration. Pass ``calibration_split(groups, y)`` for the rows that
        ``fit`` will get: an integer means stratified folds, which leak between the
        overlapping patches of neighbouring frames and leave the probabilities overconfident.
    exclude : tuple of str
        Features of :class:`SpectralFeatures` to leave out; default
        :data:`EXCLUDED_FEATURES`.
    random_state : int
        Seed of the base classifier.

    Returns
    -------
    sklearn.pipeline.Pipeline
        Steps ``features``, ``scale`` and ``classifier``. The base classifier weighs the
        classes equally (``class_weight="balanced"``), so that its posteriors do not carry
        the class frequencies of the training courses (see
        :func:`emission_log_likelihood`); it is wrapped in a ``CalibratedClassifierCV`` with
        temperature scaling (one temperature for all classes, which keeps the ranking of
        the classes and so the raw labels) and ``ensemble=False`` (one base model).
    """
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler

    if kind == "hgb":
        from sklearn.ensemble import HistGradientBoostingClassifier

        base: Any = HistGradientBoostingClassifier(
            learning_rate=0.05,
            max_iter=200,
            max_leaf_nodes=15,
            l2_regularization=1.0,
            class_weight="balanced",
            random_state=random_state,
        )
    elif kind == "logistic":
        from sklearn.linear_model import LogisticRegression

        base = LogisticRegression(C=1.0, class_weight="balanced", max_iter=2000)
    elif kind == "forest":
        from sklearn.ensemble import RandomForestClassifier

        base = RandomForestClassifier(
            n_estimators=200,
            min_samples_leaf=5,
            class_weight="balanced",
            random_state=random_state,
        )
    else:
        raise errors.InputError(f"kind must be one of {CLASSIFIERS}; got {kind!r}")
    return Pipeline(
        [
            ("features", SpectralFeatures(omega=omega, exclude=tuple(exclude))),
            ("scale", StandardScaler()),
            (
                "classifier",
                CalibratedClassifierCV(base, method="temperature", cv=cv, ensemble=False),
            ),
        ]
    )


def labels_of(table: Any) -> NDArray[np.object_]:
    """The ``label`` column of a features table as str, ``""`` for unlabelled frames."""
    return np.array([str(v) if v is not None else "" for v in table.columns["label"]], dtype=object)


def training_hash(tables: Sequence[Any]) -> str:
    """sha256 of what a model is trained on: per traverse its name, wavenumbers, input
    matrix (:func:`feature_matrix`), labels and distances along the path.

    Parameters
    ----------
    tables : sequence of FeatureTable

    Returns
    -------
    str
        Hex digest.
    """
    digest = hashlib.sha256()
    for table in tables:
        X, _ = feature_matrix(table)
        digest.update(table.name.encode())
        digest.update(np.ascontiguousarray(table.omega, dtype="<f8").tobytes())
        digest.update(np.ascontiguousarray(X, dtype="<f8").tobytes())
        digest.update("\x1f".join(labels_of(table)).encode())
        digest.update(np.ascontiguousarray(table.distance(), dtype="<f8").tobytes())
    return digest.hexdigest()


@dataclass(frozen=True, eq=False)
class TrainingFrames:
    """The labelled frames of the training traverses, stacked in traverse order.

    Attributes
    ----------
    X : ndarray, shape (n_frames, len(INPUT_SCALARS) + n_bins)
        Rows of :func:`feature_matrix` (NaN rows for frames without a valid patch).
    y : ndarray of str, shape (n_frames,)
        Terrain class per frame.
    traverse : ndarray of int, shape (n_frames,)
        Index of the frame's traverse in ``names``.
    distance : ndarray, shape (n_frames,)
        Distance travelled along the path in m, from the start of the frame's traverse.
    valid : ndarray of bool, shape (n_frames,)
        Frames with a valid patch and finite features.
    omega : ndarray, shape (n_bins,)
        Wavenumbers in rad/m of the spectrum columns.
    names : tuple of str
        Names of the traverses.
    """

    X: NDArray[np.float64]
    y: NDArray[np.object_]
    traverse: NDArray[np.intp]
    distance: NDArray[np.float64]
    valid: NDArray[np.bool_]
    omega: NDArray[np.float64]
    names: tuple[str, ...]

    @classmethod
    def from_tables(cls, tables: Sequence[Any]) -> TrainingFrames:
        """The labelled frames of features tables (frames without a label are left out).

        Parameters
        ----------
        tables : sequence of FeatureTable
            One per traverse, computed with one patch geometry, with ``label`` set.

        Raises
        ------
        InputError
            No tables, mixed wavenumbers, a traverse without labels, fewer than two
            classes, or no frame with both a label and a valid patch.
        """
        if len(tables) == 0:
            raise errors.InputError("no traverses given")
        omega = np.asarray(tables[0].omega, dtype=float)
        parts: dict[str, list[Any]] = {k: [] for k in ("X", "y", "g", "d", "v")}
        for i, table in enumerate(tables):
            if not np.allclose(table.omega, omega, rtol=1e-6):
                raise errors.InputError(
                    f"traverse {table.name!r} has other wavenumbers than {tables[0].name!r} "
                    "(another patch size or spacing); compute all features with one patch"
                )
            y = labels_of(table)
            if not (y != "").any():
                raise errors.InputError(
                    f"traverse {table.name!r} has no labelled frames; training needs a terrain "
                    "class ('label') on the frames"
                )
            X, _ = feature_matrix(table)
            parts["X"].append(X)
            parts["y"].append(y)
            parts["g"].append(np.full(len(table), i))
            parts["d"].append(table.distance())
            parts["v"].append(table.valid & np.isfinite(X).all(axis=1))
        stacked = {k: np.concatenate(v) for k, v in parts.items()}
        labelled = stacked["y"] != ""
        if not labelled.all():
            log.warning("%d frames without a label are left out of training", (~labelled).sum())
        frames = cls(
            X=stacked["X"][labelled],
            y=stacked["y"][labelled],
            traverse=stacked["g"][labelled],
            distance=stacked["d"][labelled],
            valid=stacked["v"][labelled],
            omega=omega,
            names=tuple(str(t.name) for t in tables),
        )
        classes = np.unique(frames.y)
        if len(classes) < 2:
            raise errors.InputError(
                f"training needs at least 2 terrain classes; the labels hold only {list(classes)}"
            )
        if not frames.valid.any():
            raise errors.InputError("no frame has both a label and a valid patch")
        return frames


@dataclass(frozen=True, eq=False)
class ClassifierRecipe:
    """How to fit the classifier of :func:`make_classifier` on training frames.

    Each training frame is used as it is and in ``copies`` jittered copies
    (:func:`jitter_levels`); the calibration folds keep the frames of a traverse (or of a
    run of one class) together (:func:`calibration_split`).

    Attributes
    ----------
    kind : str
        Base classifier, one of :data:`CLASSIFIERS`.
    omega : ndarray
        Wavenumbers in rad/m of the spectrum columns.
    exclude : tuple of str
        Features the classifier does not see.
    random_state : int or None
        Seed of the base classifier.
    level_jitter : float
        Standard deviation in log10 units of the random scaling of the terrain.
    waviness_jitter : float
        Standard deviation of the random shift of w (dimensionless).
    copies : int
        Jittered copies per frame.
    """

    kind: str
    omega: NDArray[np.float64]
    exclude: tuple[str, ...] = EXCLUDED_FEATURES
    random_state: int | None = 0
    level_jitter: float = 0.0
    waviness_jitter: float = 0.0
    copies: int = 0

    def fit(
        self,
        X: NDArray[np.float64],
        y: NDArray[Any],
        groups: NDArray[Any],
        rng: np.random.Generator,
    ) -> Any:
        """A classifier fitted on the rows ``X`` (labels ``y``) and their jittered copies.

        Parameters
        ----------
        X : ndarray, shape (n, len(INPUT_SCALARS) + n_bins)
            Rows of :func:`feature_matrix`, all valid.
        y : ndarray, shape (n,)
            Class per row.
        groups : ndarray, shape (n,)
            Traverse (or block) per row, for the calibration folds.
        rng : numpy.random.Generator
            Source of the jitter (drawn from in every call).

        Returns
        -------
        sklearn.pipeline.Pipeline
            Fitted.
        """
        reps = self.copies + 1
        clf = make_classifier(
            self.kind,
            omega=self.omega,
            cv=calibration_split(np.repeat(groups, reps), np.repeat(y, reps)),
            exclude=tuple(self.exclude),
            random_state=self.random_state,
        )
        return clf.fit(
            jitter_levels(X, self.level_jitter, self.copies, rng, self.waviness_jitter),
            np.repeat(y, reps),
        )


@dataclass(frozen=True, eq=False)
class Folds:
    """Cross-validation folds of the training frames.

    Attributes
    ----------
    splits : list of (ndarray, ndarray)
        ``(fit rows, test rows)`` per fold.
    groups : ndarray, shape (n_frames,)
        What keeps frames together: the traverse of each frame, or with one traverse its
        block. The calibration folds and the path filter take them as traverses.
    scheme : str
        What the folds are, for the report.
    by_traverse : bool
        True for folds of whole traverses.
    """

    splits: list[tuple[NDArray[np.intp], NDArray[np.intp]]]
    groups: NDArray[np.intp]
    scheme: str
    by_traverse: bool

    @property
    def n_splits(self) -> int:
        """Number of folds."""
        return len(self.splits)


def traverse_folds(traverse: ArrayLike, n_splits: int) -> Folds:
    """Folds of whole traverses, or contiguous blocks of frames of a single traverse.

    Parameters
    ----------
    traverse : array_like of int, shape (n_frames,)
        Traverse of each frame (frames of a traverse in order).
    n_splits : int
        Folds; fewer if there are fewer traverses.

    Returns
    -------
    Folds
    """
    from sklearn.model_selection import GroupKFold

    g = np.asarray(traverse)
    n_traverses = len(np.unique(g))
    if n_traverses >= 2:
        k = min(n_splits, n_traverses)
        splits = list(GroupKFold(k).split(g, groups=g))
        return Folds(splits, g, f"GroupKFold by traverse ({k} folds of whole traverses)", True)
    n = len(g)
    blocks = np.minimum(np.arange(n) * n_splits // n, n_splits - 1)
    splits = [(np.flatnonzero(blocks != b), np.flatnonzero(blocks == b)) for b in range(n_splits)]
    scheme = (
        f"one traverse: {n_splits} contiguous blocks of frames (neighbouring blocks "
        "share overlapping patches at their edges, so the metrics are optimistic)"
    )
    log.warning("only one traverse: cross-validation uses %s", scheme)
    return Folds(splits, blocks, scheme, False)


def held_out_posteriors(
    recipe: ClassifierRecipe, frames: TrainingFrames, folds: Folds, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Posteriors of every valid frame from a classifier fitted without its fold.

    Parameters
    ----------
    recipe : ClassifierRecipe
    frames : TrainingFrames
    folds : Folds
    rng : numpy.random.Generator
        Source of the jitter, drawn from fold by fold.

    Returns
    -------
    ndarray, shape (n_frames, K)
        Columns ``np.unique(frames.y)``; NaN rows for frames without a valid patch and for
        folds whose training part has fewer than two classes.
    """
    X, y, train = frames.X, frames.y, frames.valid
    classes = np.unique(y)
    held_out = np.full((len(y), len(classes)), np.nan)
    for fit_idx, test_idx in folds.splits:
        fit_idx, test_idx = fit_idx[train[fit_idx]], test_idx[train[test_idx]]
        if len(np.unique(y[fit_idx])) < 2 or len(test_idx) == 0:
            continue
        clf = recipe.fit(X[fit_idx], y[fit_idx], folds.groups[fit_idx], rng)
        cols = np.searchsorted(classes, clf.classes_)
        held_out[test_idx] = 0.0
        held_out[np.ix_(test_idx, cols)] = clf.predict_proba(X[test_idx])
    return held_out
