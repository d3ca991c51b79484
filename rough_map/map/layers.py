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
``roughness_rms``
    Rms height of the detrended profiles over the band the fit used, m (the features'
    ``band_rms``, a roughness that needs no extrapolation to 1 rad/m): ``exp(mean ln)``
    over the patches covering the cell.
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
``[far_]evidence_<class>``, ``votes_<level>``, ``n_<layer>``, ``sum_<layer>``.

One observation per patch
-------------------------
What one frame tells the map is one record of named fields (:data:`OBSERVED`, filled from
the features columns of the same names, and ``probs``, ``level`` and ``t``);
:func:`patch_sums` turns it into what the patch adds to each cell's accumulators. The scalar
layers are the entries of :data:`FUSED_LAYERS`, each with the fields it reads, its
accumulators and its estimate: a new layer is one entry there (and a field of
:data:`OBSERVED` if it reads a new one), and fusion, tiles, the online mapper and the
exports pick it up.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.errors import InputError
from rough_map.map.grid import GridMap

__all__ = [
    "FUSED_LAYERS",
    "GROUPS",
    "LEVEL_NAMES",
    "OBSERVED",
    "FusedLayer",
    "apply_levels",
    "init_layers",
    "patch_sums",
    "update_estimates",
]

#: Provenance groups and the prefix of their layers.
GROUPS: dict[str, str] = {"near": "", "far": "far_"}

#: Default roughness level names, smoothest first (paper section 5.5).
LEVEL_NAMES: tuple[str, ...] = ("low", "medium", "high")

#: The named fields of one patch's observation and their units (features columns of the
#: same names; ``novelty`` is the classifier's, :attr:`rough_map.classify.TerrainPrediction.
#: novelty`). NaN: not observed.
OBSERVED: dict[str, str] = {
    "R": "m^3/rad",
    "w": "1",
    "sigma_R": "m^3/rad",
    "sigma_w": "1",
    "band_rms": "m",
    "novelty": "1",
}

Sums = list[tuple[str, float]]
Estimates = dict[str, NDArray[np.float64]]


@dataclass(frozen=True)
class FusedLayer:
    """Scalar layers fused from the fields of the patches' observations.

    Attributes
    ----------
    outputs : tuple of (name, units, description)
        The estimate layers.
    accumulators : tuple of (name, units, description)
        The internal sums they come from (fill 0); the first is the patch count that says
        whether a cell has an estimate.
    sums : callable
        ``sums(observation) -> [(accumulator, value), ...]``: what one patch adds to each
        cell it covers, from the fields of :data:`OBSERVED` (NaN: not observed).
    estimate : callable
        ``estimate(get) -> {output: array}``, ``get(accumulator)`` giving its values in the
        cells to update; NaN where there is none.
    with_classes : bool
        Only in a map with classes.
    """

    outputs: tuple[tuple[str, str, str], ...]
    accumulators: tuple[tuple[str, str, str], ...]
    sums: Callable[[Mapping[str, float]], Sums]
    estimate: Callable[[Callable[[str], NDArray[np.float64]]], Estimates]
    with_classes: bool = False


def _roughness_sums(obs: Mapping[str, float]) -> Sums:
    R, w, sigma_R, sigma_w = obs["R"], obs["w"], obs["sigma_R"], obs["sigma_w"]
    if not (math.isfinite(R) and R > 0 and math.isfinite(w)):
        return []
    ln_r = math.log(R)
    sums = [
        ("n_roughness", 1.0),
        ("sum_lnR", ln_r),
        ("sum_lnR2", ln_r * ln_r),
        ("sum_w", w),
        ("sum_w2", w * w),
    ]
    if math.isfinite(sigma_R) and math.isfinite(sigma_w):
        sums += [("n_sigma", 1.0), ("sum_rel_var_R", (sigma_R / R) ** 2), ("sum_var_w", sigma_w**2)]
    return sums


def _roughness_estimate(get: Callable[[str], NDArray[np.float64]]) -> Estimates:
    n, ns = get("n_roughness"), get("n_sigma")
    seen, with_sigma = n > 0, ns > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_ln = get("sum_lnR") / n
        var_ln = np.maximum(get("sum_lnR2") / n - mean_ln**2, 0.0)
        mean_w = get("sum_w") / n
        var_w = np.maximum(get("sum_w2") / n - mean_w**2, 0.0)
        rel_var_R = get("sum_rel_var_R") / ns
        var_sw = get("sum_var_w") / ns
    R = np.where(seen, np.exp(mean_ln), np.nan)
    return {
        "R": R,
        "w": np.where(seen, mean_w, np.nan),
        "sigma_R": np.where(with_sigma, R * np.sqrt(rel_var_R + var_ln), np.nan),
        "sigma_w": np.where(with_sigma, np.sqrt(var_sw + var_w), np.nan),
    }


def _per_patch(
    name: str,
    field: str,
    units: str,
    description: str,
    value: Callable[[float], float],
    *,
    log_mean: bool = False,
    with_classes: bool = False,
) -> FusedLayer:
    """A layer that is the mean over the patches of ``value(observation[field])`` (or, with
    ``log_mean``, ``exp(mean ln)``), for the patches where the field is finite."""
    count, total = f"n_{name}", f"sum_{name}"

    def sums(obs: Mapping[str, float]) -> Sums:
        v = obs[field]
        if not math.isfinite(v) or (log_mean and v <= 0):
            return []
        return [(count, 1.0), (total, math.log(v) if log_mean else value(v))]

    def estimate(get: Callable[[str], NDArray[np.float64]]) -> Estimates:
        n = get(count)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = get(total) / n
        return {name: np.where(n > 0, np.exp(mean) if log_mean else mean, np.nan)}

    return FusedLayer(
        outputs=((name, units, description),),
        accumulators=(
            (count, "1", f"patches with a finite {field}"),
            (total, f"ln({units})" if log_mean else units, f"sum over them for {name}"),
        ),
        sums=sums,
        estimate=estimate,
        with_classes=with_classes,
    )


#: The scalar layers of the near field, in the order of the map's bands.
FUSED_LAYERS: tuple[FusedLayer, ...] = (
    FusedLayer(
        outputs=(
            ("R", "m^3/rad", "overall energy Phi(1 rad/m), log-mean over patches"),
            ("w", "1", "waviness, mean over patches"),
            ("sigma_R", "m^3/rad", "standard deviation of R"),
            ("sigma_w", "1", "standard deviation of w"),
        ),
        accumulators=(
            ("n_roughness", "1", "patches with a valid R and w"),
            ("sum_lnR", "ln(m^3/rad)", "sum of ln R"),
            ("sum_lnR2", "ln(m^3/rad)^2", "sum of (ln R)^2"),
            ("n_sigma", "1", "patches with a finite sigma_R and sigma_w"),
            ("sum_rel_var_R", "1", "sum of (sigma_R / R)^2"),
            ("sum_w", "1", "sum of w"),
            ("sum_w2", "1", "sum of w^2"),
            ("sum_var_w", "1", "sum of sigma_w^2"),
        ),
        sums=_roughness_sums,
        estimate=_roughness_estimate,
    ),
    _per_patch(
        "roughness_rms",
        "band_rms",
        "m",
        "rms of the detrended profiles over the fitted band, log-mean over patches",
        float,
        log_mean=True,
    ),
    _per_patch(
        "novel",
        "novelty",
        "1",
        "share of the classified patches unlike every trained class (novelty above 1)",
        lambda v: float(v > 1.0),
        with_classes=True,
    ),
)

#: The other layers of the near field: name -> (units, description, fill).
_NEAR_LAYERS: dict[str, tuple[str, str, float]] = {
    "level": ("1", "roughness level index (see level_names)", math.nan),
    "count": ("1", "number of patches fused into the cell", 0.0),
    "last_seen": ("s", "time of the latest patch fused into the cell", math.nan),
}


def normalised_probs(k: int, p: NDArray, n: int) -> NDArray:
    """Probability rows (one or ``n`` of ``k`` classes) scaled to sum 1 (NaN: a row of 0).

    Raises
    ------
    InputError
        Another shape, or a negative probability.
    """
    if p.ndim == 1:
        p = p.reshape(1, -1)
    if p.ndim != 2 or p.shape[1] != k or p.shape[0] not in (1, n):
        raise InputError(f"probs must have shape ({n}, {k}) or ({k},), got {p.shape}")
    if np.any(p < 0):
        raise InputError("probabilities must be >= 0")
    total = p.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, p / total, np.nan)


def patch_sums(
    class_names: Sequence[str],
    level_names: Sequence[str],
    *,
    t: float = math.nan,
    probs: ArrayLike | None = None,
    level: float = math.nan,
    count: bool = True,
    **observed: float,
) -> Sums:
    """What one patch adds to each cell it covers (:func:`~rough_map.map.fusion.fuse_patch`'s
    observation): ``(layer, value)`` pairs; ``t`` (s) goes into ``last_seen`` by a maximum,
    not here. ``observed`` holds fields of :data:`OBSERVED` (the others are NaN).

    Raises
    ------
    InputError
        A field that is not one of :data:`OBSERVED`; ``probs`` without ``class_names``, or
        not one probability per class; a ``level`` that is not an index of ``level_names``.
    """
    unknown = sorted(set(observed) - set(OBSERVED))
    if unknown:
        raise InputError(f"unknown observation fields {unknown}; expected {list(OBSERVED)}")
    obs = {k: float(observed.get(k, math.nan)) for k in OBSERVED}
    sums: Sums = [("count", 1.0)] if count else []
    for layer in FUSED_LAYERS:
        if class_names or not layer.with_classes:
            sums += layer.sums(obs)
    if probs is not None:
        if not class_names:
            raise InputError("probs given but the map has no class_names; call init_layers")
        p = normalised_probs(len(class_names), np.asarray(probs, dtype=float).reshape(1, -1), 1)
        if np.all(np.isfinite(p)):
            sums += [(f"evidence_{c}", p[0, k]) for k, c in enumerate(class_names)]
    if math.isfinite(level):
        k = int(round(level))
        if not (0 <= k < len(level_names)) or k != level:
            raise InputError(
                f"level must be an index 0..{len(level_names) - 1} or NaN, got {level!r}"
            )
        sums.append((f"votes_{level_names[k]}", 1.0))
    return sums


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
            _near_layers(grid, bool(names))
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


def _near_layers(grid: GridMap, classes: bool) -> None:
    """The near field's scalar layers (those of :data:`FUSED_LAYERS` that the map can
    hold), level, count and last_seen, then their accumulators, where missing."""
    fused = [layer for layer in FUSED_LAYERS if classes or not layer.with_classes]
    values = [*fused[0].outputs]
    values += [(n, u, d) for n, (u, d, _) in _NEAR_LAYERS.items()]
    values += [out for layer in fused[1:] for out in layer.outputs]
    for name, units, desc in values:
        if name not in grid:
            fill = _NEAR_LAYERS[name][2] if name in _NEAR_LAYERS else math.nan
            cats = grid.attrs["level_names"] if name == "level" else ()
            grid.add_layer(name, units=units, description=desc, fill=fill, categories=cats)
    for name, units, desc in (acc for layer in fused for acc in layer.accumulators):
        if name not in grid:
            grid.add_layer(name, units=units, description=desc, fill=0.0, kind="internal")


def _class_layers(grid: GridMap, prefix: str, names: tuple[str, ...]) -> None:
    where = "far-field prediction" if prefix else "near field"
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
    writes the outputs of :data:`FUSED_LAYERS` (``R``, ``w``, ``sigma_R``, ``sigma_w``,
    ``roughness_rms``, ``novel``), ``level`` (only where votes exist), ``[far_]p_<class>``
    and ``[far_]class``.

    Parameters
    ----------
    grid : GridMap
        The map.
    window : tuple of slice, optional
        ``(rows, cols)`` to update (default: the whole map).
    """
    win = window or (slice(None), slice(None))
    for layer in FUSED_LAYERS:
        if layer.accumulators[0][0] in grid:
            estimates = layer.estimate(lambda name: grid[name][win])
            for name, values in estimates.items():
                grid[name][win] = values
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
    return grid


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
