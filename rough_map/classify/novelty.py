"""How unlike every trained class a frame's ground is: the novelty score of a terrain model.

The classifier always names the nearest class, even on ground it never saw (a road's
chipseal, a cobbled track, a boulder bar). :class:`ClassDistance` measures how far a frame
lies from each class in the classifier's own feature space (the scaled features of
:class:`~rough_map.classify.SpectralFeatures`, which leave out the sensor-dependent spreads):
the Mahalanobis distance to each class's mean under its own covariance (Ledoit-Wolf
shrinkage, :class:`sklearn.covariance.LedoitWolf`), per feature, taking the nearest class.

The scale comes from held-out data: fitted on the other folds of whole traverses, the
distances of each fold's frames give the distance that a share ``quantile`` of unseen
frames of known ground stay within (``threshold_``). A frame's ``novelty`` is its distance
over that threshold: 1 is the edge of what the training ground looks like, so about
``1 - quantile`` of frames of trained ground exceed 1; ground unlike every class reads well
above it.
"""

from __future__ import annotations

import math
from numbers import Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator

from rough_map import errors
from rough_map.classify.validation import check_fitted

__all__ = ["NOVELTY_QUANTILE", "ClassDistance", "held_out_distances"]

#: Share of held-out frames of trained ground whose novelty stays at or below 1.
NOVELTY_QUANTILE = 0.99

#: Fewest frames of a class for its own covariance (fewer: the pooled one of all classes).
_MIN_CLASS_FRAMES = 10


class ClassDistance(BaseEstimator):
    """Distance of feature rows to the nearest class, in units of the held-out threshold.

    Parameters
    ----------
    quantile : float
        Share of held-out frames of trained ground that :meth:`calibrate` puts at or below
        a novelty of 1 (default :data:`NOVELTY_QUANTILE`).

    Attributes
    ----------
    classes_ : ndarray of str, shape (K,)
    means_ : ndarray, shape (K, d)
        Mean feature row of each class.
    precisions_ : ndarray, shape (K, d, d)
        Inverse of each class's shrunk covariance.
    threshold_ : float
        Distance (per feature, dimensionless) that ``quantile`` of held-out frames stay
        within; NaN until :meth:`calibrate`.
    """

    def __init__(self, quantile: float = NOVELTY_QUANTILE) -> None:
        self.quantile = quantile

    def fit(self, Z: ArrayLike, y: ArrayLike) -> ClassDistance:
        """Fit the class means and shrunk covariances on finite rows ``Z`` with labels ``y``.

        Raises
        ------
        InputError
            Rows and labels of different lengths, no finite row, or a bad ``quantile``.
        """
        from sklearn.covariance import LedoitWolf

        q = self.quantile
        if not (isinstance(q, Real) and 0.5 <= q < 1):
            raise errors.InputError(f"quantile must be in [0.5, 1); got {q!r}")
        Z = np.asarray(Z, dtype=float)
        labels = np.asarray(y).astype(str)
        if Z.ndim != 2 or len(Z) != len(labels):
            raise errors.InputError(
                f"rows and labels differ: {Z.shape} feature rows for {len(labels)} labels"
            )
        ok = np.isfinite(Z).all(axis=1)
        Z, labels = Z[ok], labels[ok]
        if len(Z) < 2:
            raise errors.InputError("the novelty score needs at least 2 frames with features")
        classes = np.unique(labels)
        centred = Z - _class_means(Z, labels, classes)[np.searchsorted(classes, labels)]
        pooled = LedoitWolf().fit(centred)
        means, precisions = [], []
        for c in classes:
            rows = Z[labels == c]
            means.append(rows.mean(axis=0))
            cov = LedoitWolf().fit(rows) if len(rows) >= _MIN_CLASS_FRAMES else pooled
            precisions.append(cov.precision_)
        self.classes_: NDArray[np.object_] = classes.astype(object)
        self.means_: NDArray[np.float64] = np.array(means)
        self.precisions_: NDArray[np.float64] = np.array(precisions)
        self.threshold_: float = math.nan
        return self

    def distance(self, Z: ArrayLike) -> NDArray[np.float64]:
        """Per row, the Mahalanobis distance to the nearest class divided by sqrt(d)
        (dimensionless; NaN for rows with a non-finite feature)."""
        check_fitted(self, "means_")
        Z = np.asarray(Z, dtype=float)
        out = np.full(len(Z), np.nan)
        ok = np.isfinite(Z).all(axis=1)
        if ok.any():
            diff = Z[ok][None, :, :] - self.means_[:, None, :]  # (K, n, d)
            sq = np.einsum("knd,kde,kne->kn", diff, self.precisions_, diff)
            out[ok] = np.sqrt(np.maximum(sq.min(axis=0), 0.0) / self.means_.shape[1])
        return out

    def calibrate(self, held_out: ArrayLike) -> ClassDistance:
        """Set ``threshold_`` to the ``quantile`` of held-out distances (finite ones).

        Raises
        ------
        InputError
            No finite held-out distance.
        """
        d = np.asarray(held_out, dtype=float)
        d = d[np.isfinite(d)]
        if d.size == 0:
            raise errors.InputError("no held-out frame to set the novelty threshold from")
        self.threshold_ = float(np.quantile(d, self.quantile))
        return self

    def novelty(self, Z: ArrayLike) -> NDArray[np.float64]:
        """Per row, :meth:`distance` over ``threshold_`` (> 1: outside what ``quantile`` of
        unseen frames of trained ground reach; NaN where a feature is not finite)."""
        check_fitted(self, "threshold_")
        return self.distance(Z) / self.threshold_

    def summary(self) -> dict[str, Any]:
        """What the model card says about the score."""
        return {
            "score": "Mahalanobis distance to the nearest class (Ledoit-Wolf covariance per "
            "class) in the classifier's scaled features, per feature, over the threshold",
            "threshold": self.threshold_,
            "quantile": float(self.quantile),
            "flag": "novel when the score is above 1",
        }


def held_out_distances(
    Z: NDArray[np.float64],
    y: NDArray[Any],
    splits: list[tuple[NDArray[np.intp], NDArray[np.intp]]],
    quantile: float = NOVELTY_QUANTILE,
) -> NDArray[np.float64]:
    """Each row's :meth:`ClassDistance.distance` from a score fitted without its fold
    (NaN for rows whose fold's other part has no finite row)."""
    out = np.full(len(Z), np.nan)
    for fit_idx, test_idx in splits:
        if len(test_idx) == 0 or not np.isfinite(Z[fit_idx]).all(axis=1).sum() >= 2:
            continue
        out[test_idx] = ClassDistance(quantile).fit(Z[fit_idx], y[fit_idx]).distance(Z[test_idx])
    return out


def _class_means(Z: NDArray[np.float64], labels: NDArray[Any], classes: NDArray[Any]) -> NDArray:
    return np.array([Z[labels == c].mean(axis=0) for c in classes])
