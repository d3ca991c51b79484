"""Classification features of a frame from its roughness parameters and its spectrum.

:func:`feature_matrix` stacks what :func:`rough_map.features.traverse_features` measured for
every frame (the scalar columns :data:`INPUT_SCALARS` and the patch-mean log10 PSD) into one
matrix; :class:`SpectralFeatures`, a scikit-learn transformer, turns that matrix into the
features of :data:`FEATURE_DOC`.
"""

from __future__ import annotations

import math
from numbers import Integral, Real
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.utils import Tags

from rough_map import errors
from rough_map.classify.validation import check_fitted, validate_frames
from rough_map.patch import PatchSpec
from rough_map.psd import grid_log_gain

__all__ = [
    "FEATURE_DOC",
    "INPUT_SCALARS",
    "SpectralFeatures",
    "default_omega",
    "feature_matrix",
    "on_model_grid",
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


def feature_matrix(
    table: Any, omega: ArrayLike | None = None
) -> tuple[NDArray[np.float64], list[str]]:
    """The input matrix of :class:`SpectralFeatures` for every frame of a features table.

    Parameters
    ----------
    table : FeatureTable
        Per-frame features of a traverse (:func:`rough_map.features.traverse_features` or
        :func:`rough_map.features.read_features`).
    omega : array_like of float, optional
        Wavenumbers in rad/m of a model's spectrum columns: the table's spectrum is mapped
        onto them (:func:`on_model_grid`). Default the table's own.

    Returns
    -------
    X : ndarray, shape (n_frames, len(INPUT_SCALARS) + n_bins)
        The columns :data:`INPUT_SCALARS` (units as in the table: m^3/rad, m, ...) followed by
        the patch-mean PSD as log10 of m^3/rad on ``omega``; NaN rows for invalid frames.
    names : list of str
        Column names: :data:`INPUT_SCALARS` then ``psd_01`` ...

    Raises
    ------
    InputError
        The table lacks one of the columns.
    ModelError
        ``omega`` is another patch's (see :func:`on_model_grid`).
    """
    missing = [c for c in INPUT_SCALARS if c not in table.columns]
    if missing:
        raise errors.InputError(f"features table {table.name!r} lacks the columns {missing}")
    scalars = np.column_stack([np.asarray(table.columns[c], dtype=float) for c in INPUT_SCALARS])
    spectrum = (
        np.asarray(table.log_psd, dtype=float) if omega is None else on_model_grid(table, omega)
    )
    X = np.hstack([scalars, spectrum])
    X[~np.asarray(table.valid, dtype=bool)] = np.nan
    bins = [f"psd_{k:02d}" for k in range(1, spectrum.shape[1] + 1)]
    return X, [*INPUT_SCALARS, *bins]


def on_model_grid(table: Any, omega: ArrayLike) -> NDArray[np.float64]:
    """log10 of the PSD in m^3/rad of each frame of ``table`` as the cell-mean grid of a
    model, whose spectrum columns are at ``omega`` (rad/m), would have measured it:
    shape (n_frames, len(omega)).

    A table on the model's wavenumbers gives its own spectrum. A grid of another step over
    the same patch (``spacing auto`` on a sparse cloud) has the same wavenumbers
    ``2 pi k / L`` up to its own ``pi / B``: its ordinates go to the model's ``k``, less
    what its grid did to them and plus what the model's grid would have
    (:func:`rough_map.psd.grid_log_gain`, at each frame's w and lateral scale). The model's
    wavenumbers above the table's band are NaN, which :class:`SpectralFeatures` leaves out
    as it leaves out ordinates below the noise floor. Both grids are taken as cell means of
    random points (a lattice read on its own nodes is corrected as if it were one), and R,
    w and the other scalar columns are left as the table has them.

    Raises
    ------
    ModelError
        The table's wavenumbers are not multiples of the model's fundamental (another
        patch size).
    """
    own = np.asarray(table.omega, dtype=float)
    target = np.asarray(omega, dtype=float)
    log_psd = np.asarray(table.log_psd, dtype=float)
    if own.shape == target.shape and np.allclose(own, target, rtol=1e-6):
        return log_psd
    k = own / target[0] if target.size else own
    if own.size < 2 or not np.allclose(k, np.arange(1, own.size + 1), rtol=1e-6):
        raise errors.ModelError(
            f"traverse {table.name!r:.40}: its spectrum has {own.size} wavenumbers from "
            f"{own[0] if own.size else float('nan'):.3g} rad/m, not the multiples of the "
            f"model's {target[0] if target.size else float('nan'):.3g} rad/m: the model was "
            f"trained on a patch of {2 * np.pi / target[0] if target.size else 0:.3g} m; "
            "compute the features with that patch size"
        )
    top = min(own.size, target.size)
    cols = table.columns
    w = np.asarray(cols["w"], dtype=float)
    scale = (
        np.asarray(cols["lateral_scale"], dtype=float) if "lateral_scale" in cols else w * np.nan
    )
    # Profile lengths in samples: pi / B at the last ordinate of an even length.
    shift = grid_log_gain(2 * target.size, w, scale)[:, :top]
    shift = shift - grid_log_gain(2 * own.size, w, scale)[:, :top]
    out = np.full((len(log_psd), target.size), np.nan)
    out[:, :top] = log_psd[:, :top] + shift / math.log(10.0)
    return out


def default_omega(n_bins: int, patch: PatchSpec | None = None) -> NDArray[np.float64]:
    """Wavenumbers ``2 pi k / L`` in rad/m, ``k = 1 ... n_bins``, of a patch of side ``L``.

    Parameters
    ----------
    n_bins : int
        Number of wavenumbers.
    patch : PatchSpec, optional
        The patch; ``L`` is its ``size`` in m. Default the paper's (:class:`PatchSpec`).

    Returns
    -------
    ndarray, shape (n_bins,)
        Wavenumbers in rad/m.
    """
    size = (patch if patch is not None else PatchSpec()).size
    return np.asarray(2.0 * np.pi * np.arange(1, n_bins + 1) / size, dtype=float)


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
        Wavenumbers in rad/m of the spectrum columns. Default :func:`default_omega`, those
        of the paper's patch.
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

    def __sklearn_tags__(self) -> Tags:
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
        Xv = validate_frames(self, X, reset=True)
        scalars = self._check_params()
        omega = self._omega(Xv.shape[1], scalars)
        inside = omega <= self.omega_max
        if inside.sum() < 2:
            raise errors.InputError(
                f"SpectralFeatures needs at least 2 spectrum columns at or below omega_max = "
                f"{self.omega_max} rad/m; X has {Xv.shape[1]} feature(s) of which "
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

    def _check_params(self) -> tuple[str, ...]:
        """Raise InputError on bad parameters; the scalar column names."""
        scalars = tuple(self.scalars)
        unknown = [s for s in scalars if s not in INPUT_SCALARS]
        if unknown or len(set(scalars)) != len(scalars):
            raise errors.InputError(
                f"scalars must be distinct names from {INPUT_SCALARS}; got {scalars!r}"
            )
        for name in ("snr_min", "omega_max"):
            value = getattr(self, name)
            if not (isinstance(value, Real) and math.isfinite(value) and float(value) >= 0):
                raise errors.InputError(f"{name} must be a finite number >= 0; got {value!r}")
        if not (isinstance(self.bands_per_octave, Integral) and self.bands_per_octave >= 1):
            raise errors.InputError(
                f"bands_per_octave must be an integer >= 1; got {self.bands_per_octave!r}"
            )
        return scalars

    def _omega(self, n_columns: int, scalars: tuple[str, ...]) -> NDArray[np.float64]:
        """Wavenumbers in rad/m of the spectrum columns, checked against the layout of X."""
        n_bins = n_columns - len(scalars)
        omega = (
            default_omega(max(n_bins, 0))
            if self.omega is None
            else np.asarray(self.omega, dtype=float)
        )
        if omega.shape != (max(n_bins, 0),):
            raise errors.InputError(
                f"omega must hold one wavenumber (rad/m) per spectrum column: X has "
                f"{n_columns} feature(s), {len(scalars)} scalar(s), so {n_bins} spectrum "
                f"columns, but omega has shape {omega.shape}"
            )
        if not (np.all(np.isfinite(omega)) and np.all(omega > 0) and np.all(np.diff(omega) > 0)):
            raise errors.InputError("omega must be positive, finite and increasing (rad/m)")
        return omega

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

    # ------------------------------------------------------------------ transform

    def transform(self, X: ArrayLike) -> NDArray[np.float64]:
        """Compute the features of every frame.

        Parameters
        ----------
        X : array_like, shape (n_frames, n_features_in_)
            As in :meth:`fit`. A row whose spectrum is NaN over the whole band gives a row
            of NaN; NaN ordinates within the band are left out, as ordinates below the noise
            floor are.

        Returns
        -------
        ndarray, shape (n_frames, len(feature_names_out_))
            The features, in the order of :meth:`get_feature_names_out`.
        """
        check_fitted(self, "feature_names_out_")
        Xv = validate_frames(self, X, reset=False)
        scalars = tuple(self.scalars)
        col = {name: Xv[:, i] for i, name in enumerate(scalars)}
        noise = col.get("noise_psd", np.zeros(len(Xv)))
        noise = np.where(np.isfinite(noise) & (noise > 0), noise, 0.0)
        spectrum = Xv[:, len(scalars) :]
        result = np.column_stack([*_scalar_features(col), self._shape(spectrum, noise)])
        # A frame without a spectrum in the band has no features; one whose spectrum ends
        # inside it (a coarser grid's, mapped by on_model_grid) is measured on what it has.
        result[np.isnan(spectrum[:, self.band_ >= 0]).all(axis=1)] = np.nan
        names = self._names(scalars, int(self.band_.max()) + 1)
        keep = np.isin(np.asarray(names, dtype=object), self.feature_names_out_)
        return np.asarray(result[:, keep], dtype=float)

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
        check_fitted(self, "band_")
        return [
            (float(self.omega_[self.band_ == j].min()), float(self.omega_[self.band_ == j].max()))
            for j in range(int(self.band_.max()) + 1)
        ]

    def get_feature_names_out(self, input_features: Any = None) -> NDArray[np.object_]:
        """Names of the output features (see :data:`FEATURE_DOC`)."""
        check_fitted(self, "feature_names_out_")
        return self.feature_names_out_.copy()


def _scalar_features(col: dict[str, NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    """The features of the scalar columns present, in the order of ``_names``."""
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
    return out


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
