"""Scores of a class map against ground truth: accuracy near and far, by distance from the
path, the confusion matrix and the abstention rate.

The one scoring code of rough_map: ``rough-map score`` (a written map folder against a
truth GeoTIFF, :func:`score_map_dir`) and the accuracy against the simulator's world
(:mod:`rough_map.evaluation.truth`, ``near_class_accuracy`` of ``rough-map map --json``)
both end in :func:`score_cells`.

Definitions, over the map's cells where the truth has a class (the *scored* cells):

accuracy (per class layer: ``class`` = near field, ``far_class`` = far field, ...)
    correct / labelled, labelled = scored cells the layer gives a class.
abstention rate
    scored cells the layer *observed* (:func:`observed_mask`: its ``count`` / ``far_count``
    band > 0 or its ``confidence`` / ``far_confidence`` band finite; every scored cell when
    the map has no such band) but left unknown / those observed cells.
per distance
    the same in bins of distance (m) from the path: the polyline through the frames'
    poses (``labels.csv`` x, y: where the vehicle was; the patch it maps lies ahead of it),
    sampled every resolution/4 (distances within resolution/8 m). Without ``labels.csv``
    there is no table by distance.
confusion matrix
    counts, rows = true classes (the map's classes, then classes only in the truth), columns
    = the map's classes then ``unknown``. Names are matched as
    :func:`~rough_map.io.truth_raster.canonical_name` does; classes only in the map or only
    in the truth are listed (a cell of a truth-only class is always an error).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rough_map.errors import InputError
from rough_map.io.truth_raster import NO_TRUTH_NAMES, canonical_name

__all__ = [
    "DEFAULT_BINS",
    "LayerPrediction",
    "LayerScore",
    "MapScore",
    "observed_mask",
    "path_distance",
    "score_cells",
]

#: Upper edges of the distance bins, m from the path (a last bin, to infinity, takes the rest).
DEFAULT_BINS = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0)


@dataclass(frozen=True)
class LayerPrediction:
    """One class layer of a map, over its cells (flattened, any order).

    Attributes
    ----------
    values : ndarray of int64
        Class index into ``names`` per cell, -1 unknown.
    names : tuple of str
        The layer's class names.
    observed : ndarray of bool, optional
        Cells the layer had observations for (count > 0); None: all.
    """

    values: NDArray[np.int64]
    names: tuple[str, ...]
    observed: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class LayerScore:
    """Scores of one class layer (see the module docstring).

    ``bins`` holds per distance bin ``lo_m``, ``hi_m``, ``cells`` (scored), ``labelled``,
    ``correct``, ``accuracy``, ``observed``, ``abstained``, ``abstention_rate``.
    ``confusion`` is (true classes, map classes + 1) counts.
    """

    cells: int
    labelled: int
    correct: int
    observed: int
    abstained: int
    confusion: NDArray[np.int64]
    bins: list[dict[str, Any]] = field(default_factory=list)

    @property
    def accuracy(self) -> float:
        """correct / labelled, NaN when nothing is labelled."""
        return self.correct / self.labelled if self.labelled else math.nan

    @property
    def abstention_rate(self) -> float:
        """abstained / observed, NaN when nothing was observed."""
        return self.abstained / self.observed if self.observed else math.nan

    @property
    def coverage(self) -> float:
        """labelled / scored cells."""
        return self.labelled / self.cells if self.cells else math.nan


@dataclass(frozen=True)
class MapScore:
    """Scores of a map's class layers against a truth.

    Attributes
    ----------
    layers : dict of str to LayerScore
        Per class layer (``class``, ``far_class``, ...).
    true_classes : tuple of str
        Rows of the confusion matrices (canonical names).
    map_classes : tuple of str
        Columns of the confusion matrices, before ``unknown``.
    map_only, truth_only : tuple of str
        Classes of the map the truth never names, and the other way round.
    scored_cells : int
        Map cells with a true class.
    cell_area_m2 : float
        Area of a map cell, m².
    resampling : str
        How the truth was put onto the map's grid.
    """

    layers: dict[str, LayerScore]
    true_classes: tuple[str, ...]
    map_classes: tuple[str, ...]
    map_only: tuple[str, ...]
    truth_only: tuple[str, ...]
    scored_cells: int
    cell_area_m2: float = math.nan
    resampling: str = "nearest"
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def near_field_accuracy(self) -> float:
        return self.layers["class"].accuracy if "class" in self.layers else math.nan

    @property
    def far_field_accuracy(self) -> float:
        return self.layers["far_class"].accuracy if "far_class" in self.layers else math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN: None)."""

        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        return {
            **self.sources,
            "resampling": self.resampling,
            "cell_area_m2": num(self.cell_area_m2),
            "scored_cells": self.scored_cells,
            "near_field_accuracy": num(self.near_field_accuracy),
            "far_field_accuracy": num(self.far_field_accuracy),
            "map_classes": list(self.map_classes),
            "true_classes": list(self.true_classes),
            "map_only_classes": list(self.map_only),
            "truth_only_classes": list(self.truth_only),
            "layers": {
                name: {
                    "cells": s.cells,
                    "labelled": s.labelled,
                    "correct": s.correct,
                    "accuracy": num(s.accuracy),
                    "coverage": num(s.coverage),
                    "observed": s.observed,
                    "abstained": s.abstained,
                    "abstention_rate": num(s.abstention_rate),
                    "by_distance_m": [
                        {k: (num(v) if isinstance(v, float) else v) for k, v in b.items()}
                        for b in s.bins
                    ],
                    "confusion": {
                        "rows_true": list(self.true_classes),
                        "columns_map": [*self.map_classes, "unknown"],
                        "counts": s.confusion.tolist(),
                    },
                }
                for name, s in self.layers.items()
            },
        }

    def to_text(self) -> str:
        """Plain text tables: summary, by distance, confusion matrices."""
        lines = [
            f"scored cells (map cells with a true class): {self.scored_cells}"
            + (
                ""
                if math.isnan(self.cell_area_m2)
                else f" ({self.scored_cells * self.cell_area_m2:.1f} m²)"
            ),
            f"truth resampled onto the map grid by {self.resampling}",
        ]
        if self.map_only:
            lines.append(f"classes of the map not in the truth: {', '.join(self.map_only)}")
        if self.truth_only:
            lines.append(f"classes of the truth not in the map: {', '.join(self.truth_only)}")
        rows = [["layer", "labelled", "accuracy", "coverage", "observed", "abstention"]]
        for name, s in self.layers.items():
            rows.append([name, str(s.labelled), _f(s.accuracy), _f(s.coverage),
                         str(s.observed), _f(s.abstention_rate)])  # fmt: skip
        lines += ["", *_table(rows)]
        for name, s in self.layers.items():
            if s.bins:
                rows = [["distance (m)", "cells", "labelled", "accuracy", "abstention"]]
                for b in s.bins:
                    if b["cells"]:
                        rows.append([_span(b["lo_m"], b["hi_m"]), str(b["cells"]),
                                     str(b["labelled"]), _f(b["accuracy"]),
                                     _f(b["abstention_rate"])])  # fmt: skip
                lines += ["", f"{name} by distance from the path", *_table(rows)]
            head = ["true \\ map", *self.map_classes, "unknown"]
            rows = [head] + [
                [t, *(str(int(v)) for v in s.confusion[i])] for i, t in enumerate(self.true_classes)
            ]
            lines += ["", f"{name} confusion matrix (cells)", *_table(rows)]
        return "\n".join(lines)


def _span(lo: float, hi: float) -> str:
    return f"> {lo:g}" if math.isinf(hi) else f"{lo:g}–{hi:g}"


def _f(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.3f}"


def _table(rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    out = ["  ".join(c.rjust(w) if k else c.ljust(w) for k, (c, w) in
                     enumerate(zip(r, widths, strict=True))) for r in rows]  # fmt: skip
    out.insert(1, "  ".join("-" * w for w in widths))
    return out


def observed_mask(
    layer: str, band: Callable[[str], NDArray[np.floating] | None]
) -> NDArray[np.bool_] | None:
    """Cells a class layer had evidence for: its count band > 0 or its confidence band
    finite (``count``/``confidence`` for ``class``, ``far_count``/``far_confidence`` for
    ``far_class``, ...); ``band(name)`` gives a band or None. None without such a band."""
    if not layer.endswith("class"):
        return None
    prefix = layer[: -len("class")]
    out = None
    count, confidence = band(f"{prefix}count"), band(f"{prefix}confidence")
    if count is not None:
        out = np.nan_to_num(np.asarray(count, dtype=float)) > 0
    if confidence is not None:
        seen = np.isfinite(np.asarray(confidence, dtype=float))
        out = seen if out is None else out | seen
    return out


def path_distance(
    x: NDArray[np.float64], y: NDArray[np.float64], path_xy: NDArray[np.float64], step: float
) -> NDArray[np.float64]:
    """Distance in m of points (x, y) (m) from the polyline ``path_xy`` (n, 2) (m), the
    polyline sampled every ``step`` m (the error is at most ``step / 2``)."""
    from scipy.spatial import cKDTree

    path_xy = np.asarray(path_xy, dtype=float).reshape(-1, 2)
    path_xy = path_xy[np.all(np.isfinite(path_xy), axis=1)]
    if len(path_xy) == 0:
        raise InputError("the path has no finite position")
    pts = [path_xy[:1]]
    for a, b in itertools.pairwise(path_xy):
        n = max(1, math.ceil(float(np.hypot(*(b - a))) / step))
        t = np.arange(1, n + 1)[:, None] / n
        pts.append(a + t * (b - a))
    dist, _ = cKDTree(np.concatenate(pts)).query(np.column_stack([x, y]))
    return np.asarray(dist, dtype=float)


def _matching(
    layers: Mapping[str, LayerPrediction], truth_names: Mapping[int, str]
) -> tuple[list[str], list[str], dict[int, int]]:
    """Map classes, true classes (rows), and truth value -> row (-1: no truth)."""
    map_classes: list[str] = []
    for pred in layers.values():
        for n in pred.names:
            c = canonical_name(n)
            if c not in map_classes and c not in NO_TRUTH_NAMES:
                map_classes.append(c)
    rows = list(map_classes)
    value_row: dict[int, int] = {}
    for value, name in sorted(truth_names.items()):
        c = canonical_name(name)
        if c in NO_TRUTH_NAMES:
            value_row[value] = -1
            continue
        if c not in rows:
            rows.append(c)
        value_row[value] = rows.index(c)
    return map_classes, rows, value_row


def score_cells(
    layers: Mapping[str, LayerPrediction],
    truth: NDArray[np.integer],
    truth_names: Mapping[int, str],
    *,
    distance: NDArray[np.float64] | None = None,
    bins: Sequence[float] = DEFAULT_BINS,
    max_distance: float = math.inf,
    cell_area_m2: float = math.nan,
    resampling: str = "nearest",
    require_common: bool = True,
) -> MapScore:
    """Score class layers against the true class of the same cells.

    Parameters
    ----------
    layers : mapping of str to LayerPrediction
        The map's class layers over its cells (flattened, the order of ``truth``).
    truth : ndarray of int
        True class value per cell (a key of ``truth_names``); values without a name (e.g.
        nodata) mean no truth.
    truth_names : mapping of int to str
        Class names of the truth values (matched by name with the layers').
    distance : ndarray of float, optional
        Distance of each cell from the path, m; without it, no per-distance table.
    bins : sequence of float
        Upper edges of the distance bins, m, increasing (a last bin takes the rest).
    max_distance : float
        Only cells up to this distance from the path (m) are scored (needs ``distance``).
    cell_area_m2 : float
        Area of a cell, m² (reported).
    resampling : str
        How the truth was resampled (reported).
    require_common : bool
        Raise when the map and the truth share no class (else every labelled cell is wrong).

    Raises
    ------
    InputError
        No class of the truth is a class of the map, or shapes differ.
    """
    truth = np.asarray(truth).ravel()
    map_classes, rows, value_row = _matching(layers, truth_names)
    named = {rows[r] for r in value_row.values() if r >= 0}
    common = set(map_classes) & named
    if require_common and not common:
        raise InputError(
            f"no class of the truth ({', '.join(sorted(set(truth_names.values())))}) is a "
            f"class of the map ({', '.join(map_classes)})"
        )
    lut_keys = np.array(sorted(value_row), dtype=np.int64)
    lut_vals = np.array([value_row[k] for k in lut_keys], dtype=np.int64)
    pos = np.clip(np.searchsorted(lut_keys, truth), 0, len(lut_keys) - 1)
    row = np.where(lut_keys[pos] == truth, lut_vals[pos], -1)
    scope = row >= 0
    edges = np.array([0.0, *bins], dtype=float)
    if distance is not None:
        distance = np.asarray(distance, dtype=float).ravel()
        if distance.shape != truth.shape:
            raise InputError(f"distance has {distance.size} cells, the truth {truth.size}")
        scope &= distance <= max_distance
        if np.any(np.diff(edges) <= 0):
            raise InputError(f"bins must be positive increasing distances (m), got {bins!r}")
        edges = np.append(edges, np.inf)
    out: dict[str, LayerScore] = {}
    for name, pred in layers.items():
        values = np.asarray(pred.values).ravel()
        if values.shape != truth.shape:
            raise InputError(f"layer {name!r} has {values.size} cells, the truth {truth.size}")
        to_col = np.array([map_classes.index(canonical_name(n))
                           if canonical_name(n) in map_classes else -1
                           for n in pred.names] + [-1], dtype=np.int64)  # fmt: skip
        col = np.where(values >= 0, to_col[np.clip(values, -1, len(pred.names))], -1)
        observed = np.ones_like(scope) if pred.observed is None else np.asarray(pred.observed)
        r, c, o = row[scope], col[scope], observed.ravel()[scope]
        confusion = np.zeros((len(rows), len(map_classes) + 1), dtype=np.int64)
        np.add.at(confusion, (r, np.where(c >= 0, c, len(map_classes))), 1)
        bins_out: list[dict[str, Any]] = []
        if distance is not None:
            d = distance[scope]
            k = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, len(edges) - 2)
            for b in range(len(edges) - 1):
                sel = k == b
                if b == len(edges) - 2 and not sel.any():
                    continue
                bins_out.append(_counts(r[sel], c[sel], o[sel], edges[b], edges[b + 1]))
        tot = _counts(r, c, o, 0.0, math.inf)
        out[name] = LayerScore(
            cells=tot["cells"],
            labelled=tot["labelled"],
            correct=tot["correct"],
            observed=tot["observed"],
            abstained=tot["abstained"],
            confusion=confusion,
            bins=bins_out,
        )
    return MapScore(
        layers=out,
        true_classes=tuple(rows),
        map_classes=tuple(map_classes),
        map_only=tuple(n for n in map_classes if n not in named),
        truth_only=tuple(rows[len(map_classes) :]),
        scored_cells=int(scope.sum()),
        cell_area_m2=cell_area_m2,
        resampling=resampling,
    )


def _counts(
    r: NDArray[np.int64], c: NDArray[np.int64], o: NDArray[np.bool_], lo: float, hi: float
) -> dict[str, Any]:
    labelled = c >= 0
    correct = int(np.sum(labelled & (r == c)))
    n_lab, n_obs = int(labelled.sum()), int(o.sum())
    abstained = int(np.sum(o & ~labelled))
    return {
        "lo_m": float(lo),
        "hi_m": float(hi),
        "cells": int(r.size),
        "labelled": n_lab,
        "correct": correct,
        "accuracy": correct / n_lab if n_lab else math.nan,
        "observed": n_obs,
        "abstained": abstained,
        "abstention_rate": abstained / n_obs if n_obs else math.nan,
    }
