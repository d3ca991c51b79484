"""Terrain class and roughness level of the patch ahead, from its PSD (scikit-learn).

Three layers, each usable on its own:

* :func:`feature_matrix` stacks what :func:`rough_map.features.traverse_features` measured
  for every frame (the scalar columns :data:`INPUT_SCALARS` and the patch-mean log10 PSD)
  into one matrix;
* :class:`SpectralFeatures`, a scikit-learn transformer, turns that matrix into the
  features of :data:`FEATURE_DOC`: the paper's roughness parameters and the level, slope
  and shape of the spectrum over a fixed band (fractional-octave residuals about a power
  law, curvature, a periodic peak), and the anisotropy between longitudinal and lateral
  profiles;
* :func:`make_classifier` is the pipeline ``SpectralFeatures -> StandardScaler -> calibrated
  classifier``; :class:`TerrainModel` bundles it with the path filter
  (:class:`rough_map.filter.PathFilter`), the roughness levels of the paper's section 5.5
  and what the model was trained on.

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
  filter leaves those frames' class out (:func:`rough_map.filter.isolated_spikes`);
* the classifier weighs the classes equally and is calibrated on folds of whole traverses
  (:func:`calibration_split`), and the path filter weighs each frame by the ground it adds
  (:func:`emission_log_likelihood`), so that the evidence per metre does not depend on the
  speed.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils.validation import check_is_fitted, validate_data

from rough_map import errors
from rough_map.patch import Extraction

log = logging.getLogger(__name__)

__all__ = [
    "CLASSIFIERS",
    "EVIDENCE_GRID",
    "EXCLUDED_FEATURES",
    "FEATURE_DOC",
    "INPUT_SCALARS",
    "MODEL_FORMAT",
    "RoughnessLevels",
    "SpectralFeatures",
    "TerrainModel",
    "TerrainPrediction",
    "calibration_split",
    "default_omega",
    "emission_log_likelihood",
    "feature_matrix",
    "frame_steps",
    "jitter_levels",
    "load_roughness_levels",
    "make_classifier",
    "roughness_level",
    "training_hash",
]

#: Scalar columns of a :class:`~rough_map.features.FeatureTable` that lead the input matrix
#: of :class:`SpectralFeatures` (the log10 PSD bins follow), with their units.
INPUT_SCALARS: tuple[str, ...] = (
    "R",  # m^3/rad, Phi(1 rad/m) of the longitudinal profiles
    "w",  # waviness, dimensionless
    "sigma_R",  # m^3/rad
    "sigma_w",  # dimensionless
    "rms",  # m
    "R_lat",  # m^3/rad, lateral profiles
    "w_lat",  # dimensionless
    "fit_residual",  # natural-log units
    "noise_psd",  # m^3/rad, noise floor of the gridded profiles
)

#: The features :class:`SpectralFeatures` computes, and what they mean. "Shape" features are
#: scale-free: multiplying the whole spectrum by a constant leaves them unchanged.
FEATURE_DOC: dict[str, str] = {
    "log10_R": "log10 of R = Phi(1 rad/m) in m^3/rad (paper Eq. 7), the overall energy",
    "w": "waviness, the slope of the log-log power law (paper Eq. 4)",
    "log10_rms": "log10 of the rms of the detrended profiles in m (paper Eq. 9)",
    "sigma_lnR": "spread of ln R between the profiles of the patch, sigma_R / R (Eq. 8)",
    "sigma_w": "spread of w between the profiles of the patch",
    "aniso_R": "log10(R_lat / R): energy across over along the direction of travel",
    "aniso_w": "w_lat - w: waviness across minus along the direction of travel",
    "fit_residual": "rms residual of the patch-mean log spectrum about the power law (ln)",
    "level": "log10 of the noise-corrected mean PSD in m^3/rad at the band's geometric centre",
    "slope": "slope of the log-log line through the mean PSD in the band (fundamental left out)",
    "curvature": "second-order coefficient of log10 PSD in log10 Omega (0 for a power law)",
    "band_{j}": "mean log10 residual of fractional-octave band j about that line (shape)",
    "peak": "largest prominence of one ordinate over its neighbours, log10 (periodic furrows)",
    "peak_omega": "log10 of the wavenumber in rad/m of that peak",
}


def feature_matrix(table: Any) -> tuple[NDArray[np.float64], list[str]]:
    """The input matrix of :class:`SpectralFeatures` for every frame of a features table.

    Parameters
    ----------
    table : FeatureTable
        Per-frame features of a traverse (:func:`rough_map.features.traverse_features` or
        :func:`rough_map.features.read_features`).

    Returns
    -------
    X : ndarray, shape (n_frames, len(INPUT_SCALARS) + n_bins)
        The columns :data:`INPUT_SCALARS` (units as in the table: m^3/rad, m, ...) followed by
        the patch-mean PSD as log10 of m^3/rad on ``table.omega``; NaN rows for invalid frames.
    names : list of str
        Column names: :data:`INPUT_SCALARS` then ``psd_01`` ...

    Raises
    ------
    InputError
        The table lacks one of the columns.
    """
    missing = [c for c in INPUT_SCALARS if c not in table.columns]
    if missing:
        raise errors.InputError(f"features table {table.name!r} lacks the columns {missing}")
    scalars = np.column_stack([np.asarray(table.columns[c], dtype=float) for c in INPUT_SCALARS])
    X = np.hstack([scalars, np.asarray(table.log_psd, dtype=float)])
    X[~np.asarray(table.valid, dtype=bool)] = np.nan
    return X, [*INPUT_SCALARS, *table.spectrum_names()]


def default_omega(n_bins: int, length: float = 0.896) -> NDArray[np.float64]:
    """Wavenumbers ``2 pi k / L`` in rad/m, ``k = 1 ... n_bins``, of a patch ``length`` m long."""
    return 2.0 * np.pi * np.arange(1, n_bins + 1) / length


class SpectralFeatures(TransformerMixin, BaseEstimator):
    """Classification features from the roughness parameters and the patch-mean spectrum.

    The input is the matrix of :func:`feature_matrix`: the scalar columns named by
    ``scalars`` followed by the patch-mean PSD as log10 of m^3/rad on ``omega``. The output
    holds the features of :data:`FEATURE_DOC` that the input supports (the scalar-derived
    ones need their columns; with ``scalars=()`` every column is a spectrum bin), less those
    named in ``exclude``:

    * the paper's roughness parameters, as ``log10_R``, ``w``, ``log10_rms``, their spreads
      ``sigma_lnR`` and ``sigma_w`` between profiles, and the anisotropy ``aniso_R``,
      ``aniso_w`` between longitudinal and lateral profiles (ruts run along the road,
      furrows across it);
    * the level and slope of the mean spectrum over a fixed band, ``omega[0]`` to
      ``omega_max`` (the same for every sensor, unlike the band of R and w, which ends
      where the noise floor takes over);
    * the shape of the spectrum in that band, which does not depend on its scale and so not
      on the slow drift of R along a stretch: ``curvature`` of the log-log spectrum, the
      mean residual ``band_j`` of each fractional-octave band about the power-law line
      (pebbles lift wavelengths of a few centimetres), and the most prominent single
      ordinate ``peak`` with its wavenumber ``peak_omega`` (the periodic furrows of
      ploughed soil).

    The measurement noise floor (column ``noise_psd``, m^3/rad) is subtracted before the
    spectrum is measured, and ordinates where the terrain's power is below ``snr_min`` times
    the floor are replaced by the fitted line (they say nothing about the terrain), so that
    the spectrum features stay comparable between sensors of different noise and density.

    Parameters
    ----------
    omega : array_like of float, optional
        Wavenumbers in rad/m of the spectrum columns. Default ``2 pi k / 0.896 m``, the
        paper's patch.
    scalars : tuple of str, default INPUT_SCALARS
        Names of the leading scalar columns of ``X`` (distinct names from
        :data:`INPUT_SCALARS`, in any order).
    omega_max : float, default 160.0
        Upper end in rad/m of the band of the spectrum features (about 4 cm wavelength).
        Wavenumbers above it are left out: there a noisy sensor sees mostly its own noise
        and the cell-mean grid its own box filter.
    bands_per_octave : int, default 2
        Resolution of the ``band_j`` residuals: ordinate ``k`` (``omega_k / omega_1``) falls in
        band ``floor(bands_per_octave * log2(k))``, renumbered from 0 without gaps.
    snr_min : float, default 1.0
        Smallest ratio of terrain power to noise floor for an ordinate to count.
    exclude : tuple of str, default ()
        Output features to leave out (names as in :data:`FEATURE_DOC`).

    Attributes
    ----------
    n_features_in_ : int
        Columns of ``X``.
    omega_ : ndarray
        Wavenumbers in rad/m of the spectrum columns.
    band_ : ndarray of int
        Band index per spectrum column (-1 for a column outside the band).
    feature_names_out_ : ndarray of str
        Names of the output columns.
    """

    def __init__(
        self,
        omega: ArrayLike | None = None,
        scalars: tuple[str, ...] = INPUT_SCALARS,
        omega_max: float = 160.0,
        bands_per_octave: int = 2,
        snr_min: float = 1.0,
        exclude: tuple[str, ...] = (),
    ) -> None:
        self.omega = omega
        self.scalars = scalars
        self.omega_max = omega_max
        self.bands_per_octave = bands_per_octave
        self.snr_min = snr_min
        self.exclude = exclude

    def __sklearn_tags__(self):  # type: ignore[no-untyped-def]
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = True  # NaN rows are frames without a valid patch
        return tags

    # ------------------------------------------------------------------ fit

    def fit(self, X: ArrayLike, y: Any = None) -> SpectralFeatures:
        """Check the layout of ``X`` and fix the output features.

        Parameters
        ----------
        X : array_like, shape (n_frames, len(scalars) + n_bins)
            Scalar columns then log10 PSD in m^3/rad (see :func:`feature_matrix`).
        y : ignored

        Returns
        -------
        SpectralFeatures
            ``self``.
        """
        X = self._validate(X, reset=True)
        scalars = tuple(self.scalars)
        unknown = [s for s in scalars if s not in INPUT_SCALARS]
        if unknown or len(set(scalars)) != len(scalars):
            raise errors.InputError(
                f"scalars must be distinct names from {INPUT_SCALARS}; got {scalars!r}"
            )
        for name in ("snr_min", "omega_max"):
            value = getattr(self, name)
            if not (isinstance(value, Real) and math.isfinite(value) and value >= 0):
                raise errors.InputError(f"{name} must be a finite number >= 0; got {value!r}")
        if not (isinstance(self.bands_per_octave, Integral) and self.bands_per_octave >= 1):
            raise errors.InputError(
                f"bands_per_octave must be an integer >= 1; got {self.bands_per_octave!r}"
            )
        n_bins = X.shape[1] - len(scalars)
        omega = (
            default_omega(max(n_bins, 0))
            if self.omega is None
            else np.asarray(self.omega, dtype=float)
        )
        if omega.shape != (max(n_bins, 0),):
            raise errors.InputError(
                f"omega must hold one wavenumber (rad/m) per spectrum column: X has "
                f"{X.shape[1]} feature(s), {len(scalars)} scalar(s), so {n_bins} spectrum "
                f"columns, but omega has shape {omega.shape}"
            )
        if not (np.all(np.isfinite(omega)) and np.all(omega > 0) and np.all(np.diff(omega) > 0)):
            raise errors.InputError("omega must be positive, finite and increasing (rad/m)")
        inside = omega <= self.omega_max
        if inside.sum() < 2:
            raise errors.InputError(
                f"SpectralFeatures needs at least 2 spectrum columns at or below omega_max = "
                f"{self.omega_max} rad/m; X has {X.shape[1]} feature(s) of which "
                f"{int(inside.sum())} qualify"
            )
        raw = np.floor(self.bands_per_octave * np.log2(omega / omega[0]) + 1e-9).astype(int)
        band = np.full(omega.shape, -1)
        band[inside] = np.unique(raw[inside], return_inverse=True)[1].ravel()
        names = self._names(scalars, int(band.max()) + 1)
        unknown = [e for e in self.exclude if e not in names]
        if unknown:
            raise errors.InputError(f"exclude names unknown features {unknown}; known: {names}")
        self.omega_ = omega
        self.band_ = band
        self.feature_names_out_ = np.array(
            [n for n in names if n not in set(self.exclude)], dtype=object
        )
        if len(self.feature_names_out_) == 0:
            raise errors.InputError("exclude leaves no feature")
        return self

    @staticmethod
    def _names(scalars: tuple[str, ...], n_bands: int) -> list[str]:
        have = set(scalars)
        names = []
        if "R" in have:
            names.append("log10_R")
        if "w" in have:
            names.append("w")
        if "rms" in have:
            names.append("log10_rms")
        if {"R", "sigma_R"} <= have:
            names.append("sigma_lnR")
        if "sigma_w" in have:
            names.append("sigma_w")
        if {"R", "R_lat"} <= have:
            names.append("aniso_R")
        if {"w", "w_lat"} <= have:
            names.append("aniso_w")
        if "fit_residual" in have:
            names.append("fit_residual")
        names += ["level", "slope", "curvature"]
        names += [f"band_{j}" for j in range(n_bands)]
        names += ["peak", "peak_omega"]
        return names

    def _validate(self, X: ArrayLike, *, reset: bool) -> NDArray[np.float64]:
        try:
            return validate_data(self, X, reset=reset, ensure_all_finite="allow-nan")
        except errors.RoughMapError:
            raise
        except ValueError as err:
            raise errors.InputError(str(err)) from err

    # ------------------------------------------------------------------ transform

    def transform(self, X: ArrayLike) -> NDArray[np.float64]:
        """Compute the features of every frame.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features_in_)
            As in :meth:`fit`. A row with NaN in its spectrum gives a row of NaN.

        Returns
        -------
        ndarray, shape (n_frames, len(feature_names_out_))
            The features, in the order of :meth:`get_feature_names_out`.
        """
        check_is_fitted(self, "feature_names_out_")
        X = self._validate(X, reset=False)
        scalars = tuple(self.scalars)
        ns = len(scalars)
        col = {name: X[:, i] for i, name in enumerate(scalars)}
        out: list[NDArray[np.float64]] = []
        with np.errstate(invalid="ignore", divide="ignore"):
            if "R" in col:
                out.append(np.log10(col["R"]))
            if "w" in col:
                out.append(col["w"])
            if "rms" in col:
                out.append(np.log10(col["rms"]))
            if "R" in col and "sigma_R" in col:
                out.append(col["sigma_R"] / col["R"])
            if "sigma_w" in col:
                out.append(col["sigma_w"])
            if "R" in col and "R_lat" in col:
                out.append(np.log10(col["R_lat"] / col["R"]))
            if "w" in col and "w_lat" in col:
                out.append(col["w_lat"] - col["w"])
            if "fit_residual" in col:
                out.append(col["fit_residual"])
        noise = col.get("noise_psd", np.zeros(len(X)))
        noise = np.where(np.isfinite(noise) & (noise > 0), noise, 0.0)
        spectrum = X[:, ns:]
        result = np.column_stack([*out, self._shape(spectrum, noise)])
        result[np.isnan(spectrum[:, self.band_ >= 0]).any(axis=1)] = np.nan
        names = self._names(scalars, int(self.band_.max()) + 1)
        keep = np.isin(np.asarray(names, dtype=object), self.feature_names_out_)
        return result[:, keep]

    def _shape(self, log_psd: NDArray[np.float64], noise: NDArray[np.float64]) -> NDArray:
        """level, slope, curvature, band residuals, peak and its wavenumber, per row."""
        use = self.band_ >= 0
        band = self.band_[use]
        n_band = int(band.max()) + 1
        x = np.log10(self.omega_[use])
        xc = x - 0.5 * (x.min() + x.max())  # about the band's geometric centre
        # The fits weigh every ordinate alike but leave out the fundamental, which the
        # detrending and the window distort and the slow drift of R along the path
        # dominates; its residual is still reported (band_0).
        bin_weight = np.ones(x.size)
        if x.size > 4:
            bin_weight[0] = 0.0
        with np.errstate(invalid="ignore", over="ignore"):
            psd = 10.0 ** log_psd[:, use]
            terrain = psd - noise[:, None]
            good = np.isfinite(terrain) & (terrain > 0) & (terrain >= self.snr_min * noise[:, None])
        # too smooth for this sensor: fall back to the raw spectrum rather than to nothing
        few = (good * bin_weight).sum(axis=1) < min(3, x.size)
        if few.any():
            good[few] = np.isfinite(psd[few]) & (psd[few] > 0)
            terrain[few] = psd[few]
        y = np.log10(np.where(good, terrain, 1.0))
        wts = good * bin_weight[None, :]
        line = _weighted_polyfit(xc, y, wts, degree=1)
        quad = _weighted_polyfit(xc, y, wts, degree=2)
        fitted = line[:, [0]] + line[:, [1]] * xc[None, :]
        resid = np.where(good, y - fitted, 0.0)
        # mean residual per band over its usable ordinates (0, on the line, if none)
        onehot = (band[:, None] == np.arange(n_band)[None, :]).astype(float)
        count = good.astype(float) @ onehot
        with np.errstate(invalid="ignore", divide="ignore"):
            bands = np.where(count > 0, (resid @ onehot) / np.maximum(count, 1.0), 0.0)
        # prominence of an ordinate over its two neighbours, all three usable
        peak = np.zeros(len(y))
        peak_omega = np.full(len(y), x.mean())
        if x.size >= 3:
            filled = np.where(good, y, fitted)
            # neighbours joined by a straight line in log-log: a power law has no peak
            frac = (x[1:-1] - x[:-2]) / (x[2:] - x[:-2])
            prom = filled[:, 1:-1] - (filled[:, :-2] + frac * (filled[:, 2:] - filled[:, :-2]))
            prom = np.where(good[:, 1:-1] & good[:, :-2] & good[:, 2:], prom, -np.inf)
            at = np.argmax(prom, axis=1)
            best = prom[np.arange(len(prom)), at]
            found = np.isfinite(best)
            peak[found] = best[found]
            peak_omega[found] = x[1:-1][at[found]]
        # too few ordinates for a curvature: call it straight
        curvature = np.where(np.isfinite(quad[:, 2]) | ~np.isfinite(line[:, 1]), quad[:, 2], 0.0)
        return np.column_stack([line[:, 0], line[:, 1], curvature, bands, peak, peak_omega])

    def band_edges(self) -> list[tuple[float, float]]:
        """Lowest and highest wavenumber in rad/m of each ``band_j``."""
        check_is_fitted(self, "band_")
        return [
            (float(self.omega_[self.band_ == j].min()), float(self.omega_[self.band_ == j].max()))
            for j in range(int(self.band_.max()) + 1)
        ]

    def get_feature_names_out(self, input_features: Any = None) -> NDArray[np.object_]:
        """Names of the output features (see :data:`FEATURE_DOC`)."""
        check_is_fitted(self, "feature_names_out_")
        return self.feature_names_out_.copy()


def _weighted_polyfit(
    x: NDArray[np.float64], y: NDArray[np.float64], w: NDArray[np.float64], degree: int
) -> NDArray[np.float64]:
    """Per-row weighted least squares ``y ~ sum_p c_p x^p``; coefficients (n_rows, degree+1).

    Rows whose weights cannot determine the fit get NaN.
    """
    powers = np.vstack([x**p for p in range(degree + 1)])  # (P, K)
    a = np.einsum("rk,pk,qk->rpq", w, powers, powers)
    b = np.einsum("rk,pk,rk->rp", w, powers, y)
    out = np.full((len(y), degree + 1), np.nan)
    det_ok = np.abs(np.linalg.det(a)) > 1e-12 * np.maximum(1.0, np.abs(a).max(axis=(1, 2))) ** (
        degree + 1
    )
    if det_ok.any():
        out[det_ok] = np.linalg.solve(a[det_ok], b[det_ok][:, :, None])[:, :, 0]
    return out


# --------------------------------------------------------------------------------------------
# Roughness levels (paper section 5.5)
# --------------------------------------------------------------------------------------------


def _iso_boundary(value: float | str) -> float:
    """A threshold in m^3/rad: a number, or an ISO 8608 boundary written ``"C/D"``."""
    from rough_map.iso8608 import CLASSES, LOWER

    if isinstance(value, str):
        parts = value.replace(" ", "").upper().split("/")
        if len(parts) != 2 or any(p not in CLASSES for p in parts):
            raise ValueError(
                f"{value!r} is not an ISO 8608 boundary such as 'C/D' (classes {CLASSES})"
            )
        lo, hi = CLASSES.index(parts[0]), CLASSES.index(parts[1])
        if hi != lo + 1:
            raise ValueError(f"{value!r}: an ISO boundary joins two adjacent classes, e.g. 'C/D'")
        return LOWER[parts[1]]
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"a threshold must be a positive R in m^3/rad; got {value!r}")
    return v


class RoughnessLevels(BaseModel):
    """Discrete roughness levels from the overall energy R (paper section 5.5).

    A frame is in the first level whose upper threshold its R is below, and in the last
    level when R is at or above every threshold. The defaults are those of
    ``configs/roughness_levels.yaml``: low (ISO A-C), medium (ISO D-E), high (ISO F and up).

    Attributes
    ----------
    levels : tuple of str
        Level names, smoothest first.
    thresholds : tuple of float or str
        ``len(levels) - 1`` increasing upper bounds on R: numbers in m^3/rad, or ISO 8608
        class boundaries written ``"C/D"`` (geometric midpoint of the two classes' centres).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    levels: tuple[str, ...] = Field(("low", "medium", "high"), min_length=2)
    thresholds: tuple[float | str, ...] = ("C/D", "E/F")

    @model_validator(mode="after")
    def _check(self) -> RoughnessLevels:
        if any(not name.strip() for name in self.levels) or len(set(self.levels)) != len(
            self.levels
        ):
            raise ValueError(f"levels must be distinct non-empty names; got {self.levels}")
        if len(self.thresholds) != len(self.levels) - 1:
            raise ValueError(
                f"{len(self.levels)} levels need {len(self.levels) - 1} thresholds; got "
                f"{len(self.thresholds)}"
            )
        values = [_iso_boundary(t) for t in self.thresholds]
        if any(b <= a for a, b in itertools.pairwise(values)):
            raise ValueError(f"thresholds must increase; got {values} m^3/rad")
        return self

    def values(self) -> NDArray[np.float64]:
        """The thresholds in m^3/rad."""
        return np.array([_iso_boundary(t) for t in self.thresholds])


def load_roughness_levels(path: str | Path | None = None) -> RoughnessLevels:
    """Read roughness levels from YAML/JSON (safe loading).

    Parameters
    ----------
    path : str or Path, optional
        A file like ``configs/roughness_levels.yaml``; None reads the one shipped with
        rough_map (:func:`rough_map.resources.config_file`).

    Returns
    -------
    RoughnessLevels

    Raises
    ------
    FileFormatError, SchemaError
        Unreadable file, or content that does not follow :class:`RoughnessLevels`.
    """
    from rough_map.config import load_model

    if path is None:
        from rough_map.resources import config_file

        path = config_file("roughness_levels.yaml")

    return load_model(path, RoughnessLevels)


def roughness_level(
    R: ArrayLike, names: tuple[str, ...] | list[str], thresholds: ArrayLike
) -> NDArray[np.object_]:
    """Level name per frame from its R.

    Parameters
    ----------
    R : array_like
        Overall energy Phi(1 rad/m) in m^3/rad; NaN for frames without a valid patch.
    names : sequence of str
        Level names, smoothest first.
    thresholds : array_like
        ``len(names) - 1`` increasing upper bounds in m^3/rad.

    Returns
    -------
    ndarray of str
        The level of each frame; ``""`` where R is NaN or not positive.
    """
    r = np.asarray(R, dtype=float)
    idx = np.searchsorted(np.asarray(thresholds, dtype=float), r, side="right")
    out = np.asarray(names, dtype=object)[np.clip(idx, 0, len(names) - 1)]
    return np.where(np.isfinite(r) & (r > 0), out, "").astype(object)


# --------------------------------------------------------------------------------------------
# The classifier pipeline
# --------------------------------------------------------------------------------------------

#: Base classifiers :func:`make_classifier` knows; the first is the default.
CLASSIFIERS: tuple[str, ...] = ("logistic", "hgb", "forest")

#: Outputs of :class:`SpectralFeatures` that the default pipeline leaves out, because they
#: describe the sensor (or the renderer of a simulator) as much as the ground:
#:
#: * ``sigma_lnR``, ``sigma_w`` and ``fit_residual``, the scatter of the per-profile fits,
#:   grow with the point noise: three to four standard deviations between a 0.3 mm and a
#:   1.5 mm sensor on the same ground;
#: * ``log10_R`` is fitted up to the Nyquist wavenumber or to the noise floor, whichever
#:   comes first, so it moves with the sensor's noise and with how finely the ground is
#:   rendered (by up to a factor of 2 between simulated worlds at 4 mm and 2 mm on the same
#:   surfaces); ``level``, the same quantity over a fixed band up to 160 rad/m, carries it.
#:
#: ``w`` moves with the sensor too (by 0.1 between those worlds), but it is the paper's
#: best single separator of smooth surfaces (concrete w = -2.0 against dirt road -2.2 at
#: overlapping R), and the band-limited ``slope`` does not replace it: on 13 held-out
#: simulated traverses (other seeds, speeds, 2-20 points per cell, 0.3-2 mm noise) the
#: filtered accuracy is 0.92 without w (0.68 on the worst traverse) and 0.97 with it (0.93
#: on the worst). The model trains with w shifted at random (``waviness_jitter``) so that a
#: bias of a few hundredths costs little; a bias of 0.1 (a sensor that smooths the ground)
#: still costs about 0.1 of accuracy: train on that sensor's data.
EXCLUDED_FEATURES: tuple[str, ...] = ("sigma_lnR", "sigma_w", "fit_residual", "log10_R")


def jitter_levels(
    X: ArrayLike,
    sd: float,
    copies: int,
    rng: np.random.Generator,
    w_sd: float = 0.0,
) -> NDArray[np.float64]:
    """Copies of the rows of a :func:`feature_matrix` with the terrain scaled at random.

    Each copy multiplies the terrain's heights by ``10**(s/2)``, ``s ~ N(0, sd)``: R,
    sigma_R and R_lat by ``10**s``, rms by ``10**(s/2)`` and the log10 PSD shifts by ``s``;
    the sensor's noise floor stays. Used in training so that the classifier leans less on
    the level of the spectrum, which drifts along a uniform stretch by about a factor of 2
    (paper section 5.1, standard deviations of R) and between stretches by more than a few
    training traverses show.

    Parameters
    ----------
    X : array_like, shape (n, len(INPUT_SCALARS) + n_bins)
        Rows of :func:`feature_matrix`.
    sd : float
        Standard deviation of the scaling in log10 units (0.25: a factor of 1.8).
    copies : int
        Jittered copies per row.
    rng : numpy.random.Generator
    w_sd : float, default 0
        Standard deviation of a shift added to the fitted waviness ``w`` and ``w_lat``
        (dimensionless): w is fitted up to where the sensor's noise or resolution takes
        over, so another sensor moves it by a few hundredths to a tenth.

    Returns
    -------
    ndarray, shape (n * (copies + 1), n_features)
        Every row followed by its copies (so that a row's copies stay next to it).
    """
    X = np.asarray(X, dtype=float)
    out = np.repeat(X, copies + 1, axis=0)
    s = sd * rng.normal(size=len(out))
    s[:: copies + 1] = 0.0
    ns = len(INPUT_SCALARS)
    for name in ("R", "sigma_R", "R_lat"):
        out[:, INPUT_SCALARS.index(name)] *= 10.0**s
    out[:, INPUT_SCALARS.index("rms")] *= 10.0 ** (s / 2)
    out[:, ns:] += s[:, None]
    if w_sd > 0:
        dw = w_sd * rng.normal(size=len(out))
        dw[:: copies + 1] = 0.0
        for name in ("w", "w_lat"):
            out[:, INPUT_SCALARS.index(name)] += dw
    return out


def calibration_split(groups: ArrayLike, y: ArrayLike, n_splits: int = 3) -> Any:
    """Calibration folds that keep overlapping frames together and every class in training.

    Neighbouring frames of a traverse see overlapping patches, so folds that split a
    traverse at random leak: the calibration would see near-copies of its training frames
    and stay overconfident. The folds are therefore whole traverses (GroupKFold) when each
    fold leaves every class in its training part; otherwise (one traverse, or a class seen
    in a single traverse) the frames of each class are cut into ``n_splits`` contiguous
    runs, one per fold, so that only the frames at the ends of a run leak. A class with a
    single frame is never held out.

    Parameters
    ----------
    groups : array_like, shape (n_frames,)
        Traverse id per training frame, in the order of the rows passed to ``fit``.
    y : array_like, shape (n_frames,)
        Class per training frame.
    n_splits : int
        Folds (fewer if there are fewer traverses or frames).

    Returns
    -------
    sklearn.model_selection.PredefinedSplit
    """
    from sklearn.model_selection import GroupKFold, PredefinedSplit

    g = np.asarray(groups)
    labels = np.asarray(y)
    if g.shape != labels.shape or g.ndim != 1:
        raise errors.InputError(
            f"groups and y must be 1-D with one value per frame; got {g.shape} and {labels.shape}"
        )
    classes = np.unique(labels)
    fold = np.full(len(g), -1, dtype=np.intp)
    n_groups = len(np.unique(g))
    if n_groups >= 2:
        k = min(n_splits, n_groups)
        for i, (_, test) in enumerate(GroupKFold(k).split(g, groups=g)):
            fold[test] = i
        if all(len(np.unique(labels[fold != i])) == len(classes) for i in range(k)):
            return PredefinedSplit(fold)
        fold[:] = -1
    for c in classes:
        idx = np.flatnonzero(labels == c)
        if len(idx) < 2:
            continue
        k = min(n_splits, len(idx))
        fold[idx] = np.minimum(np.arange(len(idx)) * k // len(idx), k - 1)
    return PredefinedSplit(fold)


def make_classifier(
    kind: str = "logistic",
    *,
    omega: ArrayLike | None = None,
    cv: Any = 3,
    exclude: tuple[str, ...] = EXCLUDED_FEATURES,
    random_state: int = 0,
) -> Any:
    """The terrain classifier: ``SpectralFeatures -> StandardScaler -> calibrated classifier``.

    Parameters
    ----------
    kind : {"logistic", "hgb", "forest"}
        Base classifier: multinomial logistic regression (default), histogram gradient
        boosting, or a random forest. On held-out simulated traverses with other seeds,
        speeds and sensors the linear model generalises best (raw macro-F1 0.85 against
        0.80 for boosting and 0.78 for the forest): the classes differ mostly by smooth
        shifts of level, slope and shape of the spectrum, and the trees learn the
        particulars of the training sensors.
    omega : array_like, optional
        Wavenumbers in rad/m of the spectrum columns (``FeatureTable.omega``).
    cv : int or cross-validation splitter, default 3
        Folds of the calibration. Pass ``calibration_split(groups, y)`` for the rows that
        ``fit`` will get: an integer means stratified folds, which leak between the
        overlapping patches of neighbouring frames and leave the probabilities overconfident.
    exclude : tuple of str
        Features of :class:`SpectralFeatures` to leave out; default
        :data:`EXCLUDED_FEATURES`.
    random_state : int
        Seed of the base classifier.

    Returns
    -------
    sklearn.pipeline.Pipeline
        Steps ``features``, ``scale`` and ``classifier``. The base classifier weighs the
        classes equally (``class_weight="balanced"``), so that its posteriors do not carry
        the class frequencies of the training courses (see
        :func:`emission_log_likelihood`); it is wrapped in a ``CalibratedClassifierCV`` with
        temperature scaling (one temperature for all classes, which keeps the ranking of
        the classes and so the raw labels) and ``ensemble=False`` (one base model).
    """
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler

    if kind == "hgb":
        from sklearn.ensemble import HistGradientBoostingClassifier

        base: Any = HistGradientBoostingClassifier(
            learning_rate=0.05,
            max_iter=200,
            max_leaf_nodes=15,
            l2_regularization=1.0,
            class_weight="balanced",
            random_state=random_state,
        )
    elif kind == "logistic":
        from sklearn.linear_model import LogisticRegression

        base = LogisticRegression(C=1.0, class_weight="balanced", max_iter=2000)
    elif kind == "forest":
        from sklearn.ensemble import RandomForestClassifier

        base = RandomForestClassifier(
            n_estimators=200,
            min_samples_leaf=5,
            class_weight="balanced",
            random_state=random_state,
        )
    else:
        raise errors.InputError(f"kind must be one of {CLASSIFIERS}; got {kind!r}")
    return Pipeline(
        [
            ("features", SpectralFeatures(omega=omega, exclude=tuple(exclude))),
            ("scale", StandardScaler()),
            (
                "classifier",
                CalibratedClassifierCV(base, method="temperature", cv=cv, ensemble=False),
            ),
        ]
    )


# --------------------------------------------------------------------------------------------
# The bundle: classifier + path filter + levels + what it was trained on
# --------------------------------------------------------------------------------------------

#: Identifies the object layout of :class:`TerrainModel`; a loaded model must match it.
MODEL_FORMAT = "rough_map.TerrainModel/1"



@dataclass(frozen=True, eq=False)
class TerrainPrediction:
    """Per-frame output of :meth:`TerrainModel.predict`.

    Attributes
    ----------
    classes : ndarray of str, shape (K,)
        Class names, the columns of the probabilities.
    valid : ndarray of bool, shape (n,)
        Frames with a valid patch (the others get no raw class, and a predict step only in
        the filter).
    raw_proba : ndarray, shape (n, K)
        Calibrated classifier posteriors; NaN rows for invalid frames.
    filtered_proba : ndarray, shape (n, K)
        Posteriors after the path filter (forward filter or smoother, per ``mode``).
    raw_class : ndarray of str, shape (n,)
        Argmax of ``raw_proba``; ``""`` for invalid frames.
    filtered_class : ndarray of str, shape (n,)
        Argmax of ``filtered_proba``, or the Viterbi path when ``mode == "viterbi"``.
    level : ndarray of str, shape (n,)
        Roughness level from R; ``""`` for invalid frames.
    distance : ndarray, shape (n,)
        Distance travelled along the path in m.
    mode : str
        Filter mode used.
    defect : ndarray of bool, shape (n,)
        Frames that see an isolated defect (a short spike of R,
        :func:`rough_map.filter.isolated_spikes`): the filter gives them a predict step
        only, so that a manhole does not turn the ground around it into rough terrain.
        Their raw class and roughness stay as measured. All False in ``"forward"`` mode
        or when the model's ``defect_ratio`` is None.
    """

    classes: NDArray[np.object_]
    valid: NDArray[np.bool_]
    raw_proba: NDArray[np.float64]
    filtered_proba: NDArray[np.float64]
    raw_class: NDArray[np.object_]
    filtered_class: NDArray[np.object_]
    level: NDArray[np.object_]
    distance: NDArray[np.float64]
    mode: str
    defect: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        if self.defect is None:
            object.__setattr__(self, "defect", np.zeros(len(self.valid), dtype=bool))

    @property
    def raw_confidence(self) -> NDArray[np.float64]:
        """Probability of the raw class (NaN for invalid frames)."""
        with np.errstate(invalid="ignore"):
            return np.where(
                self.valid, np.nanmax(np.nan_to_num(self.raw_proba, nan=-1.0), 1), np.nan
            )

    @property
    def filtered_confidence(self) -> NDArray[np.float64]:
        """Filtered probability of the filtered class."""
        idx = np.searchsorted(self.classes, self.filtered_class)
        return self.filtered_proba[np.arange(len(idx)), idx]


def _labels(table: Any) -> NDArray[np.object_]:
    return np.array([str(v) if v is not None else "" for v in table.columns["label"]], dtype=object)


def training_hash(tables: Sequence[Any]) -> str:
    """sha256 of what a model is trained on: per traverse its name, wavenumbers, input
    matrix (:func:`feature_matrix`), labels and distances along the path.

    Parameters
    ----------
    tables : sequence of FeatureTable

    Returns
    -------
    str
        Hex digest.
    """
    digest = hashlib.sha256()
    for table in tables:
        X, _ = feature_matrix(table)
        digest.update(table.name.encode())
        digest.update(np.ascontiguousarray(table.omega, dtype="<f8").tobytes())
        digest.update(np.ascontiguousarray(X, dtype="<f8").tobytes())
        digest.update("\x1f".join(_labels(table)).encode())
        digest.update(np.ascontiguousarray(table.distance(), dtype="<f8").tobytes())
    return digest.hexdigest()


#: Candidate evidence per metre travelled (1/m) that :meth:`TerrainModel.fit` chooses from.
EVIDENCE_GRID: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)


def frame_steps(distance: ArrayLike, groups: ArrayLike | None = None) -> NDArray[np.float64]:
    """Distance in m from each frame to the previous frame of its traverse.

    The first frame of a traverse gets the traverse's median step.

    Parameters
    ----------
    distance : array_like, shape (n,)
        Cumulative distance along the path in m, non-decreasing within a traverse.
    groups : array_like, shape (n,), optional
        Traverse id per frame (frames of a traverse in order). Default: one traverse.

    Returns
    -------
    ndarray, shape (n,)
        Steps in m.
    """
    d = np.asarray(distance, dtype=float)
    g = np.zeros(len(d), dtype=np.intp) if groups is None else np.asarray(groups)
    steps = np.zeros(len(d))
    for value in np.unique(g):
        idx = np.flatnonzero(g == value)
        if len(idx) > 1:
            step = np.diff(d[idx])
            steps[idx[1:]] = step
            steps[idx[0]] = float(np.median(step))
    return steps


def emission_log_likelihood(
    proba: ArrayLike,
    steps: ArrayLike,
    evidence_per_m: float,
    prior: ArrayLike | None = None,
    floor: float = 1e-6,
) -> NDArray[np.float64]:
    """Scaled log likelihoods for the path filter, weighted by the distance each frame adds.

    Consecutive patches overlap (a 0.9 m patch, a frame every 0.15 to 0.35 m at 0.3 to 0.7
    m/s and 2 Hz), so a frame brings new evidence in proportion to the ground it adds:
    its emission is ``min(1, evidence_per_m * step) * (log p(c | x) - log prior(c))``. The
    evidence per metre is then the same whatever the speed, where a fixed weight per frame
    would over-trust slow traverses and under-trust fast ones.

    Parameters
    ----------
    proba : array_like, shape (n, K)
        Classifier posteriors (rows are normalised); NaN rows for frames without one.
    steps : array_like, shape (n,)
        Ground in m each frame adds (:func:`frame_steps`).
    evidence_per_m : float
        Weight per metre travelled, 1/m.
    prior : array_like, shape (K,), optional
        Class prior the posteriors were trained under; default uniform (a classifier
        trained with balanced class weights, as :func:`make_classifier` builds it).
    floor : float
        Posteriors are clipped from below at this value.

    Returns
    -------
    ndarray, shape (n, K)
        Log likelihood per frame up to a constant; NaN rows where ``proba`` has NaN.
    """
    p = np.asarray(proba, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = p / p.sum(axis=1, keepdims=True)
        ll = np.log(np.maximum(p, floor))
        if prior is not None:
            ll = ll - np.log(np.asarray(prior, dtype=float))
    weight = np.minimum(1.0, evidence_per_m * np.asarray(steps, dtype=float))
    ll = ll * weight[:, None]
    ll[np.isnan(p).any(axis=1)] = np.nan
    return ll


class TerrainModel:
    """Terrain class and roughness level along a traverse: everything a model file holds.

    ``fit`` takes labelled feature tables (one per traverse), cross-validates the classifier
    with whole traverses as folds, fits it on all frames, and fits the path filter on the
    held-out posteriors (so that its emission weight matches what the classifier does on
    unseen ground). ``predict`` gives, for every frame of a table, the raw and the filtered
    class with their probabilities and the roughness level.

    Parameters
    ----------
    kind : {"logistic", "hgb", "forest"}, default "logistic"
        Base classifier (see :func:`make_classifier`).
    mode : {"forward", "smooth", "viterbi"}, default "smooth"
        Filter mode used by :meth:`predict` unless it is given one: ``"forward"`` is the
        online filter (each frame sees only the frames before it), ``"smooth"`` the
        forward-backward smoother and ``"viterbi"`` the most probable class sequence, for
        recorded traverses.
    level_names : tuple of str, default ("low", "medium", "high")
        Roughness levels, smoothest first (paper section 5.5).
    level_thresholds : tuple of float, optional
        Upper bounds on R in m^3/rad of all but the last level; default the ISO 8608 C/D
        and E/F boundaries (see :class:`RoughnessLevels`).
    cv : int, default 5
        Cross-validation folds (whole traverses; fewer if there are fewer traverses).
    evidence_per_m : float or "auto", default "auto"
        Weight of the classifier's evidence per metre travelled, 1/m (see
        :func:`emission_log_likelihood`). "auto" takes the value of
        :data:`EVIDENCE_GRID` with the best filtered macro-F1 on the held-out posteriors,
        the mean of the forward filter's and the smoother's (too little evidence makes the
        forward filter lag behind a change of class; too much lets a run of wrong frames
        flip it).
    exclude : tuple of str, default EXCLUDED_FEATURES
        Features of :class:`SpectralFeatures` the classifier does not see.
    level_jitter : float, default 0.4
        Standard deviation in log10 units of the random scaling of the terrain in the
        training copies (:func:`jitter_levels`); 0 trains on the frames as they are.
    waviness_jitter : float, default 0.05
        Standard deviation of the random shift of w in the training copies.
    jitter_copies : int, default 3
        Jittered copies of every training frame.
    defect_ratio : float or None, default 8.0
        A short run of frames (<= 1.5 m) whose R exceeds this many times the median of the
        frames within 3 m is an isolated defect (:func:`rough_map.filter.isolated_spikes`):
        in ``"smooth"`` and ``"viterbi"`` modes the filter does not take its class. None
        turns the test off.
    extraction : Extraction or dict, optional
        How the feature tables were computed (:class:`rough_map.patch.Extraction`: patch
        geometry in m, tilt, estimator), stored (as ``Extraction.to_dict``) so that
        ``classify`` and ``evaluate`` compute features the same way. Default the paper's.
    random_state : int, default 0
        Seed of the classifier.

    Attributes
    ----------
    classes_ : ndarray of str
        Terrain classes, from the training labels.
    classifier_ : sklearn.pipeline.Pipeline
        The fitted pipeline of :func:`make_classifier`.
    filter_ : PathFilter
        The path filter (``inputs="log_likelihood"``, fed by
        :func:`emission_log_likelihood`).
    evidence_per_m_ : float
        Evidence per metre travelled of the filter's emissions, 1/m.
    omega_ : ndarray
        Wavenumbers in rad/m of the spectrum the model expects.
    level_names_, level_thresholds_ : tuple
        Roughness levels and their thresholds in m^3/rad.
    extraction_ : dict
        Feature extraction settings.
    cv_report_ : dict
        Cross-validated metrics (see :meth:`fit`).
    training_ : dict
        Traverses, frame counts and :func:`training_hash` of the training data.
    format_ : str
        :data:`MODEL_FORMAT`.
    """

    def __init__(
        self,
        kind: str = "logistic",
        mode: str = "smooth",
        level_names: tuple[str, ...] = ("low", "medium", "high"),
        level_thresholds: tuple[float, ...] | None = None,
        cv: int = 5,
        evidence_per_m: float | str = "auto",
        exclude: tuple[str, ...] = EXCLUDED_FEATURES,
        level_jitter: float = 0.4,
        waviness_jitter: float = 0.05,
        jitter_copies: int = 3,
        defect_ratio: float | None = 8.0,
        extraction: dict[str, Any] | None = None,
        random_state: int = 0,
    ) -> None:
        self.kind = kind
        self.mode = mode
        self.level_names = level_names
        self.level_thresholds = level_thresholds
        self.cv = cv
        self.evidence_per_m = evidence_per_m
        self.exclude = exclude
        self.level_jitter = level_jitter
        self.waviness_jitter = waviness_jitter
        self.jitter_copies = jitter_copies
        self.defect_ratio = defect_ratio
        self.extraction = extraction
        self.random_state = random_state

    # ---------------------------------------------------------------- fit

    def _stack(self, tables: Sequence[Any], *, require_labels: bool) -> dict[str, Any]:
        if len(tables) == 0:
            raise errors.InputError("no traverses given")
        omega = np.asarray(tables[0].omega, dtype=float)
        parts: dict[str, list[Any]] = {k: [] for k in ("X", "y", "g", "d", "v")}
        for i, table in enumerate(tables):
            if not np.allclose(table.omega, omega, rtol=1e-6):
                raise errors.InputError(
                    f"traverse {table.name!r} has other wavenumbers than {tables[0].name!r} "
                    "(another patch size or spacing); compute all features with one patch"
                )
            y = _labels(table)
            if require_labels and not (y != "").any():
                raise errors.InputError(
                    f"traverse {table.name!r} has no labelled frames; training needs a terrain "
                    "class ('label') on the frames"
                )
            X, _ = feature_matrix(table)
            parts["X"].append(X)
            parts["y"].append(y)
            parts["g"].append(np.full(len(table), i))
            parts["d"].append(table.distance())
            parts["v"].append(table.valid & np.isfinite(X).all(axis=1))
        out = {k: np.concatenate(v) for k, v in parts.items()}
        out["omega"] = omega
        return out

    def fit(self, tables: Sequence[Any]) -> TerrainModel:
        """Train on labelled traverses.

        Frames without a label are left out; frames without a valid patch train the
        switching model of the filter but not the classifier.

        Parameters
        ----------
        tables : sequence of FeatureTable
            One per traverse, computed with one patch geometry, with ``label`` set.

        Returns
        -------
        TerrainModel
            ``self``, fitted. ``cv_report_`` holds the cross-validated metrics: ``scheme``,
            ``n_splits``, ``frames``, and under ``raw`` and ``filtered`` the ``accuracy``,
            ``macro_f1`` and ``f1`` per class, plus ``per_fold`` results.

        Raises
        ------
        InputError
            No traverses, a traverse without labels, fewer than two classes, mixed patch
            geometries, bad parameters.
        """
        from sklearn.base import clone
        from sklearn.metrics import accuracy_score, f1_score
        from sklearn.model_selection import GroupKFold

        from rough_map.filter import PathFilter

        if self.mode not in ("forward", "smooth", "viterbi"):
            raise errors.InputError(f"mode must be forward, smooth or viterbi; got {self.mode!r}")
        per_m = self.evidence_per_m
        if not (
            per_m == "auto" or (isinstance(per_m, Real) and math.isfinite(per_m) and per_m > 0)
        ):
            raise errors.InputError(
                f"evidence_per_m must be 'auto' or a positive number (1/m); got {per_m!r}"
            )
        if not (isinstance(self.cv, Integral) and self.cv >= 2):
            raise errors.InputError(f"cv must be an integer >= 2; got {self.cv!r}")
        names = tuple(str(n) for n in self.level_names)
        thresholds = (
            tuple(float(v) for v in RoughnessLevels().values())
            if self.level_thresholds is None
            else tuple(float(v) for v in self.level_thresholds)
        )
        RoughnessLevels(levels=names, thresholds=thresholds)  # validates them
        data = self._stack(tables, require_labels=True)
        labelled = data["y"] != ""
        n_unlabelled = int((~labelled).sum())
        if n_unlabelled:
            log.warning("%d frames without a label are left out of training", n_unlabelled)
        X, y, g, d, v = (data[k][labelled] for k in ("X", "y", "g", "d", "v"))
        classes = np.unique(y)
        if len(classes) < 2:
            raise errors.InputError(
                f"training needs at least 2 terrain classes; the labels hold only {list(classes)}"
            )
        train = v
        if not train.any():
            raise errors.InputError("no frame has both a label and a valid patch")
        omega = data["omega"]

        if not (
            isinstance(self.level_jitter, Real)
            and math.isfinite(self.level_jitter)
            and self.level_jitter >= 0
        ):
            raise errors.InputError(f"level_jitter must be >= 0; got {self.level_jitter!r}")
        if not (isinstance(self.jitter_copies, Integral) and self.jitter_copies >= 0):
            raise errors.InputError(
                f"jitter_copies must be an integer >= 0; got {self.jitter_copies!r}"
            )
        w_sd = self.waviness_jitter
        if not (isinstance(w_sd, Real) and math.isfinite(w_sd) and w_sd >= 0):
            raise errors.InputError(f"waviness_jitter must be >= 0; got {w_sd!r}")
        ratio = self.defect_ratio
        if ratio is not None and not (
            isinstance(ratio, Real) and math.isfinite(ratio) and ratio > 1
        ):
            raise errors.InputError(f"defect_ratio must be None or a number > 1; got {ratio!r}")
        copies = (
            int(self.jitter_copies) if (self.level_jitter > 0 or self.waviness_jitter > 0) else 0
        )
        rng = np.random.default_rng(self.random_state)

        def fit_classifier(rows: NDArray[np.intp]) -> Any:
            """A classifier fitted on ``rows`` plus their jittered copies."""
            clf = make_classifier(
                self.kind,
                omega=omega,
                cv=calibration_split(
                    np.repeat(g[rows], copies + 1), np.repeat(y[rows], copies + 1)
                ),
                exclude=tuple(self.exclude),
                random_state=self.random_state,
            )
            return clf.fit(
                jitter_levels(X[rows], self.level_jitter, copies, rng, self.waviness_jitter),
                np.repeat(y[rows], copies + 1),
            )

        # Held-out posteriors: folds of whole traverses, or contiguous blocks of one.
        n_traverses = len(np.unique(g))
        if n_traverses >= 2:
            n_splits = min(self.cv, n_traverses)
            folds = list(GroupKFold(n_splits).split(X, groups=g))
            scheme = f"GroupKFold by traverse ({n_splits} folds of whole traverses)"
        else:
            n_splits = self.cv
            blocks = np.minimum(np.arange(len(y)) * n_splits // len(y), n_splits - 1)
            folds = [
                (np.flatnonzero(blocks != b), np.flatnonzero(blocks == b)) for b in range(n_splits)
            ]
            g = blocks  # the calibration inside each fold uses blocks too
            scheme = (
                f"one traverse: {n_splits} contiguous blocks of frames (neighbouring blocks "
                "share overlapping patches at their edges, so the metrics are optimistic)"
            )
            log.warning("only one traverse: cross-validation uses %s", scheme)
        held_out = np.full((len(y), len(classes)), np.nan)
        for fit_idx, test_idx in folds:
            fit_idx, test_idx = fit_idx[train[fit_idx]], test_idx[train[test_idx]]
            if len(np.unique(y[fit_idx])) < 2 or len(test_idx) == 0:
                continue
            clf = fit_classifier(fit_idx)
            cols = np.searchsorted(classes, clf.classes_)
            held_out[test_idx] = 0.0
            held_out[np.ix_(test_idx, cols)] = clf.predict_proba(X[test_idx])
        scored = np.isfinite(held_out).all(axis=1)

        self.classifier_ = fit_classifier(np.flatnonzero(train))

        # The path filter: switching model and class prior from the labels; the evidence per
        # metre from the held-out posteriors. The classifier is trained with balanced class
        # weights, so its posteriors are likelihoods up to a constant: how often each class
        # was driven in the training traverses is an accident of the courses, and the
        # filter's switching model is where prior knowledge of the path belongs.
        steps = frame_steps(d, g)

        def evidence(proba: NDArray[np.float64], per_m: float, rows: Any = slice(None)) -> Any:
            return emission_log_likelihood(proba, steps[rows], per_m)

        self.filter_ = PathFilter(inputs="log_likelihood", emission_weight=1.0, mode=self.mode)
        self.filter_.fit(evidence(held_out, 1.0), y, distance=d, groups=g)
        if self.evidence_per_m == "auto":
            tried = []
            probe = clone(self.filter_)
            probe.__dict__.update({k: v for k, v in vars(self.filter_).items() if k.endswith("_")})
            for per_m in EVIDENCE_GRID:
                ll = evidence(held_out, per_m)
                f1 = []
                # online and offline: too little evidence makes the online filter lag
                for mode in ("forward", "smooth"):
                    probe.mode = mode
                    pred = probe.predict(ll, distance=d, groups=g, valid=scored)
                    f1.append(f1_score(y[scored], pred[scored].astype(str), average="macro"))
                tried.append(float(np.mean(f1)))
            self.evidence_per_m_ = float(EVIDENCE_GRID[int(np.argmax(tried))])
            log.info(
                "evidence per metre: held-out filtered macro-F1 %s for %s 1/m; chose %.2f 1/m",
                np.round(tried, 3).tolist(),
                list(EVIDENCE_GRID),
                self.evidence_per_m_,
            )
        else:
            self.evidence_per_m_ = float(self.evidence_per_m)

        # Filtered CV metrics: per fold, the filter's switching model and prior come from the
        # other folds' labels; its evidence per metre is the one chosen above.
        filtered = np.empty(len(y), dtype=object)
        per_fold = []
        for fit_idx, test_idx in folds:
            if len(np.unique(y[fit_idx])) < len(classes):
                flt = self.filter_  # a fold lacks a class: keep the full model's switching
            else:
                flt = clone(self.filter_).fit(
                    evidence(held_out[fit_idx], 1.0, fit_idx),
                    y[fit_idx],
                    distance=d[fit_idx],
                    groups=g[fit_idx],
                )
            filtered[test_idx] = flt.predict(
                evidence(held_out[test_idx], self.evidence_per_m_, test_idx),
                distance=d[test_idx],
                groups=g[test_idx],
                valid=scored[test_idx],
            )
            ok = test_idx[scored[test_idx]]
            if len(ok):
                raw_f = classes[np.argmax(held_out[ok], axis=1)]
                per_fold.append(
                    {
                        "traverses": sorted(
                            {str(tables[int(i)].name) for i in np.unique(data["g"][labelled][ok])}
                        )
                        if n_traverses >= 2
                        else [],
                        "frames": int(len(ok)),
                        "raw_macro_f1": float(f1_score(y[ok], raw_f, average="macro")),
                        "filtered_macro_f1": float(
                            f1_score(y[ok], filtered[ok].astype(str), average="macro")
                        ),
                    }
                )
        raw = classes[np.argmax(np.nan_to_num(held_out[scored], nan=-1.0), axis=1)]
        filt = filtered[scored].astype(str)
        truth = y[scored]

        def summary(pred: NDArray[Any]) -> dict[str, Any]:
            f1 = f1_score(truth, pred, labels=classes, average=None, zero_division=0)
            return {
                "accuracy": float(accuracy_score(truth, pred)),
                "macro_f1": float(f1_score(truth, pred, average="macro")),
                "f1": {str(c): float(f) for c, f in zip(classes, f1, strict=True)},
            }

        self.cv_report_ = {
            "scheme": scheme,
            "n_splits": int(n_splits),
            "frames": int(scored.sum()),
            "mode": self.mode,
            "raw": summary(raw),
            "filtered": summary(filt),
            "per_fold": per_fold,
        }
        self.classes_ = classes
        self.omega_ = omega
        self.level_names_ = names
        self.level_thresholds_ = thresholds
        self.extraction_ = Extraction.from_dict(self.extraction).to_dict()
        self.training_ = {
            "sha256": training_hash(tables),
            "traverses": [
                {
                    "name": str(t.name),
                    "frames": int(len(t)),
                    "labelled": int((_labels(t) != "").sum()),
                    "valid": int(np.sum(t.valid)),
                }
                for t in tables
            ],
            "class_frames": {str(c): int(np.sum(y == c)) for c in classes},
        }
        self.format_ = MODEL_FORMAT
        log.info(
            "cross-validated (%s): raw macro-F1 %.3f, filtered macro-F1 %.3f on %d frames",
            scheme,
            self.cv_report_["raw"]["macro_f1"],
            self.cv_report_["filtered"]["macro_f1"],
            self.cv_report_["frames"],
        )
        return self

    # ---------------------------------------------------------------- predict

    def _check_fitted(self) -> None:
        if not hasattr(self, "classifier_"):
            raise errors.NotFittedError("this TerrainModel is not fitted; call fit() first")

    @property
    def levels_(self) -> RoughnessLevels:
        """The roughness levels of the model, as :class:`RoughnessLevels`."""
        self._check_fitted()
        return RoughnessLevels(levels=self.level_names_, thresholds=self.level_thresholds_)

    @property
    def feature_names(self) -> list[str]:
        """Names of the features the classifier sees (see :data:`FEATURE_DOC`)."""
        self._check_fitted()
        return [str(n) for n in self.classifier_.named_steps["features"].get_feature_names_out()]

    def check_labels(self, labels: ArrayLike, where: str = "the data") -> None:
        """Raise :class:`~rough_map.errors.ModelError` if labels hold classes the model lacks.

        Parameters
        ----------
        labels : array_like of str
            Labels; ``""`` (unlabelled) is ignored.
        where : str
            What to name in the message (e.g. the traverse).
        """
        self._check_fitted()
        lab = np.asarray(labels, dtype=object)
        unknown = sorted({str(v) for v in lab[lab != ""]} - {str(c) for c in self.classes_})
        if unknown:
            raise errors.ModelError(
                f"{where} has labels the model does not know: {unknown}; it was trained on "
                f"{[str(c) for c in self.classes_]}"
            )

    def predict(self, table: Any, *, mode: str | None = None) -> TerrainPrediction:
        """Raw and filtered class, their probabilities, and the roughness level per frame.

        Parameters
        ----------
        table : FeatureTable
            Features of one traverse, computed as ``extraction_`` says.
        mode : {"forward", "smooth", "viterbi"}, optional
            Filter mode; default the model's ``mode``.

        Returns
        -------
        TerrainPrediction

        Raises
        ------
        ModelError
            The table's spectrum has other wavenumbers than the model's (another patch).
        """
        import copy

        self._check_fitted()
        mode = self.mode if mode is None else mode
        if mode not in ("forward", "smooth", "viterbi"):
            raise errors.InputError(f"mode must be forward, smooth or viterbi; got {mode!r}")
        omega = np.asarray(table.omega, dtype=float)
        if omega.shape != self.omega_.shape or not np.allclose(omega, self.omega_, rtol=1e-6):
            raise errors.ModelError(
                f"traverse {table.name!r}: its spectrum has {omega.size} wavenumbers from "
                f"{omega[0] if omega.size else float('nan'):.3g} rad/m, the model expects "
                f"{self.omega_.size} from {self.omega_[0]:.3g} rad/m; compute the features "
                f"with the model's patch {self.extraction_}"
            )
        X, _ = feature_matrix(table)
        valid = np.asarray(table.valid, dtype=bool) & np.isfinite(X).all(axis=1)
        k = len(self.classes_)
        raw = np.full((len(X), k), np.nan)
        if valid.any():
            cols = np.searchsorted(self.classes_, self.classifier_.classes_)
            raw[valid] = 0.0
            raw[np.ix_(valid, cols)] = self.classifier_.predict_proba(X[valid])
        flt = copy.copy(self.filter_)
        flt.mode = mode
        distance = np.asarray(table.distance(), dtype=float)
        ll = emission_log_likelihood(raw, frame_steps(distance), self.evidence_per_m_)
        defect = self._defects(table, valid, distance, mode)
        evidence = valid & ~defect
        filtered = flt.predict_proba(ll, distance=distance, valid=evidence)
        if mode == "viterbi":
            filtered_class = flt.predict(ll, distance=distance, valid=evidence).astype(object)
        else:
            filtered_class = self.classes_[np.argmax(filtered, axis=1)].astype(object)
        raw_class = np.full(len(X), "", dtype=object)
        if valid.any():
            raw_class[valid] = self.classes_[np.argmax(raw[valid], axis=1)]
        level = roughness_level(
            np.where(valid, table.columns["R"], np.nan), self.level_names_, self.level_thresholds_
        )
        return TerrainPrediction(
            classes=self.classes_.astype(object),
            valid=valid,
            raw_proba=raw,
            filtered_proba=filtered,
            raw_class=raw_class,
            filtered_class=filtered_class,
            level=level,
            distance=distance,
            mode=mode,
            defect=defect,
        )

    def _defects(
        self, table: Any, valid: NDArray[np.bool_], distance: NDArray[np.float64], mode: str
    ) -> NDArray[np.bool_]:
        """Frames of an isolated defect (recorded traverses only: the test looks ahead)."""
        from rough_map.filter import isolated_spikes

        ratio = getattr(self, "defect_ratio", None)
        none = np.zeros(len(valid), dtype=bool)
        if ratio is None or mode == "forward" or not valid.any():
            return none
        if not np.all(np.isfinite(distance)):
            log.warning("%s: poses not all finite; isolated defects not looked for", table.name)
            return none
        R = np.where(valid, np.asarray(table.columns["R"], dtype=float), np.nan)
        defect = isolated_spikes(R, distance, ratio=float(ratio))
        if defect.any():
            log.info(
                "%s: %d frame(s) see an isolated defect (R above %g x the local median); "
                "the filter does not take their class",
                table.name,
                int(defect.sum()),
                ratio,
            )
        return defect


