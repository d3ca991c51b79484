"""Fusing the patches seen along a traverse into grid-map layers (paper section 5.5).

Each frame's patch of interest (a :class:`~rough_map.patch.PatchSpec` square ``ahead`` m in
front of the vehicle, turned by its yaw) covers the cells whose centres lie inside it. Every
observation adds to *sums* kept as internal layers, and the estimate layers are computed
from those sums, so fusing the same observations in any order gives the same map (up to
floating-point rounding of the sums; ``last_seen`` is a max and exact).

The layers and how their estimates follow from the sums: :mod:`rough_map.map.layers`.
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
from rough_map.map.grid import DEFAULT_MARGIN, GridMap
from rough_map.map.grid_geometry import GridGeometry, patch_cells, patch_corners
from rough_map.map.layers import (
    LEVEL_NAMES,
    OBSERVED,
    apply_levels,
    group_prefix,
    init_layers,
    level_indices,
    normalised_probs,
    patch_sums,
    update_estimates,
)
from rough_map.patch import PatchSpec

log = logging.getLogger(__name__)

__all__ = [
    "fuse_cell_probabilities",
    "fuse_patch",
    "fuse_traverse",
    "log_fused",
]


def fuse_patch(
    grid: GridMap,
    x: float,
    y: float,
    yaw: float,
    *,
    t: float = math.nan,
    probs: ArrayLike | None = None,
    level: float = math.nan,
    spec: PatchSpec | None = None,
    grow: bool = True,
    margin: float = DEFAULT_MARGIN,
    update: bool = True,
    count: bool = True,
    **observed: float,
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
    probs : array_like, shape (K,), optional
        Class probabilities of the patch, in the order of ``grid.attrs["class_names"]``.
    level : float
        Roughness level index of the patch (NaN: none).
    spec : PatchSpec, optional
        Patch geometry (default: :class:`~rough_map.patch.PatchSpec`'s).
    grow : bool
        Grow the map to hold the whole patch (else cells outside are dropped).
    margin : float
        Room in m added when the map grows.
    update : bool
        Recompute the estimate layers under the patch now (else call
        :func:`update_estimates` once after many patches).
    count : bool
        Count the patch in ``count`` (False: a second fusion of a patch counted already,
        e.g. its smoothed class once the whole path is known).
    **observed : float
        The patch's observation, fields of :data:`rough_map.map.layers.OBSERVED` (NaN or
        left out: not observed): ``R`` and ``sigma_R`` (m^3/rad; R not finite or not
        positive: no roughness from this patch), ``w``, ``sigma_w``, ``band_rms`` (m),
        ``novelty``.

    Returns
    -------
    ndarray, shape (N, 2)
        ``(row, col)`` of the cells the patch covered (after any growth).

    Raises
    ------
    InputError
        A non-finite pose, or an observation :func:`~rough_map.map.layers.patch_sums`
        refuses.
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
    sums = patch_sums(
        grid.attrs.get("class_names", ()),
        grid.attrs.get("level_names", ()),
        probs=probs,
        level=level,
        count=count,
        **observed,
    )
    for name, value in sums:
        if name.startswith("votes_"):
            add_vote_layers(grid)
        if name in grid:  # as GridMap.add_at: a map made before a layer existed lacks it
            grid[name][rows, cols] += value
    if math.isfinite(t):
        grid["last_seen"][rows, cols] = np.fmax(grid["last_seen"][rows, cols], t)
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
    prefix = group_prefix(group)
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
    return normalised_probs(len(grid.attrs.get("class_names", ())), p, n)


def _add_evidence(
    grid: GridMap, prefix: str, rows: NDArray, cols: NDArray, p: NDArray, weight: NDArray
) -> None:
    for k, c in enumerate(grid.attrs["class_names"]):
        np.add.at(grid[f"{prefix}evidence_{c}"], (rows, cols), weight * p[:, k])


def add_vote_layers(grid: GridMap) -> None:
    """Create the internal layers ``votes_<level>`` (patches per roughness level) that are
    missing."""
    for name in grid.attrs["level_names"]:
        if f"votes_{name}" not in grid:
            grid.add_layer(
                f"votes_{name}",
                units="1",
                fill=0.0,
                kind="internal",
                description=f"patches whose level is {name}",
            )


def _window(cells: NDArray[np.int64]) -> tuple[slice, slice]:
    return (
        slice(int(cells[:, 0].min()), int(cells[:, 0].max()) + 1),
        slice(int(cells[:, 1].min()), int(cells[:, 1].max()) + 1),
    )


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
    novelty: ArrayLike | None = None,
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
        Patch geometry of the features (default: :class:`~rough_map.patch.PatchSpec`'s).
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
    novelty : array_like, shape (n_frames,), optional
        Novelty score per frame (NaN: none; :attr:`rough_map.classify.TerrainPrediction.
        novelty`), fused with the classes into ``novel``.

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
    grid = _traverse_map(features, x, y, yaw, posed, valid, spec, resolution, margin, crs, frame_id)
    init_layers(grid, names if probs is not None else (), level_names=level_names, prior=prior)
    frame_levels = None
    if levels is not None and not callable(levels):
        frame_levels = level_indices(levels, grid)
        if frame_levels.shape != (n,):
            raise InputError(f"levels must have shape ({n},), got {frame_levels.shape}")
    # the observation of each frame: the features columns of the fields the layers read
    get = {k: np.asarray(cols[k], dtype=float) for k in OBSERVED if k in cols}
    if novelty is not None:
        get["novelty"] = np.asarray(novelty, dtype=float)
        if get["novelty"].shape != (n,):
            raise InputError(f"novelty must have shape ({n},), got {get['novelty'].shape}")
    t = np.asarray(cols["t"], dtype=float)
    for i in np.flatnonzero(valid):
        observed: dict[str, Any] = {k: float(v[i]) for k, v in get.items()}
        fuse_patch(
            grid,
            x[i],
            y[i],
            yaw[i],
            t=t[i],
            probs=None if probs is None else probs[i],
            level=math.nan if frame_levels is None else frame_levels[i],
            spec=spec,
            grow=False,
            update=False,
            **observed,
        )
    update_estimates(grid)
    if callable(levels):
        apply_levels(grid, levels)
    log_fused(n, valid, grid, resolution)
    return grid


def _traverse_map(
    features: Any,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    yaw: NDArray[np.float64],
    posed: NDArray[np.bool_],
    valid: NDArray[np.bool_],
    spec: PatchSpec,
    resolution: float,
    margin: float,
    crs: Any,
    frame_id: str,
) -> GridMap:
    """The empty map of :func:`fuse_traverse`: covering every posed frame's patch."""
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
    return GridMap(
        geometry,
        attrs={
            "name": getattr(features, "name", ""),
            "track": np.column_stack([x[posed], y[posed]]),
            "n_frames": len(x),
            "n_valid": int(valid.sum()),
            "patch": {"ahead": spec.ahead, "size": spec.size, "lateral": spec.lateral},
        },
    )


def log_fused(
    n: int, valid: NDArray[np.bool_], grid: GridMap, resolution: float, stacklevel: int = 3
) -> None:
    """Log what a traverse's fusion fused, or warn (at the caller of the function calling
    this one, with the default ``stacklevel``) that nothing was."""
    if n == 0:
        warnings.warn(
            "the traverse has no frames: the map is all nodata",
            EmptyMapWarning,
            stacklevel=stacklevel,
        )
    elif not valid.any():
        warnings.warn(
            f"none of the {n} frames has a valid patch: the map is all nodata",
            EmptyMapWarning,
            stacklevel=stacklevel,
        )
    else:
        log.info(
            "fused %d of %d frames into a %s-cell map at %g m",
            valid.sum(),
            n,
            grid.shape,
            resolution,
        )
