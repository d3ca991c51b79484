"""The layout of map pictures: maps at 1:1 aspect, each with its keys in a band under it.

:func:`draw_map_panels` draws one or more :class:`MapPanel` stacked vertically on a
matplotlib :class:`~matplotlib.figure.Figure` with its own Agg canvas (pyplot is never
used, so the caller's backend is left alone). Every map is drawn at its true aspect
(1 m east = 1 m north) in its view; nothing is drawn over the data: the scale bar, the
vehicle path's key and the colour key sit in a band under the map. Continuous data get a
horizontal colour bar, class data a legend of colour patches in as many columns as fit the
width, so that long class names never overlap. Unknown cells (NaN) are transparent over a
light grey background.

Used by :mod:`rough_map.export.png` (one PNG per layer) and
:func:`rough_map.export.figures.map_layers` (the report's map figures). matplotlib is
imported only when something is drawn.
"""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from rough_map.errors import InputError

__all__ = [
    "MapPanel",
    "data_view",
    "display_units",
    "draw_map_panels",
    "drawn_texts",
    "drawn_texts_of_axis",
    "scale_bar_length",
]

_BACKGROUND = (0.93, 0.93, 0.93)
_FONT = 9.0  # pt: ticks, keys
_TITLE_FONT = 10.0  # pt
_LEFT = 0.85  # in: y tick labels and y label
_RIGHT = 0.3  # in
_MIN_MAP_H = 0.9  # in: thinner maps get a taller view (some blank above and below)
_TICKS_H = 0.5  # in: x tick labels and x label under a map
_SCALE_H = 0.36  # in: the row of the scale bar and the path key
_BAR_H = 0.14  # in: a horizontal colour bar
_GAP = 0.3  # in: between panels
_SUPERSCRIPTS = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")

_LEGEND_KW: dict[str, Any] = {
    "frameon": False,
    "fontsize": _FONT,
    "borderaxespad": 0.0,
    "borderpad": 0.0,
    "handlelength": 1.4,
    "handleheight": 1.0,
    "columnspacing": 1.4,
    "labelspacing": 0.45,
}


def scale_bar_length(span: float) -> float:
    """A round length in m (1, 2 or 5 x 10^k) of at most a quarter of ``span`` m."""
    if not (math.isfinite(span) and span > 0):
        raise InputError(f"span must be a positive length in m, got {span!r}")
    target = span / 4
    base = 10 ** math.floor(math.log10(target))
    return max(m * base for m in (1, 2, 5) if m * base <= target)


def display_units(units: str) -> str:
    """Units as a person reads them: ``m^3/rad`` -> ``m³/rad``; ``"1"`` (none) -> ``""``."""
    if units.strip() in ("", "1"):
        return ""
    return re.sub(r"\^(-?\d+)", lambda m: m.group(1).translate(_SUPERSCRIPTS), units)


def data_view(
    mask: np.ndarray, extent: Sequence[float], *, margin: float = 0.03
) -> tuple[float, float, float, float]:
    """The part of ``extent`` (x_min, x_max, y_min, y_max; m) where ``mask`` is true.

    ``mask`` has row 0 at y_min. The box of the true cells is padded by ``margin`` of its
    larger side (at least two cells) and clipped to ``extent``; all of ``extent`` when no
    cell is true.
    """
    x0, x1, y0, y1 = (float(v) for v in extent)
    mask = np.asarray(mask, dtype=bool)
    # the rows and columns holding a true cell (not the indices of every true cell: a long
    # map has millions)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return x0, x1, y0, y1
    ny, nx = mask.shape
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    vx0, vx1 = x0 + cols[0] * dx, x0 + (cols[-1] + 1) * dx
    vy0, vy1 = y0 + rows[0] * dy, y0 + (rows[-1] + 1) * dy
    pad = max(2 * max(dx, dy), margin * max(vx1 - vx0, vy1 - vy0))
    vx0, vx1, vy0, vy1 = vx0 - pad, vx1 + pad, vy0 - pad, vy1 + pad
    # a few known cells: show 20 cells around them, not one cell as a huge square
    least = 20 * max(dx, dy)
    if max(vx1 - vx0, vy1 - vy0) < least:
        vx0, vx1 = (vx0 + vx1 - least) / 2, (vx0 + vx1 + least) / 2
        vy0, vy1 = (vy0 + vy1 - least) / 2, (vy0 + vy1 + least) / 2
    return max(x0, vx0), min(x1, vx1), max(y0, vy0), min(y1, vy1)


def _axis_origin(lo: float, hi: float) -> float:
    """A round number to subtract from large coordinates (UTM) on an axis, else 0."""
    if max(abs(lo), abs(hi)) < 1e4:
        return 0.0
    step = 10 ** max(2, math.ceil(math.log10(max(hi - lo, 1e-9))))
    return math.floor(lo / step) * step


@dataclass
class MapPanel:
    """One map to draw (:func:`draw_map_panels`).

    Attributes
    ----------
    data : ndarray, shape (rows, cols)
        Values, row 0 at the southern edge; NaN is unknown (transparent).
    extent : (float, float, float, float)
        ``(x_min, x_max, y_min, y_max)`` of ``data``, m.
    title : str
        Title above the map.
    label : str
        Colour-bar label with units (continuous data).
    cmap : str or Colormap
        Colour map of continuous data.
    norm : Normalize, optional
        Colour scale of continuous data (default: the data's range).
    categories : tuple of str
        Names of the values 0, 1, ... of class data (drawn with a legend of patches).
    colours : sequence of RGB
        Colour (0–1) per category.
    view : (float, float, float, float), optional
        Area to show, as ``extent``; default where ``data`` is finite (:func:`data_view`).
    track : ndarray, shape (n, 2), optional
        Vehicle path (x, y), m.
    """

    data: np.ndarray
    extent: tuple[float, float, float, float]
    title: str = ""
    label: str = ""
    cmap: Any = "viridis"
    norm: Any = None
    categories: tuple[str, ...] = ()
    colours: Sequence[Sequence[float]] = ()
    view: tuple[float, float, float, float] | None = None
    track: np.ndarray | None = None


def _fit_view(
    view: tuple[float, float, float, float], avail_w: float, max_h: float
) -> tuple[tuple[float, float, float, float], float, float]:
    """The view and the map's size (in) at 1:1 aspect, at most ``avail_w`` x ``max_h``."""
    x0, x1, y0, y1 = view
    sx, sy = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
    w = avail_w
    h = w * sy / sx
    if h > max_h:
        h, w = max_h, max_h * sx / sy
    if h < _MIN_MAP_H:
        extra = (_MIN_MAP_H * sx / w - sy) / 2
        y0, y1, h = y0 - extra, y1 + extra, _MIN_MAP_H
    return (x0, x1, y0, y1), w, h


def _legend_handles(panel: MapPanel) -> list[Any]:
    from matplotlib.patches import Patch

    colours: list[Any] = [tuple(c) for c in panel.colours]
    return [
        Patch(facecolor=c, edgecolor="0.35", linewidth=0.5, label=name)
        for name, c in zip(panel.categories, colours, strict=True)
    ]


def _legend_fit(panel: MapPanel, avail_w: float, dpi: float) -> tuple[int, float]:
    """Columns of the class legend that fit ``avail_w`` in, and its height (in)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    k = len(panel.categories)
    longest = max(len(c) for c in panel.categories)
    ncol = max(1, min(k, int(avail_w / (0.45 + 0.075 * longest))))
    while True:
        scratch = Figure(figsize=(avail_w + 1, 8), dpi=dpi)
        canvas = FigureCanvasAgg(scratch)
        leg = scratch.legend(handles=_legend_handles(panel), ncol=ncol, **_LEGEND_KW)
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


def _colour_scale(panel: MapPanel) -> tuple[Any, Any]:
    from matplotlib import colormaps
    from matplotlib.colors import BoundaryNorm, Colormap, ListedColormap, Normalize

    cmap: Colormap
    if panel.categories:
        k = len(panel.categories)
        cmap = ListedColormap([tuple(c) for c in panel.colours])
        norm: Any = BoundaryNorm(np.arange(-0.5, k + 0.5), k)
    else:
        cmap = colormaps[panel.cmap] if isinstance(panel.cmap, str) else panel.cmap
        norm = panel.norm
        if norm is None:
            finite = panel.data[np.isfinite(panel.data)]
            lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
            norm = Normalize(lo, hi if hi > lo else lo + 1)
    return cmap.with_extremes(bad=(1, 1, 1, 0)), norm


def _colour_bar(fig: Any, cax: Any, image: Any, panel: MapPanel, bar_w: float) -> None:
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FixedLocator, LogFormatterSciNotation, MaxNLocator

    bar = fig.colorbar(image, cax=cax, orientation="horizontal")
    norm = image.norm
    if isinstance(norm, LogNorm):
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
        finite = panel.data[np.isfinite(panel.data)]
        whole = bool(finite.size) and bool(np.all(finite == np.round(finite)))
        nbins = max(2, int(bar_w / 0.9))
        bar.ax.xaxis.set_major_locator(MaxNLocator(nbins=nbins, integer=whole))
    bar.ax.tick_params(labelsize=_FONT)
    bar.set_label(panel.label, fontsize=_FONT)
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


def drawn_texts(fig: Any) -> list[Any]:
    """Every non-empty text a figure draws: titles, axis and tick labels, legends, notes."""
    texts: list[Any] = []
    for ax in fig.axes:
        if not ax.get_visible():
            continue
        texts += [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label]
        texts += [ax.xaxis.offsetText, ax.yaxis.offsetText]
        if ax.xaxis.get_visible():
            texts += drawn_texts_of_axis(ax.xaxis)
        if ax.yaxis.get_visible():
            texts += drawn_texts_of_axis(ax.yaxis)
        texts += list(ax.texts)
        if ax.get_legend() is not None:
            texts += [*ax.get_legend().get_texts(), ax.get_legend().get_title()]
    for leg in fig.legends:
        texts += [*leg.get_texts(), leg.get_title()]
    texts += list(fig.texts)
    return [t for t in texts if t.get_visible() and t.get_text().strip()]


@dataclass
class _Plan:
    """Where one panel goes: its data, view, map size (in) and band heights (in)."""

    panel: MapPanel
    data: np.ndarray
    view: tuple[float, float, float, float]
    map_w: float
    map_h: float
    title: str
    ncol: int
    title_h: float
    key_h: float

    @property
    def height(self) -> float:
        """Height of the panel with its title and key band, in."""
        return self.title_h + self.map_h + _TICKS_H + _SCALE_H + self.key_h


def _plan(p: MapPanel, avail_w: float, max_h: float, chars: int, dpi: float) -> _Plan:
    data = np.asarray(p.data, dtype=float)
    view = p.view or data_view(np.isfinite(data), p.extent)
    view, map_w, map_h = _fit_view(view, avail_w, max_h)
    title = "\n".join(textwrap.wrap(p.title, chars)) if p.title else ""
    title_h = 0.12 + 0.2 * (title.count("\n") + 1) if title else 0.15
    if p.categories:
        ncol, key_h = _legend_fit(p, avail_w, dpi)
    else:
        ncol, key_h = 0, _BAR_H + 0.5
    return _Plan(p, data, view, map_w, map_h, title, ncol, title_h, key_h)


def _draw_map(fig: Any, pl: _Plan, map_top: float, track_colour: str) -> Any:
    """The map's axes (x/y in m, large coordinates from a round origin); returns the image."""
    from matplotlib.ticker import FuncFormatter

    width, total = fig.get_size_inches()
    p, view = pl.panel, pl.view
    rect = (_LEFT / width, (map_top - pl.map_h) / total, pl.map_w / width, pl.map_h / total)
    ax = fig.add_axes(rect)
    ax.set_facecolor(_BACKGROUND)
    cmap, norm = _colour_scale(p)
    # NaN cells are masked (transparent) by imshow itself, which copies the data anyway.
    # Sampling the nearest cell of each pixel and then colouring it ("data") gives the
    # picture that colouring every cell and then sampling ("rgba", matplotlib's choice for
    # a map of more cells than pixels) gives, without two RGBA copies of the whole map (64
    # bytes a cell: 35 MB for a 1.8 km strip)
    image = ax.imshow(
        pl.data,
        origin="lower",
        extent=p.extent,
        cmap=cmap,
        norm=norm,
        interpolation="nearest",
        interpolation_stage="data",
    )
    if p.track is not None and len(p.track):
        tr = np.asarray(p.track, dtype=float)
        ax.plot(tr[:, 0], tr[:, 1], color=track_colour, lw=1.2)
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal", adjustable="box")
    ax.tick_params(labelsize=_FONT)
    # large (UTM) coordinates: ticks from a round origin, which the label names
    ox, oy = _axis_origin(view[0], view[1]), _axis_origin(view[2], view[3])
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _, o=ox: f"{v - o:g}"))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _, o=oy: f"{v - o:g}"))
    ax.set_xlabel(f"x (east) − {ox:.0f} [m]" if ox else "x (east) [m]", fontsize=_FONT)
    ax.set_ylabel(f"y − {oy:.0f} [m]" if oy else "y [m]", fontsize=_FONT)
    if pl.title:
        ax.set_title(pl.title, fontsize=_TITLE_FONT)
    return image


def _draw_scale_and_path(fig: Any, pl: _Plan, y: float, track_colour: str) -> None:
    """The scale bar and (with a track) the vehicle path's key on the row at ``y`` in."""
    from matplotlib.lines import Line2D

    inches = fig.dpi_scale_trans
    view = pl.view
    length = scale_bar_length(view[1] - view[0])
    bar_in = length * pl.map_w / (view[1] - view[0])
    for artist in (
        Line2D([_LEFT, _LEFT + bar_in], [y] * 2, lw=3, color="k", solid_capstyle="butt"),
        Line2D([_LEFT] * 2, [y - 0.06, y + 0.06], lw=1, color="k"),
        Line2D([_LEFT + bar_in] * 2, [y - 0.06, y + 0.06], lw=1, color="k"),
    ):
        artist.set_transform(inches)
        artist.set_gid("scale-bar")
        fig.add_artist(artist)
    text_kw: dict[str, Any] = {"transform": inches, "va": "center", "fontsize": _FONT}
    fig.text(_LEFT + bar_in + 0.1, y, f"{length:g} m", gid="scale-bar", **text_kw)
    track = pl.panel.track
    if track is not None and len(track):
        x_path = _LEFT + bar_in + 1.0
        line = Line2D([x_path, x_path + 0.4], [y] * 2, lw=1.2, color=track_colour)
        line.set_transform(inches)
        line.set_gid("path-key")
        fig.add_artist(line)
        fig.text(x_path + 0.5, y, "vehicle path", gid="path-key", **text_kw)


def _draw_key(fig: Any, pl: _Plan, image: Any, key_top: float, avail_w: float) -> None:
    """The class legend or the colour bar, its top at ``key_top`` in."""
    width, total = fig.get_size_inches()
    if pl.panel.categories:
        fig.legend(
            handles=_legend_handles(pl.panel),
            loc="upper left",
            bbox_to_anchor=(_LEFT, key_top),
            bbox_transform=fig.dpi_scale_trans,
            ncol=pl.ncol,
            **_LEGEND_KW,
        )
    else:
        bar_w = min(avail_w, 4.5)
        rect = (_LEFT / width, (key_top - _BAR_H) / total, bar_w / width, _BAR_H / total)
        _colour_bar(fig, fig.add_axes(rect), image, pl.panel, bar_w)


def draw_map_panels(
    panels: Sequence[MapPanel],
    *,
    width: float = 8.0,
    dpi: float = 120,
    max_map_height: float = 5.4,
    track_colour: str = "tab:blue",
) -> Any:
    """A figure of maps stacked vertically, each with its key under it.

    Every map is drawn at 1:1 aspect in its view, with x/y axes in m; under it, a scale
    bar, the vehicle path's key (when a track is given) and a horizontal colour bar
    (continuous data) or a legend of colour patches in as many columns as fit (classes).

    Parameters
    ----------
    panels : sequence of MapPanel
        The maps, top first.
    width : float
        Figure width, in.
    dpi : float
        Resolution, dots per in.
    max_map_height : float
        Largest height of one map, in.
    track_colour : str
        Colour of the vehicle path.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (with an Agg canvas).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not panels:
        raise InputError("no map to draw")
    avail_w = width - _LEFT - _RIGHT
    chars = max(20, int((width - 0.3) * 72 / (_TITLE_FONT * 0.56)))
    plans = [_plan(p, avail_w, max_map_height, chars, dpi) for p in panels]
    total = 0.1 + sum(pl.height for pl in plans) + _GAP * (len(plans) - 1) + 0.15
    fig = Figure(figsize=(width, total), dpi=dpi)
    FigureCanvasAgg(fig)
    top = total - 0.1  # running top edge, in from the bottom
    for pl in plans:
        map_top = top - pl.title_h
        image = _draw_map(fig, pl, map_top, track_colour)
        # the key band under the map: scale bar, vehicle path, colour bar or class legend
        band_top = map_top - pl.map_h - _TICKS_H
        _draw_scale_and_path(fig, pl, band_top - _SCALE_H / 2, track_colour)
        _draw_key(fig, pl, image, band_top - _SCALE_H, avail_w)
        top -= pl.height + _GAP
    return fig
