"""The paper's figures, drawn with matplotlib from real runs.

Every function takes the data it draws and an output path, writes one PNG atomically and
returns the path. Figures are drawn on their own Agg canvas, never through pyplot: the
caller's matplotlib backend (a notebook's inline backend) is left as it was. Figure numbers
refer to Reina et al., *Mind the ground*.

* :func:`roughness_along_path` - R and w along the path with sigma bands and ISO class
  reference lines (Figs. 7, 9, 12, 14);
* :func:`profile_psd_fit` - the PSD of one profile with its power-law fit (Fig. 4);
* :func:`profile_scatter` - per-profile (R, w) with the patch mean (Fig. 5);
* :func:`psd_lines_vs_iso` - fitted PSD lines of surfaces against the ISO classes (Fig. 10);
* :func:`class_scatter` - (R, w) by class with the low/medium/high regions (Fig. 19);
* :func:`map_layers` - elevation, roughness and class layers with the path (Figs. 20, 21).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rough_map import iso8608
from rough_map._files import atomic_output, make_dir
from rough_map.errors import InputError
from rough_map.export.layout import MapPanel, data_view, draw_map_panels
from rough_map.export.profiles import LEVEL_COLOURS, class_colour
from rough_map.patch import PatchSpec

log = logging.getLogger(__name__)

__all__ = [
    "class_colour",
    "class_scatter",
    "confusion_matrices",
    "map_layers",
    "profile_psd_fit",
    "profile_scatter",
    "psd_lines_vs_iso",
    "roughness_along_path",
]

_LEVEL_RGB = [tuple(v / 255 for v in c) for c in LEVEL_COLOURS]  # matplotlib colours


def _rgb01(name: str, index: int) -> np.ndarray:
    """The class colour (:func:`class_colour`) on matplotlib's 0-1 scale."""
    return np.array(class_colour(name, index)) / 255


def _figure(width: float = 8.0, height: float = 5.0) -> Any:
    """A :class:`~matplotlib.figure.Figure` with its own Agg canvas.

    pyplot is not used, so drawing a figure never switches the caller's backend (a
    notebook keeps its inline backend) and leaves no figure open.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path, *, tight: bool = False, layout: bool = True) -> Path:
    """Write the figure to a PNG atomically.

    ``layout`` applies the tight layout to a figure without a layout engine; ``tight``
    crops the PNG to what is drawn (nothing cut off).
    """
    path = Path(path)
    make_dir(path.parent)
    if layout and fig.get_layout_engine() is None:
        fig.tight_layout()
    with atomic_output(path) as tmp:
        if tight:
            fig.savefig(tmp, format="png", bbox_inches="tight", pad_inches=0.15)
        else:
            fig.savefig(tmp, format="png")
    log.debug("wrote %s", path)
    return path


def roughness_along_path(
    distance: np.ndarray,
    R: np.ndarray,
    sigma_R: np.ndarray,
    w: np.ndarray,
    sigma_w: np.ndarray,
    path: str | Path,
    *,
    labels: Sequence[str] | None = None,
    defects: np.ndarray | None = None,
    smoothed: Mapping[str, np.ndarray] | None = None,
    speed: Mapping[str, np.ndarray] | None = None,
    title: str = "",
) -> Path:
    """R (log scale, m³/rad) and w along the path (m) with 1-sigma bands (Figs. 7, 9, 12).

    ISO 8608 class centres A-H are drawn as reference lines on the R panel; the true or
    predicted labels, if given, shade the background; frames flagged in ``defects`` (bool
    per frame, isolated defects such as a manhole) are marked on the R curve.

    ``smoothed``, if given, holds the roughness smoothed along the path, one value per
    frame, as the features table's columns ``R_smooth`` (m³/rad), ``w_smooth``,
    ``sigma_lnR_smooth`` and ``sigma_w_smooth``
    (:class:`rough_map.filter.RoughnessSmoother`): it is drawn over the raw curves with its
    ±1σ band (``R exp(±sigma_lnR)``); the raw curves are then thinner.

    ``speed``, if given, holds a vehicle's speed advice per frame, the features' ``v_max``
    and ``v_max_95`` (m/s, :mod:`rough_map.features.driving`), drawn in a third panel.
    """
    panels = 2 if speed is None else 3
    fig = _figure(9, 6.4 if speed is None else 8.6)
    fig.set_layout_engine("constrained")
    ax1 = fig.add_subplot(panels, 1, 1)
    ax2 = fig.add_subplot(panels, 1, 2, sharex=ax1)
    d = np.asarray(distance, float)
    ok = np.isfinite(R) & np.isfinite(w)
    smooth = _smoothed(smoothed, d.size)
    raw_lw = 1.2 if smooth is None else 0.7
    _r_panel(ax1, d, R, sigma_R, ok, defects, raw_lw)
    ax2.fill_between(d, w - sigma_w, w + sigma_w, where=ok, color="0.8")
    ax2.plot(d[ok], w[ok], "k-", lw=raw_lw)
    if smooth is not None:
        _smooth_curves(ax1, ax2, d, smooth)
    ax2.axhline(-2.0, color="tab:blue", lw=0.6, ls="--")
    ax2.set_ylabel("w")
    if speed is not None:
        ax3 = fig.add_subplot(panels, 1, 3, sharex=ax1)
        v, sure = np.asarray(speed["v_max"], float), np.asarray(speed["v_max_95"], float)
        ax3.plot(d, v, "k-", lw=1.2, label="v_max")
        ax3.plot(d, sure, color="tab:blue", ls="--", lw=1.0, label="v_max, 95 % confidence")
        ax3.set_ylabel("speed advice [m/s]")
        ax3.set_ylim(bottom=0)
        ax3.legend(loc="lower right", fontsize=8, frameon=False)
        ax3.set_xlabel("distance along the path [m]")
    else:
        ax2.set_xlabel("distance along the path [m]")
    if labels is not None and len(labels) == d.size:
        _shade_classes(ax1, ax2, d, labels)
    # the key above the plot, off the data
    handles = ax1.get_legend_handles_labels()[0]
    ax1.legend(
        loc="lower left",
        bbox_to_anchor=(0.0, 1.01),
        fontsize=8,
        ncol=min(6, max(1, len(handles))),
        frameon=False,
        borderaxespad=0.0,
    )
    if title:
        fig.suptitle(title)
    return _save(fig, path)


#: Columns of the smoothed roughness :func:`roughness_along_path` draws.
_SMOOTHED = ("R_smooth", "w_smooth", "sigma_lnR_smooth", "sigma_w_smooth")
_SMOOTH_COLOUR = "tab:orange"


def _smoothed(smoothed: Mapping[str, np.ndarray] | None, n: int) -> dict[str, np.ndarray] | None:
    """The smoothed columns as float arrays of ``n`` values (None when not given)."""
    if smoothed is None:
        return None
    missing = [k for k in _SMOOTHED if k not in smoothed]
    if missing:
        raise InputError(f"smoothed needs the columns {list(_SMOOTHED)}; missing {missing}")
    out = {k: np.asarray(smoothed[k], dtype=float) for k in _SMOOTHED}
    bad = [k for k, v in out.items() if v.shape != (n,)]
    if bad:
        raise InputError(f"smoothed {bad[0]!r} needs one value per frame ({n},)")
    if not np.isfinite(out["R_smooth"]).any():
        return None  # not smoothed (a table written without the smoother)
    return out


def _smooth_curves(ax1: Any, ax2: Any, d: np.ndarray, s: dict[str, np.ndarray]) -> None:
    """The smoothed R and w with their ±1σ bands, over the raw curves."""
    R, w = s["R_smooth"], s["w_smooth"]
    sr, sw = s["sigma_lnR_smooth"], s["sigma_w_smooth"]
    ok = np.isfinite(R) & np.isfinite(w) & np.isfinite(sr) & np.isfinite(sw)
    band = dict(where=ok, color=_SMOOTH_COLOUR, alpha=0.25, lw=0)
    ax1.fill_between(d, R * np.exp(-sr), R * np.exp(sr), label="smoothed ±1σ", **band)
    ax1.plot(d[ok], R[ok], "-", color=_SMOOTH_COLOUR, lw=1.8, label="R smoothed")
    ax2.fill_between(d, w - sw, w + sw, **band)
    ax2.plot(d[ok], w[ok], "-", color=_SMOOTH_COLOUR, lw=1.8)


def _r_panel(
    ax: Any,
    d: np.ndarray,
    R: np.ndarray,
    sigma_R: np.ndarray,
    ok: np.ndarray,
    defects: np.ndarray | None,
    lw: float = 1.2,
) -> None:
    """R with its band, the ISO 8608 class centres (named in the right margin), defects."""
    from matplotlib.transforms import blended_transform_factory

    lo = np.clip(R - sigma_R, R * 0.05, None)
    ax.fill_between(d, lo, R + sigma_R, where=ok, color="0.8", label="±1σ")
    ax.plot(d[ok], R[ok], "k-", lw=lw, label="R")
    ax.set_yscale("log")
    ymin, ymax = (
        np.nanmin(lo[ok]) if ok.any() else 1e-6,
        np.nanmax((R + sigma_R)[ok]) if ok.any() else 1e-2,
    )
    right_margin = blended_transform_factory(ax.transAxes, ax.transData)
    for cls, phi in iso8608.PHI0.items():
        if ymin / 3 < phi < ymax * 3:
            ax.axhline(phi, color="tab:blue", lw=0.6, ls="--")
            # class names in the right margin, off the data
            ax.text(
                1.01,
                phi,
                f"ISO {cls}",
                color="tab:blue",
                fontsize=8,
                va="center",
                transform=right_margin,
                clip_on=False,
            )
    ax.set_ylim(ymin / 3, ymax * 3)
    if defects is not None and len(defects) == d.size:
        flagged = np.asarray(defects, dtype=bool) & ok
        if flagged.any():
            ax.plot(d[flagged], R[flagged], "v", color="tab:red", ms=5, label="isolated defect")
    ax.set_ylabel("R  [m³/rad]")


def _shade_classes(ax1: Any, ax2: Any, d: np.ndarray, labels: Sequence[str]) -> None:
    """Shade both panels by class along the path, with a band of the class colours at
    full strength along the bottom of each (pale tints alone lose the palette's lightness
    steps); the top panel's legend names them."""
    names = list(dict.fromkeys(labels))
    for k, name in enumerate(names):
        sel = np.asarray(labels) == name
        if not name or not sel.any():
            continue
        c = _rgb01(name, k)
        for ax in (ax1, ax2):
            kw: dict[str, Any] = {"where": sel, "color": c, "step": "mid", "linewidth": 0}
            kw["transform"] = ax.get_xaxis_transform()
            ax.fill_between(d, 0, 1, alpha=0.12, **kw)
            ax.fill_between(d, 0, 0.045, label=name if ax is ax1 else None, **kw)


def profile_psd_fit(
    omega: np.ndarray,
    psd: np.ndarray,
    R: float,
    w: float,
    path: str | Path,
    *,
    omega0: float = 1.0,
    title: str = "",
) -> Path:
    """PSD of one profile (m³/rad) against Omega (rad/m) with its fit R Omega^w (Fig. 4)."""
    fig = _figure(7, 5)
    ax = fig.add_subplot(1, 1, 1)
    ax.loglog(omega, psd, color="0.55", lw=1.0, label="PSD of the profile")
    ax.loglog(
        omega,
        R * (omega / omega0) ** w,
        "k-",
        lw=1.6,
        label=f"fit: R = {R:.2e} m³/rad, w = {w:.2f}",
    )
    ax.set_xlabel("Ω  [rad/m]")
    ax.set_ylabel("PSD  [m³/rad]")
    ax.legend()
    ax.set_title(title or "PSD of one longitudinal profile")
    ax.grid(True, which="both", lw=0.3)
    return _save(fig, path)


def profile_scatter(
    profile_R: np.ndarray,
    profile_w: np.ndarray,
    R: float,
    w: float,
    path: str | Path,
    *,
    title: str = "",
) -> Path:
    """Per-profile (R, w) of a patch, R on a log axis, with the patch mean (Fig. 5)."""
    fig = _figure(6, 5)
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(profile_w, profile_R, s=12, color="0.5", label="profiles")
    ax.scatter([w], [R], s=90, facecolors="none", edgecolors="k", lw=2, label="patch")
    ax.set_yscale("log")
    ax.set_xlabel("w")
    ax.set_ylabel("R  [m³/rad]")
    ax.legend()
    ax.set_title(title or "Roughness parameters of the profiles of one patch")
    return _save(fig, path)


def psd_lines_vs_iso(
    surfaces: dict[str, tuple[float, float]],
    path: str | Path,
    *,
    patch: PatchSpec | None = None,
) -> Path:
    """Fitted PSD lines ``R Omega^w`` of surfaces against the ISO 8608 classes (Fig. 10).

    ``surfaces`` maps a name to (R in m³/rad, w). The lines span the waveband of ``patch``
    (the patch the features came from; default ``PatchSpec()``): from ``2 pi / L`` to the
    Nyquist ``pi / B`` rad/m.
    """
    spec = PatchSpec() if patch is None else patch
    band = (2 * np.pi / (spec.n * spec.spacing), np.pi / spec.spacing)
    fig = _figure(7, 5)
    ax = fig.add_subplot(1, 1, 1)
    om = np.geomspace(band[0], band[1], 50)
    for cls, phi in iso8608.PHI0.items():
        ax.loglog(om, phi * om**-2.0, color="tab:blue", lw=0.7, ls="--")
        ax.text(
            om[0],
            phi * om[0] ** -2.0,
            f"{cls} ",
            color="tab:blue",
            ha="right",
            fontsize=8,
            va="center",
        )
    for k, (name, (r, w)) in enumerate(surfaces.items()):
        c = _rgb01(name, k)
        ax.loglog(om, r * om**w, color=c, lw=2.2, label=f"{name}: R={r:.1e}, w={w:.2f}")
    ax.set_xlabel("Ω  [rad/m]")
    ax.set_ylabel("PSD  [m³/rad]")
    ax.legend(fontsize=8)
    ax.set_title("Fitted PSD of the surfaces against ISO 8608 classes (w = -2)")
    ax.grid(True, which="both", lw=0.3)
    return _save(fig, path)


def class_scatter(
    R: np.ndarray,
    w: np.ndarray,
    labels: Sequence[str],
    path: str | Path,
    *,
    level_edges: Sequence[float] | None = None,
) -> Path:
    """(R, w) by class with the low/medium/high roughness regions (Fig. 19).

    ``level_edges`` are the two R thresholds (m³/rad) between low/medium and medium/high.
    """
    fig = _figure(8, 5)
    fig.set_layout_engine("constrained")
    ax = fig.add_subplot(1, 1, 1)
    names = np.asarray(labels, dtype=object)
    ok = np.isfinite(R) & np.isfinite(w)
    if level_edges is not None and ok.any():
        wmin, wmax = np.nanmin(w[ok]) - 0.2, np.nanmax(w[ok]) + 0.2
        rmin, rmax = np.nanmin(R[ok]) / 3, np.nanmax(R[ok]) * 3
        edges = [rmin, *level_edges, rmax]
        for k, name in enumerate(("low", "medium", "high")):
            ax.axhspan(
                max(edges[k], rmin),
                min(edges[k + 1], rmax),
                color=_LEVEL_RGB[k],
                alpha=0.12,
                label=f"{name} roughness",
            )
        ax.set_xlim(wmin, wmax)
    for k, name in enumerate(dict.fromkeys(names[ok])):
        sel = ok & (names == name)
        c = _rgb01(str(name), k)
        ax.scatter(
            w[sel],
            R[sel],
            s=14,
            color=c,
            label=str(name) or "(unlabelled)",
            edgecolors="k",
            linewidths=0.2,
        )
    ax.set_yscale("log")
    ax.set_xlabel("w")
    ax.set_ylabel("R  [m³/rad]")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    ax.set_title("Roughness parameters by terrain class")
    return _save(fig, path)


def map_layers(
    layers: dict[str, np.ndarray],
    extent: tuple[float, float, float, float],
    path: str | Path,
    *,
    path_xy: np.ndarray | None = None,
    class_names: Sequence[str] = (),
    titles: dict[str, str] | None = None,
    labels: dict[str, str] | None = None,
) -> Path:
    """Map layers stacked vertically with the rover's path (Figs. 20, 21).

    ``layers`` maps a name to a 2-D array whose row 0 is the southern (min y) edge;
    ``extent`` is (x_min, x_max, y_min, y_max) in m. A layer named ``class`` is drawn with
    the class colours and a legend of the class names, ``level`` with low/medium/high
    colours, others with viridis and a colour bar labelled ``labels[name]``. All layers
    share one view: the box of the cells where any of them has data. The layout (scale bar
    and keys under each map, never over it) is :func:`rough_map.export.layout.draw_map_panels`.
    """
    titles = titles or {}
    labels = labels or {}
    arrays = {k: np.asarray(v, dtype=float) for k, v in layers.items()}
    known = np.zeros(next(iter(arrays.values())).shape, dtype=bool) if arrays else None
    for arr in arrays.values():
        known |= np.isfinite(arr)
    x0, x1, y0, y1 = (float(v) for v in extent)
    box = (x0, x1, y0, y1)
    view = data_view(known, box) if known is not None else box
    panels = []
    for name, arr in arrays.items():
        panel = MapPanel(
            data=arr,
            extent=box,
            title=titles.get(name, name),
            label=labels.get(name, name),
            view=view,
            track=path_xy,
            known=known,
        )
        if name == "class" and class_names:
            panel.categories = tuple(class_names)
            panel.colours = [tuple(_rgb01(c, i)) for i, c in enumerate(class_names)]
        elif name == "level":
            panel.categories = ("low", "medium", "high")
            panel.colours = _LEVEL_RGB
        panels.append(panel)
    # several layers stacked: at most 4 pages each, so the figure stays a few screens tall
    fig = draw_map_panels(panels, width=9.0, dpi=110, max_pages=4)
    return _save(fig, path, layout=False)


def _aligned(part: dict, names: list[str]) -> np.ndarray:
    """The row-normalised matrix of ``part`` on the class list ``names`` (zeros elsewhere)."""
    cm = np.asarray(part["confusion_matrix_normalized"], dtype=float)
    index = {c: i for i, c in enumerate(part["classes"])}
    out = np.zeros((len(names), len(names)))
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if a in index and b in index:
                out[i, j] = cm[index[a], index[b]]
    return out


def confusion_matrices(evaluation: dict, path: str | Path) -> Path:
    """Row-normalised confusion matrices, raw and filtered side by side, on one class list.

    ``evaluation`` has ``raw`` and ``filtered`` parts with ``classes``,
    ``confusion_matrix_normalized``, ``accuracy`` and ``macro_f1`` (as
    :func:`rough_map.evaluation.evaluate_model` returns them). Both matrices show the same
    classes in the same order (the union, if the parts differ); the row of a class that is
    never true (predicted only, not in the macro-F1) is hatched and marked "not in truth".
    """
    parts = [evaluation["raw"], evaluation["filtered"]]
    names = list(parts[0]["classes"])
    names += [c for c in parts[1]["classes"] if c not in names]
    if names != list(parts[0]["classes"]) or names != list(parts[1]["classes"]):
        names = sorted(names)
    scored = set(evaluation.get("scored_classes") or parts[0].get("scored_classes") or names)
    longest = max(len(n) for n in names) + (14 if scored != set(names) else 0)
    side = max(3.0, 0.75 * len(names))  # in, each matrix
    fig = _figure(2 * side + 0.09 * longest + 2.6, side + 0.08 * longest + 1.6)
    fig.set_layout_engine("constrained")
    axes = fig.subplots(1, 2)
    im = None
    for ax, key, part in zip(axes, ("raw", "filtered"), parts, strict=True):
        cm = _aligned(part, names)
        im = ax.imshow(cm, vmin=0.0, vmax=1.0, cmap="Blues")
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right")
        if key == "raw":  # the same rows on the right
            ax.set_yticks(
                range(len(names)), [n if n in scored else f"{n} (not in truth)" for n in names]
            )
            ax.set_ylabel("true class")
        else:
            ax.set_yticks(range(len(names)), [""] * len(names))
        ax.set_xlabel("predicted class")
        ax.set_title(
            f"{key}\nmacro-F1 {part['macro_f1']:.3f} over {len(scored)} true classes, "
            f"accuracy {part['accuracy']:.3f}",
            fontsize=10,
        )
        for i in range(cm.shape[0]):
            if names[i] not in scored:
                ax.axhspan(i - 0.5, i + 0.5, facecolor="0.92", edgecolor="0.6", hatch="//")
                continue
            for j in range(cm.shape[1]):
                ax.text(
                    j,
                    i,
                    f"{cm[i, j]:.2f}",
                    ha="center",
                    va="center",
                    color="white" if cm[i, j] > 0.5 else "black",
                    fontsize=8,
                )
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="fraction of the true class")
    return _save(fig, path, tight=True)
