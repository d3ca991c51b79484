"""The row width a features table was read in, and a model's check of it.

A traverse read with ``--spacing auto`` over ground that is the same across the track keeps
the 8 mm step in rows wider than long (:func:`rough_map.patch.pooled_rows`). Its table
records the width (``FeatureTable.row_spacing``, m), a terrain model records the width of
each training traverse in ``training_``, and :func:`warn_other_rows` says when a table
to classify was read in other rows. Pooled rows are only chosen over ground that is the
same across the track, where the spectrum along it is the same, so this is a warning.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

__all__ = ["row_width", "warn_other_rows"]

log = logging.getLogger("rough_map.classify.model")


def row_width(table: Any) -> float | None:
    """The table's row width in m (None: square cells, or a table without the field)."""
    width = getattr(table, "row_spacing", None)
    return None if width is None else float(width)


def warn_other_rows(training: Mapping[str, Any], table: Any) -> None:
    """Log a warning when ``table`` was read in rows of another width than every training
    traverse in ``training`` (a model's ``training_``). Models saved before the training
    summary recorded the width are not checked."""
    traverses = training.get("traverses", [])
    trained = [
        t["row_spacing_m"]
        for t in (traverses if isinstance(traverses, list) else [])
        if isinstance(t, dict) and "row_spacing_m" in t
    ]
    if not trained:
        return
    got = row_width(table)
    if any(_same(got, t) for t in trained):
        return
    log.warning(
        "traverse %.40r: its profiles were read in %s, the model's training traverses in "
        "%s; the spectra compare only on ground that is the same across the track",
        getattr(table, "name", "?"),
        _text(got),
        " or ".join(sorted({_text(t) for t in trained})),
    )


def _same(a: Any, b: Any) -> bool:
    """Two row widths (m, None for square cells) are the same."""
    if a is None or b is None:
        return a is None and b is None
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-6)
    except (TypeError, ValueError):
        return False


def _text(width: Any) -> str:
    """``rows 32.0 mm wide`` or ``square cells``."""
    if width is None:
        return "square cells"
    try:
        return f"rows {float(width) * 1e3:.1f} mm wide"
    except (TypeError, ValueError):
        return f"rows of width {width!r:.20}"
