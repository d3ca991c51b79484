"""Roughness along the path: ln R and w smoothed by a Kalman filter and RTS smoother.

Per-frame R and w (the PSD fit ``PSD = R * Omega^w`` of the patch ahead) scatter from patch
to patch even on uniform ground. :class:`RoughnessSmoother` estimates the ground's
``x = (ln R, w)`` (R in m³/rad) at every frame from all the frames of a recorded traverse:

* **State model**, per metre travelled so that neither speed nor frame rate matters: a
  random walk, ``x_k = x_{k-1} + v``, ``v ~ N(0, diag(q) * Δd)`` with ``Δd`` the distance
  between the frames (m, from the poses) and ``q`` the process noise in 1/m (the variance
  of ln R, resp. w, added per metre).
* **Measurements** ``z_k = (ln R_k, w_k) = x_k + e_k``. One frame's error covariance ``C``
  is learnt from training traverses. Its two parts are told apart: R is the fit's
  intercept at 1 rad/m, below the band, so an error of the slope w moves ln R by
  ``-kappa`` times as much (``kappa ≈ 4``, the log of the wavenumber in rad/m where the
  fit pivots, mid-band); what is left, the log PSD level at the pivot
  ``ln R + kappa w``, is uncorrelated with w's error. The two parts are shared by
  consecutive frames over different *error lengths* ``L`` (m): w's over about the
  overlap of the patches (0.5 m), the level's over the metres over which the ground's
  roughness wanders (about 3 m on the simulator's courses). A frame that adds ``s`` m of
  ground counts as ``min(1, s / L)`` of an independent measurement of each part: its
  covariance is ``C`` with each part's variance multiplied by ``max(1, L / s)``. A stretch
  longer than ``L`` then carries the same information whatever the frame rate. The frame's
  own ``sigma_R`` and ``sigma_w`` (the spread over the patch's profiles) are not used:
  on the simulator's traverses they explain 1-2 % of the variance of a frame's deviation
  from its ground, which is mostly the ground's own variation from patch to patch.
* **Changes of ground** are not blurred: a random walk with small ``q`` would smear a step
  over metres. Each new frame tests, for every onset ``θ`` within ``window`` m behind it,
  the hypothesis that the ground jumped at ``θ`` against none, by the generalised
  likelihood ratio of the filter's innovations (Willsky & Jones, *IEEE TAC* 21, 1976;
  Gustafsson, *Adaptive Filtering and Change Detection*, 2000, ch. 9): with the jump
  signatures ``G_θ = I``, ``G <- (I - K_k) G`` after each update,
  ``d = Σ Gᵀ S⁻¹ ν`` and ``C_θ = Σ Gᵀ S⁻¹ G``, the statistic ``dᵀ C_θ⁻¹ d`` is χ² with
  2 degrees of freedom without a jump. When the largest exceeds
  ``chi2.isf(alpha, 2)``, the filter goes back to the likeliest onset, adds the jump
  covariance ``J`` (learnt: the spread of the changes between labelled stretches) to the
  process noise of that one step and runs on from there. The RTS smoother uses the same
  per-step process noise, so it does not carry information across a detected change.
* Frames without a valid patch, and frames that see an isolated defect (a manhole, flagged
  by :class:`~rough_map.filter.IsolatedSpikes` as for the class filter), get a predict
  step only: they do not move the curve.

The filter and smoother are filterpy's (:class:`filterpy.kalman.KalmanFilter`,
``predict``/``update`` with per-step ``Q`` and ``R`` and ``rts_smoother`` with the per-step
``Qs``). The noise model ships in ``configs/roughness_smoothing.yaml``, learnt from the
simulator's training traverses (:meth:`RoughnessSmoother.fit`; see that file for the
commands); :func:`load_roughness_smoother` reads it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator

from rough_map import errors
from rough_map.classify.evidence import frame_steps
from rough_map.classify.validation import check_fitted, is_number
from rough_map.config import load_model
from rough_map.features.table import SMOOTH_COLUMNS, FeatureTable
from rough_map.filter.defects import IsolatedSpikes
from rough_map.filter.roughness_config import CONFIG_FILE, RoughnessSmoothingConfig, spread
from rough_map.filter.roughness_fit import labelled_segments, learn_noise_model, level_transform
from rough_map.resources import config_file

__all__ = [
    "CONFIG_FILE",
    "RoughnessSmoother",
    "RoughnessSmoothingConfig",
    "SmoothedRoughness",
    "load_roughness_smoother",
    "smooth_table",
]

log = logging.getLogger(__name__)

#: The defect detector of the class filter of the shipped model.
DEFAULT_DEFECTS = IsolatedSpikes()

#: Prior variance of (ln R, w) before the first measurement (diffuse).
_DIFFUSE = 1e4


@dataclass(frozen=True, eq=False)
class SmoothedRoughness:
    """The smoothed roughness of every frame of a traverse.

    Attributes
    ----------
    lnR, w : ndarray, shape (n,)
        Smoothed ln R (R in m³/rad) and w.
    sigma_lnR, sigma_w : ndarray, shape (n,)
        Their standard deviations (sigma_lnR is a relative error of R).
    used : ndarray of bool, shape (n,)
        Frames whose measurement entered (valid, finite, not an isolated defect).
    jump : ndarray of bool, shape (n,)
        Frames where a change of ground was detected (the jump covariance was added to
        the step arriving there).
    distance : ndarray, shape (n,)
        Distance along the path, m.
    """

    lnR: NDArray[np.float64]
    w: NDArray[np.float64]
    sigma_lnR: NDArray[np.float64]
    sigma_w: NDArray[np.float64]
    used: NDArray[np.bool_]
    jump: NDArray[np.bool_]
    distance: NDArray[np.float64]

    @property
    def R(self) -> NDArray[np.float64]:
        """``exp(lnR)``, m³/rad: the smoothed R (a geometric mean, as the map's)."""
        return np.exp(self.lnR)

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """The features table columns :data:`~rough_map.features.table.SMOOTH_COLUMNS`."""
        values = (self.R, self.w, self.sigma_lnR, self.sigma_w)
        return dict(zip(SMOOTH_COLUMNS, values, strict=True))


class RoughnessSmoother(BaseEstimator):
    """Kalman filter and RTS smoother of (ln R, w) along the path, jumps at changes of ground.

    See the module docstring for the model. ``fit`` learns the noise model from labelled
    traverses; :func:`load_roughness_smoother` gives the fitted smoother that ships.

    Parameters
    ----------
    alpha : float, default 0.01
        False-alarm probability of the jump test of one onset, in (0, 1): the statistic
        must exceed ``chi2.isf(alpha, 2)`` (9.2 for 0.01). Larger values find smaller
        changes of ground and cut the smoothing more often on uniform ground. On simulated
        traverses (the noise of the shipped model, 20 m stretches, a frame every 0.25 m)
        0.01 finds a change of two ISO 8608 classes (R x 16) within 1 m of where it is
        9 times in 10, one of one class (R x 4) 7 times in 10, and cuts uniform ground
        about once per 300 m; a missed change is smoothed over metres, a false one only
        shortens the smoothing, hence a value larger than the usual 1e-3.
    window : float, default 5.0
        How far back in m (> 0) the jump test looks for the onset of a change: a change is
        found once at most ``window`` m of frames after it make the case.
    min_process_noise : float, default 1e-5
        Lower bound in 1/m (> 0) on the process noise that ``fit`` learns (ground whose
        roughness never drifts would otherwise give 0 and a curve that cannot follow it).
    defects : callable or None, default IsolatedSpikes()
        Detector of isolated defects, ``defects(R, distance) -> bool per frame`` (R in
        m³/rad, NaN where invalid; distance in m), as the terrain model's: those frames
        get a predict step only. None: no test. ``smooth(..., defect=flags)`` overrides it.

    Attributes
    ----------
    process_noise_ : ndarray, shape (2,)
        ``q`` of ln R and w, 1/m.
    measurement_cov_ : ndarray, shape (2, 2)
        Covariance of one frame's (ln R, w) about its ground.
    error_length_ : ndarray, shape (2,)
        Distance in m over which frames share their error, for its two uncorrelated parts:
        the log PSD level at the pivot (``ln R + kappa w``) and w.
    jump_cov_ : ndarray, shape (2, 2)
        Covariance of the change of (ln R, w) at a change of ground.
    n_segments_, n_changes_ : int
        Labelled stretches and changes of label the noise model was learnt from (0 when
        read from a config).
    """

    def __init__(
        self,
        alpha: float = 0.01,
        window: float = 5.0,
        min_process_noise: float = 1e-5,
        defects: Any = DEFAULT_DEFECTS,
    ) -> None:
        self.alpha = alpha
        self.window = window
        self.min_process_noise = min_process_noise
        self.defects = defects

    def _check_params(self) -> None:
        if not (is_number(self.alpha) and 0 < self.alpha < 1):
            raise errors.InputError(f"alpha must be a probability in (0, 1); got {self.alpha!r}")
        if not (is_number(self.window) and self.window > 0):
            raise errors.InputError(f"window must be a distance > 0 in m; got {self.window!r}")
        if not (is_number(self.min_process_noise) and self.min_process_noise > 0):
            raise errors.InputError(
                f"min_process_noise must be a positive number (1/m); got {self.min_process_noise!r}"
            )
        if self.defects is not None and not callable(self.defects):
            raise errors.InputError(
                "defects must be None or a callable defects(R, distance) -> bool per frame "
                f"(a rough_map.filter.IsolatedSpikes); got {self.defects!r}"
            )

    # ---------------------------------------------------------------- fit

    def fit(self, X: Sequence[FeatureTable], y: None = None) -> RoughnessSmoother:
        """Learn the noise model from labelled traverses.

        Parameters
        ----------
        X : sequence of FeatureTable
            One per traverse, with ``label`` set (the ground under each patch), poses
            (``x``, ``y`` in m, for the distance) and R (m³/rad) and w. Frames without a
            valid patch, without a label or flagged by ``defects`` are left out.
        y : None
            The labels are the tables' ``label`` column.

        Returns
        -------
        RoughnessSmoother
            ``self``, fitted (see the attributes).

        Raises
        ------
        InputError
            Bad parameters, ``y`` given, no tables, fewer than two labelled stretches of
            8 or more valid frames, or no change of label.
        """
        if y is not None:
            raise errors.InputError(
                "RoughnessSmoother.fit takes its labels from the tables' 'label' column; "
                "y must be None"
            )
        self._check_params()
        tables = list(X)
        if not tables:
            raise errors.InputError("RoughnessSmoother.fit needs at least one features table")
        traverses = []
        for table in tables:
            dist = np.asarray(table.distance(), dtype=float)
            if not np.all(np.isfinite(dist)):
                raise errors.InputError(
                    f"traverse {table.name!r}: poses (x, y in m) not all finite"
                )
            R, w = _columns(table)
            z, use = self._evidence(R, w, dist, _valid(table), None)
            traverses.append(labelled_segments(z, dist, table["label"], use))
        model = learn_noise_model(traverses, float(self.min_process_noise))
        self.process_noise_ = model.process_noise
        self.measurement_cov_ = model.measurement_cov
        self.error_length_ = model.error_length
        self.jump_cov_ = model.jump_cov
        self.n_segments_ = model.n_segments
        self.n_changes_ = model.n_changes
        log.info(
            "roughness smoother fitted on %d stretches, %d changes: q %s 1/m, error length %s m",
            model.n_segments,
            model.n_changes,
            np.array2string(model.process_noise, precision=4),
            np.array2string(model.error_length, precision=2),
        )
        return self

    # ---------------------------------------------------------------- config

    @classmethod
    def from_config(cls, config: RoughnessSmoothingConfig) -> RoughnessSmoother:
        """The fitted smoother a :class:`RoughnessSmoothingConfig` describes."""
        out = cls(
            alpha=config.alpha, window=config.window, min_process_noise=config.min_process_noise
        )
        out.process_noise_ = np.array([config.process_noise.lnR, config.process_noise.w])
        out.measurement_cov_ = config.measurement.cov()
        out.error_length_ = np.array([config.error_length.level, config.error_length.w])
        out.jump_cov_ = config.jump.cov()
        out.n_segments_ = out.n_changes_ = 0
        return out

    def to_config(self, training: dict[str, Any] | None = None) -> dict[str, Any]:
        """The fitted noise model as the mapping of ``configs/roughness_smoothing.yaml``."""
        self._check_fitted()
        return {
            "process_noise": {
                "lnR": float(self.process_noise_[0]),
                "w": float(self.process_noise_[1]),
            },
            "measurement": spread(self.measurement_cov_),
            "error_length": {
                "level": float(self.error_length_[0]),
                "w": float(self.error_length_[1]),
            },
            "jump": spread(self.jump_cov_),
            "alpha": float(self.alpha),
            "window": float(self.window),
            "min_process_noise": float(self.min_process_noise),
            "training": dict(training or {}),
        }

    def _check_fitted(self) -> None:
        check_fitted(
            self,
            ["process_noise_", "measurement_cov_", "error_length_", "jump_cov_"],
            "this RoughnessSmoother is not fitted; call fit() or load_roughness_smoother()",
        )

    # ---------------------------------------------------------------- smoothing

    def smooth(
        self,
        R: ArrayLike,
        w: ArrayLike,
        distance: ArrayLike,
        *,
        valid: ArrayLike | None = None,
        defect: ArrayLike | None = None,
    ) -> SmoothedRoughness:
        """Smoothed ln R and w, with their standard deviations, at every frame of a traverse.

        Parameters
        ----------
        R : array_like, shape (n,)
            Per-frame R in m³/rad; NaN or <= 0 for frames without one.
        w : array_like, shape (n,)
            Per-frame w; NaN for frames without one.
        distance : array_like, shape (n,)
            Cumulative distance along the path in m, finite and non-decreasing.
        valid : array_like of bool, shape (n,), optional
            False for frames without a valid patch. Default: all True.
        defect : array_like of bool, shape (n,), optional
            Frames that see an isolated defect (e.g. ``TerrainPrediction.defect``). Default:
            those of the ``defects`` detector (none when it is None).

        Returns
        -------
        SmoothedRoughness
            Frames without a measurement get the curve between their neighbours (with a
            larger sigma); all NaN when no frame has one.

        Raises
        ------
        InputError
            Bad parameters, arrays of other lengths, distance not finite or decreasing.
        """
        self._check_params()
        self._check_fitted()
        r = _array(R, "R")
        n = r.size
        wv, dist = _array(w, "w", n), _array(distance, "distance", n)
        if not np.all(np.isfinite(dist)) or np.any(np.diff(dist) < 0):
            raise errors.InputError("distance must be finite and non-decreasing (m)")
        ok = np.ones(n, dtype=bool) if valid is None else _flags(valid, "valid", n)
        flags = None if defect is None else _flags(defect, "defect", n)
        z, use = self._evidence(r, wv, dist, ok, flags)
        return self._run(z, use, dist)

    def smooth_table(self, table: FeatureTable, *, defect: ArrayLike | None = None) -> FeatureTable:
        """``table`` with the columns :data:`~rough_map.features.table.SMOOTH_COLUMNS` set
        (``R_smooth`` m³/rad, ``w_smooth``, ``sigma_lnR_smooth``, ``sigma_w_smooth``).

        Parameters
        ----------
        table : FeatureTable
            One traverse.
        defect : array_like of bool, optional
            As for :meth:`smooth`.

        Returns
        -------
        FeatureTable
            A new table; with the smoothed columns NaN (and a logged warning) when the
            poses are not all finite, as there is no distance along the path then.
        """
        R, w = _columns(table)
        dist = table.distance()
        if np.all(np.isfinite(dist)):
            smoothed = self.smooth(R, w, dist, valid=_valid(table), defect=defect).columns()
        else:
            log.warning("%s: poses not all finite; roughness not smoothed", table.name)
            smoothed = {c: np.full(len(table), np.nan) for c in SMOOTH_COLUMNS}
        cols = {**dict(table.columns), **smoothed}
        return FeatureTable(cols, table.omega, table.log_psd, table.name, table.row_spacing)

    def _evidence(
        self,
        R: NDArray[np.float64],
        w: NDArray[np.float64],
        dist: NDArray[np.float64],
        valid: NDArray[np.bool_],
        defect: NDArray[np.bool_] | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Measurements (ln R, w) and the frames whose measurement enters."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ln_r = np.where(R > 0, np.log(R), np.nan)
        z = np.column_stack([ln_r, w])
        use = valid & np.isfinite(z).all(axis=1)
        if defect is None and self.defects is not None and use.sum() >= 3:
            defect = np.asarray(self.defects(np.where(use, R, np.nan), dist), dtype=bool)
            if defect.any():
                log.info(
                    "roughness smoother: %d frame(s) of isolated defects left out", defect.sum()
                )
        if defect is not None:
            use = use & ~defect
        return z, use

    def _run(
        self, z: NDArray[np.float64], use: NDArray[np.bool_], dist: NDArray[np.float64]
    ) -> SmoothedRoughness:
        n = len(z)
        jump = np.zeros(n, dtype=bool)
        if not use.any():
            nan = np.full(n, np.nan)
            return SmoothedRoughness(nan, nan.copy(), nan.copy(), nan.copy(), use, jump, dist)
        steps = frame_steps(dist)
        kf, xs, Ps, Qs = _forward(
            z,
            use,
            dist,
            steps,
            self.process_noise_,
            self.measurement_cov_,
            self.error_length_,
            self.jump_cov_,
            -2.0 * math.log(float(self.alpha)),  # chi2.isf(alpha, 2)
            float(self.window),
            jump,
        )
        # filterpy's convention, as the filter's: Qs[k] is the noise of the step into frame k
        xs, Ps, _, _ = kf.rts_smoother(xs, Ps, Qs=Qs, inv=inv2)
        sd = np.sqrt(np.maximum(np.diagonal(Ps, axis1=1, axis2=2), 0.0))
        if jump.any():
            log.info("roughness smoother: changes of ground at %s m", np.round(dist[jump], 2))
        return SmoothedRoughness(xs[:, 0], xs[:, 1], sd[:, 0], sd[:, 1], use, jump, dist)


def _forward(
    z: NDArray[np.float64],
    use: NDArray[np.bool_],
    dist: NDArray[np.float64],
    steps: NDArray[np.float64],
    q: NDArray[np.float64],
    cov: NDArray[np.float64],
    length: NDArray[np.float64],
    jump_cov: NDArray[np.float64],
    threshold: float,
    window: float,
    jump: NDArray[np.bool_],
) -> tuple[Any, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The forward Kalman filter with the GLR jump test (module docstring).

    Returns the filter (a :class:`filterpy.kalman.KalmanFilter`), the filtered means
    (n, 2), covariances (n, 2, 2) and the process noise of the step arriving at each frame
    (n, 2, 2); sets ``jump`` where a change was found.
    """
    from filterpy.kalman import KalmanFilter

    n = len(z)
    eye = np.eye(2)
    # the frame's error in uncorrelated parts (PSD level at the pivot, w), each shared
    # over its own error length
    to_level = level_transform(cov)
    back = np.linalg.inv(to_level)
    level_var = np.diag(np.diag(to_level @ cov @ to_level.T))
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.inv = inv2  # its gain's inverse, per frame
    kf.F, kf.H = eye.copy(), eye.copy()
    kf.x = np.zeros(2)
    kf.P = _DIFFUSE * eye
    xs = np.zeros((n, 2))
    Ps = np.zeros((n, 2, 2))
    Qs = np.zeros((n, 2, 2))
    # the state before each frame's predict step, to start again from an onset
    saved: list[tuple[NDArray[np.float64], NDArray[np.float64], bool]] = []
    # the jump test's bank: onsets (frame index), signatures G, sums d and C
    onsets: list[int] = []
    G = np.zeros((0, 2, 2))
    d = np.zeros((0, 2))
    C = np.zeros((0, 2, 2))
    started = False  # a measurement has entered (no test against the diffuse prior)
    i = 0
    while i < n:
        del saved[i:]
        saved.append((kf.x.copy(), kf.P.copy(), started))
        step = dist[i] - dist[i - 1] if i else 0.0
        Qs[i] = np.diag(q * step) + (jump_cov if jump[i] else 0.0)
        kf.predict(Q=Qs[i])
        if use[i] and steps[i] > 0:
            R_i = back @ (level_var * np.maximum(1.0, length / steps[i])) @ back.T
            if started:
                old = _out_of_window(onsets, dist, i, window)
                if old:
                    onsets, G, d, C = onsets[old:], G[old:], d[old:], C[old:]
                if not jump[i]:
                    onsets.append(i)
                    G = np.concatenate([G, eye[None]])
                    d = np.concatenate([d, np.zeros((1, 2))])
                    C = np.concatenate([C, np.zeros((1, 2, 2))])
                if onsets:
                    Si = inv2(kf.P + R_i)
                    GtSi = np.transpose(G, (0, 2, 1)) @ Si
                    d = d + GtSi @ (z[i] - kf.x)
                    C = C + GtSi @ G
                    stat = quad2(C, d)
                    best = int(np.argmax(stat))
                    if stat[best] > threshold:
                        # a change of ground at the likeliest onset: start again from there
                        i = onsets[best]
                        jump[i] = True
                        x0, P0, started = saved[i]
                        kf.x, kf.P = x0.copy(), P0.copy()
                        onsets = []
                        G, d, C = np.zeros((0, 2, 2)), np.zeros((0, 2)), np.zeros((0, 2, 2))
                        continue
            kf.update(z[i], R=R_i)
            started = True
            if onsets:
                G = (eye - kf.K) @ G
        xs[i] = kf.x
        Ps[i] = kf.P
        i += 1
    return kf, xs, Ps, Qs


# ------------------------------------------------------------------------- helpers


def _out_of_window(onsets: list[int], dist: NDArray[np.float64], i: int, window: float) -> int:
    """How many of the bank's onsets (in order) lie more than ``window`` m behind frame i."""
    old = 0
    while old < len(onsets) and dist[i] - dist[onsets[old]] > window:
        old += 1
    return old


def _array(values: ArrayLike, name: str, n: int | None = None) -> NDArray[np.float64]:
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise errors.InputError(f"{name} must be numbers, one per frame") from None
    if a.ndim != 1 or (n is not None and a.size != n):
        want = "a 1-D array" if n is None else f"one value per frame, shape ({n},)"
        raise errors.InputError(f"{name} must be {want}; got shape {a.shape}")
    return a


def _flags(values: ArrayLike, name: str, n: int) -> NDArray[np.bool_]:
    a = np.asarray(values)
    if a.shape != (n,) or a.dtype != bool:
        raise errors.InputError(
            f"{name} must be a boolean array with one value per frame, shape ({n},); "
            f"got dtype {a.dtype} shape {a.shape}"
        )
    return a


def _columns(table: FeatureTable) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return np.asarray(table["R"], dtype=float), np.asarray(table["w"], dtype=float)


def _valid(table: FeatureTable) -> NDArray[np.bool_]:
    return np.asarray(table.valid, dtype=bool)


def load_roughness_smoother(path: str | Path | None = None) -> RoughnessSmoother:
    """The fitted :class:`RoughnessSmoother` of a config file.

    Parameters
    ----------
    path : str or Path, optional
        A file like ``configs/roughness_smoothing.yaml`` (:class:`RoughnessSmoothingConfig`);
        None reads the one shipped with rough_map.

    Raises
    ------
    FileFormatError, SchemaError
        Unreadable file, or content that does not follow the config.
    """
    config = load_model(
        path if path is not None else config_file(CONFIG_FILE), RoughnessSmoothingConfig
    )
    return RoughnessSmoother.from_config(config)


def smooth_table(
    table: FeatureTable,
    smoother: RoughnessSmoother | None = None,
    *,
    defect: ArrayLike | None = None,
) -> FeatureTable:
    """``table`` with the smoothed roughness columns set (:meth:`RoughnessSmoother.smooth_table`).

    Parameters
    ----------
    table : FeatureTable
        One traverse.
    smoother : RoughnessSmoother, optional
        Fitted; default the shipped one (:func:`load_roughness_smoother`).
    defect : array_like of bool, optional
        Frames of isolated defects (default: the smoother's detector finds them).
    """
    return (smoother or load_roughness_smoother()).smooth_table(table, defect=defect)


# -- 2 x 2 linear algebra written out, for the per-frame loops: at this size LAPACK's calls
# (and numpy's error-state context) cost several times the arithmetic ------------------------


def quad2(C: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
    """``d_k' C_k^-1 d_k`` for a stack of 2 x 2 matrices ``C`` (k, 2, 2) and vectors ``d``
    (k, 2), written out (the jump test's statistic, per frame); a singular ``C_k`` gives
    -inf, no change of ground."""
    a, b, c, e = C[:, 0, 0], C[:, 0, 1], C[:, 1, 0], C[:, 1, 1]
    d0, d1 = d[:, 0], d[:, 1]
    det = a * e - b * c
    num = d0 * (e * d0 - b * d1) + d1 * (a * d1 - c * d0)
    if det.all():  # (np.errstate costs more than the arithmetic here)
        return num / det
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = num / det
    return np.where(det != 0, stat, -np.inf)


def inv2(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The inverse of a 2 x 2 matrix, written out: the filter inverts two a frame, and
    LAPACK's call costs several times the arithmetic at this size."""
    (a, b), (c, d) = m.tolist()
    det = a * d - b * c
    if det == 0.0 or not math.isfinite(det):
        return np.asarray(np.linalg.inv(m), dtype=float)  # a singular one raises, as before
    return np.array([[d / det, -b / det], [-c / det, a / det]])
