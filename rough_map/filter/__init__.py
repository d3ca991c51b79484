"""Discrete Bayes (HMM) filter of terrain classes along the rover's path.

A per-frame classifier says how likely each of K terrain classes is for the patch ahead. Terrain
does not change class every frame, so these posteriors are smoothed along the path with a
hidden Markov model whose state is the terrain class under the patch.

The model is written **per metre travelled**, not per frame, so that it does not depend on the
rover's speed or the camera's frame rate:

* A generator matrix ``Q`` (K x K, 1/m) holds the rate ``Q[i, j]`` of switching from class ``i``
  to class ``j`` per metre; each row sums to 0 and ``-Q[i, i]`` is the switching rate of class
  ``i``. The transition matrix over ``d`` metres is ``expm(Q * d)``; ``d = 0`` gives identity.
* The emission of a frame is the classifier posterior divided by the class prior (a *scaled
  likelihood*, proportional to p(x | c)), floored so one over-confident frame cannot lock the
  filter, and raised to the power ``emission_weight`` because overlapping patches are not
  independent observations.

The package, module by module:

* :mod:`~rough_map.filter.discrete_bayes`: small pure functions in log space that return new
  arrays, in the manner of ``filterpy.discrete_bayes``: :func:`predict`, :func:`update`,
  :func:`forward`, :func:`smooth`, :func:`viterbi`;
* :mod:`~rough_map.filter.switching`: the per-metre switching model,
  :func:`estimate_generator` and :func:`transition_matrices`;
* :mod:`~rough_map.filter.path_filter`: :class:`PathFilter`, the scikit-learn estimator whose
  ``fit`` learns the switching model from labelled traverses and whose predictions run the
  pure functions over each traverse;
* :mod:`~rough_map.filter.posteriors`: :class:`Posteriors`, a classifier as the Pipeline step
  before a :class:`PathFilter`;
* :mod:`~rough_map.filter.defects`: isolated defects along the path
  (:func:`isolated_spikes`, :class:`IsolatedSpikes`);
* :mod:`~rough_map.filter.roughness`: :class:`RoughnessSmoother`, ln R and w smoothed along
  the path by a Kalman filter and RTS smoother (filterpy) whose process noise is per metre,
  with jumps where the ground changes; :func:`load_roughness_smoother` reads the shipped
  ``configs/roughness_smoothing.yaml`` (learnt in :mod:`~rough_map.filter.roughness_fit`);
* :mod:`~rough_map.filter.shipped`: :func:`make_terrain_model`, the
  :class:`~rough_map.classify.TerrainModel` with the path filter and the defect detector as
  rough_map ships it.
"""

from rough_map.filter.defects import IsolatedSpikes, isolated_spikes
from rough_map.filter.discrete_bayes import forward, predict, smooth, update, viterbi
from rough_map.filter.path_filter import EMISSION_WEIGHT_GRID, PathFilter
from rough_map.filter.posteriors import Posteriors
from rough_map.filter.roughness import (
    RoughnessSmoother,
    RoughnessSmoothingConfig,
    SmoothedRoughness,
    load_roughness_smoother,
    smooth_table,
)
from rough_map.filter.shipped import make_terrain_model, shipped_path_filter
from rough_map.filter.switching import (
    DISTANCE_DECIMALS,
    estimate_generator,
    transition_matrices,
)

__all__ = [
    "DISTANCE_DECIMALS",
    "EMISSION_WEIGHT_GRID",
    "IsolatedSpikes",
    "PathFilter",
    "Posteriors",
    "RoughnessSmoother",
    "RoughnessSmoothingConfig",
    "SmoothedRoughness",
    "estimate_generator",
    "forward",
    "isolated_spikes",
    "load_roughness_smoother",
    "make_terrain_model",
    "predict",
    "shipped_path_filter",
    "smooth",
    "smooth_table",
    "transition_matrices",
    "update",
    "viterbi",
]
