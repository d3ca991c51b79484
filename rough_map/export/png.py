"""One colour-mapped PNG per map layer (matplotlib, Agg), with colour bar and scale bar.

Continuous layers get a colour bar labelled with the layer's units (R and sigma_R on a
logarithmic scale); class and level layers a discrete colour bar labelled with the class
or level names. Unknown cells (NaN) are left transparent over a light grey background.
The vehicle track (``grid.attrs["track"]``) is drawn when the map has one.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from rough_map.errors import InputError
from rough_map.export.profiles import LEVEL_COLOURS, PNG_STYLE
from rough_map.map.grid import GridMap

log = logging.getLogger(__name__)

__all__ = ["scale_bar_length", "write_layer_png", "write_pngs"]


def scale_bar_length(span: float) -> float:
    """A round length (1, 2 or 5 x 10^k m) of at most a quarter of ``span`` m."""
    if not (math.isfinite(span) and span > 0):
        raise InputError(f"span must be a positive length in m, got {span!r}")
    target = span / 4
    base = 10 ** math.floor(math.log10(target))
    return max(m * base for m in (1, 2, 5) if m * base <= target)


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


def write_layer_png(
    grid: GridMap,
    layer: str,
    path: str | Path,
    *,
    style: dict[str, Any] | None = None,
    title: str | None = None,
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

    Returns
    -------
    Path
        ``path``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import BoundaryNorm, ListedColormap, LogNorm, Normalize
    from matplotlib.figure import Figure
    from mpl_toolkits.axes_grid1 import make_axes_locatable
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from rough_map.io.pointcloud import atomic_output

    st = {**PNG_STYLE, **(style or {})}
    info = grid.info(layer)
    data = np.ma.masked_invalid(grid[layer])
    x0, y0, x1, y1 = grid.geometry.bounds
    # size the figure to the map's aspect; a fixed layout (tight_layout draws twice)
    width_in = float(st["figsize"][0])
    axes_w = 0.72 * width_in
    axes_h = axes_w * (y1 - y0) / max(x1 - x0, 1e-9)
    height_in = min(max(axes_h + 1.3, 2.6), float(st["figsize"][1]) * 3)
    fig = Figure(figsize=(width_in, height_in), dpi=st["dpi"])
    # room on the right for the colour bar and its labels (about 0.09 in per character)
    label_chars = max((len(c) for c in info.categories), default=8)
    right = 1 - (0.55 + 0.09 * label_chars) / width_in
    fig.subplots_adjust(left=0.09, right=right, bottom=0.7 / height_in, top=1 - 0.45 / height_in)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set_facecolor((0.93, 0.93, 0.93))
    if info.categories:
        k = len(info.categories)
        cmap = ListedColormap(_colours(grid, layer))
        norm: Any = BoundaryNorm(np.arange(-0.5, k + 0.5), k)
    else:
        from matplotlib import colormaps

        cmap = colormaps[st["cmap"].get(layer, st["default_cmap"])]
        finite = np.asarray(data.compressed())
        if layer in st["log_layers"] and np.any(finite > 0):
            pos = finite[finite > 0]
            lo, hi = float(pos.min()), float(pos.max())
            norm = LogNorm(lo, hi) if hi > 1.01 * lo else LogNorm(lo / 2, hi * 2)
        elif finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            norm = Normalize(lo, hi if hi > lo else lo + 1)
        else:
            norm = Normalize(0, 1)
    cmap = cmap.with_extremes(bad=(1, 1, 1, 0))
    image = ax.imshow(
        data, origin="lower", extent=(x0, x1, y0, y1), cmap=cmap, norm=norm, interpolation="nearest"
    )
    cax = make_axes_locatable(ax).append_axes("right", size=0.15, pad=0.1)
    bar = fig.colorbar(image, cax=cax)
    if info.categories:
        bar.set_ticks(np.arange(len(info.categories)))
        bar.set_ticklabels(list(info.categories))
    else:
        bar.set_label(f"{layer} [{info.units}]")
    track = grid.attrs.get("track")
    if track is not None and len(track):
        tr = np.asarray(track, dtype=float)
        ax.plot(tr[:, 0], tr[:, 1], color=st["track_colour"], lw=1.2, label="vehicle path")
        ax.legend(loc="upper right", fontsize="small")
    length = scale_bar_length(x1 - x0)
    ax.add_artist(
        AnchoredSizeBar(
            ax.transData,
            length,
            f"{length:g} m",
            "lower left",
            pad=0.4,
            frameon=True,
            size_vertical=grid.resolution / 2,
        )
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (east)")
    ax.set_ylabel("y [m] (north)")
    name = grid.attrs.get("name") or "map"
    ax.set_title(title or f"{name}: {layer} — {info.description}", fontsize="medium")
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
    return {
        layer: write_layer_png(grid, layer, out / f"{name}_{layer}.png", style=style)
        for layer in layers
    }
