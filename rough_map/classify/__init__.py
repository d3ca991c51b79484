"""Terrain class and roughness level of the patch ahead, from its PSD (scikit-learn).

The package, module by module:

* :mod:`~rough_map.classify.spectral`: :func:`feature_matrix` stacks what
  :func:`rough_map.features.traverse_features` measured for every frame (the scalar columns
  :data:`INPUT_SCALARS` and the patch-mean log10 PSD) into one matrix;
  :class:`SpectralFeatures`, a scikit-learn transformer, turns that matrix into the features
  of :data:`FEATURE_DOC`: the paper's roughness parameters and the level, slope and shape of
  the spectrum over a fixed band (fractional-octave residuals about a power law, curvature,
  a periodic peak), and the anisotropy between longitudinal and lateral profiles;
* :mod:`~rough_map.classify.levels`: the roughness levels of the paper's section 5.5
  (:class:`RoughnessLevels`);
* :mod:`~rough_map.classify.training`: :func:`make_classifier`, the pipeline
  ``SpectralFeatures -> StandardScaler -> calibrated classifier``, the jittered training
  copies, the calibration and cross-validation folds;
* :mod:`~rough_map.classify.evidence`: the classifier's evidence per metre travelled for the
  path filter; :mod:`~rough_map.classify.crossval`: the cross-validated scores;
* :mod:`~rough_map.classify.model`: :class:`TerrainModel`, the classifier with a path filter
  and a defect detector as components (built as shipped by
  :func:`rough_map.filter.make_terrain_model`), the roughness levels and what the model was
  trained on; :class:`TerrainPrediction`, its output;
* :mod:`~rough_map.classify.persistence`: model files (skops) and their cards.

What makes the model hold on traverses it has not seen (other seeds, speeds and sensors):

* the spectrum features are measured over the same band for every sensor, after the noise
  floor is removed; the paper's R, fitted over a band that ends where the sensor's noise
  or resolution does, and the scatter of the per-profile fits, which grows with the
  noise, are computed but left out of the classifier (:data:`EXCLUDED_FEATURES`): the
  band-limited ``level`` carries the same information. The waviness w stays in: it
  separates concrete from dirt road where their R overlap;
* R drifts along a uniform stretch by about a factor of 2, and between stretches by more
  than a few training traverses show: the classifier trains on copies of the frames with
  the terrain scaled at random and w shifted a little (:func:`jitter_levels`), so that it
  leans on the shape of the spectrum as well as on its level;
* an isolated defect (a manhole) is a short spike of R; in recorded traverses the path
  filter leaves those frames' class out (:class:`rough_map.filter.IsolatedSpikes`);
* the classifier weighs the classes equally and is calibrated on folds of whole traverses
  (:func:`calibration_split`), and the path filter weighs each frame by the ground it adds
  (:func:`emission_log_likelihood`), so that the evidence per metre does not depend on the
  speed.
"""

from rough_map.classify.evidence import (
    EVIDENCE_GRID,
    choose_evidence_per_m,
    emission_log_likelihood,
    frame_steps,
)
from rough_map.classify.levels import RoughnessLevels, load_roughness_levels, roughness_level
from rough_map.classify.model import MODEL_FORMAT, MODES, TerrainModel, TerrainPrediction
from rough_map.classify.persistence import (
    TRUSTED_TYPES,
    load_terrain_model,
    model_paths,
    read_card,
    save_terrain_model,
    sha256_file,
)
from rough_map.classify.spectral import (
    FEATURE_DOC,
    INPUT_SCALARS,
    SpectralFeatures,
    default_omega,
    feature_matrix,
    on_model_grid,
)
from rough_map.classify.training import (
    CLASSIFIERS,
    EXCLUDED_FEATURES,
    calibration_split,
    jitter_levels,
    make_classifier,
    training_hash,
)

__all__ = [
    "CLASSIFIERS",
    "EVIDENCE_GRID",
    "EXCLUDED_FEATURES",
    "FEATURE_DOC",
    "INPUT_SCALARS",
    "MODEL_FORMAT",
    "MODES",
    "TRUSTED_TYPES",
    "RoughnessLevels",
    "SpectralFeatures",
    "TerrainModel",
    "TerrainPrediction",
    "calibration_split",
    "choose_evidence_per_m",
    "default_omega",
    "emission_log_likelihood",
    "feature_matrix",
    "frame_steps",
    "jitter_levels",
    "load_roughness_levels",
    "load_terrain_model",
    "make_classifier",
    "model_paths",
    "on_model_grid",
    "read_card",
    "roughness_level",
    "save_terrain_model",
    "sha256_file",
    "training_hash",
]
