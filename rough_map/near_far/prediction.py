"""What near-to-far predicts for one image: class probabilities of ground cells."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError

__all__ = ["FarPrediction"]


@dataclass(frozen=True)
class FarPrediction:
    """Class probabilities of ground cells seen in one image, beyond the near field.

    Attributes
    ----------
    x, y : ndarray, shape (N,)
        World coordinates of the cell centres, m.
    ahead, lateral : ndarray, shape (N,)
        The same points in the vehicle frame (x forward, y left), m.
    distance : ndarray, shape (N,)
        Horizontal distance from the vehicle origin, m.
    proba : ndarray, shape (N, K)
        Class probabilities (rows sum to 1), columns in the order of ``classes``.
    classes : tuple of str
        Class names.
    t : float or None
        Time of the frame, s.
    frame : int or None
        Index of the frame in its traverse.
    recalled : ndarray of bool, shape (N,)
        Cells predicted from their look in an earlier image (:class:`NearToFar` ``recall``);
        their ``ahead``, ``lateral`` and ``distance`` are those of that sighting. All false
        by default.
    abstained : ndarray, shape (M,)
        Distances from the vehicle (m) of the cells in view that the model left unknown,
        their confidence being below its threshold (:class:`NearToFar` ``min_confidence``);
        empty by default.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    ahead: NDArray[np.float64]
    lateral: NDArray[np.float64]
    distance: NDArray[np.float64]
    proba: NDArray[np.float64]
    classes: tuple[str, ...]
    t: float | None = None
    frame: int | None = None
    recalled: NDArray[np.bool_] | None = None
    abstained: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        n = np.shape(self.x)
        for name in ("y", "ahead", "lateral", "distance"):
            if np.shape(getattr(self, name)) != n:
                raise InputError(f"FarPrediction.{name} must have shape {n} like x")
        if np.shape(self.proba) != (*n, len(self.classes)):
            raise InputError(
                f"FarPrediction.proba must have shape {(*n, len(self.classes))} (cells, classes)"
            )
        if self.recalled is None:
            object.__setattr__(self, "recalled", np.zeros(n, dtype=bool))
        elif np.shape(self.recalled) != n:
            raise InputError(f"FarPrediction.recalled must have shape {n} like x")
        if self.abstained is None:
            object.__setattr__(self, "abstained", np.zeros(0))

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def label_index(self) -> NDArray[np.intp]:
        """Most probable class index per cell, shape (N,)."""
        return np.argmax(self.proba, axis=1) if len(self) else np.zeros(0, dtype=np.intp)

    @property
    def label(self) -> NDArray[np.str_]:
        """Most probable class name per cell, shape (N,)."""
        return np.asarray(self.classes)[self.label_index]

    @property
    def confidence(self) -> NDArray[np.float64]:
        """Probability of the most probable class per cell, shape (N,)."""
        return self.proba.max(axis=1) if len(self) else np.zeros(0)

    def select(self, mask: ArrayLike) -> FarPrediction:
        """The cells where the boolean ``mask`` (shape (N,)) is true (``abstained`` kept)."""
        m = np.asarray(mask, dtype=bool)
        if m.shape != self.x.shape:
            raise InputError(f"mask must have shape {self.x.shape}, got {m.shape}")
        return FarPrediction(
            self.x[m],
            self.y[m],
            self.ahead[m],
            self.lateral[m],
            self.distance[m],
            self.proba[m],
            self.classes,
            self.t,
            self.frame,
            self.recalled[m],  # type: ignore[index]
            self.abstained,
        )
