"""One colour-mapped PNG per map layer (matplotlib, Agg), with its key and a scale bar.

Each map is drawn at its true aspect (1 m east = 1 m north) and cropped to the cells that
hold data: the near-field layers share the extent of the near-field data, the far-field
layers (``far_*``) that of the far-field data, so a narrow near-field strip does not sit in
a mostly blank frame. Nothing is drawn over the data: the scale bar, the vehicle path's key
and the colour key sit in a band under the map.

Continuous layers get a horizontal colour bar labelled with the layer's units (R and sigma_R
on a logarithmic scale, class probabilities on a fixed 0–1 scale); class and level layers a
legend of colour patches, one per name, in as many columns as fit the width, so that long
class names never overlap. Units are written as a reader reads them (``m³/rad``). Unknown
cells (NaN; a count of 0) are transparent over a light grey background. The vehicle track
(``grid.attrs["track"]``) is drawn when the map has one.

:func:`draw_map_panels` is the layout shared with :func:`rough_map.export.figures.map_layers`.
"""

from __future__ import annotations

import logging
import math
import re
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.export.profiles import LEVEL_COLOURS, PNG_STYLE
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = [
    "MapPanel",
    "data_view",
    "display_units",
    "draw_map_panels",
    "drawn_texts",
    "is_probability_layer",
    "layer_figure",
    "layer_views",
    "scale_bar_length",
    "write_layer_png",
    "write_pngs",
]

_BACKGROUND = (0.93, 0.93, 0.93)
_FONT = 9.0  # pt: ticks, keys
_TITLE_FONT = 10.0  # pt
_LEFT = 0.85  # in: y tick labels and y label
_RIGHT = 0.3  # in
_MIN_MAP_H = 0.9  # in: thinner maps get a taller view (some blank above and below)
_SUPERSCRIPTS = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def scale_bar_length(span: float) -> float:
    """A round length (1, 2 or 5 x 10^k m) of at most a quarter of ``span`` m."""
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


def is_probability_layer(grid: GridMap, layer: str) -> bool:
    """Whether ``layer`` is a class probability (``p_<class>`` or ``far_p_<class>``)."""
    name = layer.removeprefix("far_")
    return (
        name.startswith("p_")
        and name[2:] in tuple(grid.attrs.get("class_names", ()))
        and grid.info(layer).units == "1"
    )


def data_view(
    mask: np.ndarray, extent: Sequence[float], *, margin: float = 0.03
) -> tuple[float, float, float, float]:
    """The part of ``extent`` (x_min, x_max, y_min, y_max; m) where ``mask`` is true.

    ``mask`` has row 0 at y_min. The box of the true cells is padded by ``margin`` of its
    larger side (at least two cells) and clipped to ``extent``; all of ``extent`` when no
    cell is true.
    """
    x0, x1, y0, y1 = (float(v) for v in extent)
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return x0, x1, y0, y1
    ny, nx = mask.shape
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    vx0, vx1 = x0 + cols.min() * dx, x0 + (cols.max() + 1) * dx
    vy0, vy1 = y0 + rows.min() * dy, y0 + (rows.max() + 1) * dy
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

    return [
        Patch(facecolor=tuple(c), edgecolor="0.35", linewidth=0.5, label=name)
        for name, c in zip(panel.categories, panel.colours, strict=True)
    ]


_LEGEND_KW = {
    "frameon": False,
    "fontsize": _FONT,
    "borderaxespad": 0.0,
    "borderpad": 0.0,
    "handlelength": 1.4,
    "handleheight": 1.0,
    "columnspacing": 1.4,
    "labelspacing": 0.45,
}


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
    from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize

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
        ticks = _log_ticks(norm.vmin, norm.vmax)
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
        labels = [t for t in drawn_texts_of_axis(bar.ax.xaxis)]
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
        Resolution.
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
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter

    if not panels:
        raise InputError("no map to draw")
    avail_w = width - _LEFT - _RIGHT
    chars = max(20, int((width - 0.3) * 72 / (_TITLE_FONT * 0.56)))
    plans = []
    for p in panels:
        data = np.asarray(p.data, dtype=float)
        view = p.view or data_view(np.isfinite(data), p.extent)
        view, map_w, map_h = _fit_view(view, avail_w, max_map_height)
        title = "\n".join(textwrap.wrap(p.title, chars)) if p.title else ""
        title_h = 0.12 + 0.2 * (title.count("\n") + 1) if title else 0.15
        if p.categories:
            ncol, key_h = _legend_fit(p, avail_w, dpi)
        else:
            ncol, key_h = 0, 0.14 + 0.5
        heights = (title_h, map_h, 0.5, 0.36, key_h)
        plans.append((p, data, view, map_w, map_h, title, ncol, heights))
    gap = 0.3
    total = 0.1 + sum(sum(pl[-1]) for pl in plans) + gap * (len(plans) - 1) + 0.15
    fig = Figure(figsize=(width, total), dpi=dpi)
    FigureCanvasAgg(fig)
    inches = fig.dpi_scale_trans
    top = total - 0.1  # running top edge, in from the bottom
    for p, data, view, map_w, map_h, title, ncol, heights in plans:
        title_h, _, ticks_h, scale_h, _ = heights
        map_top = top - title_h
        ax = fig.add_axes((_LEFT / width, (map_top - map_h) / total, map_w / width, map_h / total))
        ax.set_facecolor(_BACKGROUND)
        cmap, norm = _colour_scale(p)
        masked = np.ma.masked_invalid(data)
        image = ax.imshow(
            masked, origin="lower", extent=p.extent, cmap=cmap, norm=norm, interpolation="nearest"
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
        if title:
            ax.set_title(title, fontsize=_TITLE_FONT)
        # the key band under the map: scale bar, vehicle path, colour bar or class legend
        y_scale = map_top - map_h - ticks_h - scale_h / 2
        length = scale_bar_length(view[1] - view[0])
        bar_in = length * map_w / (view[1] - view[0])
        for artist in (
            Line2D([_LEFT, _LEFT + bar_in], [y_scale] * 2, lw=3, color="k", solid_capstyle="butt"),
            Line2D([_LEFT] * 2, [y_scale - 0.06, y_scale + 0.06], lw=1, color="k"),
            Line2D([_LEFT + bar_in] * 2, [y_scale - 0.06, y_scale + 0.06], lw=1, color="k"),
        ):
            artist.set_transform(inches)
            artist.set_gid("scale-bar")
            fig.add_artist(artist)
        fig.text(
            _LEFT + bar_in + 0.1,
            y_scale,
            f"{length:g} m",
            transform=inches,
            va="center",
            fontsize=_FONT,
            gid="scale-bar",
        )
        if p.track is not None and len(p.track):
            x_path = _LEFT + bar_in + 1.0
            line = Line2D([x_path, x_path + 0.4], [y_scale] * 2, lw=1.2, color=track_colour)
            line.set_transform(inches)
            line.set_gid("path-key")
            fig.add_artist(line)
            fig.text(
                x_path + 0.5,
                y_scale,
                "vehicle path",
                transform=inches,
                va="center",
                fontsize=_FONT,
                gid="path-key",
            )
        key_top = map_top - map_h - ticks_h - scale_h
        if p.categories:
            fig.legend(
                handles=_legend_handles(p),
                loc="upper left",
                bbox_to_anchor=(_LEFT, key_top),
                bbox_transform=inches,
                ncol=ncol,
                **_LEGEND_KW,
            )
        else:
            bar_w = min(avail_w, 4.5)
            cax = fig.add_axes(
                (_LEFT / width, (key_top - 0.14) / total, bar_w / width, 0.14 / total)
            )
            _colour_bar(fig, cax, image, p, bar_w)
        top -= sum(heights) + gap
    return fig


# -- layers of a GridMap --------------------------------------------------------------------


def _colours(grid: GridMap, layer: str) -> list[tuple[float, float, float]]:
    from rough_map.export.geotiff import class_colours

    info = grid.info(layer)
    if info.kind == "class":
        table = class_colours(info.categories)
        return [tuple(v / 255 for v in table[i][:3]) for i in range(len(info.categories))]
    if len(info.categories) <= len(LEVEL_COLOURS):
        return [tuple(v / 255 for v in rgb) for rgb in LEVEL_COLOURS[: len(info.categories)]]
    from matplotlib import colormaps

    cmap = colormaps["RdYlGn_r"].resampled(len(info.categories))
    return [tuple(cmap(i)[:3]) for i in range(len(info.categories))]


def _group(layer: str) -> str:
    return "far" if layer.startswith("far_") else "near"


def _display_values(grid: GridMap, layer: str) -> np.ndarray:
    """The layer with cells nothing has written as NaN (a count of 0 is no data)."""
    data = np.array(grid[layer], dtype=float)
    info = grid.info(layer)
    if info.fill == 0 and not info.categories:
        data[data == 0] = np.nan
    return data


def layer_views(
    grid: GridMap, layers: Sequence[str] | None = None
) -> dict[str, tuple[float, float, float, float]]:
    """The area to draw of each layer: where its group (near or far field) holds data.

    Near-field layers share the box of the cells where any near-field layer is known,
    far-field layers (``far_*``) the box of the far-field cells (:func:`data_view`).
    """
    if layers is None:
        layers = [n for n in grid.layers if grid.info(n).kind != "internal"]
    x0, y0, x1, y1 = grid.geometry.bounds
    masks: dict[str, np.ndarray] = {}
    for name in grid.layers:
        info = grid.info(name)
        if info.kind == "internal" or not math.isnan(info.fill):
            continue
        known = np.isfinite(grid[name])
        g = _group(name)
        masks[g] = masks[g] | known if g in masks else known
    views = {g: data_view(m, (x0, x1, y0, y1)) for g, m in masks.items()}
    full = (x0, x1, y0, y1)
    return {n: views.get(_group(n), full) for n in layers}


def layer_figure(
    grid: GridMap,
    layer: str,
    *,
    style: dict[str, Any] | None = None,
    title: str | None = None,
    view: tuple[float, float, float, float] | None = None,
) -> Any:
    """The figure :func:`write_layer_png` saves (see there); returns a matplotlib Figure."""
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm, Normalize

    st = {**PNG_STYLE, **(style or {})}
    if layer not in grid.layers:
        raise InputError(f"the map has no layer {layer!r}; it has {list(grid.layers)}")
    info = grid.info(layer)
    data = _display_values(grid, layer)
    x0, y0, x1, y1 = grid.geometry.bounds
    name = grid.attrs.get("name") or "map"
    units = display_units(info.units)
    panel = MapPanel(
        data=data,
        extent=(x0, x1, y0, y1),
        title=title or f"{name}: {layer} — {info.description}",
        view=view or layer_views(grid, [layer])[layer],
        track=grid.attrs.get("track"),
    )
    if info.categories:
        panel.categories = tuple(info.categories)
        panel.colours = _colours(grid, layer)
    else:
        panel.cmap = colormaps[st["cmap"].get(layer, st["default_cmap"])]
        finite = data[np.isfinite(data)]
        if is_probability_layer(grid, layer):
            panel.norm = Normalize(0.0, 1.0)
            panel.label = f"{layer}: {info.description} (0–1)"
        elif layer in st["log_layers"] and np.any(finite > 0):
            pos = finite[finite > 0]
            lo, hi = float(pos.min()), float(pos.max())
            panel.norm = LogNorm(lo, hi) if hi > 1.01 * lo else LogNorm(lo / 2, hi * 2)
        elif finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            panel.norm = Normalize(lo, hi if hi > lo else lo + 1)
        else:
            panel.norm = Normalize(0, 1)
        if not panel.label:
            panel.label = f"{layer} [{units}]" if units else layer
    return draw_map_panels(
        [panel],
        width=float(st["figsize"][0]),
        dpi=float(st["dpi"]),
        max_map_height=1.2 * float(st["figsize"][1]),
        track_colour=st["track_colour"],
    )


def write_layer_png(
    grid: GridMap,
    layer: str,
    path: str | Path,
    *,
    style: dict[str, Any] | None = None,
    title: str | None = None,
    view: tuple[float, float, float, float] | None = None,
) -> Path:
    """Draw one layer of a map to a PNG.

    Parameters
    ----------
    grid : GridMap
        The map.
    layer : str
        The layer to draw.
    path : str or Path
        The ``.png`` to write (its folder must exist).
    style : dict, optional
        Overrides of :data:`~rough_map.export.profiles.PNG_STYLE`.
    title : str, optional
        Figure title (default: map name, layer and description).
    view : (float, float, float, float), optional
        ``(x_min, x_max, y_min, y_max)`` in m to draw; default the box of the cells where
        the layer's group (near or far field) has data (:func:`layer_views`).

    Returns
    -------
    Path
        ``path``.
    """
    from rough_map._files import atomic_output

    fig = layer_figure(grid, layer, style=style, title=title, view=view)
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    log.debug("wrote %s", path)
    return path


def write_pngs(
    grid: GridMap,
    out_dir: str | Path,
    name: str = "map",
    *,
    layers: list[str] | tuple[str, ...] | None = None,
    style: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """One PNG per layer, ``<out_dir>/<name>_<layer>.png``.

    Parameters
    ----------
    grid : GridMap
        The map.
    out_dir : str or Path
        An existing folder.
    name : str
        File name prefix.
    layers : sequence of str, optional
        Layers to draw (default: every layer that is not internal).
    style : dict, optional
        Overrides of :data:`~rough_map.export.profiles.PNG_STYLE`.

    Returns
    -------
    dict of str to Path
        Layer name -> PNG written.
    """
    if layers is None:
        layers = [n for n in grid.layers if grid.info(n).kind != "internal"]
    out = Path(out_dir)
    views = layer_views(grid, layers)
    return {
        layer: write_layer_png(
            grid, layer, out / f"{name}_{layer}.png", style=style, view=views[layer]
        )
        for layer in layers
    }
