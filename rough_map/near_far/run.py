"""Near-to-far along a traverse: predict each imaged frame, then learn its near field."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from numbers import Integral, Real
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.near_far.model import NearToFar
from rough_map.near_far.prediction import FarPrediction
from rough_map.near_far.tiles import check_image, read_bgr, tile_features
from rough_map.patch import Extraction, PatchSpec

if TYPE_CHECKING:
    from rough_map.io.traverse import Traverse

log = logging.getLogger(__name__)

__all__ = ["run_traverse", "settled"]


def run_traverse(
    traverse: Traverse,
    near_labels: Sequence[str | int | None] | ArrayLike,
    *,
    patch: PatchSpec | Extraction | None = None,
    classes: Sequence[str] | None = None,
    model: NearToFar | None = None,
    every: int = 1,
    settle: int = 0,
    min_posterior: float = 0.0,
    posterior: ArrayLike | None = None,
    defect: ArrayLike | None = None,
    progress: bool = False,
    **kwargs: Any,
) -> list[FarPrediction]:
    """Run near-to-far along a traverse, learning frame by frame.

    Each frame with a left image (every ``every``-th of them) is first *predicted* with the
    model learnt from the earlier frames only, then *learnt* with its near label, if that
    label is *settled*. Frames before the first update give no prediction.

    Only confident, settled near labels teach appearance: a label smoothed along the path
    lags a change of ground by a few frames, and the new ground learnt under the old name
    would be copied to the far field. A frame is learnt only if every known label within
    ``settle`` frames of it names the same class, no frame within ``settle`` frames is an
    isolated defect (``defect``) and its ``posterior`` (the probability of its label) is at
    least ``min_posterior``. Its learning then waits until the frame ``settle`` frames
    later has been predicted, so that a prediction never depends on its own frame's label
    or a later one. Every known label, settled or not, checks the model's earlier
    predictions of its ground as soon as it arrives (:meth:`NearToFar.check_tiles`, the
    calibration of the confidence): a lagging name may count a right answer as wrong,
    which only makes the model more cautious, and new ground that looks like known ground
    is caught frames earlier than by the settled labels alone.

    Parameters
    ----------
    traverse : Traverse
        With a calibration and left images (colour).
    near_labels : sequence or ndarray
        One geometric near-field label per frame of the traverse (all frames, imaged or
        not): class names or indices (None or "" where unknown: the frame is not learnt), or
        an array (n_frames, K) of class probabilities (rows of NaN where unknown).
    patch : PatchSpec or Extraction
        The patch the near labels describe (that of the terrain model that gave them); the
        near field of a new model. Required without ``model``.
    classes : sequence of str, optional
        Class names of a new model, in the order of label indices and probability columns;
        by default the distinct names among ``near_labels``, sorted (which must then be
        names).
    model : NearToFar, optional
        A model to continue (then ``patch``, ``classes`` and ``kwargs`` are its own and may
        not be given).
    every : int
        Use every ``every``-th imaged frame.
    settle : int
        Frames (of the traverse) on either side of a learnt frame that must carry the same
        class and no defect; 0 learns every known label.
    min_posterior : float
        Lowest ``posterior`` of a learnt frame.
    posterior : array_like, shape (n_frames,), optional
        Probability of each frame's label (e.g. the path filter's); by default the largest
        class probability of probability labels, 1 for names and indices.
    defect : array_like of bool, shape (n_frames,), optional
        Frames of isolated defects (a manhole, a rock): they and their ``settle``
        neighbours are not learnt.
    progress : bool
        Show a progress bar on stderr.
    **kwargs
        Passed to :class:`~rough_map.near_far.NearToFar`.

    Returns
    -------
    list of FarPrediction
        One per predicted frame, in time order, with ``frame`` and ``t`` set.

    Raises
    ------
    InputError
        No calibration, labels of the wrong length, an unknown label, ``every < 1``, no
        ``patch`` for a new model, or no class names.
    """
    from tqdm import tqdm

    if not (isinstance(every, Integral) and every >= 1):
        raise InputError(f"every must be an integer >= 1, got {every!r}")
    calib = traverse.spec.calibration
    if calib is None:
        raise InputError(f"{traverse.source} has no stereo calibration")
    labels = _labels(near_labels, len(traverse))
    learnable = settled(labels, settle, min_posterior, posterior, defect)
    if model is None:
        if patch is None:
            raise InputError("near-to-far needs the patch of the near labels (patch=...)")
        model = NearToFar(_classes(classes, labels), patch, **kwargs)
    elif patch is not None or classes is not None or kwargs:
        raise InputError("a model to continue brings its own patch, classes and settings")
    imaged = [i for i, f in enumerate(traverse.frames) if f.left is not None][::every]
    out: list[FarPrediction] = []
    waiting: list[tuple[int, NDArray[np.float64]]] = []  # learnt once settle frames later
    n_learnt = 0
    start = time.perf_counter()
    for i in tqdm(imaged, desc="near-to-far", unit="frame", disable=not progress):
        frame = traverse.frames[i]
        left = traverse.resolve(frame.left, f"frames[{i}].left")
        image = check_image(read_bgr(left), calib)
        tiles = tile_features(image, model.tile_px)  # once for predict and update
        if hasattr(model, "looks_"):
            out.append(model.predict_tiles(tiles, calib, frame.pose, t=frame.t, frame=i))
        if labels[i] is not None and hasattr(model, "looks_"):
            model.check_tiles(tiles, calib, labels[i], frame.pose)
        if learnable[i]:
            waiting.append((i, tiles))
        while waiting and waiting[0][0] + settle <= i:
            j, old = waiting.pop(0)
            model.update_tiles(old, calib, labels[j], check=False)
            n_learnt += 1
    for j, old in waiting:  # the last frames: their model is returned, not used here
        model.update_tiles(old, calib, labels[j], check=False)
        n_learnt += 1
    log.info(
        "near-to-far: %d frames, %d learnt, %d predictions in %.1f s",
        len(imaged),
        n_learnt,
        len(out),
        time.perf_counter() - start,
    )
    return out


def settled(
    labels: Sequence[Any],
    settle: int = 0,
    min_posterior: float = 0.0,
    posterior: ArrayLike | None = None,
    defect: ArrayLike | None = None,
) -> NDArray[np.bool_]:
    """Which frames' near labels may teach appearance (see :func:`run_traverse`).

    Parameters
    ----------
    labels : sequence
        One label per frame (None: unknown): a class name, an index or a probability row.
    settle, min_posterior, posterior, defect
        As :func:`run_traverse`.

    Returns
    -------
    ndarray of bool, shape (n_frames,)
    """
    n = len(labels)
    if not (isinstance(settle, Integral) and settle >= 0):
        raise InputError(f"settle must be an integer >= 0 (frames), got {settle!r}")
    if not (isinstance(min_posterior, Real) and 0.0 <= min_posterior <= 1.0):
        raise InputError(f"min_posterior must be in [0, 1], got {min_posterior!r}")
    known = np.array([x is not None for x in labels], dtype=bool)
    names = [_class_of(x) for x in labels]
    if posterior is None:
        post = np.array([_posterior_of(x) for x in labels])
    else:
        post = np.asarray(posterior, dtype=float).ravel()
        if post.shape != (n,):
            raise InputError(f"posterior has {post.size} entries but there are {n} frames")
    bad = np.zeros(n, dtype=bool)
    if defect is not None:
        bad = np.asarray(defect, dtype=bool).ravel()
        if bad.shape != (n,):
            raise InputError(f"defect has {bad.size} entries but there are {n} frames")
    with np.errstate(invalid="ignore"):
        out = known & ~(post < min_posterior)
    for j in np.flatnonzero(out):
        lo, hi = max(0, j - settle), min(n, j + settle + 1)
        window = [names[k] for k in range(lo, hi) if known[k]]
        if bad[lo:hi].any() or any(w != names[j] for w in window):
            out[j] = False
    return out


def _class_of(label: Any) -> Any:
    """The class of a label, comparable between frames: its name, index or argmax."""
    if label is None or isinstance(label, str):
        return label
    arr = np.asarray(label)
    return int(np.argmax(arr)) if arr.ndim == 1 else arr.item()


def _posterior_of(label: Any) -> float:
    """Largest class probability of a probability row; 1 for a name or an index."""
    if label is None or isinstance(label, str):
        return 1.0
    arr = np.asarray(label, dtype=float)
    return float(arr.max() / arr.sum()) if arr.ndim == 1 and arr.sum() > 0 else 1.0


def _labels(near_labels: Sequence[str | int | None] | ArrayLike, n_frames: int) -> list[Any]:
    """One label per frame, None where unknown."""
    if isinstance(near_labels, np.ndarray) and near_labels.ndim == 2:
        labels: list[Any] = [None if np.any(np.isnan(r)) else r for r in near_labels]
    else:
        labels = [
            None if isinstance(x, str) and not x else x for x in cast(Iterable[Any], near_labels)
        ]
    if len(labels) != n_frames:
        raise InputError(
            f"near_labels has {len(labels)} entries but the traverse has {n_frames} frames"
        )
    return labels


def _classes(classes: Sequence[str] | None, labels: list[Any]) -> tuple[str, ...]:
    """The class names given, or the distinct names among the labels, sorted."""
    if classes is not None:
        return tuple(str(c) for c in classes)
    known = [x for x in labels if x is not None]
    if not all(isinstance(x, str) for x in known):
        raise InputError("near labels that are indices or probabilities need classes=...")
    return tuple(sorted(set(known)))
