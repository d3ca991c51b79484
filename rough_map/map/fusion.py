"""Fusing the patches seen along a traverse into grid-map layers (paper section 5.5).

Each frame's patch of interest (a :class:`~rough_map.patch.PatchSpec` square ``ahead`` m in
front of the vehicle, turned by its yaw) covers the cells whose centres lie inside it. Every
observation adds to *sums* kept as internal layers, and the estimate layers are computed
from those sums, so fusing the same observations in any order gives the same map (up to
floating-point rounding of the sums; ``last_seen`` is a max and exact).

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
``count``, ``last_seen``
    Number of patches fused into the cell (0 never seen) and the latest time, s.

Far field (group ``"far"``, prefix ``far_``): ``far_p_<class>``, ``far_class``,
``far_count``, ``far_last_seen`` — class predictions of a near-to-far model, fused by
:func:`fuse_cell_probabilities` with a lower weight into layers of their own, so their
provenance shows.

Internal layers (``kind="internal"``, not exported): ``n_roughness``, ``sum_lnR``,
``sum_lnR2``, ``n_sigma``, ``sum_rel_var_R``, ``sum_w``, ``sum_w2``, ``sum_var_w``,
``[far_]evidence_<class>``, ``votes_<level>``.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rough_map.config import Crs
from rough_map.errors import EmptyMapWarning, InputError
from rough_map.map.grid import DEFAULT_MARGIN, GridGeometry, GridMap
from rough_map.patch import PatchSpec

log = logging.getLogger(__name__)

__all__ = [
    "GROUPS",
    "LEVEL_NAMES",
    "EmptyMapWarning",
    "apply_levels",
    "fuse_cell_probabilities",
    "fuse_patch",
    "fuse_traverse",
    "init_layers",
    "patch_cells",
    "patch_corners",
    "update_estimates",
]

#: Provenance groups and the prefix of their layers.
GROUPS: dict[str, str] = {"near": "", "far": "far_"}

#: Default roughness level names, smoothest first (paper section 5.5).
LEVEL_NAMES: tuple[str, ...] = ("low", "medium", "high")

#: Layers of the near field that :func:`init_layers` creates: name -> (units, description,
#: fill, kind).
_NEAR_LAYERS: dict[str, tuple[str, str, float, str]] = {
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


# ------------------------------------------------------------------------------------------
# Footprints
# ------------------------------------------------------------------------------------------


def patch_corners(x: float, y: float, yaw: float, spec: PatchSpec | None = None) -> NDArray:
    """World corners of the patch of a vehicle at (x, y) m heading ``yaw`` rad.

    Returns
    -------
    ndarray, shape (4, 2)
        x, y in m, counter-clockwise from the near right corner.
    """
    spec = spec or PatchSpec()
    h = spec.size / 2
    u = spec.ahead + np.array([-h, h, h, -h])  # along the heading
    v = spec.lateral + np.array([-h, -h, h, h])  # to the left
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([x + c * u - s * v, y + s * u + c * v])


def patch_cells(
    geometry: GridGeometry, x: float, y: float, yaw: float, spec: PatchSpec | None = None
) -> NDArray[np.int64]:
    """Cells ``(N, 2)`` as ``(row, col)`` whose centres lie in the patch (inside the map).

    A patch smaller than a cell that holds no cell centre covers the cell of its centre.
    """
    spec = spec or PatchSpec()
    corners = patch_corners(x, y, yaw, spec)
    r0, c0 = geometry.cell_of(corners[:, 0].min(), corners[:, 1].min())
    r1, c1 = geometry.cell_of(corners[:, 0].max(), corners[:, 1].max())
    rows = np.arange(max(int(r0), 0), min(int(r1), geometry.shape[0] - 1) + 1)
    cols = np.arange(max(int(c0), 0), min(int(c1), geometry.shape[1] - 1) + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    xc, yc = geometry.cell_center(rr, cc)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = xc - x, yc - y
    u = c * dx + s * dy - spec.ahead
    v = -s * dx + c * dy - spec.lateral
    h = spec.size / 2
    inside = (np.abs(u) <= h) & (np.abs(v) <= h)
    cells = np.column_stack([rr[inside], cc[inside]]).astype(np.int64)
    if cells.size == 0:
        cx = x + c * spec.ahead - s * spec.lateral
        cy = y + s * spec.ahead + c * spec.lateral
        r, col = geometry.cell_of(cx, cy)
        if geometry.inside(r, col):
            cells = np.array([[int(r), int(col)]], dtype=np.int64)
    return cells


# ------------------------------------------------------------------------------------------
# Layers
# ------------------------------------------------------------------------------------------


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
        prefix = _prefix(group)
        if group == "near":
            for name, (units, desc, fill, kind) in _NEAR_LAYERS.items():
                if name not in grid:
                    cats = grid.attrs["level_names"] if name == "level" else ()
                    grid.add_layer(
                        name, units=units, description=desc, fill=fill, kind=kind, categories=cats
                    )  # type: ignore[arg-type]
        else:
            for name, units, desc, fill in (
                ("count", "1", "number of far-field predictions fused into the cell", 0.0),
                ("last_seen", "s", "time of the latest far-field prediction", math.nan),
            ):
                if prefix + name not in grid:
                    grid.add_layer(prefix + name, units=units, description=desc, fill=fill)
        if names:
            _class_layers(grid, prefix, names)
    return grid


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


def _prefix(group: str) -> str:
    try:
        return GROUPS[group]
    except KeyError:
        raise InputError(f"group must be one of {tuple(GROUPS)}, got {group!r}") from None


# ------------------------------------------------------------------------------------------
# Fusion
# ------------------------------------------------------------------------------------------


def fuse_patch(
    grid: GridMap,
    x: float,
    y: float,
    yaw: float,
    *,
    t: float = math.nan,
    R: float = math.nan,
    w: float = math.nan,
    sigma_R: float = math.nan,
    sigma_w: float = math.nan,
    probs: ArrayLike | None = None,
    level: float = math.nan,
    spec: PatchSpec | None = None,
    grow: bool = True,
    margin: float = DEFAULT_MARGIN,
    update: bool = True,
) -> NDArray[np.int64]:
    """Fuse the patch seen from one vehicle pose into the near-field layers, in place.

    Parameters
    ----------
    grid : GridMap
        The map (:func:`init_layers` is called if its layers are missing).
    x, y : float
        Vehicle position in the world, m.
    yaw : float
        Vehicle heading, rad (0 = +x, counter-clockwise).
    t : float
        Time of the frame, s (NaN: unknown, ``last_seen`` unchanged).
    R, sigma_R : float
        Overall energy of the patch and its standard deviation, m^3/rad. R not finite
        or not positive: no roughness from this patch.
    w, sigma_w : float
        Waviness and its standard deviation, dimensionless.
    probs : array_like, shape (K,), optional
        Class probabilities of the patch, in the order of ``grid.attrs["class_names"]``.
    level : float
        Roughness level index of the patch (NaN: none).
    spec : PatchSpec, optional
        Patch geometry (default: 0.896 m square, 1 m ahead).
    grow : bool
        Grow the map to hold the whole patch (else cells outside are dropped).
    margin : float
        Room in m added when the map grows.
    update : bool
        Recompute the estimate layers under the patch now (else call
        :func:`update_estimates` once after many patches).

    Returns
    -------
    ndarray, shape (N, 2)
        ``(row, col)`` of the cells the patch covered (after any growth).
    """
    spec = spec or PatchSpec()
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise InputError(f"pose must be finite (x, y in m, yaw in rad), got {(x, y, yaw)}")
    if "count" not in grid:
        init_layers(grid, grid.attrs.get("class_names", ()))
    if grow:
        corners = patch_corners(x, y, yaw, spec)
        grid.ensure_covers((*corners.min(axis=0), *corners.max(axis=0)), margin=margin)
    cells = patch_cells(grid.geometry, x, y, yaw, spec)
    if cells.size == 0:
        return cells
    rows, cols = cells[:, 0], cells[:, 1]
    grid["count"][rows, cols] += 1.0
    if math.isfinite(t):
        grid["last_seen"][rows, cols] = np.fmax(grid["last_seen"][rows, cols], t)
    if math.isfinite(R) and R > 0 and math.isfinite(w):
        ln_r = math.log(R)
        grid["n_roughness"][rows, cols] += 1.0
        grid["sum_lnR"][rows, cols] += ln_r
        grid["sum_lnR2"][rows, cols] += ln_r * ln_r
        grid["sum_w"][rows, cols] += w
        grid["sum_w2"][rows, cols] += w * w
        if math.isfinite(sigma_R) and math.isfinite(sigma_w):
            grid["n_sigma"][rows, cols] += 1.0
            grid["sum_rel_var_R"][rows, cols] += (sigma_R / R) ** 2
            grid["sum_var_w"][rows, cols] += sigma_w**2
    if probs is not None:
        if not grid.attrs.get("class_names"):
            raise InputError("probs given but the map has no class_names; call init_layers")
        p = _check_probs(grid, np.asarray(probs, dtype=float).reshape(1, -1), 1)
        if np.all(np.isfinite(p)):
            _add_evidence(
                grid,
                "",
                rows,
                cols,
                np.broadcast_to(p, (rows.size, p.shape[1])),
                np.ones(rows.size),
            )
    if math.isfinite(level):
        _add_vote(grid, rows, cols, level)
    if update:
        update_estimates(grid, _window(cells))
    return cells


def fuse_cell_probabilities(
    grid: GridMap,
    cells: ArrayLike,
    probs: ArrayLike,
    weight: ArrayLike = 1.0,
    *,
    group: str = "near",
    t: float | None = None,
    update: bool = True,
) -> NDArray[np.int64]:
    """Fuse class probabilities predicted for given cells (e.g. near-to-far), in place.

    Parameters
    ----------
    grid : GridMap
        The map; its ``attrs["class_names"]`` give the column order of ``probs``.
    cells : array_like
        Either a boolean mask of the map's shape, or integer ``(N, 2)`` indices
        ``(row, col)``. For world positions use ``grid.cells_at(x, y)`` first (it grows
        the map if needed, which shifts earlier indices).
    probs : array_like, shape (N, K) or (K,)
        Class probabilities per cell (mask cells in row-major order), or one row for all.
        Rows are normalised; rows with NaN are skipped.
    weight : float or array_like of shape (N,)
        Weight of each prediction in the Dirichlet evidence (1 = one near-field patch);
        give far-field predictions a lower weight.
    group : {"near", "far"}
        Provenance group: ``"far"`` writes ``far_p_<class>``, ``far_class``,
        ``far_count`` and ``far_last_seen``.
    t : float, optional
        Time of the prediction, s (updates ``<group>last_seen``).
    update : bool
        Recompute the probability and class layers of the cells now.

    Returns
    -------
    ndarray, shape (N, 2)
        The ``(row, col)`` of the cells fused.
    """
    prefix = _prefix(group)
    names = tuple(grid.attrs.get("class_names", ()))
    if not names:
        raise InputError("the map has no class_names; call init_layers(grid, class_names)")
    init_layers(grid, names, groups=(group,))
    idx = _check_cells(grid, cells)
    n = idx.shape[0]
    p = _check_probs(grid, np.asarray(probs, dtype=float), n)
    p = np.broadcast_to(p, (n, len(names)))
    wt = np.broadcast_to(np.asarray(weight, dtype=float), (n,))
    if not np.all(np.isfinite(wt) & (wt >= 0)):
        raise InputError("weight must be finite and >= 0")
    keep = np.all(np.isfinite(p), axis=1) & (wt > 0)
    idx, p, wt = idx[keep], p[keep], wt[keep]
    if idx.size == 0:
        return idx
    rows, cols = idx[:, 0], idx[:, 1]
    _add_evidence(grid, prefix, rows, cols, p, wt)
    np.add.at(grid[f"{prefix}count"], (rows, cols), 1.0)
    if t is not None and math.isfinite(t):
        np.fmax.at(grid[f"{prefix}last_seen"], (rows, cols), float(t))
    if update:
        update_estimates(grid, _window(idx))
    return idx


def _check_cells(grid: GridMap, cells: ArrayLike) -> NDArray[np.int64]:
    arr = np.asarray(cells)
    if arr.dtype == bool:
        if arr.shape != grid.shape:
            raise InputError(f"a cell mask must have the map's shape {grid.shape}, got {arr.shape}")
        return np.argwhere(arr).astype(np.int64)
    if arr.size == 0:
        return np.empty((0, 2), dtype=np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputError(
            "cells must be a boolean mask or integer (row, col) indices; for world "
            "positions in m use grid.cells_at(x, y)"
        )
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"cells must have shape (N, 2) as (row, col), got {arr.shape}")
    if not np.all(grid.geometry.inside(arr[:, 0], arr[:, 1])):
        raise InputError(f"some cells lie outside the map of shape {grid.shape}")
    return arr.astype(np.int64)


def _check_probs(grid: GridMap, p: NDArray, n: int) -> NDArray:
    k = len(grid.attrs.get("class_names", ()))
    if p.ndim == 1:
        p = p.reshape(1, -1)
    if p.ndim != 2 or p.shape[1] != k or p.shape[0] not in (1, n):
        raise InputError(f"probs must have shape ({n}, {k}) or ({k},), got {p.shape}")
    if np.any(p < 0):
        raise InputError("probabilities must be >= 0")
    total = p.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, p / total, np.nan)


def _add_evidence(
    grid: GridMap, prefix: str, rows: NDArray, cols: NDArray, p: NDArray, weight: NDArray
) -> None:
    for k, c in enumerate(grid.attrs["class_names"]):
        np.add.at(grid[f"{prefix}evidence_{c}"], (rows, cols), weight * p[:, k])


def _add_vote(grid: GridMap, rows: NDArray, cols: NDArray, level: float) -> None:
    names = grid.attrs["level_names"]
    k = int(round(level))
    if not (0 <= k < len(names)) or k != level:
        raise InputError(f"level must be an index 0..{len(names) - 1} or NaN, got {level!r}")
    for name in names:
        if f"votes_{name}" not in grid:
            grid.add_layer(
                f"votes_{name}",
                units="1",
                fill=0.0,
                kind="internal",
                description=f"patches whose level is {name}",
            )
    grid[f"votes_{names[k]}"][rows, cols] += 1.0


def _window(cells: NDArray[np.int64]) -> tuple[slice, slice]:
    return (
        slice(int(cells[:, 0].min()), int(cells[:, 0].max()) + 1),
        slice(int(cells[:, 1].min()), int(cells[:, 1].max()) + 1),
    )


def update_estimates(grid: GridMap, window: tuple[slice, slice] | None = None) -> GridMap:
    """Recompute the estimate layers from the accumulator layers, in place.

    Reads ``n_roughness``, ``sum_*``, ``[far_]evidence_<class>`` and ``votes_<level>``;
    writes ``R``, ``w``, ``sigma_R``, ``sigma_w``, ``level`` (only where votes exist),
    ``[far_]p_<class>`` and ``[far_]class``.

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
    grid[f"{prefix}class"][win] = np.where(seen, np.argmax(p, axis=0), np.nan)


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
    grid["level"] = np.where(np.isfinite(R), _level_indices(levels(R.copy()), grid), np.nan)
    return grid


def _level_indices(values: ArrayLike, grid: GridMap) -> NDArray[np.float64]:
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


# ------------------------------------------------------------------------------------------
# A whole traverse
# ------------------------------------------------------------------------------------------


def fuse_traverse(
    features: Any,
    class_probs: ArrayLike | None = None,
    class_names: Sequence[str] = (),
    levels: ArrayLike | Callable[[NDArray[np.float64]], ArrayLike] | None = None,
    resolution: float = 0.1,
    *,
    spec: PatchSpec | None = None,
    crs: Any = None,
    level_names: Sequence[str] = LEVEL_NAMES,
    prior: float = 1.0,
    margin: float = 1.0,
    frame_id: str = "map",
) -> GridMap:
    """Map of a traverse: every valid frame's patch fused into the near-field layers.

    Parameters
    ----------
    features : FeatureTable
        Per-frame features (:func:`rough_map.features.traverse_features`): columns ``t``
        (s), ``x``, ``y`` (m), ``yaw`` (rad), ``R``, ``sigma_R`` (m^3/rad), ``w``,
        ``sigma_w`` and ``valid``. Invalid frames are skipped.
    class_probs : array_like, shape (n_frames, K), optional
        Class probabilities per frame (NaN rows for frames without one). None: no class
        layers.
    class_names : sequence of str
        The K class names, in the column order of ``class_probs``.
    levels : array_like of shape (n_frames,) or callable, optional
        Roughness level per frame (index, NaN unknown; or name, ``""`` unknown), fused by
        majority; or a callable mapping the fused ``R`` layer to levels
        (:func:`apply_levels`). None: the ``level`` layer stays unknown.
    resolution : float
        Cell size in m.
    spec : PatchSpec, optional
        Patch geometry of the features (default: 0.896 m square, 1 m ahead).
    crs : optional
        CRS of the world frame: a traverse's ``spec.crs``, ``"EPSG:32633"``, a
        :class:`~rough_map.config.Crs`... (default: local, no geodetic origin).
    level_names : sequence of str
        Level names, smoothest first.
    prior : float
        Total concentration of the Dirichlet prior on the class probabilities.
    margin : float
        Room in m around the patches of the traverse.
    frame_id : str
        ROS frame name of the map.

    Returns
    -------
    GridMap
        Covering every frame's patch (valid or not) plus ``margin``. ``attrs`` holds
        ``class_names``, ``level_names``, ``class_prior``, ``name``, ``track`` (the
        vehicle positions, (n, 2) m) and ``n_frames``/``n_valid``.

    Warns
    -----
    EmptyMapWarning
        No frame, or no valid patch: the map is all nodata.
    """
    spec = spec or PatchSpec()
    cols = features.columns
    n = len(cols["t"])
    names = tuple(str(c) for c in class_names)
    probs = None
    if class_probs is not None:
        probs = np.asarray(class_probs, dtype=float)
        if probs.shape != (n, len(names)):
            raise InputError(
                f"class_probs must have shape (n_frames, len(class_names)) = "
                f"({n}, {len(names)}), got {probs.shape}"
            )
    x, y, yaw = (np.asarray(cols[k], dtype=float) for k in ("x", "y", "yaw"))
    posed = np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
    valid = np.asarray(cols["valid"], dtype=bool) & posed
    if np.any(posed):
        corners = np.concatenate(
            [patch_corners(x[i], y[i], yaw[i], spec) for i in np.flatnonzero(posed)]
        )
        bounds = (*corners.min(axis=0), *corners.max(axis=0))
    else:
        bounds = (0.0, 0.0, 0.0, 0.0)
    geometry = GridGeometry.covering(
        bounds, resolution, margin=margin, crs=Crs.from_any(crs), frame_id=frame_id
    )
    grid = GridMap(
        geometry,
        attrs={
            "name": getattr(features, "name", ""),
            "track": np.column_stack([x[posed], y[posed]]),
            "n_frames": n,
            "n_valid": int(valid.sum()),
            "patch": {"ahead": spec.ahead, "size": spec.size, "lateral": spec.lateral},
        },
    )
    init_layers(grid, names if probs is not None else (), level_names=level_names, prior=prior)
    frame_levels = None
    if levels is not None and not callable(levels):
        frame_levels = _level_indices(levels, grid)
        if frame_levels.shape != (n,):
            raise InputError(f"levels must have shape ({n},), got {frame_levels.shape}")
    get = {k: np.asarray(cols[k], dtype=float) for k in ("t", "R", "w", "sigma_R", "sigma_w")}
    for i in np.flatnonzero(valid):
        fuse_patch(
            grid,
            x[i],
            y[i],
            yaw[i],
            t=get["t"][i],
            R=get["R"][i],
            w=get["w"][i],
            sigma_R=get["sigma_R"][i],
            sigma_w=get["sigma_w"][i],
            probs=None if probs is None else probs[i],
            level=math.nan if frame_levels is None else frame_levels[i],
            spec=spec,
            grow=False,
            update=False,
        )
    update_estimates(grid)
    if callable(levels):
        apply_levels(grid, levels)
    if n == 0:
        warnings.warn(
            "the traverse has no frames: the map is all nodata", EmptyMapWarning, stacklevel=2
        )
    elif not valid.any():
        warnings.warn(
            f"none of the {n} frames has a valid patch: the map is all nodata",
            EmptyMapWarning,
            stacklevel=2,
        )
    else:
        log.info(
            "fused %d of %d frames into a %s-cell map at %g m",
            valid.sum(),
            n,
            grid.shape,
            resolution,
        )
    return grid
