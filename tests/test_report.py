"""The HTML report (``rough-map report``) as a person reads it, and in a real browser.

The browser checks run ``tools/check_report.py`` (headless Chromium through the DevTools
pipe) as CI does; they are skipped only when no Chromium binary is found.
"""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from browser import CHECKER, needs_chromium

from rough_map.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    """``rough-map report`` of a short simulated mixed course (labelled, no images)."""
    root = tmp_path_factory.mktemp("report")
    sim, out = root / "sim", root / "rep"
    assert main(["-q", "simulate", "--out", str(sim), "--course", "mixed", "--length", "8",
                 "--seed", "3", "--no-images"]) == 0  # fmt: skip
    assert main(["-q", "report", str(sim), "--out", str(out)]) == 0
    return out / "index.html"


class Page(HTMLParser):
    """The tags of a page, with each <img>'s enclosing <figure> and its <figcaption>."""

    def __init__(self) -> None:
        super().__init__()
        self.stack: list[str] = []
        self.tags: list[str] = []
        self.images: list[dict] = []
        self.figures: list[dict] = []
        self.links: list[str] = []
        self._caption: dict | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if tag == "figure":
            self.figures.append({"images": [], "caption": ""})
        if tag == "img":
            fig = self.figures[-1] if "figure" in self.stack else None
            self.images.append({"src": a.get("src"), "figure": fig})
            if fig is not None:
                fig["images"].append(a.get("src"))
        if tag == "figcaption" and "figure" in self.stack:
            self._caption = self.figures[-1]
        if tag == "a" and a.get("href"):
            self.links.append(a["href"])
        if tag not in ("img", "meta", "br", "link"):
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in self.stack:
            while self.stack.pop() != tag:
                pass
        if tag == "figcaption":
            self._caption = None

    def handle_data(self, data):
        if self._caption is not None:
            self._caption["caption"] += data


def parse(path: Path) -> tuple[str, Page]:
    text = path.read_text(encoding="utf-8")
    page = Page()
    page.feed(text)
    return text, page


def test_report_shows_tables_not_reprs(report):
    text, page = parse(report)
    assert "<pre" not in text and "array(" not in text
    assert not re.search(r"\b[A-Z]\w*\(\w+=", text)  # no dataclass repr
    assert page.tags.count("table") >= 4  # summary, evaluation, per class, matrices, files
    assert "m^3" not in text and "m³/rad" in text


def test_every_figure_has_a_caption(report):
    _, page = parse(report)
    figs = sorted(p.name for p in report.parent.glob("fig_*.png"))
    assert sorted(i["src"] for i in page.images) == figs  # every figure shown, once
    for img in page.images:
        assert img["figure"] is not None, img["src"]
        assert len(img["figure"]["caption"].split()) >= 12, img  # a sentence, not a name


def test_the_report_leads_with_the_map(report):
    _, page = parse(report)
    assert page.tags.index("figure") < page.tags.index("table")  # figures, then tables
    assert page.images[0]["src"] == "fig_map_class.png"


def test_report_links_geotiffs_layer_pngs_and_tables(report):
    _, page = parse(report)
    out = report.parent
    links = set(page.links)
    assert {p.name for p in out.glob("*.tif")} <= links and "map.tif" in links
    layer_pngs = {p.name for p in out.glob("map_*.png")}
    assert {"map_R.png", "map_class.png", "map_p_gravel.png"} <= layer_pngs <= links
    assert {"features.csv", "labels.csv", "evaluation.json"} <= links
    for href in links:
        if not href.startswith("#"):
            assert (out / href).is_file(), href


def test_report_says_which_classes_the_macro_f1_scores(report):
    text, _ = parse(report)
    ev = json.loads((report.parent / "evaluation.json").read_text())
    assert ev["raw"]["classes"] == ev["filtered"]["classes"]
    truth = ev["scored_classes"]
    with open(report.parent / "labels.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert truth == sorted({r["label"] for r in rows if r["valid"] == "true"} - {""})
    assert f"mean F1 over the {len(truth)} classes present in the truth: " in text
    assert ", ".join(truth) in text


def run_checker(page: Path, *args: str) -> tuple[int, dict]:
    proc = subprocess.run(
        [sys.executable, str(CHECKER), str(page), "--json", *args],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode in (0, 1), proc.stderr
    return proc.returncode, json.loads(proc.stdout)


@needs_chromium
def test_report_in_a_browser(report):
    code, res = run_checker(report, "--size", "1366x768", "--size", "1024x768")
    assert code == 0, res["failures"]
    for f in res["findings"]:
        assert f["scrollWidth"] <= f["clientWidth"], f
        assert f["images"] == f["images_loaded"] >= 5
        assert f["tables"] >= 4


@needs_chromium
def test_a_wide_table_scrolls_in_its_own_box(report):
    """40 columns of numbers: the table scrolls, the page does not."""
    from rough_map.export.tables import table

    wide = table([f"column {k} [m³/rad]" for k in range(40)], [list(np.arange(40) * 1e-4)])
    text = report.read_text(encoding="utf-8").replace("</body>", wide + "</body>")
    page = report.with_name("wide.html")
    page.write_text(text, encoding="utf-8")
    code, res = run_checker(page, "--size", "1366x768")
    assert code == 0, res["failures"]


@needs_chromium
def test_the_checker_finds_what_is_wrong(tmp_path):
    (tmp_path / "ok.png").write_bytes(_png())
    (tmp_path / "tall.png").write_bytes(_png((5000, 2)))
    (tmp_path / "huge.png").write_bytes(_png((2, 3000)))
    (tmp_path / "index.html").write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>bad</title></head><body>"
        "<h1>bad</h1><div style='width:3000px'>wide</div>"
        "<figure><img src='ok.png' alt=''><figcaption>fine</figcaption></figure>"
        "<img src='missing.png' alt=''>"
        "<figure><img src='tall.png' alt=''><figcaption>tall</figcaption></figure>"
        "<figure><img src='huge.png' alt='' style='max-width:100%'><figcaption>wide"
        "</figcaption></figure>"
        "<a href='nowhere.tif'>x</a><a href='#nope'>y</a>"
        "<p>AccuracyTable(edges=array([0. , 1.5]))</p></body></html>",
        encoding="utf-8",
    )
    code, res = run_checker(tmp_path / "index.html", "--size", "1366x768")
    assert code == 1
    text = "\n".join(res["failures"])
    assert "horizontal overflow: scrollWidth 3" in text and "div" in text
    assert "image 'missing.png' does not load" in text
    assert "image 'missing.png' has no <figure>" in text and "'ok.png'" not in text
    assert "nowhere.tif" in text and "no element with id 'nope'" in text
    assert "Python repr" in text
    assert "'tall.png' is 5000 px tall, more than 6 screens" in text
    assert "'huge.png' is shown" in text and "under half its 3000 px" in text


def _png(shape: tuple[int, int] = (2, 2)) -> bytes:
    """A grey PNG of ``shape`` (rows, columns) pixels."""
    import io

    import matplotlib.image as mpimg

    buf = io.BytesIO()
    mpimg.imsave(buf, np.full(shape, 0.5), cmap="gray", format="png")
    return buf.getvalue()
