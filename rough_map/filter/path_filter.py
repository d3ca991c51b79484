"""The path filter: a fitted per-metre switching model run over each traverse.

:class:`PathFilter` is a scikit-learn estimator whose ``fit`` learns the classes, their
prior and the per-metre generator of the switching model from labelled traverses
(:mod:`rough_map.filter.switching`); its prediction methods run the pure functions of
:mod:`rough_map.filter.discrete_bayes` over each traverse. It filters what a classifier
says about each frame; it holds no classifier. To filter a classifier's output, put the
classifier before it in a Pipeline (:class:`rough_map.filter.Posteriors`).
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils import Tags
from sklearn.utils.multiclass import check_classification_targets

from rough_map import errors
from rough_map.classify.model import MODES
from rough_map.classify.validation import (
    check_fitted,
    is_number,
    validate_frames,
    validate_labelled,
)
from rough_map.filter.discrete_bayes import forward, smooth, viterbi
from rough_map.filter.switching import (
    consecutive_steps,
    generator_from_counts,
    switch_statistics,
    transition_matrices,
)

__all__ = ["EMISSION_WEIGHT_GRID", "PathFilter"]

logger = logging.getLogger(__name__)

#: Candidate emission weights tried by ``PathFilter(emission_weight="auto")``.
EMISSION_WEIGHT_GRID = (0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)

_INPUTS = ("proba", "log_likelihood")


class PathFilter(ClassifierMixin, BaseEstimator):
    """HMM filter of terrain classes along the path, with a per-metre switching model.

    ``fit`` learns the classes, their prior and the per-metre generator from labelled
    traverses; ``predict_proba`` runs the filter over each traverse, starting from the class
    prior.

    What ``X`` holds is set by ``inputs``:

    * ``"proba"`` (default): the columns of ``X`` are posteriors p(c | x) of an upstream
      classifier for ``classes_`` in sorted order (``np.unique(y)``). Only ratios within a
      row matter: rows are normalised. For ``emission_weight="auto"`` they must be held-out
      posteriors, as :class:`~rough_map.filter.Posteriors` gives them in a Pipeline.
    * ``"log_likelihood"``: the columns are finite log p(x | c), up to an additive constant
      per frame.

    Rows of ``X`` containing NaN are frames without a measurement: they get a predict step
    only (in ``fit`` they still count for the switching model).

    Parameters
    ----------
    switch_rate_prior : float, default 0.02
        Prior switching rate in 1/m (one class change per 50 m), worth one pseudo-switch; see
        :func:`~rough_map.filter.estimate_generator`.
    min_switch_rate : float, default 1e-3
        Lower bound on each class's switching rate in 1/m.
    emission_weight : float in (0, 1] or "auto", default 0.5
        Exponent applied to each frame's likelihood (a temperature). Consecutive patches
        overlap (~70 % at 0.25 m frame spacing), so their classifier errors are partly shared
        and a frame carries less than one frame's worth of new evidence; with fully shared
        errors the right weight would be about ``1 - overlap`` = 0.3, with independent errors
        1. The default 0.5 was chosen on simulated 500 m traverses (4 classes, 65 % raw
        accuracy, frames every 0.25 m; forward filter accuracy on 4 test traverses at weights
        0.3 / 0.5 / 1.0): independent errors 0.95 / 0.96 / 0.95; half the error variance
        shared over 3 frames 0.93 / 0.94 / 0.91; all of it shared 0.88 / 0.86 / 0.79. The
        weight is per frame: if you know the errors are mostly shared, use about
        ``spacing / patch length``; or use ``"auto"``, which picks the value from
        :data:`EMISSION_WEIGHT_GRID` that maximises the mean log posterior of the true class
        on the training traverses.
    mode : {"forward", "smooth", "viterbi"}, default "forward"
        ``"forward"``: online filter, each frame uses only past frames. ``"smooth"``:
        forward-backward marginals using all frames of the traverse. ``"viterbi"``:
        ``predict`` returns the jointly most probable class sequence and ``predict_proba`` the
        smoothed marginals (whose argmax may differ from that sequence).
    floor : float, default 1e-6
        Posteriors are clipped from below at ``floor`` (after row normalisation), and
        log-likelihoods at ``log(floor)`` below the row maximum, so that no single frame can
        rule a class out.
    inputs : {"proba", "log_likelihood"}, default "proba"
        What the columns of ``X`` are; see above.

    Attributes
    ----------
    classes_ : ndarray, shape (K,)
        Class labels, ``np.unique(y)``.
    class_prior_ : ndarray, shape (K,)
        Class frequencies in the training labels; the initial belief of every traverse and the
        divisor that turns posteriors into scaled likelihoods.
    generator_ : ndarray, shape (K, K)
        Generator ``Q`` in 1/m; ``transition_matrix(d)`` is ``expm(Q * d)``.
    switch_counts_ : ndarray, shape (K, K)
        Class switches ``i -> j`` counted in the training traverses.
    distance_per_class_ : ndarray, shape (K,)
        Metres travelled in each class in the training traverses.
    emission_weight_ : float
        The emission weight in use (equal to ``emission_weight`` unless "auto").
    n_features_in_ : int
        Number of columns of ``X`` (K).

    Notes
    -----
    ``fit``, ``predict_proba``, ``predict`` and ``predict_log_proba`` take keyword-only
    ``distance`` (cumulative distance in m per frame; default 1 m per frame, with a logged
    warning) and ``groups`` (traverse id per frame; frames of a traverse are taken in array
    order). The prediction methods also take ``valid`` (bool per frame; False means predict
    step only).
    """

    def __init__(
        self,
        switch_rate_prior: float = 0.02,
        min_switch_rate: float = 1e-3,
        emission_weight: float | Literal["auto"] = 0.5,
        mode: str = "forward",
        floor: float = 1e-6,
        inputs: Literal["proba", "log_likelihood"] = "proba",
    ) -> None:
        self.switch_rate_prior = switch_rate_prior
        self.min_switch_rate = min_switch_rate
        self.emission_weight = emission_weight
        self.mode = mode
        self.floor = floor
        self.inputs = inputs

    def __sklearn_tags__(self) -> Tags:
        tags = super().__sklearn_tags__()
        # NaN marks a frame without a measurement (predict step only)
        tags.input_tags.allow_nan = True
        return tags

    # ---------------------------------------------------------------- validation helpers

    def _check_params(self) -> None:
        for name in ("switch_rate_prior", "min_switch_rate"):
            value = getattr(self, name)
            if not (is_number(value) and value > 0):
                raise errors.InputError(f"{name} must be a positive number (1/m); got {value!r}")
        if not (is_number(self.floor) and 0 < self.floor < 1):
            raise errors.InputError(f"floor must be in (0, 1); got {self.floor!r}")
        w = self.emission_weight
        if not (w == "auto" or (is_number(w) and 0 < w <= 1)):
            raise errors.InputError(f"emission_weight must be in (0, 1] or 'auto'; got {w!r}")
        if self.mode not in MODES:
            raise errors.InputError(f"mode must be one of {MODES}; got {self.mode!r}")
        if self.inputs not in _INPUTS:
            raise errors.InputError(f"inputs must be one of {_INPUTS}; got {self.inputs!r}")

    # ---------------------------------------------------------------- emissions

    def _log_likelihood(
        self, X: NDArray[np.float64], valid: NDArray[np.bool_], weight: float
    ) -> NDArray[np.float64]:
        """Weighted, floored log likelihood per frame (n, K); zero rows where not valid."""
        ll = np.zeros((len(X), len(self.classes_)))
        if not valid.any():
            return ll
        xv = X[valid]
        if self.inputs == "log_likelihood":
            lv = np.maximum(xv - xv.max(axis=1, keepdims=True), np.log(self.floor))
        else:
            if np.any(xv < 0):
                raise errors.InputError("posteriors in X must be >= 0 (inputs='proba')")
            total = xv.sum(axis=1, keepdims=True)
            if np.any(total <= 0):
                raise errors.InputError(
                    "each valid row of posteriors must have a positive sum; mark frames without "
                    "a measurement with NaN or valid=False"
                )
            lv = np.log(np.maximum(xv / total, self.floor)) - np.log(self.class_prior_)
        ll[valid] = weight * lv
        return ll

    # ---------------------------------------------------------------- fit

    def fit(
        self,
        X: ArrayLike,
        y: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
    ) -> PathFilter:
        """Learn the classes, the class prior and the switching generator from traverses.

        Parameters
        ----------
        X : array_like, shape (n_frames, K)
            Per-frame posteriors or log-likelihoods (see ``inputs``), one column per class.
            Only ``emission_weight="auto"`` uses their values.
        y : array_like, shape (n_frames,)
            True class label per frame (any labels ``np.unique`` can sort, e.g. strings).
        distance : array_like, shape (n_frames,), optional
            Cumulative distance travelled along the path in m per frame, non-decreasing within
            each traverse. Default: 1 m between frames (a warning is logged).
        groups : array_like, shape (n_frames,), optional
            Traverse id per frame; switches are not counted across traverses.

        Returns
        -------
        PathFilter
            ``self``, fitted.

        Raises
        ------
        InputError
            Bad parameters, mismatched lengths, decreasing distance, fewer than two classes,
            or a column count other than the number of classes.
        """
        self._check_params()
        Xv, yv = validate_labelled(self, X, y, reset=True)
        check_classification_targets(yv)
        self.classes_, y_idx = np.unique(yv, return_inverse=True)
        y_idx = y_idx.ravel()
        k = len(self.classes_)
        if k < 2:
            raise errors.InputError(
                f"PathFilter needs at least 2 classes in y to filter between; got {k} class"
            )
        if Xv.shape[1] != k:
            raise errors.InputError(
                f"with inputs={self.inputs!r} the columns of X are the classes "
                f"{list(self.classes_)} (sorted); X has {Xv.shape[1]} columns but y has {k} classes"
            )
        dist, codes = _path(len(Xv), distance, groups)
        self.class_prior_ = np.bincount(y_idx, minlength=k) / len(y_idx)
        self.switch_counts_, self.distance_per_class_ = switch_statistics(y_idx, k, dist, codes)
        self.generator_ = generator_from_counts(
            self.switch_counts_,
            self.distance_per_class_,
            self.switch_rate_prior,
            self.min_switch_rate,
        )
        if self.emission_weight == "auto":
            self.emission_weight_ = self._choose_emission_weight(Xv, y_idx, dist, codes)
        else:
            self.emission_weight_ = float(self.emission_weight)
        logger.info(
            "PathFilter fitted: %d classes, switching rates %s 1/m, emission weight %.2f",
            k,
            np.array2string(-np.diag(self.generator_), precision=4),
            self.emission_weight_,
        )
        return self

    def _choose_emission_weight(
        self,
        X: NDArray[np.float64],
        y_idx: NDArray[np.intp],
        dist: NDArray[np.float64],
        codes: NDArray[np.intp],
    ) -> float:
        """Emission weight from the grid maximising the mean log posterior of the true class."""
        finite_rows = _nan_free(X)
        scores = []
        for w in EMISSION_WEIGHT_GRID:
            log_post = self._run(X, dist, codes, finite_rows, w)[0]
            scores.append(float(np.mean(log_post[np.arange(len(y_idx)), y_idx])))
        best = EMISSION_WEIGHT_GRID[int(np.argmax(scores))]
        logger.info(
            "PathFilter emission_weight='auto': mean log posterior of the true class %s for %s; "
            "chose %.2f",
            np.round(scores, 4).tolist(),
            list(EMISSION_WEIGHT_GRID),
            best,
        )
        return float(best)

    # ---------------------------------------------------------------- inference

    def transition_matrix(self, d_m: ArrayLike) -> NDArray[np.float64]:
        """Class transition matrix over a distance travelled.

        Parameters
        ----------
        d_m : float or array_like
            Distance travelled in m, >= 0 (rounded to 1 mm).

        Returns
        -------
        ndarray, shape (K, K) or (..., K, K)
            ``expm(generator_ * d_m)``: ``[i, j]`` is the probability of being in class
            ``classes_[j]`` after ``d_m`` metres when starting in ``classes_[i]``.
        """
        check_fitted(self, ["classes_", "generator_"])
        return transition_matrices(self.generator_, d_m)

    def _run(
        self,
        X: NDArray[np.float64],
        dist: NDArray[np.float64],
        codes: NDArray[np.intp],
        valid: NDArray[np.bool_],
        weight: float,
        decode: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
        """Filter every traverse: log posteriors (n, K) and, if ``decode``, the Viterbi path."""
        ll = self._log_likelihood(X, valid, weight)
        _, nxt, step = consecutive_steps(dist, codes)
        trans = transition_matrices(self.generator_, step)
        with np.errstate(divide="ignore"):
            log_trans = np.log(trans)
        # index of the step arriving at each frame (-1 for the first frame of a traverse)
        step_into = np.full(len(X), -1, dtype=np.intp)
        step_into[nxt] = np.arange(len(nxt))
        log_init = np.log(self.class_prior_)
        log_post = np.empty_like(ll)
        path = np.empty(len(X), dtype=np.intp) if decode else None
        run = forward if self.mode == "forward" else smooth
        for g in np.unique(codes):
            idx = np.flatnonzero(codes == g)
            lt = log_trans[step_into[idx[1:]]]
            log_post[idx] = run(ll[idx], lt, log_init)
            if path is not None:
                path[idx] = viterbi(ll[idx], lt, log_init)
        return log_post, path

    def _filter(
        self,
        X: ArrayLike,
        distance: ArrayLike | None,
        groups: ArrayLike | None,
        valid: ArrayLike | None,
        decode: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
        check_fitted(self, ["classes_", "generator_"])
        Xv = validate_frames(self, X, reset=False)
        dist, codes = _path(len(Xv), distance, groups)
        mask = _valid_mask(Xv, valid)
        return self._run(Xv, dist, codes, mask, self.emission_weight_, decode)

    def predict_log_proba(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """Log of :meth:`predict_proba`.

        Parameters
        ----------
        X, distance, groups, valid
            As for :meth:`predict_proba`.

        Returns
        -------
        ndarray, shape (n_frames, K)
            Log posterior per frame and class.
        """
        return self._filter(X, distance, groups, valid)[0]

    def predict_proba(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[np.float64]:
        """Filtered (mode "forward") or smoothed (other modes) class posteriors per frame.

        Parameters
        ----------
        X : array_like, shape (n_frames, K)
            As in ``fit``; rows with NaN are frames without a measurement.
        distance : array_like, shape (n_frames,), optional
            Cumulative distance in m per frame, non-decreasing within each traverse. Default:
            1 m between frames (a warning is logged).
        groups : array_like, shape (n_frames,), optional
            Traverse id per frame. Each traverse starts from ``class_prior_``.
        valid : array_like of bool, shape (n_frames,), optional
            False for frames that get a predict step only. Default: rows of ``X`` without NaN.

        Returns
        -------
        ndarray, shape (n_frames, K)
            Posterior per frame over ``classes_``; rows sum to 1.

        Raises
        ------
        InputError
            Shape mismatches, decreasing distance, NaN in a frame marked valid, bad posteriors.
        """
        return np.exp(self.predict_log_proba(X, distance=distance, groups=groups, valid=valid))

    def predict(
        self,
        X: ArrayLike,
        *,
        distance: ArrayLike | None = None,
        groups: ArrayLike | None = None,
        valid: ArrayLike | None = None,
    ) -> NDArray[Any]:
        """Class per frame: argmax of :meth:`predict_proba`, or the Viterbi path.

        Parameters
        ----------
        X, distance, groups, valid
            As for :meth:`predict_proba`.

        Returns
        -------
        ndarray, shape (n_frames,)
            Labels from ``classes_``.
        """
        log_post, path = self._filter(X, distance, groups, valid, self.mode == "viterbi")
        return self.classes_[path if path is not None else np.argmax(log_post, axis=1)]


def _path(
    n: int, distance: ArrayLike | None, groups: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Distance in m and traverse code per frame, checked (non-decreasing per traverse)."""
    if distance is None:
        logger.warning("PathFilter: no distance given; assuming 1 m between frames")
        dist = np.arange(n, dtype=float)
    else:
        dist = np.asarray(distance, dtype=float)
        if dist.shape != (n,):
            raise errors.InputError(
                f"distance must have one value (m) per frame, shape ({n},); got {dist.shape}"
            )
        if not np.all(np.isfinite(dist)):
            raise errors.InputError("distance (m) must be finite")
    if groups is None:
        codes = np.zeros(n, dtype=np.intp)
    else:
        g = np.asarray(groups)
        if g.shape != (n,):
            raise errors.InputError(
                f"groups must have one traverse id per frame, shape ({n},); got {g.shape}"
            )
        codes = np.unique(g, return_inverse=True)[1].ravel().astype(np.intp)
    prev, _, step = consecutive_steps(dist, codes)
    bad = np.flatnonzero(step < 0)
    if len(bad):
        i = int(prev[bad[0]])
        raise errors.InputError(
            f"distance must be non-decreasing within each traverse (group); it decreases "
            f"after frame {i} ({dist[i]} m -> {dist[i] - abs(step[bad[0]])} m)"
        )
    return dist, codes


def _valid_mask(X: NDArray[np.float64], valid: ArrayLike | None) -> NDArray[np.bool_]:
    """Frames with a measurement: ``valid``, or the rows of ``X`` without NaN."""
    finite_rows = _nan_free(X)
    if valid is None:
        return finite_rows
    v = np.asarray(valid)
    if v.shape != (len(X),) or v.dtype != bool:
        raise errors.InputError(
            f"valid must be a boolean array with one value per frame, shape ({len(X)},); "
            f"got dtype {v.dtype} shape {v.shape}"
        )
    bad = np.flatnonzero(v & ~finite_rows)
    if len(bad):
        raise errors.InputError(
            f"X has NaN in frames marked valid=True (first: frame {bad[0]}); mark them "
            "valid=False or leave valid=None to skip NaN frames"
        )
    return v


def _nan_free(X: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Rows of ``X`` without NaN (frames with a measurement)."""
    return np.asarray(~np.isnan(X).any(axis=1), dtype=bool)
