"""The terrain model as rough_map ships it: classifier, path filter and defect detector.

:class:`~rough_map.classify.TerrainModel` takes its path filter and its defect detector as
components; this is where the configuration of ``models/default`` and of
``rough-map train`` puts them together, one layer above the classifier.
"""

from __future__ import annotations

from typing import Any

from rough_map.classify.model import TerrainModel
from rough_map.filter.defects import IsolatedSpikes
from rough_map.filter.path_filter import PathFilter

__all__ = ["make_terrain_model", "shipped_path_filter"]


def shipped_path_filter(mode: str = "smooth") -> PathFilter:
    """The path filter of the shipped model, before fitting.

    It takes the log likelihoods of :func:`~rough_map.classify.emission_log_likelihood`,
    already weighted by the ground each frame adds, so its own emission weight is 1.

    Parameters
    ----------
    mode : {"forward", "smooth", "viterbi"}
        Filter mode.

    Returns
    -------
    PathFilter
    """
    return PathFilter(inputs="log_likelihood", emission_weight=1.0, mode=mode)


def make_terrain_model(
    *, mode: str = "smooth", defect_ratio: float | None = 8.0, **params: Any
) -> TerrainModel:
    """The terrain model of ``models/default`` and ``rough-map train``, before fitting.

    The classifier of :func:`~rough_map.classify.make_classifier`, the path filter of
    :func:`shipped_path_filter` and the defect detector :class:`IsolatedSpikes`.

    Parameters
    ----------
    mode : {"forward", "smooth", "viterbi"}, default "smooth"
        Filter mode of :meth:`TerrainModel.predict` unless it is given one.
    defect_ratio : float or None, default 8.0
        ``ratio`` of :class:`IsolatedSpikes`: a short run of frames (<= 1.5 m) whose R
        exceeds this many times the median R of the frames within 3 m is an isolated defect.
        None: no defect detector.
    **params
        Other parameters of :class:`~rough_map.classify.TerrainModel` (``kind``, ``cv``,
        ``level_names``, ``level_thresholds``, ``extraction``, ...).

    Returns
    -------
    TerrainModel
    """
    return TerrainModel(
        mode=mode,
        path_filter=shipped_path_filter(mode),
        defects=None if defect_ratio is None else IsolatedSpikes(ratio=defect_ratio),
        **params,
    )
