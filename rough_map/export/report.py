"""A report folder for one traverse: the paper's figures and an ``index.html`` showing them."""

from __future__ import annotations

import html
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.export import figures as fig

log = logging.getLogger(__name__)


def write_report(
    result: Any,
    out_dir: str | Path,
    *,
    evaluation: dict | None = None,
    level_edges: tuple[float, float] | None = None,
) -> dict[str, Path]:
    """Draw every figure of a :class:`rough_map.workflow.TraverseAnalysis`; write index.html.

    Parameters
    ----------
    result : TraverseAnalysis
        Output of :func:`rough_map.workflow.analyse`.
    out_dir : str or Path
        Folder to write into (created).
    evaluation : dict, optional
        Scores as :func:`rough_map.classify.evaluate_model` returns them.
    level_edges : (float, float), optional
        R thresholds (m^3/rad) of the roughness levels, for the (R, w) scatter.

    Returns
    -------
    dict of str to Path
        The files written, ``index`` last.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    f = result.features
    pred = result.prediction
    d = f.distance()
    labels = (
        list(f["label"])
        if any(f["label"])
        else (list(pred.filtered_class) if pred is not None else None)
    )
    paths: dict[str, Path] = {}
    name = result.traverse.name
    paths["path"] = fig.roughness_along_path(
        d,
        f["R"],
        f["sigma_R"],
        f["w"],
        f["sigma_w"],
        out / "fig_path.png",
        labels=labels,
        defects=None if result.prediction is None else result.prediction.defect,
        title=f"{name}: roughness along the path",
    )
    frame = _representative_frame(f)
    if frame is not None:
        one = _frame_roughness(result.traverse, frame, result)
        if one is not None:
            rough, omega, profile, k = one
            paths["psd"] = fig.profile_psd_fit(
                omega,
                profile,
                float(rough.profile_R[k]),
                float(rough.profile_w[k]),
                out / "fig_psd_profile.png",
                title=f"frame {frame}: PSD of profile {k} and its fit",
            )
            paths["profiles"] = fig.profile_scatter(
                rough.profile_R,
                rough.profile_w,
                rough.R,
                rough.w,
                out / "fig_profiles.png",
                title=f"frame {frame}: roughness of the {rough.n_profiles} profiles",
            )
    by_class = _class_means(f, labels)
    if by_class:
        paths["iso"] = fig.psd_lines_vs_iso(by_class, out / "fig_psd_iso.png")
        paths["classes"] = fig.class_scatter(
            f["R"], f["w"], labels, out / "fig_classes.png", level_edges=level_edges
        )
    paths["map"] = _map_figure(result, out / "fig_map.png")
    if evaluation is not None:
        from rough_map.export.figures import confusion_matrices

        paths["confusion"] = confusion_matrices(evaluation, out / "fig_confusion.png")
        with open(out / "evaluation.json", "w") as fh:
            json.dump(evaluation, fh, indent=1, default=_plain)
        paths["evaluation"] = out / "evaluation.json"
    paths["index"] = _index(result, out, paths, evaluation)
    return paths


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def _representative_frame(f: Any) -> int | None:
    ok = np.flatnonzero(f.valid)
    if ok.size == 0:
        return None
    lr = np.log(f["R"][ok])
    return int(f["frame"][ok[np.argsort(lr)[lr.size // 2]]])


def _frame_roughness(traverse: Any, frame: int, result: Any):
    """PatchRoughness of one frame, recomputed, with one profile's PSD."""
    from rough_map.errors import RoughMapError
    from rough_map.patch import grid_points
    from rough_map.psd import patch_roughness, profile_psd

    try:
        pts = traverse.load_cloud(frame)
        fr = traverse.frames[frame]
        roll, pitch = (fr.imu.roll, fr.imu.pitch) if fr.imu is not None else (None, None)
        grid = grid_points(pts, roll=roll, pitch=pitch)
        rough = patch_roughness(grid.heights, grid.spec.spacing, gridding=grid.gridding)
    except RoughMapError as exc:
        log.info("report: frame %d not redrawn: %s", frame, exc)
        return None
    k = rough.n_profiles // 2
    omega, psd = profile_psd(grid.heights, grid.spec.spacing)
    rows = np.flatnonzero(np.all(np.isfinite(psd), axis=1))
    if rows.size == 0:
        return None
    return rough, omega, psd[rows[min(k, rows.size - 1)]], min(k, rough.n_profiles - 1)


def _class_means(f: Any, labels: list | None) -> dict[str, tuple[float, float]]:
    if labels is None:
        return {}
    lab = np.asarray(labels, dtype=object)
    out = {}
    for name in dict.fromkeys(lab):
        sel = f.valid & (lab == name)
        if name and sel.any():
            out[str(name)] = (
                math.exp(float(np.mean(np.log(f["R"][sel])))),
                float(np.mean(f["w"][sel])),
            )
    return out


def _map_figure(result: Any, path: Path) -> Path:
    grid = result.map
    x0, y0 = grid.geometry.origin
    ny, nx = grid.shape
    res = grid.geometry.resolution
    extent = (x0, x0 + nx * res, y0, y0 + ny * res)
    layers: dict[str, np.ndarray] = {}
    titles = {}
    if "elevation" in grid.layers:
        layers["elevation"] = grid["elevation"]
        titles["elevation"] = "elevation [m] (from the range data)"
    with np.errstate(divide="ignore", invalid="ignore"):
        layers["log10 R"] = np.log10(grid["R"])
    titles["log10 R"] = "log10 R [m³/rad]"
    if "level" in grid.layers:
        layers["level"] = grid["level"]
        titles["level"] = "roughness level"
    names: tuple[str, ...] = ()
    if "class" in grid.layers:
        layers["class"] = grid["class"]
        names = tuple(grid.info("class").categories)
        titles["class"] = "terrain class (geometry, filtered)"
    if "far_class" in grid.layers and np.isfinite(grid["far_class"]).any():
        both = np.where(np.isfinite(grid["class"]), grid["class"], grid["far_class"])
        layers["class + near-to-far"] = both
        titles["class + near-to-far"] = "terrain class with near-to-far (RGB appearance)"
    path_xy = np.column_stack([result.features["x"], result.features["y"]])
    values = {k: v for k, v in layers.items() if not k.startswith("class")}
    out = fig.map_layers(
        values, extent, path.with_name(path.stem + "_values.png"), path_xy=path_xy, titles=titles
    )
    if names:
        cls = {"class": layers["class"]}
        fig.map_layers(
            cls,
            extent,
            path.with_name(path.stem + "_class.png"),
            path_xy=path_xy,
            class_names=names,
            titles=titles,
        )
        if "class + near-to-far" in layers:
            fig.map_layers(
                {"class": layers["class + near-to-far"]},
                extent,
                path.with_name(path.stem + "_class_far.png"),
                path_xy=path_xy,
                class_names=names,
                titles={"class": titles["class + near-to-far"]},
            )
    return out


def _index(result: Any, out: Path, paths: dict[str, Path], evaluation: dict | None) -> Path:
    from rough_map.io.pointcloud import atomic_output

    f = result.features
    pics = sorted(p.name for p in out.glob("fig_*.png"))
    esc = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>rough_map report: {esc(result.traverse.name)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "img{max-width:100%;border:1px solid #ccc;margin:6px 0}"
        "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:3px 8px}</style>",
        "</head><body>",
        f"<h1>rough_map report: {esc(result.traverse.name)}</h1>",
        f"<p>{len(f)} frames, {int(f.valid.sum())} with a valid patch; map "
        f"{result.map.shape[1]} x {result.map.shape[0]} cells of "
        f"{result.map.geometry.resolution:g} m.</p>",
    ]
    if result.far_report:
        r = result.far_report
        parts.append(
            f"<p>Near field {r['near_area_m2']:.1f} m², with near-to-far "
            f"{r['near_far_area_m2']:.1f} m² (×{r['area_ratio']:.1f}).</p>"
        )
        acc = r.get("far_accuracy_by_distance")
        if acc is not None:
            parts.append("<h2>Near-to-far accuracy against distance</h2>" + _html_table(acc))
    if evaluation is not None:
        parts.append("<h2>Evaluation</h2>")
        rows = [
            [k, f"{evaluation[k]['accuracy']:.3f}", f"{evaluation[k]['macro_f1']:.3f}"]
            for k in ("raw", "filtered")
            if k in evaluation
        ]
        parts.append(_html_table({"labels": ["", "accuracy", "macro-F1"], "rows": rows}))
    for name in pics:
        parts.append(f"<h3>{esc(name)}</h3><img src='{esc(name)}' alt='{esc(name)}'>")
    parts.append("</body></html>")
    path = out / "index.html"
    with atomic_output(path) as tmp:
        Path(tmp).write_text("\n".join(parts), encoding="utf-8")
    return path


def _html_table(tab: Any) -> str:
    esc = html.escape
    if isinstance(tab, dict) and "rows" in tab:
        head, rows = tab["labels"], tab["rows"]
    elif isinstance(tab, list) and tab and isinstance(tab[0], dict):
        head = list(tab[0])
        rows = [[r[h] for h in head] for r in tab]
    else:
        return f"<pre>{esc(json.dumps(tab, default=_plain, indent=1))}</pre>"

    def cell(v: Any) -> str:
        return esc(f"{v:.3f}" if isinstance(v, float) else str(v))

    out = ["<table><tr>" + "".join(f"<th>{esc(str(h))}</th>" for h in head) + "</tr>"]
    out += ["<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows]
    return "".join(out) + "</table>"
