"""The keys of a map picture: colour bars and class legends.

* continuous data get a horizontal colour bar: decades on a logarithmic scale (R also with
  the ISO 8608 class boundaries and letters), shares on 0–1, discrete levels (counts) with
  a tick per level, other data round ticks;
* class data get a legend of colour patches in as many columns as fit the width.

Used by :mod:`rough_map.export.layout`; matplotlib is imported only when something is drawn.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import pairwise
from typing import Any, cast

import numpy as np

from rough_map import iso8608

__all__ = [
    "FONT",
    "LEGEND_KW",
    "colour_bar",
    "colour_scale",
    "drawn_texts_of_axis",
    "legend_fit",
    "legend_handles",
]

FONT = 9.0  # pt: ticks, keys

LEGEND_KW: dict[str, Any] = {
    "frameon": False,
    "fontsize": FONT,
    "borderaxespad": 0.0,
    "borderpad": 0.0,
    "handlelength": 1.4,
    "handleheight": 1.0,
    "columnspacing": 1.4,
    "labelspacing": 0.45,
}


def legend_handles(categories: Sequence[str], colours: Sequence[Sequence[float]]) -> list[Any]:
    """Colour patches, one per category, for a legend."""
    from matplotlib.patches import Patch

    return [
        Patch(facecolor=cast(Any, tuple(c)), edgecolor="0.35", linewidth=0.5, label=name)
        for name, c in zip(categories, colours, strict=True)
    ]


def legend_fit(
    categories: Sequence[str], colours: Sequence[Sequence[float]], avail_w: float, dpi: float
) -> tuple[int, float]:
    """Columns of the class legend that fit ``avail_w`` in, and its height (in)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    k = len(categories)
    longest = max(len(c) for c in categories)
    ncol = max(1, min(k, int(avail_w / (0.45 + 0.075 * longest))))
    while True:
        scratch = Figure(figsize=(avail_w + 1, 8), dpi=dpi)
        canvas = FigureCanvasAgg(scratch)
        leg = scratch.legend(handles=legend_handles(categories, colours), ncol=ncol, **LEGEND_KW)
        box = leg.get_window_extent(canvas.get_renderer())
        width, height = box.width / dpi, box.height / dpi
        if width <= avail_w or ncol == 1:
            return ncol, height
        ncol -= 1


def _log_ticks(lo: float, hi: float) -> list[float]:
    decades = [10.0**k for k in range(math.ceil(math.log10(lo)), math.floor(math.log10(hi)) + 1)]
    if len(decades) >= 2:
        return decades
    return sorted({float(f"{v:.2g}") for v in np.geomspace(lo, hi, 4)})


def colour_scale(
    data: np.ndarray,
    cmap: Any,
    norm: Any,
    categories: Sequence[str] = (),
    colours: Sequence[Sequence[float]] = (),
) -> tuple[Any, Any]:
    """The colour map and norm of a map: one colour per category, or ``cmap`` (a name or a
    Colormap) on ``norm`` (default the data's range); NaN is transparent."""
    from matplotlib import colormaps
    from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize

    if categories:
        k = len(categories)
        cmap = ListedColormap([tuple(c) for c in colours])
        norm = BoundaryNorm(np.arange(-0.5, k + 0.5), k)
    else:
        cmap = colormaps[cmap] if isinstance(cmap, str) else cmap
        if norm is None:
            finite = data[np.isfinite(data)]
            lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
            norm = Normalize(lo, hi if hi > lo else lo + 1)
    return cmap.with_extremes(bad=(1, 1, 1, 0)), norm


def _iso_marks(cax: Any, lo: float, hi: float) -> None:
    """ISO 8608 class boundaries (white lines) across a log colour bar of R, and the class
    letters above it at each class's centre (:mod:`rough_map.iso8608`)."""
    from matplotlib.transforms import blended_transform_factory

    on_bar = blended_transform_factory(cax.transData, cax.transAxes)
    for c in iso8608.CLASSES[1:]:
        if lo < iso8608.LOWER[c] < hi:
            cax.axvline(iso8608.LOWER[c], color="white", lw=0.9, gid="iso-class")
    for i, c in enumerate(iso8608.CLASSES):
        upper = iso8608.LOWER[iso8608.CLASSES[i + 1]] if i + 1 < len(iso8608.CLASSES) else hi
        left, right = max(lo, iso8608.LOWER[c] or lo), min(hi, upper)
        if right / left > 1.6:  # room for the letter
            cax.text(math.sqrt(left * right), 1.08, c, transform=on_bar, ha="center",
                     va="bottom", fontsize=FONT - 1, gid="iso-class")  # fmt: skip


def colour_bar(
    fig: Any, cax: Any, image: Any, data: np.ndarray, label: str, bar_w: float,
    iso_classes: bool = False,
) -> None:  # fmt: skip
    """A horizontal colour bar of ``image`` in ``cax`` (``bar_w`` in wide): decades on a log
    scale (with the ISO 8608 classes of R when ``iso_classes``), a tick per level of
    discrete levels, 0–1 in quarters for shares, else round ticks (whole numbers for whole
    data); tick labels are thinned until none touch."""
    from matplotlib.colors import BoundaryNorm, LogNorm
    from matplotlib.ticker import FixedLocator, LogFormatterSciNotation, MaxNLocator

    bar = fig.colorbar(image, cax=cax, orientation="horizontal")
    norm = image.norm
    if isinstance(norm, BoundaryNorm):  # discrete levels: a tick per level, at its centre
        edges = np.asarray(norm.boundaries, dtype=float)
        centres = (edges[:-1] + edges[1:]) / 2
        step = edges[1] - edges[0] if len(edges) > 1 else 1.0
        bar.set_ticks(list(centres))
        if step == 1:
            bar.set_ticklabels([f"{c:.0f}" for c in centres])
        else:
            bar.set_ticklabels([f"{a + 0.5:.0f}–{b - 0.5:.0f}" for a, b in pairwise(edges)])
        bar.ax.xaxis.set_minor_locator(FixedLocator([]))
    elif isinstance(norm, LogNorm):
        ticks = _log_ticks(cast(float, norm.vmin), cast(float, norm.vmax))
        bar.set_ticks(ticks)
        if all(math.log10(t).is_integer() for t in ticks):
            bar.ax.xaxis.set_major_formatter(LogFormatterSciNotation())
        else:
            bar.set_ticklabels([f"{t:.2g}" for t in ticks])
        bar.ax.xaxis.set_minor_locator(FixedLocator([]))
    elif norm.vmin == 0.0 and norm.vmax == 1.0:
        bar.set_ticks([0.0, 0.25, 0.5, 0.75, 1.0])
    else:
        finite = data[np.isfinite(data)]
        whole = bool(finite.size) and bool(np.all(finite == np.round(finite)))
        nbins = max(2, int(bar_w / 0.9))
        bar.ax.xaxis.set_major_locator(MaxNLocator(nbins=nbins, integer=whole))
    if iso_classes and isinstance(norm, LogNorm):
        _iso_marks(bar.ax, cast(float, norm.vmin), cast(float, norm.vmax))
    bar.ax.tick_params(labelsize=FONT)
    label += "; letters: ISO 8608 classes" if iso_classes else ""
    bar.set_label(label, fontsize=FONT)
    # the last guard: drop every other tick label while any two of them touch
    renderer = fig.canvas.get_renderer()
    for _ in range(4):
        labels = drawn_texts_of_axis(bar.ax.xaxis)
        boxes = [t.get_window_extent(renderer) for t in labels]
        if not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :]):
            break
        locs = bar.ax.xaxis.get_majorticklocs()
        bar.set_ticks(list(locs[::2]))


def drawn_texts_of_axis(axis: Any) -> list[Any]:
    """The tick labels an axis draws (inside its view, visible, not empty)."""
    out = []
    for tick in axis._update_ticks():
        out += [t for t in (tick.label1, tick.label2) if t.get_visible() and t.get_text().strip()]
    return out
