"""The layout of map pictures: maps at 1:1 aspect, each with its keys in a band under it.

:func:`draw_map_panels` draws one or more :class:`MapPanel` stacked vertically on a
matplotlib :class:`~matplotlib.figure.Figure` with its own Agg canvas (pyplot is never
used, so the caller's backend is left alone). Every map is drawn at its true aspect
(1 m east = 1 m north) in its view; a long map (a traverse's thin strip) is cut into pages
along the path (:mod:`rough_map.export.pages`), drawn under each other at one scale.
Nothing is drawn over the data but a thin vehicle path: the scale bar, the path's key and
the colour key sit in a band under the map (under its last page). Continuous data get a
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
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.export.keys import (
    FONT,
    LEGEND_KW,
    colour_bar,
    colour_scale,
    drawn_texts_of_axis,
    legend_fit,
    legend_handles,
)
from rough_map.export.pages import page_views

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
_TITLEFONT = 10.0  # pt
_LEFT = 0.85  # in: y tick labels and y label
_RIGHT = 0.3  # in
_MIN_MAP_H = 0.9  # in: thinner maps get a taller view (some blank above and below)
_TICKS_H = 0.5  # in: x tick labels and x label under a map
_SCALE_H = 0.36  # in: the row of the scale bar and the path key
_BAR_H = 0.14  # in: a horizontal colour bar
_ISO_H = 0.16  # in: the ISO 8608 class letters above a colour bar of R
_GAP = 0.3  # in: between panels
_SUPERSCRIPTS = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


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
    known : ndarray of bool, optional
        Cells that decide the view and the pages (default where ``data`` is finite).
    key : bool
        Draw the key band (scale bar, path key, colour key) under the map; the pages of a
        map but the last have none.
    scale : float, optional
        Drawing scale, in per m (default: the largest that fits).
    iso_classes : bool
        Mark the ISO 8608 classes (A–H boundaries of R, m³/rad) on the colour bar.
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
    known: np.ndarray | None = None
    key: bool = True
    scale: float | None = None
    iso_classes: bool = False


def _largest_scale(view: Sequence[float], avail_w: float, max_h: float) -> float:
    """The largest scale (in per m) that fits ``view`` in ``avail_w`` x ``max_h`` in."""
    x0, x1, y0, y1 = view
    return min(avail_w / max(x1 - x0, 1e-9), max_h / max(y1 - y0, 1e-9))


def _fit_view(
    view: tuple[float, float, float, float],
    avail_w: float,
    max_h: float,
    scale: float | None = None,
) -> tuple[tuple[float, float, float, float], float, float]:
    """The view and the map's size (in) at 1:1 aspect, at most ``avail_w`` x ``max_h`` (at
    ``scale`` in per m when given); a thin view is widened to the least map height."""
    x0, x1, y0, y1 = view
    sx, sy = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
    scale = scale or _largest_scale(view, avail_w, max_h)
    w, h = sx * scale, sy * scale
    if h < _MIN_MAP_H:
        extra = (_MIN_MAP_H / scale - sy) / 2
        y0, y1, h = y0 - extra, y1 + extra, _MIN_MAP_H
    return (x0, x1, y0, y1), w, h


def _paged(
    panels: Sequence[MapPanel], avail_w: float, max_h: float, page_length: float | None,
    max_pages: int,
) -> list[MapPanel]:  # fmt: skip
    """The panels with each long map cut into pages along the path (:func:`page_views`),
    all pages of a map at one scale, the key band under its last page only."""
    out: list[MapPanel] = []
    for p in panels:
        known = np.isfinite(np.asarray(p.data, dtype=float)) if p.known is None else p.known
        view = p.view or data_view(known, p.extent)
        if page_length is None:
            out.append(replace(p, view=view))
            continue
        pages = page_views(
            known, p.extent, view, p.track, page_length=page_length, max_pages=max_pages
        )
        if len(pages) == 1:
            out.append(replace(p, view=view))
            continue
        scale = min(_largest_scale(pg.view, avail_w, max_h) for pg in pages)
        n = len(pages)
        for k, pg in enumerate(pages):
            title = f"{p.title} ({pg.label(k, n)})" if k == 0 else pg.label(k, n)
            out.append(replace(p, view=pg.view, title=title, key=k == n - 1, scale=scale))
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
        band = _SCALE_H + self.key_h if self.panel.key else 0.0
        return self.title_h + self.map_h + _TICKS_H + band

    @property
    def gap(self) -> float:
        """Space under the panel, in: less between the pages of one map."""
        return _GAP if self.panel.key else 0.1


def _plan(p: MapPanel, avail_w: float, max_h: float, chars: int, dpi: float) -> _Plan:
    data = np.asarray(p.data, dtype=float)
    view = p.view or data_view(np.isfinite(data), p.extent)
    view, map_w, map_h = _fit_view(view, avail_w, max_h, p.scale)
    title = "\n".join(textwrap.wrap(p.title, chars)) if p.title else ""
    title_h = 0.12 + 0.2 * (title.count("\n") + 1) if title else 0.15
    if p.categories:
        ncol, key_h = legend_fit(p.categories, p.colours, avail_w, dpi)
    else:
        ncol, key_h = 0, _BAR_H + 0.5 + (_ISO_H if p.iso_classes else 0.0)
    return _Plan(p, data, view, map_w, map_h, title, ncol, title_h, key_h)


def _draw_map(fig: Any, pl: _Plan, map_top: float, track_colour: str) -> Any:
    """The map's axes (x/y in m, large coordinates from a round origin); returns the image."""
    from matplotlib.ticker import FuncFormatter

    width, total = fig.get_size_inches()
    p, view = pl.panel, pl.view
    rect = (_LEFT / width, (map_top - pl.map_h) / total, pl.map_w / width, pl.map_h / total)
    ax = fig.add_axes(rect)
    ax.set_facecolor(_BACKGROUND)
    cmap, norm = colour_scale(p.data, p.cmap, p.norm, p.categories, p.colours)
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
        from matplotlib import patheffects

        # a thin line with a white halo: it shows on every class colour and hides little
        halo = [
            patheffects.Stroke(linewidth=2.2, foreground="white", alpha=0.7),
            patheffects.Normal(),
        ]
        ax.plot(tr[:, 0], tr[:, 1], color=track_colour, lw=0.9, path_effects=halo)
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal", adjustable="box")
    ax.tick_params(labelsize=FONT)
    # large (UTM) coordinates: ticks from a round origin, which the label names
    ox, oy = _axis_origin(view[0], view[1]), _axis_origin(view[2], view[3])
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _, o=ox: f"{v - o:g}"))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _, o=oy: f"{v - o:g}"))
    ax.set_xlabel(f"x (east) − {ox:.0f} [m]" if ox else "x (east) [m]", fontsize=FONT)
    ax.set_ylabel(f"y − {oy:.0f} [m]" if oy else "y [m]", fontsize=FONT)
    if pl.title:
        ax.set_title(pl.title, fontsize=_TITLEFONT)
    if not np.isfinite(pl.data).any():
        ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center",
                fontsize=_TITLEFONT, color="0.3", gid="no-data")  # fmt: skip
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
    text_kw: dict[str, Any] = {"transform": inches, "va": "center", "fontsize": FONT}
    fig.text(_LEFT + bar_in + 0.1, y, f"{length:g} m", gid="scale-bar", **text_kw)
    track = pl.panel.track
    if track is not None and len(track):
        x_path = _LEFT + bar_in + 1.0
        line = Line2D([x_path, x_path + 0.4], [y] * 2, lw=0.9, color=track_colour)
        line.set_transform(inches)
        line.set_gid("path-key")
        fig.add_artist(line)
        fig.text(x_path + 0.5, y, "vehicle path", gid="path-key", **text_kw)


def _draw_key(fig: Any, pl: _Plan, image: Any, key_top: float, avail_w: float) -> None:
    """The class legend or the colour bar, its top at ``key_top`` in."""
    width, total = fig.get_size_inches()
    if not np.isfinite(pl.data).any():
        fig.text(_LEFT, key_top - 0.1, "no data: nothing was mapped in this layer",
                 transform=fig.dpi_scale_trans, va="top", fontsize=FONT, gid="no-data")  # fmt: skip
        return
    if pl.panel.categories:
        fig.legend(
            handles=legend_handles(pl.panel.categories, pl.panel.colours),
            loc="upper left",
            bbox_to_anchor=(_LEFT, key_top),
            bbox_transform=fig.dpi_scale_trans,
            ncol=pl.ncol,
            **LEGEND_KW,
        )
    else:
        bar_w = min(avail_w, 4.5)
        key_top -= _ISO_H if pl.panel.iso_classes else 0.0
        rect = (_LEFT / width, (key_top - _BAR_H) / total, bar_w / width, _BAR_H / total)
        p = pl.panel
        colour_bar(fig, fig.add_axes(rect), image, pl.data, p.label, bar_w, p.iso_classes)


def draw_map_panels(
    panels: Sequence[MapPanel],
    *,
    width: float = 8.0,
    dpi: float = 120,
    max_map_height: float = 5.4,
    track_colour: str = "black",
    page_length: float | None = 10.0,
    max_pages: int = 8,
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
    page_length : float or None
        A long map is drawn as pages of this much path, m, stacked under each other
        (:func:`rough_map.export.pages.page_views`); None: one view, however long.
    max_pages : int
        Most pages per map (longer maps get longer pages).

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
    chars = max(20, int((width - 0.3) * 72 / (_TITLEFONT * 0.56)))
    panels = _paged(panels, avail_w, max_map_height, page_length, max_pages)
    plans = [_plan(p, avail_w, max_map_height, chars, dpi) for p in panels]
    total = 0.1 + sum(pl.height + pl.gap for pl in plans) - plans[-1].gap + 0.15
    fig = Figure(figsize=(width, total), dpi=dpi)
    FigureCanvasAgg(fig)
    top = total - 0.1  # running top edge, in from the bottom
    for pl in plans:
        map_top = top - pl.title_h
        image = _draw_map(fig, pl, map_top, track_colour)
        if pl.panel.key:
            # the key band under the map: scale bar, vehicle path, colour bar or legend
            band_top = map_top - pl.map_h - _TICKS_H
            _draw_scale_and_path(fig, pl, band_top - _SCALE_H / 2, track_colour)
            _draw_key(fig, pl, image, band_top - _SCALE_H, avail_w)
        top -= pl.height + pl.gap
    return fig
