"""A classifier's posteriors as a Pipeline step, so that a :class:`PathFilter` can follow it.

``make_pipeline(StandardScaler(), Posteriors(LogisticRegression()), PathFilter())`` is a
classifier of frames filtered along the path: the path filter takes what ``Posteriors``
gives (``inputs="proba"``), and the pipeline routes ``distance`` and ``groups`` to the steps
that use them (``posteriors__groups``, ``pathfilter__distance``, ``pathfilter__groups``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator, TransformerMixin, clone
from sklearn.utils import Tags

from rough_map import errors
from rough_map.classify.validation import check_fitted, validate_frames, validate_labelled

__all__ = ["Posteriors"]


class Posteriors(TransformerMixin, BaseEstimator):
    """Per-frame class posteriors of a classifier, one column per class.

    ``fit`` fits the classifier on the frames without NaN. ``transform`` gives its
    ``predict_proba``, with a column for every class of ``y`` in sorted order (0 for a class
    the classifier never saw) and a NaN row for a frame with NaN (no measurement: the path
    filter gives it a predict step only). ``fit_transform`` gives *held-out* posteriors
    instead (``cross_val_predict``), as scikit-learn's ``StackingClassifier`` and
    ``TargetEncoder`` do, so that the step after it (a :class:`PathFilter` with
    ``emission_weight="auto"``) learns from what the classifier does on frames it has not
    seen: consecutive frames see overlapping patches, so in-sample posteriors are
    overconfident.

    Parameters
    ----------
    classifier : classifier, default None
        scikit-learn classifier with ``predict_proba``; cloned in ``fit``. None means
        ``LogisticRegression()``.
    cv : int, default 5
        Folds of the held-out posteriors of ``fit_transform``: whole traverses
        (``GroupKFold``) if ``groups`` has at least ``cv`` traverses, else contiguous blocks
        of frames (``KFold`` without shuffling), so that overlapping neighbouring patches do
        not leak between the folds.

    Attributes
    ----------
    classes_ : ndarray, shape (K,)
        ``np.unique(y)``, the output columns.
    classifier_ : classifier
        The classifier fitted on all frames without NaN.
    n_features_in_ : int
        Columns of ``X``.
    """

    def __init__(self, classifier: Any = None, cv: int = 5) -> None:
        self.classifier = classifier
        self.cv = cv

    def __sklearn_tags__(self) -> Tags:
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = True  # a frame without a measurement
        tags.target_tags.required = True
        return tags

    def _base(self) -> Any:
        if self.classifier is not None:
            return self.classifier
        from sklearn.linear_model import LogisticRegression

        return LogisticRegression()

    def fit(self, X: ArrayLike, y: ArrayLike, *, groups: ArrayLike | None = None) -> Posteriors:
        """Fit the classifier on the frames without NaN.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features)
            Per-frame features; rows with NaN are frames without a measurement.
        y : array_like, shape (n_frames,)
            Class label per frame.
        groups : array_like, shape (n_frames,), optional
            Traverse id per frame (used by :meth:`fit_transform` only).

        Returns
        -------
        Posteriors
            ``self``.

        Raises
        ------
        InputError
            ``cv`` not an integer >= 2, mismatched lengths, or NaN in every row.
        """
        if not (isinstance(self.cv, int | np.integer) and self.cv >= 2):
            raise errors.InputError(f"cv must be an integer >= 2; got {self.cv!r}")
        Xv, yv = validate_labelled(self, X, y, reset=True)
        self.classes_ = np.unique(yv)
        finite = _nan_free(Xv)
        if not finite.any():
            raise errors.InputError("X has NaN in every row; nothing to train the classifier")
        self.classifier_ = clone(self._base()).fit(Xv[finite], yv[finite])
        return self

    def fit_transform(
        self, X: ArrayLike, y: ArrayLike | None = None, **fit_params: Any
    ) -> NDArray[np.float64]:
        """Fit, and return held-out posteriors of the training frames.

        Parameters
        ----------
        X, y
            As for :meth:`fit`.
        **fit_params
            ``groups``: traverse id per frame, for folds of whole traverses.

        Returns
        -------
        ndarray, shape (n_frames, K)
            Posteriors from ``cross_val_predict``: each frame's from a classifier fitted
            without its fold; NaN rows for frames with NaN.
        """
        from sklearn.model_selection import GroupKFold, KFold, cross_val_predict

        if y is None:
            raise errors.InputError("Posteriors requires y to fit the classifier")
        groups = fit_params.get("groups")
        self.fit(X, y, groups=groups)
        Xv, yv = validate_labelled(self, X, y, reset=False)
        finite = _nan_free(Xv)
        codes = (
            np.zeros(len(Xv), dtype=np.intp)
            if groups is None
            else np.unique(np.asarray(groups), return_inverse=True)[1].ravel()
        )
        by_traverse = len(np.unique(codes[finite])) >= self.cv
        held_out = cross_val_predict(
            clone(self._base()),
            Xv[finite],
            yv[finite],
            groups=codes[finite] if by_traverse else None,
            cv=GroupKFold(self.cv) if by_traverse else KFold(self.cv),
            method="predict_proba",
        )
        return self._columns(held_out, finite)

    def transform(self, X: ArrayLike) -> NDArray[np.float64]:
        """Posteriors of the fitted classifier.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features)

        Returns
        -------
        ndarray, shape (n_frames, K)
            ``predict_proba`` in the columns of ``classes_``; NaN rows where ``X`` has NaN.
        """
        check_fitted(self, "classifier_")
        Xv = validate_frames(self, X, reset=False)
        finite = _nan_free(Xv)
        proba = self.classifier_.predict_proba(Xv[finite]) if finite.any() else None
        return self._columns(proba, finite)

    def _columns(self, proba: NDArray[np.float64] | None, finite: NDArray[np.bool_]) -> Any:
        """Posteriors of the finite rows in the columns of ``classes_``, NaN elsewhere."""
        out = np.full((len(finite), len(self.classes_)), np.nan)
        out[finite] = 0.0
        if proba is not None:
            cols = np.searchsorted(self.classes_, self.classifier_.classes_)
            out[np.ix_(finite, cols)] = proba
        return out

    def get_feature_names_out(self, input_features: Any = None) -> NDArray[np.object_]:
        """``proba_<class>`` per output column."""
        check_fitted(self, "classes_")
        return np.array([f"proba_{c}" for c in self.classes_], dtype=object)


def _nan_free(X: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Rows of ``X`` without NaN (frames with a measurement)."""
    return np.asarray(~np.isnan(X).any(axis=1), dtype=bool)
