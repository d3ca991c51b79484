"""The paper's figures, drawn with matplotlib (Agg) from real runs.

Every function takes the data it draws and an output path, writes one PNG atomically and
returns the path. Figure numbers refer to Reina et al., *Mind the ground*.

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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rough_map import iso8608
from rough_map.export.profiles import CLASS_COLOURS, LEVEL_COLOURS

log = logging.getLogger(__name__)

_LEVEL_RGB = [tuple(v / 255 for v in c) for c in LEVEL_COLOURS]  # matplotlib colours


def class_colour(name: str, index: int = 0) -> tuple[int, int, int]:
    """RGB of a class; classes not in :data:`CLASS_COLOURS` get a tab10 colour."""
    if name in CLASS_COLOURS:
        return CLASS_COLOURS[name]
    import matplotlib

    r, g, b, _ = matplotlib.colormaps["tab10"](index % 10)
    return int(255 * r), int(255 * g), int(255 * b)


def _figure(width: float = 8.0, height: float = 5.0):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt, plt.figure(figsize=(width, height), dpi=110)


def _save(plt, fig, path: str | Path) -> Path:
    from rough_map.io.pointcloud import atomic_output

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
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
    title: str = "",
) -> Path:
    """R (log scale, m^3/rad) and w along the path (m) with 1-sigma bands (Figs. 7, 9, 12).

    ISO 8608 class centres A-H are drawn as reference lines on the R panel; the true or
    predicted labels, if given, shade the background; frames flagged in ``defects`` (bool
    per frame, isolated defects such as a manhole) are marked on the R curve.
    """
    plt, fig = _figure(9, 6)
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    d = np.asarray(distance, float)
    ok = np.isfinite(R) & np.isfinite(w)
    lo = np.clip(R - sigma_R, R * 0.05, None)
    ax1.fill_between(d, lo, R + sigma_R, where=ok, color="0.8", label="±1σ")
    ax1.plot(d[ok], R[ok], "k-", lw=1.2, label="R")
    ax1.set_yscale("log")
    ymin, ymax = (
        np.nanmin(lo[ok]) if ok.any() else 1e-6,
        np.nanmax((R + sigma_R)[ok]) if ok.any() else 1e-2,
    )
    for cls, phi in iso8608.PHI0.items():
        if ymin / 3 < phi < ymax * 3:
            ax1.axhline(phi, color="tab:blue", lw=0.6, ls="--")
            ax1.text(
                d[0] if d.size else 0, phi, f" ISO {cls}", color="tab:blue", fontsize=8, va="bottom"
            )
    if defects is not None and len(defects) == d.size:
        flagged = np.asarray(defects, dtype=bool) & ok
        if flagged.any():
            ax1.plot(d[flagged], R[flagged], "v", color="tab:red", ms=5, label="isolated defect")
    ax1.set_ylabel("R  [m³/rad]")
    ax2.fill_between(d, w - sigma_w, w + sigma_w, where=ok, color="0.8")
    ax2.plot(d[ok], w[ok], "k-", lw=1.2)
    ax2.axhline(-2.0, color="tab:blue", lw=0.6, ls="--")
    ax2.set_ylabel("w")
    ax2.set_xlabel("distance along the path [m]")
    if labels is not None and len(labels) == d.size:
        names = list(dict.fromkeys(labels))
        for k, name in enumerate(names):
            sel = np.asarray(labels) == name
            if not name or not sel.any():
                continue
            c = np.array(class_colour(name, k)) / 255
            for ax in (ax1, ax2):
                ax.fill_between(
                    d,
                    0,
                    1,
                    where=sel,
                    color=c,
                    alpha=0.15,
                    transform=ax.get_xaxis_transform(),
                    step="mid",
                    label=name if ax is ax1 else None,
                )
    ax1.legend(loc="upper right", fontsize=8, ncol=3)
    if title:
        ax1.set_title(title)
    return _save(plt, fig, path)


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
    """PSD of one profile (m^3/rad) against Omega (rad/m) with its fit R Omega^w (Fig. 4)."""
    plt, fig = _figure(7, 5)
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
    return _save(plt, fig, path)


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
    plt, fig = _figure(6, 5)
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(profile_w, profile_R, s=12, color="0.5", label="profiles")
    ax.scatter([w], [R], s=90, facecolors="none", edgecolors="k", lw=2, label="patch")
    ax.set_yscale("log")
    ax.set_xlabel("w")
    ax.set_ylabel("R  [m³/rad]")
    ax.legend()
    ax.set_title(title or "Roughness parameters of the profiles of one patch")
    return _save(plt, fig, path)


def psd_lines_vs_iso(
    surfaces: dict[str, tuple[float, float]],
    path: str | Path,
    *,
    band: tuple[float, float] = (2 * np.pi / 0.896, np.pi / 0.008),
) -> Path:
    """Fitted PSD lines ``R Omega^w`` of surfaces against the ISO 8608 classes (Fig. 10).

    ``surfaces`` maps a name to (R in m^3/rad, w).
    """
    plt, fig = _figure(7, 5)
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
        c = np.array(class_colour(name, k)) / 255
        ax.loglog(om, r * om**w, color=c, lw=2.2, label=f"{name}: R={r:.1e}, w={w:.2f}")
    ax.set_xlabel("Ω  [rad/m]")
    ax.set_ylabel("PSD  [m³/rad]")
    ax.legend(fontsize=8)
    ax.set_title("Fitted PSD of the surfaces against ISO 8608 classes (w = -2)")
    ax.grid(True, which="both", lw=0.3)
    return _save(plt, fig, path)


def class_scatter(
    R: np.ndarray,
    w: np.ndarray,
    labels: Sequence[str],
    path: str | Path,
    *,
    level_edges: tuple[float, float] | None = None,
) -> Path:
    """(R, w) by class with the low/medium/high roughness regions (Fig. 19).

    ``level_edges`` are the two R thresholds (m^3/rad) between low/medium and medium/high.
    """
    plt, fig = _figure(7, 5)
    ax = fig.add_subplot(1, 1, 1)
    labels = np.asarray(labels, dtype=object)
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
    for k, name in enumerate(dict.fromkeys(labels[ok])):
        sel = ok & (labels == name)
        c = np.array(class_colour(str(name), k)) / 255
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
    ax.legend(fontsize=8, ncol=2)
    ax.set_title("Roughness parameters by terrain class")
    return _save(plt, fig, path)


def map_layers(
    layers: dict[str, np.ndarray],
    extent: tuple[float, float, float, float],
    path: str | Path,
    *,
    path_xy: np.ndarray | None = None,
    class_names: Sequence[str] = (),
    titles: dict[str, str] | None = None,
) -> Path:
    """Map layers stacked vertically with the rover's path (Figs. 20, 21).

    ``layers`` maps a name to a 2-D array whose row 0 is the southern (min y) edge;
    ``extent`` is (x_min, x_max, y_min, y_max) in m. A layer named ``class`` is drawn with
    the class colours, ``level`` with low/medium/high colours, others with viridis.
    """
    from matplotlib.colors import BoundaryNorm, ListedColormap

    n = len(layers)
    width = 10.0
    span_x, span_y = extent[1] - extent[0], extent[3] - extent[2]
    height = max(2.0, min(4.0, width * span_y / max(span_x, 1e-6))) * n + 0.6
    plt, fig = _figure(width, height)
    titles = titles or {}
    for k, (name, arr) in enumerate(layers.items(), start=1):
        ax = fig.add_subplot(n, 1, k)
        data = np.ma.masked_invalid(np.asarray(arr, float))
        if name == "class" and class_names:
            cols = [np.array(class_colour(c, i)) / 255 for i, c in enumerate(class_names)]
            cmap = ListedColormap(cols)
            norm = BoundaryNorm(np.arange(len(class_names) + 1) - 0.5, len(class_names))
            im = ax.imshow(
                data, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest"
            )
            cb = fig.colorbar(im, ax=ax, ticks=range(len(class_names)), fraction=0.025)
            cb.ax.set_yticklabels(class_names, fontsize=7)
        elif name == "level":
            cmap = ListedColormap(_LEVEL_RGB)
            norm = BoundaryNorm([-0.5, 0.5, 1.5, 2.5], 3)
            im = ax.imshow(
                data, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest"
            )
            cb = fig.colorbar(im, ax=ax, ticks=[0, 1, 2], fraction=0.025)
            cb.ax.set_yticklabels(["low", "medium", "high"], fontsize=7)
        else:
            im = ax.imshow(
                data, origin="lower", extent=extent, cmap="viridis", interpolation="nearest"
            )
            fig.colorbar(im, ax=ax, fraction=0.025)
        if path_xy is not None and len(path_xy):
            ax.plot(path_xy[:, 0], path_xy[:, 1], "-", color="tab:blue", lw=1.2)
        ax.set_title(titles.get(name, name), fontsize=10)
        ax.set_aspect("equal")
        ax.set_ylabel("y [m]")
    ax.set_xlabel("x [m]")
    return _save(plt, fig, path)


def confusion_matrices(evaluation: dict, path: str | Path) -> Path:
    """Row-normalised confusion matrices, raw and filtered side by side.

    ``evaluation`` has ``raw`` and ``filtered`` parts with ``classes``,
    ``confusion_matrix_normalized``, ``accuracy`` and ``macro_f1``.
    """
    plt, fig = _figure(11, 4.8)
    fig.set_layout_engine("constrained")
    axes = fig.subplots(1, 2)
    im = None
    for ax, key in zip(axes, ("raw", "filtered"), strict=True):
        part = evaluation[key]
        cm = np.asarray(part["confusion_matrix_normalized"], dtype=float)
        names = part["classes"]
        im = ax.imshow(cm, vmin=0.0, vmax=1.0, cmap="Blues")
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right")
        ax.set_yticks(range(len(names)), names)
        ax.set_xlabel("predicted class")
        ax.set_ylabel("true class")
        ax.set_title(f"{key}: macro-F1 {part['macro_f1']:.3f}, accuracy {part['accuracy']:.3f}")
        for i in range(cm.shape[0]):
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
    return _save(plt, fig, path)
