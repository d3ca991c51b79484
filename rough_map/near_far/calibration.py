"""Calibration of near-to-far's confidence: how often a prediction of a given raw
confidence turned out right, learnt from predictions that the near field checked.

The looks are diagonal Gaussians, tile features are neither Gaussian nor independent, far
ground is seen smaller and at a glancing angle (fine texture fades), and terrain of a class
not driven over yet may look like a known one: so the raw posteriors are overconfident
where looks overlap, and the more so the farther the ground. Two sources of checked
predictions are kept, each a bounded reservoir of (raw confidence, right or wrong):

* *held out near field*: every near-field batch is scored before it is learnt
  (prequential: the model has not seen it), against its label;
* *far field checked later*: every far cell's raw prediction is remembered with the
  distance it was made from, and scored when the near-field patch passes over the cell and
  geometry labels it (the rover drives on, so the far field becomes near field).

A prediction whose true class had no look yet counts as wrong: that is the error that
overlapping looks cause when new ground comes into view. Per source (and per distance bin
for the far field) a reliability curve ``P(right | s)`` of the logit ``s`` of the raw top
probability is fitted by isotonic regression (non-decreasing) over blocks of rows shrunk
towards 1/2, each true class weighing the same. The calibrated
confidence of a far cell is the smaller of its distance bin's (or, while that has too few
rows, the nearest nearer bin's) and the near field's; the other classes share the rest
in proportion to their raw probabilities. A confidence threshold on it then means what it
says, and where appearance cannot separate the classes the confidence falls and the
model abstains.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["DistanceCalibration", "ReliabilityCurve", "apply_confidence", "top_logit"]

#: Pseudo-rows (half of them right) each block of the reliability curve is shrunk with.
_PRIOR = 20.0

#: Raw top probabilities are clipped to [1 - _CLIP, _CLIP] before their logit.
_CLIP = 1.0 - 1e-6


def top_logit(proba: NDArray[np.float64]) -> NDArray[np.float64]:
    """Logit of the largest probability of each row, shape (N,)."""
    p = np.clip(proba.max(axis=1), 1.0 - _CLIP, _CLIP)
    return np.asarray(np.log(p / (1.0 - p)))


def apply_confidence(proba: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
    """``proba`` (N, K) with the top class's probability replaced by ``q`` (N,) and the
    other classes sharing ``1 - q`` evenly: the calibration says how often the top class is
    right, not which other class is right when it is not (sharing in proportion to the raw
    probabilities would hand a runner-up of 1e-6 everything the top class lost)."""
    n, k = proba.shape
    top = np.argmax(proba, axis=1)
    out = np.repeat(((1.0 - q) / max(k - 1, 1))[:, None], k, axis=1)
    out[np.arange(n), top] = q
    return out


class ReliabilityCurve:
    """``P(right | s)`` of the logit ``s`` of the raw top probability, from checked rows
    (isotonic regression, :class:`sklearn.isotonic.IsotonicRegression`).

    Parameters
    ----------
    max_rows : int
        Most rows kept (the oldest go first).
    per_batch : int
        Most rows kept of one batch (evenly spaced), so that no frame dominates.
    min_rows : int
        Rows needed before the curve is used (:attr:`ready`); they must also hold checks
        of two classes or more (checks of one class cannot show the classes' looks
        overlapping).
    """

    def __init__(self, max_rows: int = 4000, per_batch: int = 64, min_rows: int = 100) -> None:
        self.max_rows = max_rows
        self.per_batch = per_batch
        self.min_rows = min_rows
        self._curve: Any = None
        self._s: list[NDArray[np.float64]] = []
        self._right: list[NDArray[np.float64]] = []
        self._labels: list[NDArray[np.intp]] = []
        self._dirty = False

    @property
    def n_rows(self) -> int:
        """Checked rows kept."""
        return sum(len(s) for s in self._s)

    @property
    def ready(self) -> bool:
        """Whether enough rows, of two classes or more, were checked for the curve to be
        used."""
        if self.n_rows < self.min_rows:
            return False
        return len(np.unique(np.concatenate(self._labels))) >= 2

    def add(self, s: NDArray[np.float64], right: NDArray[np.bool_], label: int) -> None:
        """Keep checked rows (raw top logits ``s`` and whether the top class was right) of
        true class ``label``, and refit."""
        if not len(s):
            return
        pick = np.unique(np.linspace(0, len(s) - 1, min(self.per_batch, len(s))).astype(np.intp))
        self._s.append(np.asarray(s, dtype=float)[pick])
        self._right.append(np.asarray(right, dtype=float)[pick])
        self._labels.append(np.full(len(pick), label, dtype=np.intp))
        while self.n_rows > self.max_rows and len(self._s) > 1:
            self._s.pop(0)
            self._right.pop(0)
            self._labels.pop(0)
        self._dirty = True

    def _fit(self) -> None:
        s = np.concatenate(self._s)
        y = np.concatenate(self._right)
        labels = np.concatenate(self._labels)
        # each true class weighs the same: the far field may hold any mix of classes, and
        # the first checks of a new class (the errors overlapping looks make) must not
        # drown among the many checks of the class driven on for long
        _, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
        w = 1.0 / counts[inverse]

        from sklearn.isotonic import IsotonicRegression

        # a non-decreasing curve (isotonic regression); its blocks, each shrunk towards
        # 1/2 by _PRIOR pseudo-rows (a few lucky rows at the top of the range must not
        # vouch for a confident label), made non-decreasing again
        w = w / w.sum() * len(w)
        fitted = IsotonicRegression(increasing=True).fit_transform(s, y, sample_weight=w)
        order = np.argsort(s, kind="stable")
        level = fitted[order]
        start = np.flatnonzero(np.r_[True, np.diff(level) != 0])
        block = np.cumsum(np.r_[True, np.diff(level) != 0]) - 1
        weight = np.bincount(block, weights=w[order])
        hits = np.bincount(block, weights=(w * y)[order])
        share = (hits + 0.5 * _PRIOR) / (weight + _PRIOR)
        again = IsotonicRegression(increasing=True).fit_transform(
            np.arange(len(share)), share, sample_weight=weight + _PRIOR
        )
        self._curve = (s[order][start[1:]], np.asarray(again, dtype=float))

    def __call__(self, s: NDArray[np.float64]) -> NDArray[np.float64]:
        """Probability that the top class is right, of raw top logits ``s`` (the curve is
        refitted here if rows came since the last call)."""
        if self._dirty and self.ready:
            self._fit()
            self._dirty = False
        if self._curve is None:
            return np.full(np.shape(s), np.nan)
        edges, values = self._curve
        return np.asarray(values[np.searchsorted(edges, np.asarray(s, dtype=float), side="right")])


class DistanceCalibration:
    """:class:`ReliabilityCurve` per bin of the distance a far prediction was made from,
    plus one for the held-out near field (see the module notes).

    Parameters
    ----------
    edges : sequence of float
        Upper edges of the distance bins, m (the last bin is open).
    min_rows : int
        Checked rows a curve needs before it is used.
    """

    def __init__(
        self, edges: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 6.0), min_rows: int = 100
    ) -> None:
        self.edges = np.asarray(edges, dtype=float)
        self.near = ReliabilityCurve(per_batch=64, min_rows=min_rows)
        self.bins = [
            ReliabilityCurve(max_rows=3000, per_batch=200, min_rows=min_rows)
            for _ in range(len(edges) + 1)
        ]

    def _bin(self, distance: NDArray[np.float64]) -> NDArray[np.intp]:
        return np.asarray(np.searchsorted(self.edges, distance, side="right"))

    def add_far(
        self,
        s: NDArray[np.float64],
        right: NDArray[np.bool_],
        distance: NDArray[np.float64],
        label: int,
    ) -> None:
        """Keep far predictions (raw top logits, right or wrong) checked by a near-field
        label of class ``label``, made from ``distance`` m."""
        b = self._bin(distance)
        for k in np.unique(b):
            self.bins[int(k)].add(s[b == k], right[b == k], label)

    def confidence(
        self, s: NDArray[np.float64], distance: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Calibrated confidence of rows (raw top logits ``s``) predicted from ``distance``
        m: the smaller of the near field's curve (when ready) and the curve of the
        distance bin, or of the nearest nearer bin that is ready; NaN where no far-field
        curve is ready (the near field alone cannot vouch for far ground)."""
        out = np.full(len(s), np.nan)
        near = self.near(s) if self.near.ready else np.full(len(s), np.inf)
        b = self._bin(distance)
        curve: ReliabilityCurve | None = None
        for k, c in enumerate(self.bins):
            curve = c if c.ready else curve
            sel = b == k
            if curve is not None and sel.any():
                out[sel] = np.fmin(near[sel], curve(s[sel]))
        return out

    def summary(self) -> dict[str, object]:
        """Rows and the share right at the highest raw confidence, of the near field and
        of each distance bin (upper edge, m)."""
        edges = [*self.edges.tolist(), float("inf")]

        def top(c: ReliabilityCurve) -> float:
            return float(c(np.array([13.8]))[0]) if c.ready else float("nan")

        far = [(e, c.n_rows, top(c)) for e, c in zip(edges, self.bins, strict=True)]
        return {"near": (self.near.n_rows, top(self.near)), "far": far}
