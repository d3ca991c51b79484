"""Pages along the path: a long map drawn as a stack of views, each of a stretch of path.

At 1:1 aspect the map of a 60 m traverse is a strip 1 m wide in a frame 60 m long: a
picture 1000 pixels wide shows the strip 15 pixels tall, with the path line over it.
:func:`page_views` cuts such a map into pages: every known cell goes to the page of the
stretch of path it lies nearest to (by arc length along the vehicle track; without a track,
by distance along the long side of the map), and each page shows the box of its cells. The
pages are stacked top to bottom by :func:`rough_map.export.layout.draw_map_panels`, each at
1:1 aspect with its own x/y axes in m, so a page reads like a map sheet.

A map is paged only when it is long (its long side more than 1.5 page lengths and 3 times
its short side). A page covers ``page_length`` m of path, or more when that would take more
than ``max_pages`` pages: a long survey stays a readable overview in a few pages, and its
GeoTIFF holds every cell.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rough_map.errors import InputError

__all__ = ["Page", "page_views"]

#: Cells sampled to place the pages (a strided subset of the known cells of a large map).
_SAMPLE = 200_000


@dataclass(frozen=True)
class Page:
    """One page of a map: its view and the stretch of path it covers.

    Attributes
    ----------
    view : (float, float, float, float)
        ``(x_min, x_max, y_min, y_max)`` to draw, m.
    start, end : float
        The stretch covered, m along the path (or along the map's long side).
    along : str
        What ``start`` and ``end`` are measured along: ``"the path"``, ``"x"`` or ``"y"``.
    """

    view: tuple[float, float, float, float]
    start: float
    end: float
    along: str

    def label(self, index: int, count: int) -> str:
        """``"page 2/6: 10–20 m along the path"``."""
        return f"page {index + 1}/{count}: {self.start:.0f}–{self.end:.0f} m along {self.along}"


def _known_points(
    known: np.ndarray, extent: Sequence[float], view: Sequence[float], step: int
) -> np.ndarray:
    """Centres (n, 2) of every ``step``-th true cell of ``known`` (in rows and columns)
    inside ``view``."""
    ny, nx = known.shape
    x0, x1, y0, y1 = (float(v) for v in extent)
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    rows, cols = np.nonzero(known[::step, ::step])
    pts = np.column_stack([x0 + (cols * step + 0.5) * dx, y0 + (rows * step + 0.5) * dy])
    vx0, vx1, vy0, vy1 = view
    inside = (pts[:, 0] >= vx0) & (pts[:, 0] <= vx1) & (pts[:, 1] >= vy0) & (pts[:, 1] <= vy1)
    return pts[inside]


def _arc_positions(pts: np.ndarray, track: np.ndarray | None, long_axis: int) -> np.ndarray:
    """Each point's position in m along the track (that of its nearest track vertex), or
    along ``long_axis`` without a track."""
    if track is None or len(track) < 2:
        return pts[:, long_axis] - pts[:, long_axis].min()
    from scipy.spatial import cKDTree

    tr = np.asarray(track, dtype=float)[:, :2]
    tr = tr[np.all(np.isfinite(tr), axis=1)]
    if len(tr) < 2:
        return pts[:, long_axis] - pts[:, long_axis].min()
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(tr, axis=0).T))])
    _, nearest = cKDTree(tr).query(pts)
    return arc[nearest]


def page_views(
    known: np.ndarray,
    extent: Sequence[float],
    view: Sequence[float],
    track: np.ndarray | None = None,
    *,
    page_length: float = 10.0,
    max_pages: int = 8,
) -> list[Page]:
    """The pages to draw a map on (see the module docstring).

    Parameters
    ----------
    known : ndarray of bool, shape (rows, cols)
        Cells that hold data, row 0 at the southern edge.
    extent : (float, float, float, float)
        ``(x_min, x_max, y_min, y_max)`` of ``known``, m.
    view : (float, float, float, float)
        The whole area to draw, as ``extent``.
    track : ndarray, shape (n, 2), optional
        Vehicle path (x, y), m.
    page_length : float
        Stretch of path per page, m.
    max_pages : int
        Most pages; longer maps get longer pages.

    Returns
    -------
    list of Page
        One page (the whole ``view``) when the map is not long.
    """
    if not (math.isfinite(page_length) and page_length > 0):
        raise InputError(f"page_length must be a positive length in m, got {page_length!r}")
    if max_pages < 1:
        raise InputError(f"max_pages must be at least 1, got {max_pages!r}")
    vx0, vx1, vy0, vy1 = (float(v) for v in view)
    sides = (vx1 - vx0, vy1 - vy0)
    long_axis = int(sides[1] > sides[0])
    long, short = max(sides), max(min(sides), 1e-9)
    whole = [Page((vx0, vx1, vy0, vy1), 0.0, long, "the map")]
    if max_pages == 1 or long <= 1.5 * page_length or long <= 3 * short:
        return whole
    known = np.asarray(known, dtype=bool)
    step = max(1, math.ceil(math.sqrt(known.size / _SAMPLE)))
    pts = _known_points(known, extent, (vx0, vx1, vy0, vy1), step)
    if len(pts) == 0:
        return whole
    s = _arc_positions(pts, track, long_axis)
    along = "the path" if track is not None and len(track) >= 2 else "xy"[long_axis]
    lo, hi = float(s.min()), float(s.max())
    length = max(page_length, (hi - lo) / max_pages)
    count = max(1, math.ceil((hi - lo) / length - 1e-9))
    page = np.minimum(((s - lo) / length).astype(int), count - 1)
    ny, nx = known.shape
    cell = max((extent[1] - extent[0]) / nx, (extent[3] - extent[2]) / ny)
    pad = max(2 * cell, 0.15) + step * cell
    pages = []
    for k in range(count):
        mine = pts[page == k]
        if len(mine) == 0:  # a stretch of path with no data
            continue
        (px0, py0), (px1, py1) = mine.min(axis=0) - pad, mine.max(axis=0) + pad
        box = (max(vx0, px0), min(vx1, px1), max(vy0, py0), min(vy1, py1))
        start = lo + k * length
        pages.append(Page(box, start, min(hi, start + length), along))
    return pages or whole
