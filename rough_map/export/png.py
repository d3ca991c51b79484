"""One colour-mapped PNG per map layer, with its key and a scale bar.

Each map is drawn at its true aspect (1 m east = 1 m north) and cropped to the cells that
hold data: the near-field layers share the extent of the near-field data, the far-field
layers (``far_*``) that of the far-field data, so a narrow near-field strip does not sit in
a mostly blank frame. The layout (keys in a band under the map, never over it) is
:func:`rough_map.export.layout.draw_map_panels`, drawn on an Agg canvas without pyplot.

Continuous layers get a horizontal colour bar labelled with the layer's units (R and sigma_R
on a logarithmic scale, class probabilities on a fixed 0–1 scale); class and level layers a
legend of colour patches (class colours of :func:`rough_map.export.profiles.class_colour`).
Units are written as a reader reads them (``m³/rad``). Unknown cells (NaN; a count of 0)
are transparent over a light grey background. The vehicle track (``grid.attrs["track"]``)
is drawn when the map has one.
"""

from __future__ import annotations

import gc
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map._files import atomic_output
from rough_map.errors import InputError
from rough_map.export.layout import (
    MapPanel,
    data_view,
    display_units,
    draw_map_panels,
    drawn_texts,
    scale_bar_length,
)
from rough_map.export.profiles import LEVEL_COLOURS, PNG_STYLE, class_colour
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

# MapPanel, data_view, display_units, draw_map_panels, drawn_texts and scale_bar_length
# live in rough_map.export.layout; they are re-exported here, where they were first.
__all__ = [
    "MapPanel",
    "data_view",
    "display_units",
    "draw_map_panels",
    "drawn_texts",
    "is_probability_layer",
    "is_share_layer",
    "layer_figure",
    "layer_views",
    "scale_bar_length",
    "write_layer_png",
    "write_pngs",
]

# -- layers of a GridMap --------------------------------------------------------------------


def is_probability_layer(grid: GridMap, layer: str) -> bool:
    """Whether ``layer`` is a class probability (``p_<class>`` or ``far_p_<class>``)."""
    name = layer.removeprefix("far_")
    return (
        name.startswith("p_")
        and name[2:] in tuple(grid.attrs.get("class_names", ()))
        and grid.info(layer).units == "1"
    )


def _rgb01(rgb: Sequence[int]) -> tuple[float, float, float]:
    r, g, b = rgb
    return r / 255, g / 255, b / 255


def _colours(grid: GridMap, layer: str) -> list[tuple[float, float, float]]:
    """Colour (0–1) per category of a class or level layer."""
    info = grid.info(layer)
    if info.kind == "class":
        return [_rgb01(class_colour(name, i)) for i, name in enumerate(info.categories)]
    if len(info.categories) <= len(LEVEL_COLOURS):
        return [_rgb01(rgb) for rgb in LEVEL_COLOURS[: len(info.categories)]]
    from matplotlib import colormaps

    cmap = colormaps["RdYlGn_r"].resampled(len(info.categories))
    rgba = [cmap(i) for i in range(len(info.categories))]
    return [(float(r), float(g), float(b)) for r, g, b, _ in rgba]


def _group(layer: str) -> str:
    return "far" if layer.startswith("far_") else "near"


def _display_values(grid: GridMap, layer: str) -> np.ndarray:
    """The layer with cells nothing has written as NaN (a count of 0 is no data); the
    layer itself (not a copy) when it is float and needs no change. Read only."""
    data = np.asarray(grid[layer], dtype=float)
    info = grid.info(layer)
    if info.fill == 0 and not info.categories:
        return np.where(data == 0, np.nan, data)
    return data


def _group_masks(grid: GridMap) -> dict[str, np.ndarray]:
    """The cells where any layer of each group (``"near"``, ``"far"``) is known."""
    masks: dict[str, np.ndarray] = {}
    for name in grid.layers:
        info = grid.info(name)
        if info.kind == "internal" or not math.isnan(info.fill):
            continue
        known = np.isfinite(grid[name])
        g = _group(name)
        masks[g] = masks[g] | known if g in masks else known
    return masks


def layer_views(
    grid: GridMap,
    layers: Sequence[str] | None = None,
    masks: dict[str, np.ndarray] | None = None,
) -> dict[str, tuple[float, float, float, float]]:
    """The area to draw of each layer: where its group (near or far field) holds data.

    Near-field layers share the box of the cells where any near-field layer is known,
    far-field layers (``far_*``) the box of the far-field cells (:func:`data_view`).
    """
    if layers is None:
        layers = [n for n in grid.layers if grid.info(n).kind != "internal"]
    x0, y0, x1, y1 = grid.geometry.bounds
    masks = _group_masks(grid) if masks is None else masks
    views = {g: data_view(m, (x0, x1, y0, y1)) for g, m in masks.items()}
    full = (x0, x1, y0, y1)
    return {n: views.get(_group(n), full) for n in layers}


def is_share_layer(grid: GridMap, layer: str) -> bool:
    """Whether ``layer`` holds a share on 0–1: a class probability, a confidence or the
    share of novel patches."""
    return is_probability_layer(grid, layer) or (
        layer.removeprefix("far_") in ("confidence", "novel") and grid.info(layer).units == "1"
    )


def _count_norm(finite: np.ndarray, cmap: Any) -> tuple[Any, Any]:
    """Discrete levels for counts 1..max: one colour per count, or per round bin of counts
    (1, 2 or 5 x 10^k wide) when there are more than 12."""
    from matplotlib.colors import BoundaryNorm

    top = int(finite.max()) if finite.size else 1
    step = 1
    while math.ceil(top / step) > 12:
        step = next(m * 10**k for k in range(12) for m in (1, 2, 5) if m * 10**k > step)
    edges = np.arange(0.5, top + step + 0.5, step)
    levels = len(edges) - 1
    return cmap.resampled(max(levels, 2)), BoundaryNorm(edges, max(levels, 2))


def _continuous_scale(
    grid: GridMap, layer: str, data: np.ndarray, st: dict[str, Any]
) -> tuple[Any, Any, str]:
    """The colour map, norm and label of a continuous layer (see :func:`write_layer_png`)."""
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm, Normalize

    info = grid.info(layer)
    cmap = colormaps[st["cmap"].get(layer, st["default_cmap"])]
    finite = data[np.isfinite(data)]
    units = display_units(info.units)
    label = f"{layer} [{units}]" if units else layer
    if is_share_layer(grid, layer):
        return cmap, Normalize(0.0, 1.0), f"{layer}: {info.description} (0–1)"
    if layer.removeprefix("far_") in st["count_layers"]:
        cmap, norm = _count_norm(finite, cmap)
        return cmap, norm, f"{layer}: {info.description}"
    if layer in st["log_layers"] and np.any(finite > 0):
        pos = finite[finite > 0]
        lo, hi = float(pos.min()), float(pos.max())
        return cmap, LogNorm(lo, hi) if hi > 1.01 * lo else LogNorm(lo / 2, hi * 2), label
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        return cmap, Normalize(lo, hi if hi > lo else lo + 1), label
    return cmap, Normalize(0, 1), label


def layer_figure(
    grid: GridMap,
    layer: str,
    *,
    style: dict[str, Any] | None = None,
    title: str | None = None,
    view: tuple[float, float, float, float] | None = None,
    known: np.ndarray | None = None,
) -> Any:
    """The figure :func:`write_layer_png` saves (see there); returns a matplotlib Figure."""
    st = {**PNG_STYLE, **(style or {})}
    if layer not in grid.layers:
        raise InputError(f"the map has no layer {layer!r}; it has {list(grid.layers)}")
    info = grid.info(layer)
    data = _display_values(grid, layer)
    x0, y0, x1, y1 = grid.geometry.bounds
    name = grid.attrs.get("name") or "map"
    panel = MapPanel(
        data=data,
        extent=(x0, x1, y0, y1),
        title=title or f"{name}: {layer} — {info.description}",
        view=view or layer_views(grid, [layer])[layer],
        track=grid.attrs.get("track"),
        known=known,
    )
    if info.categories:
        panel.categories = tuple(info.categories)
        panel.colours = _colours(grid, layer)
    else:
        panel.cmap, panel.norm, panel.label = _continuous_scale(grid, layer, data, st)
        panel.iso_classes = layer == "R"
    return draw_map_panels(
        [panel],
        width=float(st["figsize"][0]),
        dpi=float(st["dpi"]),
        max_map_height=1.2 * float(st["figsize"][1]),
        track_colour=st["track_colour"],
        page_length=st["page_length"],
        max_pages=int(st["max_pages"]),
    )


def write_layer_png(
    grid: GridMap,
    layer: str,
    path: str | Path,
    *,
    style: dict[str, Any] | None = None,
    title: str | None = None,
    view: tuple[float, float, float, float] | None = None,
    known: np.ndarray | None = None,
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
    known : ndarray of bool, optional
        The cells that place the pages of a long map (default where the layer is known).

    Returns
    -------
    Path
        ``path``.
    """
    fig = layer_figure(grid, layer, style=style, title=title, view=view, known=known)
    path = Path(path)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        # a figure is a web of reference cycles, which only a collection frees: without one,
        # the figures of a long map (each holding copies of its layer and a canvas) pile up
        # over the PNGs. Its objects are young: collecting generations 0 and 1 frees them
        # (a full collection would walk every object of the process, 0.1 s a PNG).
        del fig
        gc.collect(1)
    log.debug("wrote %s", path)
    return path


def write_pngs(
    grid: GridMap,
    out_dir: str | Path,
    name: str = "map",
    *,
    layers: list[str] | tuple[str, ...] | None = None,
    style: dict[str, Any] | None = None,
    progress: bool = False,
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
    progress : bool
        Progress bar on stderr.

    Returns
    -------
    dict of str to Path
        Layer name -> PNG written.
    """
    from tqdm import tqdm

    if layers is None:
        layers = [n for n in grid.layers if grid.info(n).kind != "internal"]
    out = Path(out_dir)
    masks = _group_masks(grid)
    views = layer_views(grid, layers, masks)
    written = {}
    for layer in tqdm(layers, desc="PNG", unit="layer", disable=not progress):
        written[layer] = write_layer_png(
            grid,
            layer,
            out / f"{name}_{layer}.png",
            style=style,
            view=views[layer],
            known=masks.get(_group(layer)),
        )
    gc.collect()  # the figures' last objects (each PNG collects the young ones)
    return written
