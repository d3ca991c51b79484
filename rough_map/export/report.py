"""A report folder for one traverse: the paper's figures and an ``index.html`` showing them.

:func:`write_report` draws the figures (:mod:`rough_map.export.figures`) of an analysed
traverse and writes the page (:mod:`rough_map.export.report_html`). It reads the analysis
through :class:`~rough_map.export.report_inputs.AnalysisResult` (what
:class:`rough_map.workflow.TraverseAnalysis` holds), so the export layer does not depend
on the workflow above it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output, make_dir
from rough_map.errors import RoughMapError
from rough_map.export import figures as fig
from rough_map.export.report_html import write_index
from rough_map.export.report_inputs import AnalysisResult, ReportTable
from rough_map.export.tables import plain
from rough_map.features import FeatureTable, label_summary
from rough_map.features.table import SMOOTH_COLUMNS
from rough_map.patch import PatchSpec, grid_points
from rough_map.psd import PatchRoughness, patch_roughness, profile_psd

log = logging.getLogger(__name__)

__all__ = ["AnalysisResult", "ReportTable", "write_report"]


def write_report(
    result: AnalysisResult,
    out_dir: str | Path,
    *,
    evaluation: Mapping[str, Any] | None = None,
    level_edges: Sequence[float] | None = None,
    tables: Sequence[ReportTable] = (),
) -> dict[str, Path]:
    """Draw every figure of an analysed traverse and write ``index.html`` showing them.

    Parameters
    ----------
    result : AnalysisResult
        The analysis (:func:`rough_map.workflow.analyse` returns one).
    out_dir : str or Path
        Folder to write into (created). GeoTIFFs, layer PNGs (``<name>_<layer>.png``),
        ``features.csv`` and ``labels.csv`` already there are linked from the page.
    evaluation : dict, optional
        Scores as :func:`rough_map.evaluation.evaluate_model` returns them.
    level_edges : sequence of float, optional
        R thresholds (m³/rad) of the roughness levels, for the (R, w) scatter.
    tables : sequence of ReportTable
        More tables to show, after the summary (the demo's).

    Returns
    -------
    dict of str to Path
        The files written, ``index`` last.
    """
    out = Path(out_dir)
    make_dir(out)
    figs: dict[str, tuple[Path, str]] = {}
    labels, which = _labels(result)
    figs["path"] = _path_figure(result, labels, which, out)
    figs.update(_frame_figures(result, out))
    figs.update(
        _class_figures(result.features, labels, which, level_edges, out, result.extraction.patch)
    )
    figs.update(_map_figures(result, out))
    if evaluation is not None:
        figs["confusion"] = _confusion_figure(evaluation, out)
    paths = {key: path for key, (path, _) in figs.items()}
    if evaluation is not None:
        path = out / "evaluation.json"
        with atomic_output(path) as tmp, open(tmp, "w") as fh:
            json.dump(evaluation, fh, indent=1, default=plain)
        paths["evaluation"] = path
    captions = {key: caption for key, (_, caption) in figs.items()}
    paths["index"] = write_index(result, out, paths, captions, evaluation, list(tables))
    return paths


def _labels(result: AnalysisResult) -> tuple[list[str] | None, str]:
    """The class of each frame (the true labels, else the filtered prediction) and which."""
    f, pred = result.features, result.prediction
    if any(f["label"]):
        return list(f["label"]), "true"
    return (list(pred.filtered_class) if pred is not None else None), "predicted (filtered)"


def _path_figure(
    result: AnalysisResult, labels: list[str] | None, which: str, out: Path
) -> tuple[Path, str]:
    f, pred = result.features, result.prediction
    advised = "v_max" in f.columns and bool(np.isfinite(f["v_max"]).any())
    path = fig.roughness_along_path(
        f.distance(),
        f["R"],
        f["sigma_R"],
        f["w"],
        f["sigma_w"],
        out / "fig_path.png",
        labels=labels,
        defects=None if pred is None else pred.defect,
        smoothed={k: f[k] for k in SMOOTH_COLUMNS if k in f.columns} or None,
        speed={k: f[k] for k in ("v_max", "v_max_95")} if advised else None,
        title=f"{result.traverse.name}: roughness along the path",
    )
    defects = (
        "; red triangles mark frames the path filter flagged as isolated defects (e.g. a manhole)"
        if pred is not None
        else ""
    )
    caption = (
        "Roughness along the path: R (log scale, m³/rad, top) and w (bottom) of each frame's "
        "patch against the distance travelled (m), with ±1σ bands; in orange, R and w "
        "smoothed along the path (Kalman smoother, ±1σ). Dashed lines mark the ISO "
        f"8608 class centres A–H (w = −2); the background is shaded by the {which} class"
        f"{defects}. Paper Figs. 7, 9, 12."
        + (
            " Bottom: the speed advice for the vehicle, v_max (m/s, the highest speed keeping "
            "its limits), and the speed that holds with 95 % confidence."
            if advised
            else ""
        )
    )
    return path, caption


def _frame_figures(result: AnalysisResult, out: Path) -> dict[str, tuple[Path, str]]:
    """The PSD of one profile with its fit, and the profiles' (R, w), of the median frame."""
    frame = _representative_frame(result.features)
    one = None if frame is None else _frame_roughness(result, frame)
    if frame is None or one is None:
        return {}
    rough, omega, profile, k = one
    psd = fig.profile_psd_fit(
        omega,
        profile,
        float(rough.profile_R[k]),
        float(rough.profile_w[k]),
        out / "fig_psd_profile.png",
        title=f"frame {frame}: PSD of profile {k} and its fit",
    )
    profiles = fig.profile_scatter(
        rough.profile_R,
        rough.profile_w,
        rough.R,
        rough.w,
        out / "fig_profiles.png",
        title=f"frame {frame}: roughness of the {rough.n_profiles} profiles",
    )
    return {
        "psd": (
            psd,
            f"PSD (m³/rad) of longitudinal profile {k} of the patch of frame {frame} "
            "(the frame with the median R) against the wavenumber Ω (rad/m), on log "
            "axes, with its power-law fit R·Ω^w. Paper Fig. 4.",
        ),
        "profiles": (
            profiles,
            f"R (m³/rad) and w of each of the {rough.n_profiles} longitudinal profiles of "
            f"frame {frame}'s patch (grey dots) and of the patch (circle: geometric mean "
            "of R, mean of w). Paper Fig. 5.",
        ),
    }


def _representative_frame(f: FeatureTable) -> int | None:
    """The valid frame with the median R."""
    ok = np.flatnonzero(f.valid)
    if ok.size == 0:
        return None
    lr = np.log(f["R"][ok])
    return int(f["frame"][ok[np.argsort(lr)[lr.size // 2]]])


def _frame_roughness(
    result: AnalysisResult, frame: int
) -> tuple[PatchRoughness, np.ndarray, np.ndarray, int] | None:
    """PatchRoughness of one frame, recomputed with the analysis's patch and method, and
    the PSD of one profile (the middle one, or the nearest kept one).

    The noise floor is not subtracted: the figure shows the fit of the measured PSD.
    """
    ex = result.extraction
    try:
        pts = result.traverse.load_cloud(frame)
        imu = result.traverse.frames[frame].imu if ex.use_imu else None
        roll, pitch = (imu.roll, imu.pitch) if imu is not None else (None, None)
        grid = grid_points(pts, ex.patch, roll=roll, pitch=pitch)
        spacing = grid.spec.spacing
        rough = patch_roughness(grid.heights, spacing, method=ex.method, gridding=grid.gridding)
    except RoughMapError as exc:
        log.info("report: frame %d not redrawn: %s", frame, exc)
        return None
    k = rough.n_profiles // 2
    omega, psd = profile_psd(grid.heights, spacing)
    rows = np.flatnonzero(np.all(np.isfinite(psd), axis=1))
    if rows.size == 0:
        return None
    return rough, omega, psd[rows[min(k, rows.size - 1)]], min(k, rough.n_profiles - 1)


def _class_figures(
    f: FeatureTable,
    labels: list[str] | None,
    which: str,
    level_edges: Sequence[float] | None,
    out: Path,
    patch: PatchSpec,
) -> dict[str, tuple[Path, str]]:
    """The classes' PSD lines against ISO 8608 over the patch's waveband, and (R, w) by
    class."""
    summary = label_summary(f, labels) if labels is not None else {}
    by_class = {name: (s.R, s.w) for name, s in summary.items() if name}
    if labels is None or not by_class:
        return {}
    iso = fig.psd_lines_vs_iso(by_class, out / "fig_psd_iso.png", patch=patch)
    classes = fig.class_scatter(
        f["R"], f["w"], labels, out / "fig_classes.png", level_edges=level_edges
    )
    edges = (
        ""
        if level_edges is None
        else " The shaded bands are the low/medium/high roughness levels, split at R = "
        + " and ".join(f"{v:.2g}" for v in level_edges)
        + " m³/rad."
    )
    return {
        "iso": (
            iso,
            f"Fitted PSD line R·Ω^w of each {which} class (geometric mean of R, mean of w "
            "over its frames) against the ISO 8608 class lines A–H (dashed, w = −2), over "
            "the wavenumber band of a patch. Paper Fig. 10.",
        ),
        "classes": (
            classes,
            f"R (m³/rad, log scale) against w of every valid frame, coloured by its {which} "
            f"class.{edges} Paper Fig. 19.",
        ),
    }


def _map_figures(result: AnalysisResult, out: Path) -> dict[str, tuple[Path, str]]:
    """The map figures and their captions: values, class, class with near-to-far."""
    grid = result.map
    x0, y0 = grid.geometry.origin
    ny, nx = grid.shape
    res = grid.geometry.resolution
    extent = (x0, x0 + nx * res, y0, y0 + ny * res)
    path_xy = np.column_stack([result.features["x"], result.features["y"]])
    figs = {"map": _map_values_figure(result, extent, path_xy, out)}
    if "class" in grid.layers:
        figs.update(_map_class_figures(result, extent, path_xy, out))
    return figs


def _map_values_figure(
    result: AnalysisResult,
    extent: tuple[float, float, float, float],
    path_xy: np.ndarray,
    out: Path,
) -> tuple[Path, str]:
    """Elevation (when mapped), log10 R and the roughness level, stacked."""
    grid = result.map
    layers: dict[str, np.ndarray] = {}
    titles, labels = {}, {}
    if "elevation" in grid.layers:
        layers["elevation"] = grid["elevation"]
        titles["elevation"] = "elevation (from the range data)"
        labels["elevation"] = "elevation [m]"
    with np.errstate(divide="ignore", invalid="ignore"):
        layers["log10 R"] = np.log10(grid["R"])
    titles["log10 R"] = "roughness: log10 R"
    labels["log10 R"] = "log10 R [m³/rad]"
    if "level" in grid.layers:
        layers["level"] = grid["level"]
        titles["level"] = "roughness level"
    described = {
        "elevation": "elevation from the range data (m)",
        "log10 R": "log10 R (m³/rad)",
    }
    shown = ", ".join(described.get(k, "roughness level (low/medium/high)") for k in layers)
    path = fig.map_layers(
        layers,
        extent,
        out / "fig_map_values.png",
        path_xy=path_xy,
        titles=titles,
        labels=labels,
    )
    caption = (
        f"Map layers on {grid.geometry.resolution:g} m cells, top to bottom: {shown}. All "
        "are cropped to the cells the near field measured; the blue line is the vehicle "
        "path. Paper Figs. 20, 21."
    )
    return path, caption


def _map_class_figures(
    result: AnalysisResult,
    extent: tuple[float, float, float, float],
    path_xy: np.ndarray,
    out: Path,
) -> dict[str, tuple[Path, str]]:
    """The class layer, and with near-to-far the class with the far field filled in."""
    grid = result.map
    names = tuple(grid.info("class").categories)
    figs = {
        "map_class": (
            fig.map_layers(
                {"class": grid["class"]},
                extent,
                out / "fig_map_class.png",
                path_xy=path_xy,
                class_names=names,
                titles={"class": "terrain class (geometry, filtered)"},
            ),
            "Terrain class of each map cell from the near-field geometry: the path-filtered "
            "class probabilities of the patches fused into the grid, most probable class shown.",
        )
    }
    if "far_class" in grid.layers and np.isfinite(grid["far_class"]).any():
        both = np.where(np.isfinite(grid["class"]), grid["class"], grid["far_class"])
        figs["map_class_far"] = (
            fig.map_layers(
                {"class": both},
                extent,
                out / "fig_map_class_far.png",
                path_xy=path_xy,
                class_names=names,
                titles={"class": "terrain class with near-to-far (RGB appearance)"},
            ),
            "Terrain class with near-to-far: cells the near field measured keep their "
            "geometric class; the others take the class predicted from the appearance of "
            "the RGB images, learnt on line from the near field.",
        )
    return figs


def _confusion_figure(evaluation: Mapping[str, Any], out: Path) -> tuple[Path, str]:
    path = fig.confusion_matrices(dict(evaluation), out / "fig_confusion.png")
    scored = evaluation.get("scored_classes") or evaluation["raw"].get("scored_classes")
    caption = (
        "Row-normalised confusion matrices of the raw classifier output (left) and the "
        "path-filtered classes (right), on the same classes in the same order: each row "
        "is a true class, the diagonal its recall. The macro-F1 in the titles is the mean "
        f"F1 over the classes present in the truth ({', '.join(scored or [])})"
        "; a hatched row is a class predicted but never true."
    )
    return path, caption
