"""The features table of a traverse: :class:`FeatureTable`, its columns and their units."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rough_map.errors import InputError
from rough_map.iso8608 import iso_class

__all__ = [
    "COLUMNS",
    "COLUMN_UNITS",
    "OPTIONAL_COLUMNS",
    "SE_COLUMNS",
    "SMOOTH_COLUMNS",
    "FeatureTable",
    "LabelSummary",
    "label_summary",
]

#: Roughness smoothed along the path (:class:`rough_map.filter.RoughnessSmoother`): R in
#: m³/rad, w, and the standard deviations of ln R and of w. NaN until a traverse's table is
#: smoothed (``rough-map features`` and ``map`` do it; the features pass cannot, as it runs
#: frame by frame).
SMOOTH_COLUMNS = ("R_smooth", "w_smooth", "sigma_lnR_smooth", "sigma_w_smooth")
#: Standard errors of a frame's ln R and w, with the correlation between its profiles
#: (:attr:`rough_map.psd.PatchRoughness.se_lnR`).
SE_COLUMNS = ("se_lnR", "se_w")
#: What else a frame's reading says (:class:`rough_map.psd.PatchRoughness`): the ground's
#: lateral scale (1 isotropic, 0 the same across the track, up to 5 rougher across than
#: along; NaN when not read), the wavenumber in rad/m up to which the ground stays above
#: the sensor's noise floor, the band's rms height in m and the fitted PSD at the band's
#: log centre (roughness without extrapolation), the fit's rms over the band's, and the
#: curvature of the log spectrum in its own standard errors (:mod:`rough_map.psd._fit`).
READING_COLUMNS = (
    "lateral_scale",
    "omega_noise",
    "band_rms",
    "centre_psd",
    "omega_centre",
    "rms_ratio",
    "curvature_z",
)
#: Where the frame's patch is: its centre in the world frame (m), ``ahead`` and
#: ``lateral`` of the pose along its heading.
PLACE_COLUMNS = ("patch_x", "patch_y")
#: The speed advice for a vehicle (:mod:`rough_map.features.driving`; NaN without one):
#: the highest speed keeping its limits, the same with 95 % confidence, and the rms
#: responses at a chosen speed.
DRIVE_COLUMNS = (
    "v_max",
    "v_max_95",
    "weighted_acceleration",
    "suspension_travel",
    "dynamic_load_ratio",
)
#: Columns a table written before they existed may lack (read as NaN).
OPTIONAL_COLUMNS = frozenset(
    SMOOTH_COLUMNS + SE_COLUMNS + READING_COLUMNS + PLACE_COLUMNS + DRIVE_COLUMNS
)

#: Columns of a features table, in order (spectrum columns follow).
COLUMNS = (
    "frame",
    "t",
    "x",
    "y",
    "yaw",
    "R",
    "w",
    "sigma_R",
    "sigma_w",
    "rms",
    "iso_class",
    "n_points",
    "valid",
    "reason",
    "label",
    "R_lat",
    "w_lat",
    "fit_residual",
    "fill",
    "point_noise",
    "noise_psd",
    "level_angle",
    *SE_COLUMNS,
    *SMOOTH_COLUMNS,
    *READING_COLUMNS,
    *PLACE_COLUMNS,
    *DRIVE_COLUMNS,
)
TEXT_COLUMNS = frozenset({"iso_class", "reason", "label"})
BOOL_COLUMNS = frozenset({"valid"})
INT_COLUMNS = frozenset({"frame", "n_points"})

#: Units of the columns of a features table ("" for counts, flags, text and ratios).
COLUMN_UNITS = {
    "frame": "",
    "t": "s",
    "x": "m",
    "y": "m",
    "yaw": "rad",
    "R": "m³/rad",
    "w": "",
    "sigma_R": "m³/rad",
    "sigma_w": "",
    "rms": "m",
    "iso_class": "",
    "n_points": "",
    "valid": "",
    "reason": "",
    "label": "",
    "R_lat": "m³/rad",
    "w_lat": "",
    "fit_residual": "",
    "fill": "",
    "point_noise": "m",
    "noise_psd": "m³/rad",
    "level_angle": "rad",
    "se_lnR": "",  # standard error of ln R: a relative error of R
    "se_w": "",
    "R_smooth": "m³/rad",
    "w_smooth": "",
    "sigma_lnR_smooth": "",  # standard deviation of ln R: a relative error of R
    "sigma_w_smooth": "",
    "lateral_scale": "",
    "omega_noise": "rad/m",
    "band_rms": "m",
    "centre_psd": "m³/rad",
    "omega_centre": "rad/m",
    "rms_ratio": "",
    "curvature_z": "",
    "patch_x": "m",
    "patch_y": "m",
    "v_max": "m/s",
    "v_max_95": "m/s",
    "weighted_acceleration": "m/s²",
    "suspension_travel": "m",
    "dynamic_load_ratio": "",
}


def _read_only(values: ArrayLike) -> np.ndarray:
    """A read-only view of ``values`` (the caller's array stays writeable)."""
    view = np.asarray(values).view()
    view.flags.writeable = False
    return view


@dataclass(frozen=True, eq=False)
class FeatureTable:
    """Per-frame features of a traverse; read-only.

    The table owns read-only views of the arrays it is given (the caller's arrays are not
    changed): a changed table is a new one, :meth:`replace`.

    Attributes
    ----------
    columns : mapping of str to ndarray
        The :data:`COLUMNS` (R in m³/rad, rms in m, t in s, x/y in m, yaw in rad, ...).
    omega : ndarray
        Wavenumbers in rad/m of the spectrum columns.
    log_psd : ndarray, shape (n_frames, len(omega))
        log10 of the patch-mean PSD in m³/rad (NaN rows for invalid frames).
    name : str
        Name of the traverse.
    row_spacing : float or None
        Width in m of the grid's cells across the track when a sparse traverse's rows were
        pooled (:func:`rough_map.patch.pooled_rows`); None: square cells, as long as the
        step along the profiles (``pi / omega[-1]``).
    """

    columns: Mapping[str, np.ndarray]
    omega: np.ndarray
    log_psd: np.ndarray
    name: str = ""
    row_spacing: float | None = None

    def __post_init__(self) -> None:
        cols = {str(k): _read_only(v) for k, v in self.columns.items()}
        object.__setattr__(self, "columns", MappingProxyType(cols))
        object.__setattr__(self, "omega", _read_only(self.omega))
        object.__setattr__(self, "log_psd", _read_only(self.log_psd))
        if self.row_spacing is not None:
            width = float(self.row_spacing)
            if not (math.isfinite(width) and width > 0):
                raise ValueError(f"row_spacing must be a positive width in m, got {width}")
            object.__setattr__(self, "row_spacing", width)

    def __reduce__(self) -> tuple[Any, ...]:  # a mappingproxy does not pickle
        return (
            type(self),
            (dict(self.columns), self.omega, self.log_psd, self.name, self.row_spacing),
        )

    def __len__(self) -> int:
        return len(self.columns["t"])

    def __getitem__(self, key: str) -> np.ndarray:
        return self.columns[key]

    def row(self, index: int) -> dict[str, Any]:
        """The scalar columns of frame ``index`` as Python values."""
        return {
            k: v[index].item() if hasattr(v[index], "item") else v[index]
            for k, v in self.columns.items()
        }

    def require_valid(self) -> FeatureTable:
        """``self``, or :class:`InputError` when no frame has a valid patch, with the reason
        most of them give: a map, labels or a table of nothing is not a result."""
        valid = self.valid
        if len(valid) and not valid.any():
            reasons = [str(r) for r in np.asarray(self.columns.get("reason", []), dtype=object)]
            kinds: dict[str, list[str]] = {}  # by the words before the figures
            for r in reasons:
                kinds.setdefault(r.split(":")[0], []).append(r)
            same = max(kinds.values(), key=len) if kinds else []
            raise InputError(
                f"{self.name}: none of its {len(valid)} frames has a valid patch"
                + (f"; {len(same)} like frame {reasons.index(same[0])}: {same[0]}" if same else "")
            )
        return self

    @property
    def valid(self) -> np.ndarray:
        """Frames with a valid patch (bool per frame)."""
        return self.columns["valid"].astype(bool)

    def distance(self) -> np.ndarray:
        """Cumulative distance travelled along the path, m (from the poses)."""
        x, y = self.columns["x"], self.columns["y"]
        step = np.hypot(np.diff(x), np.diff(y))
        return np.concatenate([[0.0], np.cumsum(step)])

    def spectrum_names(self) -> list[str]:
        """Names of the spectrum columns: ``psd_01`` ... one per wavenumber."""
        return [f"psd_{k:02d}" for k in range(1, self.omega.size + 1)]

    def replace(
        self, *, log_psd: ArrayLike | None = None, name: str | None = None, **columns: ArrayLike
    ) -> FeatureTable:
        """A copy with some columns (``label=...``), the spectra or the name replaced.

        Raises
        ------
        KeyError
            A column the table does not have.
        ValueError
            A column or spectra of another number of frames.
        """
        unknown = sorted(set(columns) - set(self.columns))
        if unknown:
            raise KeyError(f"no such columns {unknown}; the columns are {list(self.columns)}")
        new_cols = dict(self.columns)
        for key, value in columns.items():
            arr = np.array(value, dtype=self.columns[key].dtype)
            if arr.shape != self.columns[key].shape:
                raise ValueError(f"column {key!r} needs {len(self)} values, got {arr.shape}")
            new_cols[key] = arr
        spectra = self.log_psd if log_psd is None else np.array(log_psd, dtype=float)
        if spectra.shape != self.log_psd.shape:
            raise ValueError(f"log_psd must have shape {self.log_psd.shape}, got {spectra.shape}")
        return FeatureTable(
            new_cols,
            self.omega,
            spectra,
            self.name if name is None else name,
            self.row_spacing,
        )


@dataclass(frozen=True)
class LabelSummary:
    """Roughness of the valid frames of one label.

    Attributes
    ----------
    frames : int
        Valid frames with the label.
    R : float
        Geometric mean of R, m³/rad.
    w : float
        Mean of w.
    iso_class : str
        ISO 8608 class of ``R``.
    """

    frames: int
    R: float
    w: float
    iso_class: str

    def to_dict(self) -> dict[str, Any]:
        """``frames``, ``R``, ``w``, ``iso`` (the form of ``rough-map features --json``)."""
        return {"frames": self.frames, "R": self.R, "w": self.w, "iso": self.iso_class}


def label_summary(table: FeatureTable, labels: ArrayLike | None = None) -> dict[str, LabelSummary]:
    """R and w by label over the valid frames: the per-label table of the CLI and reports.

    Parameters
    ----------
    table : FeatureTable
        The features.
    labels : array_like of str, optional
        One label per frame (e.g. predicted classes); default the table's ``label``
        column.

    Returns
    -------
    dict of str to LabelSummary
        In order of first appearance; a label with no valid frame is left out; frames
        without a label are under ``""``.
    """
    labs = np.asarray(table["label"] if labels is None else labels, dtype=object)
    if labs.shape != (len(table),):
        raise InputError(f"labels needs one label per frame ({len(table)}), got {labs.shape}")
    valid = table.valid
    out: dict[str, LabelSummary] = {}
    for lab in dict.fromkeys(labs):
        sel = valid & (labs == lab)
        if not sel.any():
            continue
        r = math.exp(float(np.mean(np.log(table["R"][sel]))))
        out[str(lab)] = LabelSummary(
            frames=int(sel.sum()),
            R=r,
            w=float(np.mean(table["w"][sel])),
            iso_class=str(iso_class(r)),
        )
    return out
