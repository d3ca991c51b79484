"""The appearance model of near-to-far: per class a few "looks" (diagonal Gaussians) of
tile features, learnt batch by batch.

A *batch* is the tiles that see one frame's near-field patch, with the geometric class of
the patch as its label (or class probabilities). :meth:`LooksClassifier.learn` drops the
outliers of the batch (more than ``outlier_k`` robust standard deviations from the batch
median in some feature: a manhole rim), keeps the main look of a patch across a class
boundary (:func:`main_look`: a two-component Gaussian mixture chosen by BIC), then merges
the batch into the nearest familiar look of its class or starts a new look (:class:`Looks`:
running means and variances, Chan's parallel update). A look is used only once
``min_support`` batches fed it: a wrong geometric label starts a look of its own that
stays unused, or light, instead of corrupting the class's main look.

``p(class | tile)`` is proportional to the sum over the class's looks in use of
``n_look * N(features; look)``, ``n_look`` the tiles the look learnt: a mixture over all
looks, so a look taught by a few wrong labels weighs little against the same look learnt by
its own class. A tile far from every look in use (its smallest squared Mahalanobis distance
has a chi-square tail probability below ``novelty_alpha``) is *unfamiliar*: its
probabilities are pulled towards uniform.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import logsumexp
from scipy.stats import chi2, median_abs_deviation
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_is_fitted, validate_data

from rough_map.errors import InputError, RoughMapError

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_MIN_STD", "Looks", "LooksClassifier", "inliers", "main_look"]

#: Default lowest standard deviation of a class per tile feature (units of
#: :data:`rough_map.near_far.tiles.FEATURE_NAMES`). Measured on rendered terrain, a
#: class's far-field tile means stay within about 0.5 L*, 0.05 a* and 0.1 b* of its
#: near-field means, and its log-stds drift by up to 0.4 (L*, fine texture fading with
#: distance) and 0.08 (a*, b*).
DEFAULT_MIN_STD: tuple[float, ...] = (1.0, 0.1, 0.2, 0.25, 0.15, 0.15)


@dataclass
class Looks:
    """Appearance modes ("looks") of the classes: running Gaussians with diagonal covariance.

    Attributes
    ----------
    cls : ndarray of int, shape (L,)
        Class index of each look.
    n : ndarray, shape (L,)
        Tiles learnt (weighted by the label probability).
    mean : ndarray, shape (L, F)
        Mean features.
    m2 : ndarray, shape (L, F)
        Sums of squared deviations from the mean (``var = m2 / n``).
    support : ndarray, shape (L,)
        Updates that fed the look, weighted by the label probability.
    """

    cls: NDArray[np.intp]
    n: NDArray[np.float64]
    mean: NDArray[np.float64]
    m2: NDArray[np.float64]
    support: NDArray[np.float64]

    @classmethod
    def empty(cls, n_features: int) -> Looks:
        """No look yet."""
        return cls(
            np.zeros(0, dtype=np.intp),
            np.zeros(0),
            np.zeros((0, n_features)),
            np.zeros((0, n_features)),
            np.zeros(0),
        )

    @property
    def var(self) -> NDArray[np.float64]:
        """Variances, shape (L, F)."""
        return self.m2 / self.n[:, None]

    def add(
        self, c: int, n: float, mean: NDArray[np.float64], m2: NDArray[np.float64], w: float
    ) -> None:
        """Append a look of class ``c`` from a batch (``n`` tiles, ``mean``, ``m2``)."""
        self.cls = np.append(self.cls, c)
        self.n = np.append(self.n, n)
        self.mean = np.vstack([self.mean, mean])
        self.m2 = np.vstack([self.m2, m2])
        self.support = np.append(self.support, w)

    def merge(
        self, i: int, n: float, mean: NDArray[np.float64], m2: NDArray[np.float64], w: float
    ) -> None:
        """Merge a batch into look ``i`` (Chan et al.'s parallel update of mean and m2)."""
        total = self.n[i] + n
        delta = mean - self.mean[i]
        self.mean[i] = self.mean[i] + delta * (n / total)
        self.m2[i] = self.m2[i] + m2 + delta**2 * (self.n[i] * n / total)
        self.n[i] = total
        self.support[i] += w

    def drop(self, i: int) -> None:
        """Forget look ``i``."""
        keep = np.arange(len(self.cls)) != i
        self.cls, self.n, self.support = self.cls[keep], self.n[keep], self.support[keep]
        self.mean, self.m2 = self.mean[keep], self.m2[keep]


def main_look(x: NDArray[np.float64], min_var: NDArray[np.float64]) -> NDArray[np.float64]:
    """The tiles of the main look of a near-field batch.

    A patch across a class boundary holds two looks, and its label is the class of (at
    most) one of them. A two-component Gaussian mixture (diagonal covariances) is fitted;
    if the Bayesian information criterion prefers it to one Gaussian and the two means are
    told apart (squared distance above the chi-square 0.999 quantile with the variances
    floored at ``min_var``), only the tiles of the larger component are kept.
    """
    # sklearn.mixture pulls in sklearn.cluster, .neighbors, .linear_model ... (~0.3 s):
    # imported only when a near field is split.
    from sklearn.mixture import GaussianMixture

    if len(x) < 20:
        return x
    var1 = np.maximum(x.var(axis=0), 1e-12)
    # BIC of one diagonal Gaussian, in closed form: -2 log L + p log n with p = 2 F.
    bic1 = len(x) * np.sum(np.log(2.0 * np.pi * var1) + 1.0) + 2 * x.shape[1] * np.log(len(x))
    gmm = GaussianMixture(
        2, covariance_type="diag", init_params="k-means++", random_state=0, reg_covar=1e-6
    )
    gmm.fit(x)
    if gmm.bic(x) >= bic1:
        return x
    var = np.maximum(gmm.covariances_.max(axis=0), min_var[0])
    d2 = float((np.diff(gmm.means_, axis=0) ** 2 / var).sum())
    if d2 <= chi2.isf(1e-3, df=x.shape[1]):
        return x
    labels = gmm.predict(x)
    main = int(np.argmax(np.bincount(labels, minlength=2)))
    log.debug(
        "near-to-far: near field holds two looks; keeping %d of %d tiles",
        int((labels == main).sum()),
        len(x),
    )
    return x[labels == main]


def inliers(features: NDArray[np.float64], k: float) -> NDArray[np.bool_]:
    """Rows within ``k`` robust standard deviations (the normal-consistent median absolute
    deviation, at least 1e-6) of the column medians in every column; all rows when ``k`` is
    not finite or there are fewer than 10."""
    if not np.isfinite(k) or len(features) < 10:
        return np.ones(len(features), dtype=bool)
    median = np.median(features, axis=0)
    mad = np.maximum(median_abs_deviation(features, axis=0, scale="normal"), 1e-6)
    return np.all(np.abs(features - median) <= k * mad, axis=1)


class LooksClassifier(ClassifierMixin, BaseEstimator):
    """Classifier of tile features by the looks of their classes (see the module notes).

    Learnt online, one near-field batch at a time (:meth:`learn`, :meth:`partial_fit`);
    :class:`~rough_map.near_far.NearToFar` feeds it one batch per frame.

    Parameters
    ----------
    novelty_alpha : float
        A row whose squared Mahalanobis distance to the nearest look in use has a
        chi-square tail probability ``q`` below this is unfamiliar: its probabilities are
        mixed with the uniform distribution, with weight ``1 - q / novelty_alpha``. 0
        disables the gate. A batch joins a look of its class if its mean passes the same
        test, and starts a new look otherwise.
    outlier_k : float
        Rows of a batch further than this many robust standard deviations (normal-consistent
        MAD) from the batch median in some feature are not learnt; ``inf`` learns them all.
    min_std : float or sequence of float
        Lowest standard deviation of each feature within a look (units of the features):
        one per feature, or one for all; see :data:`DEFAULT_MIN_STD` for the tile features.
    min_support : float
        Batches (weighted by the label's probability) a look needs before it is used: a
        look learnt once may be a wrong label.
    max_looks : int
        Most looks kept per class; the least supported goes first.

    Attributes
    ----------
    classes_ : ndarray, shape (K,)
        Class labels, in the column order of :meth:`predict_proba`.
    n_features_in_ : int
        Features per row.
    looks_ : Looks
        The learnt looks.
    n_updates_ : int
        Batches learnt (empty batches, all outliers, are not counted).
    """

    def __init__(
        self,
        novelty_alpha: float = 1e-3,
        outlier_k: float = 4.0,
        min_std: float | Sequence[float] = DEFAULT_MIN_STD,
        min_support: float = 2.0,
        max_looks: int = 8,
    ) -> None:
        self.novelty_alpha = novelty_alpha
        self.outlier_k = outlier_k
        self.min_std = min_std
        self.min_support = min_support
        self.max_looks = max_looks

    # ------------------------------------------------------------------------ validation

    def _check_params(self, n_features: int) -> None:
        def number(value: Any) -> bool:
            return isinstance(value, Real) and not isinstance(value, bool)

        if not (number(self.novelty_alpha) and 0.0 <= self.novelty_alpha < 1.0):
            raise InputError(f"novelty_alpha must be in [0, 1), got {self.novelty_alpha!r}")
        if not (number(self.outlier_k) and self.outlier_k > 0):
            raise InputError(
                f"outlier_k must be a positive number (or inf), got {self.outlier_k!r}"
            )
        try:
            min_std = np.asarray(self.min_std, dtype=float)
        except (TypeError, ValueError):
            min_std = np.zeros(0)
        if min_std.shape not in ((), (n_features,)) or not np.all(min_std > 0):
            raise InputError(
                f"min_std must be a positive number or {n_features} (one per feature), got "
                f"{self.min_std!r}"
            )
        if not (number(self.min_support) and self.min_support > 0):
            raise InputError(f"min_support must be a positive number, got {self.min_support!r}")
        if not (isinstance(self.max_looks, Integral) and self.max_looks >= 1):
            raise InputError(f"max_looks must be an integer >= 1, got {self.max_looks!r}")

    def _validate_X(self, X: ArrayLike, y: Any = "no_validation", *, reset: bool) -> Any:
        try:
            return validate_data(self, X, y, reset=reset)
        except RoughMapError:
            raise
        except ValueError as err:
            raise InputError(str(err)) from err

    def _start(self, classes: ArrayLike, n_features: int) -> None:
        """Check the parameters and start learning from nothing."""
        self._check_params(n_features)
        labels = np.asarray(classes)
        if labels.ndim != 1 or len(labels) == 0 or len(np.unique(labels)) != len(labels):
            raise InputError(f"classes must be distinct class labels, got {classes!r}")
        self.classes_ = labels
        self.looks_ = Looks.empty(n_features)
        self.n_updates_ = 0

    @property
    def _min_var(self) -> NDArray[np.float64]:
        std = np.broadcast_to(np.asarray(self.min_std, dtype=float), (self.n_features_in_,))
        return np.square(std)[None, :]

    # ------------------------------------------------------------------------ learning

    def fit(self, X: ArrayLike, y: ArrayLike) -> LooksClassifier:
        """Forget everything, then learn the rows of each class of ``y`` as one batch.

        With the default ``min_support`` of 2 a single batch per class puts no look in use,
        and the predictions stay uniform: call :meth:`partial_fit` once per batch instead.

        Parameters
        ----------
        X : array_like, shape (N, F)
            Feature rows.
        y : array_like, shape (N,)
            Class label per row; the classes are those of ``y``, sorted.
        """
        x, labels = self._validate_X(X, y, reset=True)
        check_classification_targets(labels)
        self._start(np.unique(labels), x.shape[1])
        return self.partial_fit(x, labels)

    def partial_fit(
        self, X: ArrayLike, y: ArrayLike, classes: ArrayLike | None = None
    ) -> LooksClassifier:
        """Learn the rows of each class of ``y`` as one batch of that class.

        Parameters
        ----------
        X : array_like, shape (N, F)
            Feature rows.
        y : array_like, shape (N,)
            Class label per row, one of ``classes``.
        classes : array_like, shape (K,), optional
            All the class labels; required at the first call.
        """
        first = not hasattr(self, "looks_")
        x, labels = self._validate_X(X, y, reset=first)
        check_classification_targets(labels)
        if first:
            if classes is None:
                raise InputError("classes must be given at the first call of partial_fit")
            self._start(classes, x.shape[1])
        unknown = sorted(set(np.unique(labels).tolist()) - set(self.classes_.tolist()))
        if unknown:
            raise InputError(f"unknown class labels {unknown}; expected {self.classes_.tolist()}")
        eye = np.eye(len(self.classes_))
        for k, c in enumerate(self.classes_):
            rows = labels == c
            if rows.any():
                self._learn_batch(x[rows], eye[k])
        return self

    def learn(
        self, X: ArrayLike, weights: ArrayLike, *, classes: ArrayLike | None = None
    ) -> LooksClassifier:
        """Learn one batch (the tiles of one near-field patch) with class weights.

        Parameters
        ----------
        X : array_like, shape (N, F)
            Feature rows of the batch.
        weights : array_like, shape (K,)
            Weight of the batch for each class (a one-hot row for a class label, or class
            probabilities); classes of weight 1e-3 or less do not learn it.
        classes : array_like, shape (K,), optional
            All the class labels, in the order of ``weights``; required at the first call.
        """
        first = not hasattr(self, "looks_")
        x = self._validate_X(X, reset=first)
        if first:
            if classes is None:
                raise InputError("classes must be given at the first call of learn")
            self._start(classes, x.shape[1])
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(self.classes_),) or not np.all(np.isfinite(w) & (w >= 0)):
            raise InputError(
                f"weights must be {len(self.classes_)} non-negative numbers, one per class"
            )
        return self._learn_batch(x, w)

    def _learn_batch(self, x: NDArray[np.float64], weights: NDArray[np.float64]) -> LooksClassifier:
        kept = main_look(x[inliers(x, self.outlier_k)], self._min_var)
        if not len(kept):
            log.debug("near-to-far update skipped: no near-field tile left to learn")
            return self
        for c in np.flatnonzero(weights > 1e-3):
            self._learn(int(c), kept, float(weights[c]))
        self.n_updates_ += 1
        log.debug(
            "near-to-far update %d: %d of %d tiles learnt as %s; %d looks",
            self.n_updates_,
            len(kept),
            len(x),
            {str(self.classes_[c]): round(float(weights[c]), 3) for c in np.flatnonzero(weights)},
            len(self.looks_.cls),
        )
        return self

    def _learn(self, c: int, x: NDArray[np.float64], weight: float) -> None:
        """Merge a batch of rows (weight per row) into the nearest familiar look of class
        ``c``, or start a new look."""
        looks = self.looks_
        n = weight * len(x)
        mean = x.mean(axis=0)
        m2 = weight * ((x - mean) ** 2).sum(axis=0)
        mine = np.flatnonzero(looks.cls == c)
        if len(mine):
            var = np.maximum(looks.var[mine], self._min_var)
            d2 = (((mean - looks.mean[mine]) ** 2) / var).sum(axis=1)
            best = int(np.argmin(d2))
            if chi2.sf(d2[best], df=x.shape[1]) >= max(self.novelty_alpha, 1e-12):
                looks.merge(int(mine[best]), n, mean, m2, weight)
                return
        looks.add(c, n, mean, m2, weight)
        if len(mine) + 1 > self.max_looks:
            weakest = mine[np.argmin(looks.support[mine])]
            looks.drop(int(weakest))

    # ------------------------------------------------------------------------ prediction

    def _distances(
        self, x: NDArray[np.float64]
    ) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:
        """Looks in use, squared Mahalanobis distances (N, L) and variances (L, F).

        Each look's variances are floored at ``min_std ** 2``: a few frames of near field
        underestimate how much a class varies elsewhere (shading with the viewing angle,
        fine texture fading with distance), and Gaussians of very different spreads
        extrapolate wildly between them.
        """
        looks = self.looks_
        used = np.flatnonzero(looks.support >= self.min_support)
        var = np.maximum(looks.var[used], self._min_var)
        d2 = (((x[:, None, :] - looks.mean[used][None]) ** 2) / var[None]).sum(axis=-1)
        return used, d2, var

    def predict_proba(self, X: ArrayLike) -> NDArray[np.float64]:
        """Class probabilities of feature rows.

        The looks in use form one Gaussian mixture weighted by the rows each learnt
        (variances floored at ``min_std ** 2``); a class's probability is the share of its
        looks in the mixture's density, zero for classes without a look in use. Unfamiliar
        rows are pulled towards uniform over all classes (see ``novelty_alpha``). Uniform
        while no look is in use.

        Parameters
        ----------
        X : array_like, shape (N, F)
            Feature rows.

        Returns
        -------
        ndarray, shape (N, K)
            Probabilities, rows summing to 1, columns in the order of ``classes_``.
        """
        check_is_fitted(self, "looks_")
        x = self._validate_X(X, reset=False)
        k = len(self.classes_)
        scores, d2 = self._scores(x)
        if scores is None:
            return np.full((len(x), k), 1.0 / k)
        post = np.exp(scores - logsumexp(scores, axis=1, keepdims=True))
        if self.novelty_alpha > 0:
            tail = chi2.sf(d2.min(axis=1), df=x.shape[1])
            known = np.clip(tail / self.novelty_alpha, 0.0, 1.0)[:, None]
            post = known * post + (1.0 - known) / k
        return post

    def _scores(
        self, x: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64]]:
        """Log class scores (N, K): the log of each class's share of the mixture density,
        up to a constant per row, ``-inf`` for classes without a look in use (None while no
        look is in use); and the squared distances (N, L) to the looks in use."""
        used, d2, var = self._distances(x)
        if not len(used):
            return None, d2
        cls = self.looks_.cls[used]
        n = self.looks_.n[used]
        loglik = (
            np.log(n / n.sum())[None]
            - 0.5 * d2
            - 0.5 * np.log(2.0 * np.pi * var).sum(axis=-1)[None]
        )
        scores = np.full((len(x), len(self.classes_)), -np.inf)
        for c in np.unique(cls):
            scores[:, c] = logsumexp(loglik[:, cls == c], axis=1)
        return scores, d2

    def predict(self, X: ArrayLike) -> NDArray[Any]:
        """The most probable class label of each row, shape (N,)."""
        proba = self.predict_proba(X)
        return np.asarray(self.classes_[np.argmax(proba, axis=1)])

    def familiarity(self, X: ArrayLike) -> NDArray[np.float64]:
        """Chi-square tail probability of each row's squared Mahalanobis distance to the
        nearest look in use (0 while no look is in use), shape (N,): a row is familiar when
        this is at least ``novelty_alpha``."""
        check_is_fitted(self, "looks_")
        x = self._validate_X(X, reset=False)
        used, d2, _ = self._distances(x)
        if not len(used):
            return np.zeros(len(x))
        best = np.argmin(d2, axis=1)
        return np.asarray(chi2.sf(d2[np.arange(len(x)), best], df=x.shape[1]), dtype=float)
