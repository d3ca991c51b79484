"""Near-to-far: learn the look of the terrain near the rover, classify it far away.

Geometry (stereo or range clouds, :mod:`rough_map.psd`, :mod:`rough_map.classify`) is only
trustworthy in the patch of interest, about 1 m ahead. Appearance reaches further: every
frame, the image tiles that see the patch are labelled with the geometric class of the patch
and teach an online appearance model; the model then classifies the tiles that see the ground
beyond, and their class probabilities are handed to the map as ground-cell predictions
(the conclusion of the paper names this "near-to-far" extension as future work).

Steps, per frame
----------------
1. *Tiles* (:mod:`.tiles`): the left image is cut into square tiles of ``tile_px`` px. The
   ray through each tile centre is intersected with the vehicle's ground plane ``z = 0``
   (flat-ground assumption, :func:`~rough_map.geometry.pixel_to_ground`); tiles that see no
   ground within reach are dropped.
2. *Features* (:func:`.tiles.tile_features`): per tile the mean CIE L*a*b* colour and the
   log of the standard deviation of each L*a*b* channel (six numbers). L*a*b* separates brightness
   from chroma, so a grey surface and a brown one differ in a*, b* whatever the exposure of
   their texture, and a tile's mean colour hardly depends on how far away it is. Texture
   descriptors at a fixed pixel scale (LBP, gradient energy) were left out: the same ground
   seen 3 m away shows its texture at half the pixel scale with its fine detail blurred, so
   they drift with distance and, learnt at 1 m only, mislead the far field
   (``benchmarks/bench_near_far.py`` measures both). The log-stds drift too (fine texture
   fades), so they only get a weak say (``min_std``).
3. *Update* (:meth:`NearToFar.update`, :mod:`.looks`): the tiles whose ground point lies
   in the patch (the terrain model's patch, :class:`~rough_map.patch.Extraction`) are one
   batch. Outliers within it (more than ``outlier_k`` robust standard deviations from
   the batch median in some feature: a manhole rim) are dropped, and a patch across a class
   boundary keeps only its main look (:func:`.looks.main_look`: a two-component Gaussian
   mixture chosen by BIC). The batch then joins the nearest familiar *look* of its class, or
   starts a new one (:class:`Looks`: running means and variances, Chan's parallel update). A look
   is used only once ``min_support`` frames fed it: a wrong geometric label starts a look
   of its own that stays unused, or light, instead of corrupting the class's main look. A
   probability vector as the near label feeds every class with its weight.
4. *Prediction* (:meth:`NearToFar.predict`): ``p(class | tile)`` is proportional to the sum
   over the class's looks in use of ``n_look * N(features; look)``, ``n_look`` the tiles the
   look learnt: a mixture over all looks, so a look taught by a few wrong labels weighs
   little against the same look learnt by its own class (and the class priors follow how
   much of each class the rover drove over). Then an *unfamiliarity* gate: a tile far from
   every look in use (its smallest squared Mahalanobis distance has a chi-square tail
   probability below ``novelty_alpha``) has its probabilities pulled towards uniform.
   Terrain of a class the rover has not driven over yet thus comes out as "unknown", not as
   the nearest known class; with ``recall`` its look is remembered and it is predicted once
   the class is learnt (new terrain is always seen far ahead first).
5. *Ground cells* (:mod:`.cells`): predictions are returned on the world lattice of cell
   centres ``((i + 0.5) * ground_step, (j + 0.5) * ground_step)`` (the lattice of
   :class:`rough_map.map.grid.GridMap` maps of that resolution), for cells in view within
   ``max_range`` of the vehicle and outside the patch: a cell averages the tiles whose
   centres fall in it, or takes the tile its centre projects into when none does (far away
   one tile covers several cells).

Knowing when it does not know
-----------------------------
* *Settled labels* (:func:`run_traverse`, ``settle``): only frames whose label every known
  label within ``settle`` frames shares, with no isolated defect among them and a path
  posterior of at least ``min_posterior``, teach appearance, so a smoothed label lagging a
  change of ground does not teach the new look under the old name, nor one wrong geometric
  label a look of its own. Learning waits ``settle`` frames (no prediction uses its own
  frame's label or a later one).
* *Calibrated confidence* (:mod:`.calibration`): every near label checks the model: its
  near-field tiles scored before they are learnt, and the far cells predicted earlier
  where the near field now lies (by the distance they were predicted from). A reliability
  curve per distance bin (isotonic, shrunk, each class weighing the same) turns the raw
  top probability into how often such predictions were right; the calibrated confidence
  is never above the raw one. Nothing is confident before far predictions of two classes
  were checked and two classes are in use. Cells below ``min_confidence`` are left out:
  the model abstains (:attr:`FarPrediction.abstained`), and the map's ``far_confidence``
  layer shows the fused confidence.
* *Recall* of remembered cells needs ``recall_min_confidence`` (0.9): no wholesale
  relabelling of ground seen earlier on weak evidence.

Frames and units
----------------
Vehicle frame x forward, y left, z up; camera frame OpenCV (x right, y down, z forward); world
frame as the poses, ``p_world = Rz(yaw) Ry(pitch) Rx(roll) p_vehicle + t``; all in m and rad.
Pixel ``(u, v)`` = (column, row), integer coordinates at pixel centres.

Modules
-------
:mod:`.tiles` (image tiles, their features and ground points), :mod:`.looks` (the
appearance model, :class:`LooksClassifier`: an X, y scikit-learn classifier of tile
features), :mod:`.cells` (ground cells in view), :mod:`.prediction` (:class:`FarPrediction`),
:mod:`.model` (:class:`NearToFar`), :mod:`.run` (:func:`run_traverse`, :func:`settled`),
:mod:`.calibration` (the reliability curves), :mod:`.settings` (``configs/near_far.yaml``,
:class:`NearFarSettings`), :mod:`.checks` (parameter checks). The scores against a known
world are in :mod:`rough_map.evaluation.near_far` and, on the path band against the
nearest-near-field-cell baseline, :mod:`rough_map.evaluation.near_far_path`.

Limits
------
Only classes the rover has driven over can be predicted, and a far cell of another class is
"unknown" (uniform) at best. Flat ground: a tile's ground point is where its ray meets the
vehicle's ``z = 0`` plane, so slopes and steps displace far predictions (by
``dz / tan(elevation angle)``, about 3 cm per cm of height at 3 m). Classes that look alike
in colour (different roughness of the same material) cannot be told apart by this model;
the near field is then the only source of their class.
"""

from rough_map.near_far.cells import NearField
from rough_map.near_far.looks import DEFAULT_MIN_STD, Looks, LooksClassifier
from rough_map.near_far.model import NearToFar
from rough_map.near_far.prediction import FarPrediction
from rough_map.near_far.run import run_traverse, settled
from rough_map.near_far.settings import NearFarSettings, load_near_far_settings
from rough_map.near_far.tiles import FEATURE_NAMES, tile_features

__all__ = [
    "DEFAULT_MIN_STD",
    "FEATURE_NAMES",
    "FarPrediction",
    "Looks",
    "LooksClassifier",
    "NearFarSettings",
    "NearField",
    "NearToFar",
    "load_near_far_settings",
    "run_traverse",
    "settled",
    "tile_features",
]
