"""Input checks shared by the scikit-learn estimators of rough_map (classify and filter).

scikit-learn raises ``ValueError`` and its own ``NotFittedError``; rough_map raises
:class:`~rough_map.errors.InputError` and :class:`~rough_map.errors.NotFittedError`. The
helpers here raise errors that are both, so that callers of either library catch them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from numbers import Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.exceptions import NotFittedError as _SklearnNotFittedError
from sklearn.utils.validation import check_is_fitted, validate_data

from rough_map import errors

__all__ = [
    "NotFittedError",
    "check_fitted",
    "is_number",
    "model_failures",
    "validate_frames",
    "validate_labelled",
]


class NotFittedError(errors.NotFittedError, _SklearnNotFittedError):
    """Raised before ``fit``; is both rough_map's and scikit-learn's ``NotFittedError``."""


def check_fitted(estimator: Any, attributes: str | list[str], message: str | None = None) -> None:
    """Raise :class:`NotFittedError` unless ``estimator`` has the fitted ``attributes``.

    Parameters
    ----------
    estimator : estimator
    attributes : str or list of str
        Attributes that ``fit`` sets.
    message : str, optional
        The error message (scikit-learn's by default).
    """
    try:
        check_is_fitted(estimator, attributes)
    except _SklearnNotFittedError as err:
        raise NotFittedError(message or str(err)) from err


def validate_frames(estimator: Any, X: ArrayLike, *, reset: bool) -> NDArray[np.float64]:
    """``sklearn.utils.validation.validate_data`` of ``X`` allowing NaN rows, raising InputError.

    NaN marks a frame without a measurement.

    Parameters
    ----------
    estimator : estimator
    X : array_like, shape (n_frames, n_features)
    reset : bool
        True in ``fit`` (records ``n_features_in_``), False after.

    Returns
    -------
    ndarray, shape (n_frames, n_features)

    Raises
    ------
    InputError
        What ``validate_data`` raises as ``ValueError``.
    """
    return _validate(estimator, X, "no_validation", reset)


def validate_labelled(
    estimator: Any, X: ArrayLike, y: ArrayLike | None, *, reset: bool
) -> tuple[NDArray[np.float64], NDArray[Any]]:
    """Like :func:`validate_frames`, with the labels ``y`` (one per frame).

    ``y=None`` reaches ``validate_data``, which raises scikit-learn's standard "requires y"
    message.

    Returns
    -------
    X : ndarray, shape (n_frames, n_features)
    y : ndarray, shape (n_frames,)
    """
    return _validate(estimator, X, y, reset)


def _validate(estimator: Any, X: ArrayLike, y: Any, reset: bool) -> Any:
    try:
        return validate_data(estimator, X, y, reset=reset, ensure_all_finite="allow-nan")
    except errors.RoughMapError:
        raise
    except ValueError as err:
        raise errors.InputError(str(err)) from err


def is_number(value: Any) -> bool:
    """True for a finite real number that is not a bool."""
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


@contextmanager
def model_failures(model: Any, part: str) -> Iterator[None]:
    """Turn an unexpected failure of a model's component into a one-line ModelError."""
    try:
        yield
    except errors.RoughMapError:
        raise
    except (
        ValueError,
        IndexError,
        AttributeError,
        TypeError,
        KeyError,
        ArithmeticError,
        RuntimeError,
        MemoryError,
    ) as err:
        text = repr(str(err))
        text = text if len(text) <= 80 else text[:77] + "..."
        raise errors.ModelError(
            f"the model's {part} ({model.kind!r:.20}) failed: {type(err).__name__}: {text}; "
            "the model file is malformed or was written by another version"
        ) from err


def check_components(path_filter: Any, defects: Any) -> None:
    """Raise InputError unless the components have the interface TerrainModel uses."""
    if path_filter is not None:
        methods = ("fit", "predict", "predict_proba", "set_params", "get_params")
        missing = [m for m in methods if not callable(getattr(path_filter, m, None))]
        params = path_filter.get_params() if not missing else {}
        if missing or "mode" not in params:
            raise errors.InputError(
                "path_filter must be an estimator with fit, predict, predict_proba and a mode "
                f"parameter (a rough_map.filter.PathFilter); got {path_filter!r}"
            )
        if params.get("inputs", "log_likelihood") != "log_likelihood":
            raise errors.InputError(
                "path_filter takes the log likelihoods of emission_log_likelihood: set "
                f"inputs='log_likelihood'; got inputs={params['inputs']!r}"
            )
    if defects is not None and not callable(defects):
        raise errors.InputError(
            "defects must be None or a callable defects(R, distance) -> bool per frame (a "
            f"rough_map.filter.IsolatedSpikes); got {defects!r}"
        )
