"""A report folder for one traverse: the paper's figures and an ``index.html`` showing them.

The page is for a person on a laptop screen: a narrow column (max 1100 px), images that
shrink with the window, numbers in HTML tables (wide ones scroll inside their own box, the
page never scrolls sideways), a caption under every figure saying what it shows, and links
to the GeoTIFFs, the layer PNGs and the tables in the folder. ``tools/check_report.py``
opens it in headless Chromium and checks exactly that.
"""

from __future__ import annotations

import dataclasses
import html
import json
import logging
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.export import figures as fig

log = logging.getLogger(__name__)

__all__ = ["ReportTable", "write_report"]


@dataclass
class ReportTable:
    """A table for the report (e.g. the demo's synthetic-patch and stereo tables).

    Attributes
    ----------
    title : str
        Heading above the table.
    head : list of str
        Column names (with units, e.g. ``"R [m³/rad]"``).
    rows : list of list
        Cells; floats are shown with 3 decimals, NaN as a dash.
    caption : str
        What the table shows, under the heading.
    notes : list of str
        Lines under the table (e.g. a timing).
    """

    title: str
    head: list[str]
    rows: list[list[Any]]
    caption: str = ""
    notes: list[str] = field(default_factory=list)


def write_report(
    result: Any,
    out_dir: str | Path,
    *,
    evaluation: dict | None = None,
    level_edges: tuple[float, float] | None = None,
    tables: Sequence[ReportTable] = (),
) -> dict[str, Path]:
    """Draw every figure of a :class:`rough_map.workflow.TraverseAnalysis`; write index.html.

    Parameters
    ----------
    result : TraverseAnalysis
        Output of :func:`rough_map.workflow.analyse`.
    out_dir : str or Path
        Folder to write into (created). GeoTIFFs, layer PNGs (``<name>_<layer>.png``),
        ``features.csv`` and ``labels.csv`` already there are linked from the page.
    evaluation : dict, optional
        Scores as :func:`rough_map.evaluation.evaluate_model` returns them.
    level_edges : (float, float), optional
        R thresholds (m³/rad) of the roughness levels, for the (R, w) scatter.
    tables : sequence of ReportTable
        More tables to show, after the summary (the demo's).

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
    truth_labels = any(f["label"])
    labels = (
        list(f["label"])
        if truth_labels
        else (list(pred.filtered_class) if pred is not None else None)
    )
    which = "true" if truth_labels else "predicted (filtered)"
    paths: dict[str, Path] = {}
    captions: dict[str, str] = {}
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
    captions["path"] = (
        "Roughness along the path: R (log scale, m³/rad, top) and w (bottom) of each frame's "
        "patch against the distance travelled (m), with ±1σ bands. Dashed lines mark the ISO "
        "8608 class centres A–H (w = −2); the background is shaded by the "
        f"{which} class"
        + (
            "; red triangles mark frames the path filter flagged as isolated defects "
            "(e.g. a manhole)"
            if result.prediction is not None
            else ""
        )
        + ". Paper Figs. 7, 9, 12."
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
            captions["psd"] = (
                f"PSD (m³/rad) of longitudinal profile {k} of the patch of frame {frame} "
                "(the frame with the median R) against the wavenumber Ω (rad/m), on log "
                "axes, with its power-law fit R·Ω^w. Paper Fig. 4."
            )
            paths["profiles"] = fig.profile_scatter(
                rough.profile_R,
                rough.profile_w,
                rough.R,
                rough.w,
                out / "fig_profiles.png",
                title=f"frame {frame}: roughness of the {rough.n_profiles} profiles",
            )
            captions["profiles"] = (
                f"R (m³/rad) and w of each of the {rough.n_profiles} longitudinal profiles of "
                f"frame {frame}'s patch (grey dots) and of the patch (circle: geometric mean "
                "of R, mean of w). Paper Fig. 5."
            )
    by_class = _class_means(f, labels)
    if by_class:
        paths["iso"] = fig.psd_lines_vs_iso(by_class, out / "fig_psd_iso.png")
        captions["iso"] = (
            f"Fitted PSD line R·Ω^w of each {which} class (geometric mean of R, mean of w over "
            "its frames) against the ISO 8608 class lines A–H (dashed, w = −2), over the "
            "wavenumber band of a patch. Paper Fig. 10."
        )
        paths["classes"] = fig.class_scatter(
            f["R"], f["w"], labels, out / "fig_classes.png", level_edges=level_edges
        )
        edges = (
            ""
            if level_edges is None
            else " The shaded bands are the low/medium/high roughness levels, split at R = "
            + " and ".join(f"{v:.2g}" for v in level_edges)
            + " m³/rad."
        )
        captions["classes"] = (
            f"R (m³/rad, log scale) against w of every valid frame, coloured by its {which} "
            f"class.{edges} Paper Fig. 19."
        )
    for key, (path, caption) in _map_figures(result, out).items():
        paths[key] = path
        captions[key] = caption
    if evaluation is not None:
        from rough_map.export.figures import confusion_matrices

        paths["confusion"] = confusion_matrices(evaluation, out / "fig_confusion.png")
        scored = evaluation.get("scored_classes") or evaluation["raw"].get("scored_classes")
        captions["confusion"] = (
            "Row-normalised confusion matrices of the raw classifier output (left) and the "
            "path-filtered classes (right), on the same classes in the same order: each row "
            "is a true class, the diagonal its recall. The macro-F1 in the titles is the mean "
            f"F1 over the classes present in the truth ({', '.join(scored or [])})"
            "; a hatched row is a class predicted but never true."
        )
        with open(out / "evaluation.json", "w") as fh:
            json.dump(evaluation, fh, indent=1, default=_plain)
        paths["evaluation"] = out / "evaluation.json"
    paths["index"] = _index(result, out, paths, captions, evaluation, list(tables))
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


def _map_figures(result: Any, out: Path) -> dict[str, tuple[Path, str]]:
    """The map figures and their captions: values, class, class with near-to-far."""
    grid = result.map
    x0, y0 = grid.geometry.origin
    ny, nx = grid.shape
    res = grid.geometry.resolution
    extent = (x0, x0 + nx * res, y0, y0 + ny * res)
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
    path_xy = np.column_stack([result.features["x"], result.features["y"]])
    figs: dict[str, tuple[Path, str]] = {}
    shown = ", ".join(
        {"elevation": "elevation from the range data (m)", "log10 R": "log10 R (m³/rad)"}.get(
            k, "roughness level (low/medium/high)"
        )
        for k in layers
    )
    figs["map"] = (
        fig.map_layers(
            layers,
            extent,
            out / "fig_map_values.png",
            path_xy=path_xy,
            titles=titles,
            labels=labels,
        ),
        f"Map layers on {res:g} m cells, top to bottom: {shown}. All are cropped to the "
        "cells the near field measured; the blue line is the vehicle path. Paper Figs. 20, 21.",
    )
    if "class" in grid.layers:
        names = tuple(grid.info("class").categories)
        figs["map_class"] = (
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


# -- the page --------------------------------------------------------------------------------

_CSS = """
*{box-sizing:border-box}
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;line-height:1.45;color:#222;
 max-width:1100px;margin:0 auto;padding:0 16px 48px;overflow-wrap:anywhere}
h1{font-size:1.6em;margin:.8em 0 .3em}h2{font-size:1.3em;margin-top:1.6em;
 border-bottom:1px solid #ddd;padding-bottom:.2em}h3{font-size:1.05em;margin:1.2em 0 .3em}
p.note{color:#555;font-size:.92em;max-width:80ch}
nav ul{margin:.3em 0;padding-left:1.2em}
figure{margin:1.2em 0 1.8em}
figure img{display:block;max-width:100%;height:auto;border:1px solid #ccc}
figcaption{font-size:.92em;color:#333;margin-top:.4em;max-width:85ch}
.table-box{max-width:100%;overflow-x:auto;margin:.4em 0 1em}
table{border-collapse:collapse;font-size:.88em}
caption{caption-side:top;text-align:left;color:#444;padding:.2em 0 .4em;font-size:.95em}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:left;white-space:nowrap}
th{background:#f3f3f3}.num{text-align:right}
td.text{white-space:normal;min-width:24ch}
"""


def _png_size(path: Path) -> tuple[int, int] | None:
    try:
        head = path.read_bytes()[:24]
    except OSError:
        return None
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


def _cell(v: Any) -> str:
    if isinstance(v, bool | np.bool_):
        return "yes" if v else "no"
    if isinstance(v, float | np.floating):
        return "–" if not math.isfinite(float(v)) else f"{float(v):.3f}"
    if isinstance(v, np.integer):
        return str(int(v))
    return str(v)


def _table(
    head: Sequence[Any],
    rows: Sequence[Sequence[Any]],
    caption: str = "",
    *,
    text_columns: Sequence[int] = (),
) -> str:
    """An HTML table in a box that scrolls sideways when the table is wider than the page.

    Numeric columns are right-aligned; ``text_columns`` wrap their long text.
    """
    esc = html.escape
    ncol = max([len(head), *(len(r) for r in rows)])
    numeric = [
        bool(rows) and all(i >= len(r) or r[i] == "" or _is_number(r[i]) for r in rows)
        for i in range(ncol)
    ]

    def attrs(i: int) -> str:
        cls = [c for c, on in (("num", numeric[i]), ("text", i in text_columns)) if on]
        return f" class='{' '.join(cls)}'" if cls else ""

    out = ["<div class='table-box'><table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    if any(str(h) for h in head):
        cells = "".join(f"<th{attrs(i)}>{esc(str(h))}</th>" for i, h in enumerate(head))
        out.append(f"<thead><tr>{cells}</tr></thead>")
    out.append("<tbody>")
    for r in rows:
        cells = "".join(
            f"<td{attrs(i)}>{v if isinstance(v, _Html) else esc(_cell(v))}</td>"
            for i, v in enumerate(r)
        )
        out.append(f"<tr>{cells}</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


def _is_number(v: Any) -> bool:
    if isinstance(v, bool | np.bool_ | _Html):
        return False
    if isinstance(v, int | float | np.number):
        return True
    try:
        float(str(v).replace(",", "").replace("×", "").replace("−", "-"))
    except ValueError:
        return False
    return True


class _Html(str):
    """Cell content that is already HTML (a link)."""


def _link(href: str, text: str | None = None) -> _Html:
    return _Html(f"<a href='{html.escape(href)}'>{html.escape(text or href)}</a>")


def _any_table(value: Any, caption: str = "") -> str:
    """An HTML table of a value of the report: AccuracyTable, rows of dicts, a dict."""
    if all(hasattr(value, a) for a in ("edges", "n", "n_confident", "accuracy", "accuracy_all")):
        t = value
        rows = [
            [
                f"{t.edges[k]:g}–{t.edges[k + 1]:g}",
                int(t.n[k]),
                int(t.n_confident[k]),
                float(t.accuracy[k]),
                float(t.accuracy_all[k]),
            ]
            for k in range(len(t.n))
        ]
        head = [
            "distance [m]",
            "cells",
            f"confident (p ≥ {t.threshold:g})",
            "accuracy (confident)",
            "accuracy (all)",
        ]
        return _table(head, rows, caption)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, list) and value and isinstance(value[0], dict):
        head = list(value[0])
        return _table(head, [[r.get(h, "") for h in head] for r in value], caption)
    if isinstance(value, dict):
        rows = [[k, _plain_text(v)] for k, v in value.items()]
        return _table(["", "value"], rows, caption, text_columns=(1,))
    return f"<p>{html.escape(caption)}: {html.escape(_plain_text(value))}</p>"


def _plain_text(v: Any) -> Any:
    if isinstance(v, float | int | np.generic | str):
        return v
    if isinstance(v, np.ndarray | list | tuple):
        return ", ".join(_cell(x) for x in np.asarray(v).ravel())
    return json.dumps(v, default=_plain)


_FIGURE_ORDER = ("path", "psd", "profiles", "iso", "classes", "map", "map_class",
                 "map_class_far", "confusion")  # fmt: skip


def _index(
    result: Any,
    out: Path,
    paths: dict[str, Path],
    captions: dict[str, str],
    evaluation: dict | None,
    tables: list[ReportTable],
) -> Path:
    from rough_map._files import atomic_output

    esc = html.escape
    f = result.features
    grid = result.map
    name = result.traverse.name
    body: list[str] = []
    toc: list[tuple[str, str]] = []

    def section(anchor: str, title: str) -> None:
        toc.append((anchor, title))
        body.append(f"<h2 id='{anchor}'>{esc(title)}</h2>")

    section("summary", "Summary")
    rows: list[list[Any]] = [
        ["frames", len(f)],
        ["frames with a valid patch", int(f.valid.sum())],
        ["map", f"{grid.shape[1]} × {grid.shape[0]} cells of {grid.geometry.resolution:g} m"],
    ]
    if result.model is not None and getattr(result.prediction, "mode", None):
        rows.append(["path filter", str(result.prediction.mode)])
    far = result.far_report or {}
    if far:
        rows += [
            ["area seen by the near field", f"{far['near_area_m2']:.1f} m²"],
            ["area with near-to-far", f"{far['near_far_area_m2']:.1f} m²"],
            ["near-to-far area gain", f"×{far['area_ratio']:.1f}"],
        ]
    truth = _truth_accuracy(result)
    if "near_class_accuracy" in truth:
        rows.append(["map class accuracy, near field (simulator truth)",
                     truth["near_class_accuracy"]])  # fmt: skip
    if "far_class_accuracy" in truth:
        rows.append(["map class accuracy, far field (simulator truth)",
                     truth["far_class_accuracy"]])  # fmt: skip
    body.append(_table(["", ""], rows, f"traverse {name}"))
    acc = far.get("far_accuracy_by_distance")
    if acc is not None:
        body.append("<h3>Near-to-far accuracy against distance from the vehicle</h3>")
        body.append(
            _any_table(
                acc,
                "Far-field predictions compared with the simulator's class map, by distance "
                "of the predicted cell from the vehicle; a dash marks an empty bin.",
            )
        )
    for other, value in far.items():
        if other not in ("near_area_m2", "near_far_area_m2", "area_ratio",
                         "far_accuracy_by_distance"):  # fmt: skip
            body.append(f"<h3>{esc(other.replace('_', ' '))}</h3>" + _any_table(value))

    for k, t in enumerate(tables):
        section(f"table-{k + 1}", t.title)
        if t.caption:
            body.append(f"<p class='note'>{esc(t.caption)}</p>")
        body.append(_table(t.head, t.rows))
        body += [f"<p class='note'>{esc(n)}</p>" for n in t.notes]

    if evaluation is not None:
        section("evaluation", "Evaluation against the labels")
        body.append(_evaluation_html(evaluation))

    section("figures", "Figures")
    keys = [k for k in _FIGURE_ORDER if k in paths] + [
        k for k in paths if k not in _FIGURE_ORDER and paths[k].name.startswith("fig_")
    ]
    for n, key in enumerate(keys, start=1):
        p = paths[key]
        size = _png_size(p)
        dims = f" width='{size[0]}' height='{size[1]}'" if size else ""
        caption = captions.get(key, p.stem.removeprefix("fig_").replace("_", " "))
        body.append(
            f"<figure id='fig-{esc(key)}'><a href='{esc(p.name)}'>"
            f"<img src='{esc(p.name)}' alt='{esc(caption)}'{dims}></a>"
            f"<figcaption><b>Figure {n}.</b> {esc(caption)}</figcaption></figure>"
        )

    files = _files_html(out, grid)
    if files:
        section("files", "Files")
        body.append(files)

    head = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>rough_map report: {esc(name)}</title>",
        f"<style>{_CSS}</style>",
        "</head><body>",
        f"<h1>rough_map report: {esc(name)}</h1>",
        "<nav><ul>" + "".join(f"<li><a href='#{a}'>{esc(t)}</a></li>" for a, t in toc) + "</ul>"
        "</nav>",
    ]
    page = "\n".join([*head, *body, "</body></html>\n"])
    path = out / "index.html"
    with atomic_output(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return path


def _truth_accuracy(result: Any) -> dict[str, float]:
    from rough_map.errors import RoughMapError
    from rough_map.workflow import truth_accuracy

    try:
        return truth_accuracy(result)
    except (RoughMapError, OSError, ValueError) as exc:
        log.info("report: no accuracy against the truth: %s", exc)
        return {}


def _evaluation_html(ev: dict) -> str:
    esc = html.escape
    parts = [p for p in ("raw", "filtered") if p in ev]
    names = list(ev[parts[0]]["classes"])
    scored = list(ev.get("scored_classes") or ev[parts[0]].get("scored_classes") or names)
    extra = [c for c in names if c not in scored]
    fr = ev.get("frames", {})
    out = []
    if fr:
        out.append(
            f"<p>Scored {fr.get('scored')} of {fr.get('total')} frames: those with a label and "
            f"a valid patch ({fr.get('unlabelled')} without a label and {fr.get('invalid')} "
            "without a valid patch are skipped).</p>"
        )
    rows = [
        [
            "raw (classifier)" if p == "raw" else f"filtered ({ev.get('mode', '')})",
            ev[p]["accuracy"],
            ev[p]["macro_f1"],
            ev[p]["frames"],
        ]
        for p in parts
    ]
    out.append(_table(["classes", "accuracy", "macro-F1", "frames"], rows))
    note = (
        f"The macro-F1 is the mean F1 over the {len(scored)} classes present in the truth: "
        f"{', '.join(scored)}."
    )
    if extra:
        note += (
            f" Predicted but never true, so not averaged: {', '.join(extra)} (such predictions "
            "lower the recall of the true classes)."
        )
    out.append(f"<p class='note'>{esc(note)}</p>")
    head = ["class", "in macro-F1", "support"]
    for p in parts:
        head += [f"{p} precision", f"{p} recall", f"{p} F1"]
    rows = []
    for c in names:
        row: list[Any] = [c, c in scored, ev[parts[0]]["support"][c]]
        for p in parts:
            row += [ev[p]["precision"][c], ev[p]["recall"][c], ev[p]["f1"][c]]
        rows.append(row)
    out.append(_table(head, rows, "Scores per class (support: scored frames of the class)."))
    for p in parts:
        cm = ev[p]["confusion_matrix"]
        out.append(
            _table(
                ["true \\ predicted", *names],
                [[c, *row] for c, row in zip(names, cm, strict=True)],
                f"Confusion matrix, {p} (frames; rows: true class, columns: predicted).",
            )
        )
    return "".join(out)


def _files_html(out: Path, grid: Any) -> str:
    """Tables of links to the GeoTIFFs, the layer PNGs and the data files in ``out``."""
    from rough_map.export.geotiff import value_layers
    from rough_map.export.png import display_units

    parts = []
    tifs = sorted(out.glob("*.tif"))
    if tifs:
        rows = []
        for p in tifs:
            if p.stem.endswith("_far_class"):
                what = "far-field terrain class (near-to-far), uint8 with a colour table"
            elif p.stem.endswith("_class"):
                what = "terrain class (near field), uint8 class indices with a colour table"
            else:
                what = "float32, one band per value layer: " + ", ".join(value_layers(grid))
            rows.append([_link(p.name), what])
        parts.append(
            _table(
                ["GeoTIFF", "contents"],
                rows,
                "Cloud-Optimized GeoTIFFs of the map (open in QGIS or with rasterio).",
                text_columns=(1,),
            )
        )
    layer_rows = []
    pngs = {p.name: p for p in out.glob("*.png") if not p.name.startswith("fig_")}
    for layer in grid.layers:
        info = grid.info(layer)
        if info.kind == "internal":
            continue
        match = sorted(n for n in pngs if n.endswith(f"_{layer}.png"))
        match = [n for n in match if not any(
            n.endswith(f"_{other}.png") and len(other) > len(layer) and other.endswith(layer)
            for other in grid.layers)]  # fmt: skip
        if match:
            units = display_units(info.units) or ("0–1" if layer.removeprefix("far_")
                                                  .startswith("p_") else "—")  # fmt: skip
            layer_rows.append([_link(match[0]), layer, units, info.description])
    if layer_rows:
        parts.append(
            _table(
                ["PNG", "layer", "units", "what it shows"],
                layer_rows,
                "One picture per map layer, cropped to the cells with data.",
                text_columns=(3,),
            )
        )
    data = []
    for fname, what in (
        ("features.csv", "per-frame features: pose, R, w, σ, validity, label"),
        ("features.csv.json", "what features.csv holds: columns, units, wavenumbers, source"),
        ("labels.csv", "per-frame raw and filtered class with confidence, level, defect flag"),
        ("evaluation.json", "the evaluation: confusion matrices and scores, raw and filtered"),
    ):
        if (out / fname).is_file():
            data.append([_link(fname), what])
    if data:
        parts.append(_table(["file", "contents"], data, "Tables.", text_columns=(1,)))
    return "".join(parts)
