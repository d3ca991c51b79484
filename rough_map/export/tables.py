"""HTML tables of the report: numbers right-aligned, wide tables scrolling in their own box.

Values are shown as a person reads them: floats with 3 decimals, NaN as a dash, booleans as
yes/no; lists, dicts and dataclasses become rows, never a Python repr.
"""

from __future__ import annotations

import dataclasses
import html
import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["Html", "any_table", "cell_text", "link", "plain", "table"]


class Html(str):
    """Cell content that is already HTML (a link)."""


def link(href: str, text: str | None = None) -> Html:
    """An ``<a>`` to ``href`` (escaped), showing ``text`` (default the href)."""
    return Html(f"<a href='{html.escape(href)}'>{html.escape(text or href)}</a>")


def plain(v: Any) -> Any:
    """JSON fallback of numpy values: numbers and lists; anything else as text."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def cell_text(v: Any) -> str:
    """A value as shown in a cell: 3 decimals, a dash for NaN, yes/no."""
    if isinstance(v, bool | np.bool_):
        return "yes" if v else "no"
    if isinstance(v, float | np.floating):
        return "–" if not math.isfinite(float(v)) else f"{float(v):.3f}"
    if isinstance(v, np.integer):
        return str(int(v))
    return str(v)


def _is_number(v: Any) -> bool:
    if isinstance(v, bool | np.bool_ | Html):
        return False
    if isinstance(v, int | float | np.number):
        return True
    try:
        float(str(v).replace(",", "").replace("×", "").replace("−", "-"))
    except ValueError:
        return False
    return True


def table(
    head: Sequence[Any],
    rows: Sequence[Sequence[Any]],
    caption: str = "",
    *,
    text_columns: Sequence[int] = (),
) -> str:
    """An HTML table in a box that scrolls sideways when the table is wider than the page.

    Numeric columns are right-aligned; ``text_columns`` wrap their long text. Cells that
    are :class:`Html` go in as they are, others are escaped.
    """
    esc = html.escape
    ncol = max([len(head), *(len(r) for r in rows)])
    numeric = [
        bool(rows) and all(i >= len(r) or r[i] == "" or _is_number(r[i]) for r in rows)
        for i in range(ncol)
    ]

    def attrs(i: int) -> str:
        cls = [c for c, on in (("num", numeric[i]), ("text", i in text_columns)) if on]
        return f" class='{' '.join(cls)}'" if cls else ""

    out = ["<div class='table-box'><table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    if any(str(h) for h in head):
        cells = "".join(f"<th{attrs(i)}>{esc(str(h))}</th>" for i, h in enumerate(head))
        out.append(f"<thead><tr>{cells}</tr></thead>")
    out.append("<tbody>")
    for r in rows:
        cells = "".join(
            f"<td{attrs(i)}>{v if isinstance(v, Html) else esc(cell_text(v))}</td>"
            for i, v in enumerate(r)
        )
        out.append(f"<tr>{cells}</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


def _accuracy_table(t: Any, caption: str) -> str:
    """An accuracy-by-distance table (``edges`` in m, ``n``, ``n_confident``, accuracies)."""
    rows = [
        [
            f"{t.edges[k]:g}–{t.edges[k + 1]:g}",
            int(t.n[k]),
            int(t.n_confident[k]),
            float(t.accuracy[k]),
            float(t.accuracy_all[k]),
        ]
        for k in range(len(t.n))
    ]
    head = [
        "distance [m]",
        "cells",
        f"confident (p ≥ {t.threshold:g})",
        "accuracy (confident)",
        "accuracy (all)",
    ]
    return table(head, rows, caption)


def any_table(value: Any, caption: str = "") -> str:
    """An HTML table of a value of the report: an accuracy table, rows of dicts, a dict."""
    if all(hasattr(value, a) for a in ("edges", "n", "n_confident", "accuracy", "accuracy_all")):
        return _accuracy_table(value, caption)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, list) and value and isinstance(value[0], dict):
        head = list(value[0])
        return table(head, [[r.get(h, "") for h in head] for r in value], caption)
    if isinstance(value, dict):
        rows = [[k, _plain_text(v)] for k, v in value.items()]
        return table(["", "value"], rows, caption, text_columns=(1,))
    return f"<p>{html.escape(caption)}: {html.escape(_plain_text(value))}</p>"


def _plain_text(v: Any) -> Any:
    if isinstance(v, float | int | np.generic | str):
        return v
    if isinstance(v, np.ndarray | list | tuple):
        return ", ".join(cell_text(x) for x in np.asarray(v).ravel())
    return json.dumps(v, default=plain)
