"""The layers of a fused map: what they hold, their creation, and their estimates.

Fusion (:mod:`rough_map.map.fusion`) only adds observations to accumulator layers (sums,
Dirichlet evidence, votes); :func:`update_estimates` computes the estimate layers from
them, so the order of the observations does not matter.

Layers of the near field (group ``"near"``, no prefix)
------------------------------------------------------
``R``
    Overall energy Phi(1 rad/m), m^3/rad: ``exp(mean ln R)`` over the patches covering the
    cell (the log-mean: R spans decades and its estimate is log-normal).
``w``
    Waviness, dimensionless: mean over the patches.
``sigma_R``
    Standard deviation of R, m^3/rad (delta method):
    ``R * sqrt(mean (sigma_R_k / R_k)^2 + var ln R_k)``, the typical uncertainty of one
    observation plus the spread between observations. It does not shrink as ``1/sqrt(n)``:
    consecutive patches overlap by about 70 % and share most of their data.
``sigma_w``
    Standard deviation of w, dimensionless: ``sqrt(mean sigma_w_k^2 + var w_k)``.
``level``
    Roughness level index (0 = ``level_names[0]``, smoothest), NaN unknown: the majority
    of the per-frame levels (ties go to the rougher level), or a function of the fused
    ``R`` (:func:`apply_levels`).
``p_<class>``, ``class``
    Class probabilities and their argmax index (NaN unknown), fused by a Dirichlet update:
    each observation adds ``weight * p`` to the cell's evidence (pseudo-counts), and
    ``p_c = (prior / K + evidence_c) / (prior + sum(evidence))``.
``novel``
    Share of the cell's classified patches whose ground is unlike every class the model was
    trained on (novelty above 1, :attr:`rough_map.classify.TerrainPrediction.novelty`), 0 to
    1; NaN where no patch had a novelty score. Where it is high, ``class`` is only the
    nearest class.
``count``, ``last_seen``
    Number of patches fused into the cell (0 never seen) and the latest time, s.

Far field (group ``"far"``, prefix ``far_``): ``far_p_<class>``, ``far_class``,
``far_count``, ``far_last_seen`` — class predictions of a near-to-far model, fused by
:func:`~rough_map.map.fusion.fuse_cell_probabilities` with a lower weight into layers of
their own, so their provenance shows — and ``far_confidence``: the share of the cell's
far-field evidence on its most probable class (the mean calibrated probability of that
class over the predictions, without the prior); where it is below
``grid.attrs["far_min_confidence"]`` (default 0) ``far_class`` is NaN: the map abstains.

Internal layers (``kind="internal"``, not exported): ``n_roughness``, ``sum_lnR``,
``sum_lnR2``, ``n_sigma``, ``sum_rel_var_R``, ``sum_w``, ``sum_w2``, ``sum_var_w``,
``[far_]evidence_<class>``, ``votes_<level>``, ``n_novelty``, ``sum_novel``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.map.grid import GridMap, LayerKind

__all__ = [
    "GROUPS",
    "LEVEL_NAMES",
    "apply_levels",
    "init_layers",
    "update_estimates",
]

#: Provenance groups and the prefix of their layers.
GROUPS: dict[str, str] = {"near": "", "far": "far_"}

#: Default roughness level names, smoothest first (paper section 5.5).
LEVEL_NAMES: tuple[str, ...] = ("low", "medium", "high")

#: Layers of the near field that :func:`init_layers` creates: name -> (units, description,
#: fill, kind).
_NEAR_LAYERS: dict[str, tuple[str, str, float, LayerKind]] = {
    "R": ("m^3/rad", "overall energy Phi(1 rad/m), log-mean over patches", math.nan, "value"),
    "w": ("1", "waviness, mean over patches", math.nan, "value"),
    "sigma_R": ("m^3/rad", "standard deviation of R", math.nan, "value"),
    "sigma_w": ("1", "standard deviation of w", math.nan, "value"),
    "level": ("1", "roughness level index (see level_names)", math.nan, "value"),
    "count": ("1", "number of patches fused into the cell", 0.0, "value"),
    "last_seen": ("s", "time of the latest patch fused into the cell", math.nan, "value"),
    "n_roughness": ("1", "patches with a valid R and w", 0.0, "internal"),
    "sum_lnR": ("ln(m^3/rad)", "sum of ln R", 0.0, "internal"),
    "sum_lnR2": ("ln(m^3/rad)^2", "sum of (ln R)^2", 0.0, "internal"),
    "n_sigma": ("1", "patches with a finite sigma_R and sigma_w", 0.0, "internal"),
    "sum_rel_var_R": ("1", "sum of (sigma_R / R)^2", 0.0, "internal"),
    "sum_w": ("1", "sum of w", 0.0, "internal"),
    "sum_w2": ("1", "sum of w^2", 0.0, "internal"),
    "sum_var_w": ("1", "sum of sigma_w^2", 0.0, "internal"),
}


def init_layers(
    grid: GridMap,
    class_names: Sequence[str] = (),
    *,
    level_names: Sequence[str] = LEVEL_NAMES,
    prior: float = 1.0,
    groups: Sequence[str] = ("near",),
) -> GridMap:
    """Create the fusion layers of ``groups`` on ``grid`` (those missing), in place.

    Parameters
    ----------
    grid : GridMap
        The map.
    class_names : sequence of str
        Terrain classes, in the column order of the probabilities to come. Stored in
        ``grid.attrs["class_names"]``; must match what the map already holds.
    level_names : sequence of str
        Roughness level names, smoothest first (``grid.attrs["level_names"]``).
    prior : float
        Total concentration of the uniform Dirichlet prior (pseudo-observations spread
        evenly over the classes; ``grid.attrs["class_prior"]``).
    groups : sequence of {"near", "far"}
        Provenance groups to create.

    Returns
    -------
    GridMap
        ``grid``.
    """
    names = tuple(str(c) for c in class_names)
    if len(set(names)) != len(names) or any(not n for n in names):
        raise InputError(f"class_names must be distinct non-empty names, got {names}")
    known = tuple(grid.attrs.get("class_names", ()))
    if known and names and known != names:
        raise InputError(f"class_names {names} differ from the map's {known}")
    names = names or known
    levels = tuple(str(v) for v in level_names)
    if not levels or len(set(levels)) != len(levels):
        raise InputError(f"level_names must be distinct names, got {levels}")
    if not (math.isfinite(prior) and prior > 0):
        raise InputError(f"prior must be a positive concentration, got {prior!r}")
    grid.attrs["class_names"] = names
    grid.attrs.setdefault("level_names", levels)
    grid.attrs.setdefault("class_prior", float(prior))
    for group in groups:
        prefix = group_prefix(group)
        if group == "near":
            for name, (units, desc, fill, kind) in _NEAR_LAYERS.items():
                if name not in grid:
                    cats = grid.attrs["level_names"] if name == "level" else ()
                    grid.add_layer(
                        name, units=units, description=desc, fill=fill, kind=kind, categories=cats
                    )
        else:
            for name, units, desc, fill in (
                ("count", "1", "number of far-field predictions fused into the cell", 0.0),
                ("last_seen", "s", "time of the latest far-field prediction", math.nan),
                (
                    "confidence",
                    "1",
                    "share of the far-field evidence on the most probable class",
                    math.nan,
                ),
            ):
                if prefix + name not in grid:
                    grid.add_layer(prefix + name, units=units, description=desc, fill=fill)
        if names:
            _class_layers(grid, prefix, names)
    return grid


#: Layers of the near field's novelty (with its classes): name -> (units, description, fill,
#: kind).
_NOVELTY_LAYERS: dict[str, tuple[str, str, float, LayerKind]] = {
    "novel": (
        "1",
        "share of the classified patches unlike every trained class (novelty above 1)",
        math.nan,
        "value",
    ),
    "n_novelty": ("1", "patches with a novelty score", 0.0, "internal"),
    "sum_novel": ("1", "patches whose novelty is above 1", 0.0, "internal"),
}


def _class_layers(grid: GridMap, prefix: str, names: tuple[str, ...]) -> None:
    where = "far-field prediction" if prefix else "near field"
    if not prefix:
        for name, (units, desc, fill, kind) in _NOVELTY_LAYERS.items():
            if name not in grid:
                grid.add_layer(name, units=units, description=desc, fill=fill, kind=kind)
    for c in names:
        if f"{prefix}p_{c}" not in grid:
            grid.add_layer(
                f"{prefix}p_{c}", units="1", description=f"probability of class {c} ({where})"
            )
    for c in names:
        if f"{prefix}evidence_{c}" not in grid:
            grid.add_layer(
                f"{prefix}evidence_{c}",
                units="1",
                fill=0.0,
                kind="internal",
                description=f"Dirichlet evidence of class {c}: sum of weight * p",
            )
    if f"{prefix}class" not in grid:
        grid.add_layer(
            f"{prefix}class",
            units="1",
            kind="class",
            categories=names,
            description=f"most probable terrain class index ({where})",
        )


def group_prefix(group: str) -> str:
    """The layer-name prefix of a provenance group (``"near"``: none, ``"far"``: ``far_``)."""
    try:
        return GROUPS[group]
    except KeyError:
        raise InputError(f"group must be one of {tuple(GROUPS)}, got {group!r}") from None


def update_estimates(grid: GridMap, window: tuple[slice, slice] | None = None) -> GridMap:
    """Recompute the estimate layers from the accumulator layers, in place.

    Reads ``n_roughness``, ``sum_*``, ``[far_]evidence_<class>`` and ``votes_<level>``;
    writes ``R``, ``w``, ``sigma_R``, ``sigma_w``, ``level`` (only where votes exist),
    ``[far_]p_<class>``, ``[far_]class`` and ``novel``.

    Parameters
    ----------
    grid : GridMap
        The map.
    window : tuple of slice, optional
        ``(rows, cols)`` to update (default: the whole map).
    """
    win = window or (slice(None), slice(None))
    if "n_roughness" in grid:
        _update_roughness(grid, win)
    levels = grid.attrs.get("level_names", ())
    if levels and f"votes_{levels[0]}" in grid:
        votes = np.stack([grid[f"votes_{v}"][win] for v in levels])
        # ties go to the rougher level: argmax over the levels in reverse order
        top = len(levels) - 1 - np.argmax(votes[::-1], axis=0)
        grid["level"][win] = np.where(votes.sum(axis=0) > 0, top, np.nan)
    names = grid.attrs.get("class_names", ())
    for prefix in GROUPS.values():
        if names and f"{prefix}evidence_{names[0]}" in grid:
            _update_classes(grid, prefix, names, win)
    if "n_novelty" in grid:
        n = grid["n_novelty"][win]
        with np.errstate(invalid="ignore", divide="ignore"):
            grid["novel"][win] = np.where(n > 0, grid["sum_novel"][win] / n, np.nan)
    return grid


def _update_roughness(grid: GridMap, win: tuple[slice, slice]) -> None:
    n = grid["n_roughness"][win]
    ns = grid["n_sigma"][win]
    seen, with_sigma = n > 0, ns > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_ln = grid["sum_lnR"][win] / n
        var_ln = np.maximum(grid["sum_lnR2"][win] / n - mean_ln**2, 0.0)
        mean_w = grid["sum_w"][win] / n
        var_w = np.maximum(grid["sum_w2"][win] / n - mean_w**2, 0.0)
        rel_var_R = grid["sum_rel_var_R"][win] / ns
        var_sw = grid["sum_var_w"][win] / ns
    R = np.where(seen, np.exp(mean_ln), np.nan)
    grid["R"][win] = R
    grid["w"][win] = np.where(seen, mean_w, np.nan)
    grid["sigma_R"][win] = np.where(with_sigma, R * np.sqrt(rel_var_R + var_ln), np.nan)
    grid["sigma_w"][win] = np.where(with_sigma, np.sqrt(var_sw + var_w), np.nan)


def _update_classes(
    grid: GridMap, prefix: str, names: Sequence[str], win: tuple[slice, slice]
) -> None:
    prior = float(grid.attrs.get("class_prior", 1.0))
    ev = np.stack([grid[f"{prefix}evidence_{c}"][win] for c in names])
    total = ev.sum(axis=0)
    seen = total > 0
    p = (ev + prior / len(names)) / (total + prior)
    for k, c in enumerate(names):
        grid[f"{prefix}p_{c}"][win] = np.where(seen, p[k], np.nan)
    label = np.where(seen, np.argmax(p, axis=0), np.nan)
    if f"{prefix}confidence" in grid:
        # far field: the calibrated probabilities' agreement, without the prior; below the
        # map's far_min_confidence the cell stays unknown (abstains)
        with np.errstate(invalid="ignore", divide="ignore"):
            confidence = np.where(seen, ev.max(axis=0) / total, np.nan)
        grid[f"{prefix}confidence"][win] = confidence
        threshold = float(grid.attrs.get(f"{prefix}min_confidence", 0.0))
        label = np.where(confidence >= threshold, label, np.nan)
    grid[f"{prefix}class"][win] = label


def apply_levels(grid: GridMap, levels: Callable[[NDArray[np.float64]], ArrayLike]) -> GridMap:
    """Write the ``level`` layer as a function of the fused ``R`` layer, in place.

    Parameters
    ----------
    grid : GridMap
        The map, with an ``R`` layer (m^3/rad).
    levels : callable
        Called with the ``R`` layer (m^3/rad, NaN unknown); returns per cell a level index
        (NaN unknown) or a level name (``""`` unknown) of ``grid.attrs["level_names"]``,
        e.g. ``lambda R: roughness_level(R, names, thresholds)`` of
        :mod:`rough_map.classify`.
    """
    R = grid["R"]
    grid["level"] = np.where(np.isfinite(R), level_indices(levels(R.copy()), grid), np.nan)
    return grid


def level_indices(values: ArrayLike, grid: GridMap) -> NDArray[np.float64]:
    """Level indices (float, NaN unknown) of level indices or names (``""`` unknown) of
    ``grid.attrs["level_names"]``.

    Raises
    ------
    InputError
        An unknown name, or an index that is not one of the levels.
    """
    names = tuple(grid.attrs.get("level_names", LEVEL_NAMES))
    arr = np.asarray(values)
    if arr.dtype.kind in "OUS":
        lookup = {n: float(i) for i, n in enumerate(names)}
        unknown = {str(v) for v in arr.ravel()} - set(lookup) - {"", "nan", "None"}
        if unknown:
            raise InputError(f"unknown level names {sorted(unknown)}; expected {names}")
        out = np.array([lookup.get(str(v), math.nan) for v in arr.ravel()]).reshape(arr.shape)
    else:
        out = arr.astype(float)
    ok = np.isfinite(out)
    if np.any((out[ok] < 0) | (out[ok] > len(names) - 1) | (out[ok] != np.round(out[ok]))):
        raise InputError(f"level indices must be 0..{len(names) - 1} or NaN")
    return out
