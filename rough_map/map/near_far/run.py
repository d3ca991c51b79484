"""Near-to-far along a traverse: predict each imaged frame, then learn its near field."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from numbers import Integral
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import ArrayLike

from rough_map.errors import InputError
from rough_map.map.near_far.model import NearToFar
from rough_map.map.near_far.prediction import FarPrediction
from rough_map.map.near_far.tiles import check_image, read_bgr, tile_features
from rough_map.patch import Extraction, PatchSpec

if TYPE_CHECKING:
    from rough_map.io.traverse import Traverse

log = logging.getLogger(__name__)

__all__ = ["run_traverse"]


def run_traverse(
    traverse: Traverse,
    near_labels: Sequence[str | int | None] | ArrayLike,
    *,
    patch: PatchSpec | Extraction | None = None,
    classes: Sequence[str] | None = None,
    model: NearToFar | None = None,
    every: int = 1,
    progress: bool = False,
    **kwargs: Any,
) -> list[FarPrediction]:
    """Run near-to-far along a traverse, learning frame by frame.

    Each frame with a left image (every ``every``-th of them) is first *predicted* with the
    model learnt from the earlier frames only, then *learnt* with its near label. Frames
    before the first update give no prediction.

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
    progress : bool
        Show a progress bar on stderr.
    **kwargs
        Passed to :class:`~rough_map.map.near_far.NearToFar`.

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
    if model is None:
        if patch is None:
            raise InputError("near-to-far needs the patch of the near labels (patch=...)")
        model = NearToFar(_classes(classes, labels), patch, **kwargs)
    elif patch is not None or classes is not None or kwargs:
        raise InputError("a model to continue brings its own patch, classes and settings")
    imaged = [i for i, f in enumerate(traverse.frames) if f.left is not None][::every]
    out: list[FarPrediction] = []
    start = time.perf_counter()
    for i in tqdm(imaged, desc="near-to-far", unit="frame", disable=not progress):
        frame = traverse.frames[i]
        image = check_image(read_bgr(traverse.resolve(frame.left)), calib)
        tiles = tile_features(image, model.tile_px)  # once for predict and update
        if hasattr(model, "looks_"):
            out.append(model.predict_tiles(tiles, calib, frame.pose, t=frame.t, frame=i))
        if labels[i] is not None:
            model.update_tiles(tiles, calib, labels[i])
    log.info(
        "near-to-far: %d frames, %d predictions in %.1f s",
        len(imaged),
        len(out),
        time.perf_counter() - start,
    )
    return out


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
