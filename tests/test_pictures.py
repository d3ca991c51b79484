"""Pictures a person reads at a glance: pages along the path, keys, palette, empty maps.

The map PNGs and the report's figures of a long traverse, checked in matplotlib (every
text inside the picture, none overlapping, one key per map) and in headless Chromium
(every picture loads, is shown at a readable size and is not absurdly tall).
"""

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest
from browser import CHECKER, needs_chromium

from rough_map import iso8608
from rough_map.export.layout import MapPanel, draw_map_panels, drawn_texts
from rough_map.export.pages import page_views
from rough_map.export.png import layer_figure, write_pngs
from rough_map.export.profiles import CLASS_COLOURS, LEVEL_COLOURS
from rough_map.features import FeatureTable
from rough_map.map import EmptyMapWarning, fuse_traverse
from rough_map.terrain import SURFACES

CLASS_NAMES = tuple(SURFACES)


def _table(x, y, R) -> FeatureTable:
    n = len(x)
    yaw = np.arctan2(np.gradient(y), np.gradient(x)) if n > 1 else np.zeros(n)
    cols = {"frame": np.arange(n), "t": np.arange(n) * 0.5, "x": x, "y": y, "yaw": yaw,
            "R": R, "w": np.full(n, -2.2), "sigma_R": R * 0.2, "sigma_w": np.full(n, 0.1),
            "valid": np.ones(n, bool)}  # fmt: skip
    return FeatureTable(cols, np.zeros(0), np.zeros((n, 0)), "pictures")


def _long_map(length: float = 60.0, *, bend: float = 2.0):
    """A traverse of ``length`` m along x, wiggling ``bend`` m to the side, 5 classes."""
    x = np.arange(0.0, length, 0.25)
    y = bend * np.sin(x / length * 2 * np.pi)
    n = x.size
    R = np.geomspace(3e-6, 3e-3, n)
    k = len(CLASS_NAMES)
    probs = np.full((n, k), 0.05)
    probs[np.arange(n), (np.arange(n) * k) // n] = 0.8
    g = fuse_traverse(_table(x, y, R), probs, CLASS_NAMES, (np.arange(n) * 3) // n)
    g.attrs["track"] = np.column_stack([x, y])
    return g


@pytest.fixture(scope="module")
def long_map():
    return _long_map()


# -- pages along the path ---------------------------------------------------------------------


def test_a_long_map_is_drawn_in_pages_at_one_scale(long_map):
    fig = layer_figure(long_map, "R")
    maps = [ax for ax in fig.axes if ax.images]
    assert 5 <= len(maps) <= 8  # 60 m of path, 10 m a page
    scales = []
    for ax in maps:
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        box = ax.get_window_extent()
        scales.append(box.width / (x1 - x0))
        assert box.width / (x1 - x0) == pytest.approx(box.height / (y1 - y0), rel=0.02)  # 1:1
        assert (x1 - x0) <= 13.0  # a page is about 10 m of path, not the whole strip
    assert max(scales) == pytest.approx(min(scales), rel=0.01)
    # the 1 m strip is drawn at least 50 px wide (it was 15 px on one 60 m frame)
    assert min(scales) * 0.9 >= 50
    # one key: one colour bar, one scale bar
    bars = [ax for ax in fig.axes if not ax.images]
    assert len(bars) == 1
    assert sum(t.get_text().endswith(" m") for t in fig.texts) == 1
    titles = [ax.get_title() for ax in maps]
    assert titles[0].startswith("pictures: R") and "page 1/" in titles[0]
    assert all("m along the path" in t for t in titles)


def test_every_cell_is_on_a_page(long_map):
    known = np.isfinite(long_map["R"])
    x0, y0, x1, y1 = long_map.geometry.bounds
    extent = (x0, x1, y0, y1)
    pages = page_views(known, extent, extent, long_map.attrs["track"])
    rows, cols = np.nonzero(known)
    res = long_map.resolution
    px, py = x0 + (cols + 0.5) * res, y0 + (rows + 0.5) * res
    on_some = np.zeros(px.size, bool)
    for pg in pages:
        vx0, vx1, vy0, vy1 = pg.view
        on_some |= (px >= vx0) & (px <= vx1) & (py >= vy0) & (py <= vy1)
    assert on_some.all()
    starts = [pg.start for pg in pages]
    track = long_map.attrs["track"]
    arc = np.hypot(*np.diff(track, axis=0).T).sum()  # a little over 60 m: the path bends
    assert starts == sorted(starts) and pages[-1].end <= arc + 1e-9


def test_short_maps_and_the_page_limit():
    short = _long_map(12.0)
    fig = layer_figure(short, "R")
    assert sum(bool(ax.images) for ax in fig.axes) == 1
    known = np.ones((10, 4000), bool)  # a 400 m strip without a track: pages along x
    pages = page_views(known, (0, 400, 0, 1), (0, 400, 0, 1), page_length=10.0, max_pages=8)
    assert len(pages) == 8 and all(pg.along == "x" for pg in pages)
    assert pages[0].end - pages[0].start == pytest.approx(50.0, abs=0.2)
    fig = draw_map_panels([MapPanel(np.ones((10, 4000)), (0, 400, 0, 1))], page_length=None)
    assert sum(bool(ax.images) for ax in fig.axes) == 1


LAYERS = ["R", "w", "sigma_R", "level", "count", "class", "p_gravel", "last_seen"]


@pytest.mark.parametrize("layer", LAYERS)
def test_every_text_fits_and_every_map_has_a_key(long_map, layer):
    fig = layer_figure(long_map, layer)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    width, height = fig.bbox.width, fig.bbox.height
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in drawn_texts(fig)]
    for k, (text, b) in enumerate(boxes):
        assert b.x0 >= 0 and b.y0 >= 0 and b.x1 <= width and b.y1 <= height, text  # not clipped
        for other, b2 in boxes[k + 1 :]:
            assert not (b.x0 < b2.x1 and b2.x0 < b.x1 and b.y0 < b2.y1 and b2.y0 < b.y1), (
                text,
                other,
            )
    keyed = bool(fig.legends) or any(not ax.images for ax in fig.axes)
    assert keyed, f"{layer} has neither a legend nor a colour bar"


def test_R_is_on_decades_with_the_iso_classes(long_map):
    fig = layer_figure(long_map, "R")
    fig.canvas.draw()
    bar = next(ax for ax in fig.axes if not ax.images)
    ticks = [t for t in bar.get_xticks() if bar.get_xlim()[0] <= t <= bar.get_xlim()[1]]
    assert len(ticks) >= 2 and all(math.log10(t).is_integer() for t in ticks)
    letters = {t.get_text() for t in bar.texts if t.get_gid() == "iso-class"}
    lo, hi = bar.get_xlim()
    inside = {c for c in iso8608.CLASSES if lo < iso8608.PHI0[c] < hi}
    assert letters and letters <= set(iso8608.CLASSES) and len(letters) >= len(inside) - 1
    lines = [ln.get_xdata()[0] for ln in bar.lines if ln.get_gid() == "iso-class"]
    assert sorted(lines) == sorted(v for v in iso8608.LOWER.values() if lo < v < hi)


def test_counts_are_discrete_levels(long_map):
    from matplotlib.colors import BoundaryNorm

    fig = layer_figure(long_map, "count")
    norm = fig.axes[0].images[0].norm
    assert isinstance(norm, BoundaryNorm)
    counts = long_map["count"][long_map["count"] > 0]
    assert list(norm.boundaries) == [k + 0.5 for k in range(int(counts.max()) + 1)]
    bar = next(ax for ax in fig.axes if not ax.images)
    labels = [t.get_text() for t in bar.get_xticklabels() if t.get_text()]
    assert labels and all(s.isdigit() for s in labels)


def test_a_share_is_drawn_on_0_to_1(tmp_path):
    g = _long_map(8.0)
    g.add_layer("far_confidence", units="1", description="a share", data=np.where(
        np.isfinite(g["R"]), 0.9, np.nan))  # fmt: skip
    fig = layer_figure(g, "far_confidence")
    norm = fig.axes[0].images[0].norm
    assert (norm.vmin, norm.vmax) == (0.0, 1.0)


def test_an_empty_map_says_no_data(tmp_path):
    with pytest.warns(EmptyMapWarning):
        g = fuse_traverse(_table(np.zeros(0), np.zeros(0), np.zeros(0)), np.zeros((0, 5)),
                          CLASS_NAMES)  # fmt: skip
    for layer in ("R", "class"):
        fig = layer_figure(g, layer)
        texts = [t.get_text() for t in drawn_texts(fig)]
        assert "no data" in texts and any(t.startswith("no data:") for t in texts)
        assert not fig.legends and all(ax.images for ax in fig.axes)  # no key of nothing


# -- the palette ---------------------------------------------------------------------------


def _linear(rgb):
    c = np.asarray(rgb, float) / 255
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _lab(linear):
    xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722],
                    [0.0193, 0.1192, 0.9505]]) @ linear  # fmt: skip
    t = xyz / np.array([0.95047, 1.0, 1.08883])
    f = np.where(t > (6 / 29) ** 3, np.cbrt(t), t / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


#: Machado, Oliveira & Fernandes (2009), severity 1.0.
CVD = {
    "protanopia": [[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216],
                   [-0.003882, -0.048116, 1.051998]],
    "deuteranopia": [[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                     [-0.011820, 0.042940, 0.968881]],
    "tritanopia": [[1.255528, -0.076749, -0.178779], [-0.078411, 0.930809, 0.147602],
                   [0.004733, 0.691367, 0.303900]],
}  # fmt: skip


@pytest.mark.parametrize(
    ("palette", "least_lightness"),
    [(dict(CLASS_COLOURS), 13.0), (dict(enumerate(LEVEL_COLOURS)), 25.0)],
)
def test_the_palettes_are_colour_blind_safe(palette, least_lightness):
    for (a, ca), (b, cb) in itertools.combinations(palette.items(), 2):
        la, lb = _lab(_linear(ca)), _lab(_linear(cb))
        assert abs(la[0] - lb[0]) >= least_lightness, (a, b)  # apart in grey too
        for kind, m in CVD.items():
            sa = _lab(np.clip(np.array(m) @ _linear(ca), 0, 1))
            sb = _lab(np.clip(np.array(m) @ _linear(cb), 0, 1))
            assert np.linalg.norm(sa - sb) >= 20.0, (a, b, kind)


# -- in a browser --------------------------------------------------------------------------


@needs_chromium
def test_every_map_picture_in_a_browser(tmp_path, long_map):
    """Every PNG of a 60 m map, on one page in headless Chromium at a laptop's size."""
    paths = write_pngs(long_map, tmp_path)
    figures = "".join(
        f"<figure><img src='{p.name}' alt='{layer}' style='max-width:100%'>"
        f"<figcaption>{layer}</figcaption></figure>"
        for layer, p in paths.items()
    )
    page = tmp_path / "index.html"
    head = "<!doctype html><html><head><meta charset='utf-8'><title>maps</title></head>"
    page.write_text(f"{head}<body><h1>maps</h1>{figures}</body></html>", encoding="utf-8")
    shot = tmp_path / "shot.png"
    res = subprocess.run(
        [sys.executable, str(CHECKER), str(page), "--size", "1366x768", "--size", "1024x768",
         "--screenshot", str(shot)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    import matplotlib.image as mpimg

    pixels = mpimg.imread(shot)  # the whole page as Chromium drew it
    assert pixels.shape[1] == 1366 and pixels.shape[0] > 768 * len(paths) / 3
    assert pixels[..., :3].std() > 0.05  # drawn, not blank
