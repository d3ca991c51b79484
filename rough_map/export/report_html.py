"""The report's ``index.html``: the map and figures first, then the summary, extra tables,
evaluation and files.

The page is for a person on a laptop screen: a narrow column (max 1100 px), images that
shrink with the window, numbers in HTML tables (:mod:`rough_map.export.tables`; wide ones
scroll inside their own box, the page never scrolls sideways), a caption under every figure
saying what it shows, and links to the GeoTIFFs, the layer PNGs and the tables in the
folder. ``tools/check_report.py`` opens it in headless Chromium and checks exactly that.
"""

from __future__ import annotations

import html
import logging
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output
from rough_map.errors import RoughMapError
from rough_map.export.geotiff import value_layers
from rough_map.export.layout import display_units
from rough_map.export.report_inputs import AnalysisResult, ReportTable
from rough_map.export.tables import any_table, link, table
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = ["FIGURE_ORDER", "write_index"]

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

#: Order of the figures on the page (by key of the report's paths), the maps first; others
#: follow.
FIGURE_ORDER = ("map_class", "map", "map_class_far", "path", "psd", "profiles", "iso",
                "classes", "confusion")  # fmt: skip

#: Keys of ``far_report`` shown in the summary rows (the others get a table each).
_FAR_SUMMARY = ("near_area_m2", "near_far_area_m2", "area_ratio", "far_accuracy_by_distance")

#: The data files the page links when they are in the folder, with what they hold.
_DATA_FILES = (
    ("features.csv", "per-frame features: pose, R, w, σ, validity, label"),
    ("features.csv.json", "what features.csv holds: columns, units, wavenumbers, source"),
    (
        "labels.csv",
        "per-frame raw and filtered class with confidence, level, defect flag and novelty",
    ),
    ("map_path.geojson", "the path and the frames (R, w, ISO class, class, level) for GIS"),
    ("evaluation.json", "the evaluation: confusion matrices and scores, raw and filtered"),
)


class _Page:
    """The body of the page and its table of contents."""

    def __init__(self) -> None:
        self.body: list[str] = []
        self.toc: list[tuple[str, str]] = []

    def section(self, anchor: str, title: str) -> None:
        self.toc.append((anchor, title))
        self.body.append(f"<h2 id='{anchor}'>{html.escape(title)}</h2>")

    def html(self, name: str) -> str:
        esc = html.escape
        nav = "".join(f"<li><a href='#{a}'>{esc(t)}</a></li>" for a, t in self.toc)
        head = [
            "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
            "<meta name='viewport' content='width=device-width, initial-scale=1'>",
            f"<title>rough_map report: {esc(name)}</title>",
            f"<style>{_CSS}</style>",
            "</head><body>",
            f"<h1>rough_map report: {esc(name)}</h1>",
            f"<nav><ul>{nav}</ul></nav>",
        ]
        return "\n".join([*head, *self.body, "</body></html>\n"])


def write_index(
    result: AnalysisResult,
    out: Path,
    paths: Mapping[str, Path],
    captions: Mapping[str, str],
    evaluation: Mapping[str, Any] | None,
    tables: Sequence[ReportTable],
) -> Path:
    """Write ``out/index.html`` showing the figures in ``paths`` with their captions.

    Returns
    -------
    Path
        The page.
    """
    page = _Page()
    # the map and the figures lead; the tables follow
    page.section("figures", "Map and figures")
    page.body += _figures(paths, captions)
    page.section("summary", "Summary")
    page.body += _summary(result)
    for k, t in enumerate(tables):
        page.section(f"table-{k + 1}", t.title)
        if t.caption:
            page.body.append(f"<p class='note'>{html.escape(t.caption)}</p>")
        page.body.append(table(t.head, t.rows))
        page.body += [f"<p class='note'>{html.escape(n)}</p>" for n in t.notes]
    if evaluation is not None:
        page.section("evaluation", "Evaluation against the labels")
        page.body.append(_evaluation_html(evaluation))
    files = _files_html(out, result.map)
    if files:
        page.section("files", "Files")
        page.body.append(files)
    path = out / "index.html"
    with atomic_output(path) as tmp:
        Path(tmp).write_text(page.html(result.traverse.name), encoding="utf-8")
    return path


def _summary(result: AnalysisResult) -> list[str]:
    """The summary table, then the near-to-far tables."""
    f, grid = result.features, result.map
    rows: list[list[Any]] = [
        ["frames", len(f)],
        ["frames with a valid patch", int(f.valid.sum())],
        ["map", f"{grid.shape[1]} × {grid.shape[0]} cells of {grid.geometry.resolution:g} m"],
    ]
    mode = getattr(result.prediction, "mode", None)
    if result.model is not None and mode:
        rows.append(["path filter", str(mode)])
    novelty = None if result.prediction is None else result.prediction.novelty
    if novelty is not None and np.isfinite(novelty).any():
        n_novel = int(np.sum(np.asarray(novelty)[np.isfinite(novelty)] > 1))
        rows.append(
            [
                "frames unlike every trained class (novelty above 1)",
                f"{n_novel} of {int(np.isfinite(novelty).sum())}: their class is the nearest one",
            ]
        )
    far = result.far_report or {}
    if far:
        rows += [
            ["area seen by the near field", f"{far['near_area_m2']:.1f} m²"],
            ["area with near-to-far", f"{far['near_far_area_m2']:.1f} m²"],
            ["near-to-far area gain", f"×{far['area_ratio']:.1f}"],
        ]
    truth = _truth_accuracy(result)
    for key, field in (("near", "near_class_accuracy"), ("far", "far_class_accuracy")):
        if field in truth:
            rows.append([f"map class accuracy, {key} field (simulator truth)", truth[field]])
    out = [table(["", ""], rows, f"traverse {result.traverse.name}")]
    acc = far.get("far_accuracy_by_distance")
    if acc is not None:
        out.append("<h3>Near-to-far accuracy against distance from the vehicle</h3>")
        out.append(
            any_table(
                acc,
                "Far-field predictions compared with the simulator's class map, by distance "
                "of the predicted cell from the vehicle; a dash marks an empty bin.",
            )
        )
    for other, value in far.items():
        if other not in _FAR_SUMMARY:
            out.append(f"<h3>{html.escape(other.replace('_', ' '))}</h3>" + any_table(value))
    return out


def _truth_accuracy(result: AnalysisResult) -> Mapping[str, float]:
    try:
        return result.truth_accuracy()
    except (RoughMapError, OSError, ValueError) as exc:
        log.info("report: no accuracy against the truth: %s", exc)
        return {}


def _png_size(path: Path) -> tuple[int, int] | None:
    try:
        head = path.read_bytes()[:24]
    except OSError:
        return None
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


def _figures(paths: Mapping[str, Path], captions: Mapping[str, str]) -> list[str]:
    """Numbered ``<figure>``s with captions, in :data:`FIGURE_ORDER`."""
    esc = html.escape
    keys = [k for k in FIGURE_ORDER if k in paths] + [
        k for k in paths if k not in FIGURE_ORDER and paths[k].name.startswith("fig_")
    ]
    out = []
    for n, key in enumerate(keys, start=1):
        p = paths[key]
        size = _png_size(p)
        dims = f" width='{size[0]}' height='{size[1]}'" if size else ""
        caption = captions.get(key, p.stem.removeprefix("fig_").replace("_", " "))
        out.append(
            f"<figure id='fig-{esc(key)}'><a href='{esc(p.name)}'>"
            f"<img src='{esc(p.name)}' alt='{esc(caption)}'{dims}></a>"
            f"<figcaption><b>Figure {n}.</b> {esc(caption)}</figcaption></figure>"
        )
    return out


def _evaluation_html(ev: Mapping[str, Any]) -> str:
    """Scores, the classes the macro-F1 averages, scores per class, confusion matrices."""
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
    out.append(table(["classes", "accuracy", "macro-F1", "frames"], rows))
    note = (
        f"The macro-F1 is the mean F1 over the {len(scored)} classes present in the truth: "
        f"{', '.join(scored)}."
    )
    if extra:
        note += (
            f" Predicted but never true, so not averaged: {', '.join(extra)} (such predictions "
            "lower the recall of the true classes)."
        )
    out.append(f"<p class='note'>{html.escape(note)}</p>")
    out.append(_per_class_html(ev, parts, names, scored))
    for p in parts:
        cm = ev[p]["confusion_matrix"]
        out.append(
            table(
                ["true \\ predicted", *names],
                [[c, *row] for c, row in zip(names, cm, strict=True)],
                f"Confusion matrix, {p} (frames; rows: true class, columns: predicted).",
            )
        )
    return "".join(out)


def _per_class_html(
    ev: Mapping[str, Any], parts: list[str], names: list[str], scored: list[str]
) -> str:
    head = ["class", "in macro-F1", "support"]
    for p in parts:
        head += [f"{p} precision", f"{p} recall", f"{p} F1"]
    rows = []
    for c in names:
        row: list[Any] = [c, c in scored, ev[parts[0]]["support"][c]]
        for p in parts:
            row += [ev[p]["precision"][c], ev[p]["recall"][c], ev[p]["f1"][c]]
        rows.append(row)
    return table(head, rows, "Scores per class (support: scored frames of the class).")


def _files_html(out: Path, grid: GridMap) -> str:
    """Tables of links to the GeoTIFFs, the layer PNGs and the data files in ``out``."""
    parts = [_geotiff_table(out, grid), _layer_png_table(out, grid)]
    data = [[link(name), what] for name, what in _DATA_FILES if (out / name).is_file()]
    if data:
        parts.append(table(["file", "contents"], data, "Tables.", text_columns=(1,)))
    return "".join(parts)


def _geotiff_table(out: Path, grid: GridMap) -> str:
    rows = []
    for p in sorted(out.glob("*.tif")):
        if p.stem.endswith("_far_class"):
            what = "far-field terrain class (near-to-far), uint8 with a colour table"
        elif p.stem.endswith("_class"):
            what = "terrain class (near field), uint8 class indices with a colour table"
        else:
            what = "float32, one band per value layer: " + ", ".join(value_layers(grid))
        rows.append([link(p.name), what])
    if not rows:
        return ""
    return table(
        ["GeoTIFF", "contents"],
        rows,
        "Cloud-Optimized GeoTIFFs of the map (open in QGIS or with rasterio).",
        text_columns=(1,),
    )


def _layer_png(pngs: list[str], layer: str, layers: Sequence[str]) -> str | None:
    """The PNG of ``layer`` among ``pngs`` (not that of a longer layer name ending alike)."""
    match = [
        n
        for n in sorted(n for n in pngs if n.endswith(f"_{layer}.png"))
        if not any(
            n.endswith(f"_{other}.png") and len(other) > len(layer) and other.endswith(layer)
            for other in layers
        )
    ]
    return match[0] if match else None


def _layer_png_table(out: Path, grid: GridMap) -> str:
    rows = []
    pngs = [p.name for p in out.glob("*.png") if not p.name.startswith("fig_")]
    for layer in grid.layers:
        info = grid.info(layer)
        if info.kind == "internal":
            continue
        name = _layer_png(pngs, layer, list(grid.layers))
        if name is not None:
            probability = layer.removeprefix("far_").startswith("p_")
            units = display_units(info.units) or ("0–1" if probability else "—")
            rows.append([link(name), layer, units, info.description])
    if not rows:
        return ""
    return table(
        ["PNG", "layer", "units", "what it shows"],
        rows,
        "One picture per map layer, cropped to the cells with data.",
        text_columns=(3,),
    )
