"""Learning the roughness smoother's noise model from labelled traverses.

:meth:`rough_map.filter.RoughnessSmoother.fit` calls :func:`learn_noise_model`. The labels
(the ground under each patch) cut every traverse into *segments* of one kind of ground;
within a segment the model of :mod:`rough_map.filter.roughness` says that the measured
``z = (ln R, w)`` is the ground's slowly drifting ``(ln R, w)`` plus a frame error, and at
a change of label the ground jumps. Three things are learnt, in this order:

1. **Error lengths** ``L`` (m): the integral scale of a frame's error along the path,
   ``L = ∫ rho(d) dd`` over both signs of the lag, from the autocorrelation ``rho`` of the
   frames' deviations from their segment's mean (integrated up to its first non-positive
   value), for the two uncorrelated parts of the error: the log PSD level at the fit's
   pivot, ``ln R + kappa w`` (:func:`level_transform`), and w. Consecutive patches overlap
   and the ground's roughness varies over metres, so frames closer than ``L`` share their
   error; frames over a stretch ``D > L`` carry about ``D / L`` independent measurements.
2. **Process noise** ``q`` (1/m) and the **measurement covariance** of one frame (2 x 2):
   maximum likelihood of the random-walk model on the frames of each segment thinned to
   one every ``d0`` m, where ``d0`` is the lag at which the autocorrelation first reaches 0
   (so that the thinned frames' errors are about independent), each thinned sequence
   starting at its first frame, so that only the drift within segments counts. Thinning
   is done from several starting offsets and their log-likelihoods are added (a composite
   likelihood). ``q`` is kept at or above ``min_process_noise``.
3. **Jump covariance** (2 x 2): the mean outer product of the differences between the
   means of consecutive segments, the size of a change of ground.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from rough_map import errors

__all__ = [
    "NoiseModel",
    "Segment",
    "error_length",
    "labelled_segments",
    "learn_noise_model",
    "level_transform",
]

log = logging.getLogger(__name__)

#: Lag bin in m of the autocorrelation of the frames' errors.
LAG_BIN = 0.25
#: Longest lag in m looked at for the error length.
MAX_LAG = 10.0
#: Fewest frames of a segment that count (shorter ones are mostly transition).
MIN_SEGMENT_FRAMES = 8
#: Starting offsets (fractions of the thinning distance) of the thinned sequences.
THIN_OFFSETS = (0.0, 0.25, 0.5, 0.75)


@dataclass(frozen=True)
class Segment:
    """The frames of one stretch of one kind of ground.

    Attributes
    ----------
    distance : ndarray, shape (n,)
        Distance along the path, m.
    z : ndarray, shape (n, 2)
        Measured ``(ln R, w)`` (R in m³/rad), frames with a measurement only.
    label : str
        The ground's label.
    """

    distance: NDArray[np.float64]
    z: NDArray[np.float64]
    label: str


@dataclass(frozen=True)
class NoiseModel:
    """What :func:`learn_noise_model` learns (see the module docstring for the units)."""

    process_noise: NDArray[np.float64]
    measurement_cov: NDArray[np.float64]
    error_length: NDArray[np.float64]
    jump_cov: NDArray[np.float64]
    n_segments: int
    n_changes: int


def labelled_segments(
    z: NDArray[np.float64],
    distance: NDArray[np.float64],
    labels: NDArray[Any],
    use: NDArray[np.bool_],
) -> list[Segment]:
    """Runs of one non-empty label in a traverse (frames without a measurement dropped).

    A frame without a label ends a run; runs are kept in path order, also the short ones
    (they still mark a change of ground for the jump covariance).
    """
    out: list[Segment] = []
    lab = np.asarray(labels, dtype=object)
    n = len(lab)
    start = 0
    for i in range(1, n + 1):
        if i == n or lab[i] != lab[start]:
            if lab[start] != "":
                sel = np.arange(start, i)[use[start:i]]
                if sel.size:
                    out.append(Segment(distance[sel], z[sel], str(lab[start])))
            start = i
    return out


def learn_noise_model(traverses: Sequence[list[Segment]], min_process_noise: float) -> NoiseModel:
    """The noise model of the segments of several traverses (module docstring).

    Raises
    ------
    InputError
        Fewer than two segments of at least :data:`MIN_SEGMENT_FRAMES` frames, or no
        change of label between two segments.
    """
    long = [s for segs in traverses for s in segs if len(s.distance) >= MIN_SEGMENT_FRAMES]
    if len(long) < 2:
        raise errors.InputError(
            f"fitting the roughness smoother needs at least 2 labelled stretches of "
            f"{MIN_SEGMENT_FRAMES} or more valid frames; got {len(long)}"
        )
    jumps = [
        a.z.mean(axis=0) - b.z.mean(axis=0)
        for segs in traverses
        for a, b in itertools.pairwise(segs)
        if a.label != b.label and min(len(a.distance), len(b.distance)) >= MIN_SEGMENT_FRAMES
    ]
    if not jumps:
        raise errors.InputError(
            "fitting the roughness smoother needs at least one change of label between "
            "two labelled stretches (the size of a change of ground)"
        )
    length, apart = error_length(long)
    q, cov = _max_likelihood(long, apart, min_process_noise)
    d = np.asarray(jumps)
    return NoiseModel(q, cov, length, d.T @ d / len(d), len(long), len(d))


def error_length(segments: Sequence[Segment]) -> tuple[NDArray[np.float64], float]:
    """Integral scale in m of the frames' errors along the path, for the log PSD level at
    the pivot and for w (:func:`level_transform`), and the distance in m beyond which they
    are uncorrelated.

    The autocorrelation of the deviations from each segment's mean, pooled over the
    segments in lag bins of :data:`LAG_BIN` m, integrated over both signs of the lag up to
    its first non-positive bin (at least one bin); that bin's lag, the larger of the two,
    is the distance.
    """
    nbins = int(round(MAX_LAG / LAG_BIN)) + 1
    sums = np.zeros((nbins, 2))
    counts = np.zeros(nbins)
    pooled = np.vstack([seg.z - seg.z.mean(axis=0) for seg in segments])
    to_level = level_transform(np.cov(pooled.T))
    for seg in segments:
        r = (seg.z - seg.z.mean(axis=0)) @ to_level.T
        s = seg.distance
        for i in range(len(s)):
            k = np.rint((s[i:] - s[i]) / LAG_BIN).astype(np.intp)
            inside = k < nbins
            np.add.at(sums, k[inside], r[i:][inside] * r[i])
            np.add.at(counts, k[inside], 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        acf = sums / counts[:, None]
        acf = acf / acf[0]
    out = np.empty(2)
    apart = LAG_BIN
    for j in range(2):
        bad = ~(acf[:, j] > 0)  # NaN (an empty bin) ends the sum too
        end = int(np.argmax(bad)) if bad.any() else nbins
        # bin 0 counts once, the others on both sides of zero lag
        out[j] = max(LAG_BIN, LAG_BIN * (2.0 * float(acf[:end, j].sum()) - 1.0))
        apart = max(apart, LAG_BIN * end)
    return out, apart


def level_transform(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T`` (2 x 2) with ``T @ (ln R, w) = (ln R + kappa w, w)`` and ``kappa`` such that
    the errors of the two are uncorrelated under the error covariance ``cov`` of
    (ln R, w): the first is the log PSD level at ``exp(kappa)`` rad/m, near the middle of
    the band, where the fit pivots."""
    kappa = -float(cov[0, 1]) / float(cov[1, 1])
    return np.array([[1.0, kappa], [0.0, 1.0]])


def thinned(distance: NDArray[np.float64], spacing: float, offset: float) -> NDArray[np.intp]:
    """Indices of frames at least ``spacing`` m apart, the first ``offset`` m or more
    from the first frame."""
    idx = []
    last = -math.inf
    for i, d in enumerate(distance):
        if d - distance[0] >= offset and d - last >= spacing:
            idx.append(i)
            last = d
    return np.asarray(idx, dtype=np.intp)


def _max_likelihood(
    segments: Sequence[Segment], spacing: float, min_q: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Process noise (1/m) and one frame's covariance, by maximum (composite) likelihood of
    the random walk on the segments thinned to one frame every ``spacing`` m."""
    seqs = []
    for seg in segments:
        for frac in THIN_OFFSETS:
            idx = thinned(seg.distance, spacing, frac * spacing)
            if idx.size >= 2:
                seqs.append((np.diff(seg.distance[idx]), seg.z[idx]))
    if not seqs:
        raise errors.InputError(
            f"the labelled stretches are all shorter than the error length ({spacing:.2f} m): "
            "no drift to learn from"
        )
    pooled = np.vstack([s.z - s.z.mean(axis=0) for s in segments])
    var = pooled.var(axis=0)
    corr = float(np.corrcoef(pooled.T)[0, 1])
    theta0 = np.array(
        [
            math.log(max(0.01 * var[0], min_q)),
            math.log(max(0.01 * var[1], min_q)),
            0.5 * math.log(var[0]),
            0.5 * math.log(var[1]),
            math.atanh(np.clip(corr, -0.9, 0.9)),
        ]
    )
    low = math.log(min_q)
    bounds = [(low, 5.0), (low, 5.0), (-12.0, 5.0), (-12.0, 5.0), (-3.0, 3.0)]
    res = minimize(
        _neg_log_likelihood,
        theta0,
        args=(seqs,),
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": 500, "ftol": 1e-12, "gtol": 1e-8},
    )
    if not res.success:
        log.warning("roughness smoother fit: the optimiser stopped early (%s)", res.message)
    q, cov = _unpack(res.x)
    log.info(
        "roughness smoother fit on %d thinned sequences (%.2f m apart): q %s 1/m",
        len(seqs),
        spacing,
        np.array2string(q, precision=4),
    )
    return q, cov


def _unpack(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    q = np.exp(theta[:2])
    s = np.exp(theta[2:4])
    rho = math.tanh(float(theta[4]))
    cov = np.array([[s[0] ** 2, rho * s[0] * s[1]], [rho * s[0] * s[1], s[1] ** 2]])
    return q, cov


def _neg_log_likelihood(
    theta: NDArray[np.float64], seqs: list[tuple[NDArray[np.float64], NDArray[np.float64]]]
) -> float:
    """Mean negative log-likelihood per innovation of the random walk (prediction error
    decomposition); each sequence starts at its first frame with that frame's covariance."""
    q, cov = _unpack(theta)
    total = 0.0
    count = 0
    for steps, z in seqs:
        x = z[0].copy()
        P = cov.copy()
        for k in range(1, len(z)):
            P = P + np.diag(q * steps[k - 1])
            S = P + cov
            nu = z[k] - x
            Si = np.linalg.inv(S)
            total += 0.5 * (float(nu @ Si @ nu) + math.log(np.linalg.det(S)))
            count += 1
            K = P @ Si
            x = x + K @ nu
            P = P - K @ P
    return total / max(count, 1) + math.log(2 * math.pi)
