#!/usr/bin/env python3
"""Check a rough_map report page (index.html) in a real headless browser.

    python tools/check_report.py rough_map_demo/index.html [--size 1366x768 ...] [--json]
                                 [--screenshot page.png] [--chromium /usr/bin/chromium]

Opens the page in headless Chromium at each window size (default 1366x768, a laptop, and
1024x768) and checks that

* the page loads (``document.readyState`` is ``complete``, it has a title and an h1);
* nothing makes it scroll sideways: ``document.documentElement.scrollWidth <=
  clientWidth`` (a wide table must scroll inside its own box); the elements that stick out
  are named when it fails;
* every image resolves (``img.complete && img.naturalWidth > 0``), is shown at least half
  its width (its text stays readable) and is at most 6 window heights tall, and sits in a
  ``<figure>`` with a non-empty ``<figcaption>``;
* every local link (``href``/``src`` without a scheme, or ``file:``) names a file that
  exists, and every ``#fragment`` an element of the page with that id;
* the text shows no Python reprs (``array(``, ``Name(field=``).

Chromium runs with ``--headless --no-sandbox --disable-gpu --disable-background-networking
--disable-component-update --disable-sync --no-first-run`` and a temporary
``--user-data-dir``, and is driven through the DevTools protocol over a pipe
(``--remote-debugging-pipe``: JSON messages, each ended by a NUL byte, on file descriptors
3 and 4), so the page itself is checked, untouched, with only the standard library.

Exit status: 0 all checks pass; 1 a check failed (each failure on its own line, or in the
``--json`` output); 2 usage error, no page, or no Chromium found (the message says which).
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-extensions",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
    "--remote-debugging-pipe",
)
DEFAULT_SIZES = ((1366, 768), (1024, 768))
TIMEOUT_S = 60.0

# Runs in the page; returns what the checks need, as plain JSON.
PROBE = r"""
(() => {
  const de = document.documentElement;
  const scrollsX = (el) => {
    for (let p = el.parentElement; p && p !== document.body; p = p.parentElement) {
      const o = getComputedStyle(p).overflowX;
      if (o === 'auto' || o === 'scroll' || o === 'hidden' || o === 'clip') return true;
    }
    return false;
  };
  const describe = (el) => {
    let s = el.tagName.toLowerCase();
    if (el.id) s += '#' + el.id;
    if (el.className && typeof el.className === 'string') s += '.' + el.className.split(' ')[0];
    const src = el.getAttribute('src') || el.getAttribute('href');
    if (src) s += '[' + src + ']';
    const r = el.getBoundingClientRect();
    return s + ' (right edge ' + Math.round(Math.max(r.right, r.left + el.scrollWidth)) + ' px)';
  };
  const spills = (el) => getComputedStyle(el).overflowX === 'visible'
    && el.scrollWidth > el.clientWidth + 1 && el.clientWidth > 0 && !scrollsX(el);
  const wide = [...document.body.querySelectorAll('*')]
    .filter((el) => (el.getBoundingClientRect().right > de.clientWidth + 0.5 && !scrollsX(el))
      || (spills(el) && el.getBoundingClientRect().left + el.scrollWidth > de.clientWidth + 0.5))
    .slice(0, 8).map(describe);
  const images = [...document.images].map((img) => {
    const fig = img.closest('figure');
    const cap = fig ? fig.querySelector('figcaption') : null;
    return {
      src: img.getAttribute('src') || '',
      complete: img.complete,
      naturalWidth: img.naturalWidth,
      naturalHeight: img.naturalHeight,
      shownWidth: Math.round(img.getBoundingClientRect().width),
      caption: cap ? cap.textContent.trim() : null,
    };
  });
  const refs = [...document.querySelectorAll('[href],[src]')]
    .map((el) => el.getAttribute('href') ?? el.getAttribute('src'));
  return {
    readyState: document.readyState,
    title: document.title,
    h1: document.querySelectorAll('h1').length,
    scrollWidth: de.scrollWidth,
    clientWidth: de.clientWidth,
    innerWidth: window.innerWidth,
    wide: wide,
    images: images,
    refs: refs,
    ids: [...document.querySelectorAll('[id]')].map((el) => el.id),
    tables: document.querySelectorAll('table').length,
    pre: document.querySelectorAll('pre').length,
    text: document.body ? document.body.innerText : '',
  };
})()
"""

#: The tallest picture, in window heights.
MAX_SCREENS = 6

REPR = re.compile(r"\barray\(|\b[A-Z]\w*\(\w+=")


class CheckError(Exception):
    """The check could not run (no browser, no page, the browser failed)."""


def find_chromium(given: str | None = None) -> str | None:
    """The Chromium binary: ``given``, $CHROMIUM, or the first of CHROMIUM_NAMES on PATH."""
    for name in (given, os.environ.get("CHROMIUM"), *CHROMIUM_NAMES):
        if name:
            path = shutil.which(name)
            if path:
                return path
    return None


class DevTools:
    """A headless Chromium driven through --remote-debugging-pipe."""

    def __init__(self, binary: str, width: int, height: int) -> None:
        self._profile = tempfile.TemporaryDirectory(prefix="check_report_")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # in the child: fd 3 reads commands, fd 4 writes replies
            high_r = fcntl.fcntl(to_child_r, fcntl.F_DUPFD, 10)  # out of the way of 3 and 4
            high_w = fcntl.fcntl(from_child_w, fcntl.F_DUPFD, 10)
            os.dup2(high_r, 3)  # inheritable: kept across exec
            os.dup2(high_w, 4)

        self.proc = subprocess.Popen(
            [
                binary,
                *FLAGS,
                f"--user-data-dir={self._profile.name}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            # Python's own descriptors are not inheritable (PEP 446): only 3 and 4 pass on
            preexec_fn=fds,
            close_fds=False,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._buf = b""
        self._id = 0
        self.events: list[dict] = []

    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CheckError("Chromium did not answer in time")
            ready, _, _ = select.select([self._from_child], [], [], left)
            if not ready:
                continue
            chunk = os.read(self._from_child, 1 << 16)
            if not chunk:
                raise CheckError(f"Chromium exited (status {self.proc.poll()})")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise CheckError(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_event(self, method: str, session: str) -> dict:
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            for k, ev in enumerate(self.events):
                if ev.get("method") == method and ev.get("sessionId") == session:
                    return self.events.pop(k)
            self.events.append(self._read_message(deadline))

    def close(self) -> None:
        try:
            self.send("Browser.close")
        except (CheckError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._to_child, self._from_child):
            try:
                os.close(fd)
            except OSError:
                pass
        self._profile.cleanup()


def probe_page(
    page: Path, sizes: list[tuple[int, int]], binary: str, screenshot: Path | None = None
) -> list[dict]:
    """Load ``page`` at each window size; the probe's findings per size."""
    import base64

    out = []
    browser = DevTools(binary, *sizes[0])
    try:
        target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = browser.send("Target.attachToTarget", {"targetId": target, "flatten": True})[
            "sessionId"
        ]
        browser.send("Page.enable", session=session)
        for k, (width, height) in enumerate(sizes):
            browser.send(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                session=session,
            )
            browser.events.clear()
            browser.send("Page.navigate", {"url": page.resolve().as_uri()}, session=session)
            browser.wait_event("Page.loadEventFired", session)
            res = browser.send(
                "Runtime.evaluate",
                {"expression": PROBE, "returnByValue": True, "awaitPromise": True},
                session=session,
            )
            if "exceptionDetails" in res:
                raise CheckError(f"the probe failed: {res['exceptionDetails'].get('text')}")
            found = res["result"]["value"]
            found["size"] = [width, height]
            out.append(found)
            if screenshot is not None and k == 0:
                shot = browser.send(
                    "Page.captureScreenshot",
                    {"format": "png", "captureBeyondViewport": True},
                    session=session,
                )
                screenshot.write_bytes(base64.b64decode(shot["data"]))
    finally:
        browser.close()
    return out


def local_target(page: Path, ref: str) -> tuple[Path | None, str]:
    """The file a reference names (None: the page itself, or not local) and its fragment."""
    parts = urlsplit(ref)
    if parts.scheme and parts.scheme != "file":
        return None, ""
    if parts.scheme == "file":
        return Path(unquote(parts.path)), parts.fragment
    if not parts.path:
        return page, parts.fragment
    return (page.parent / unquote(parts.path)).resolve(), parts.fragment


def check(page: Path, findings: list[dict]) -> list[str]:
    """Failures (empty: the page passes)."""
    bad: list[str] = []
    for f in findings:
        at = f"at {f['size'][0]}x{f['size'][1]}"
        if f["readyState"] != "complete" or not f["title"] or f["h1"] < 1:
            bad.append(f"{at}: the page did not load fully (state {f['readyState']!r}, "
                       f"title {f['title']!r}, {f['h1']} h1)")  # fmt: skip
        if f["scrollWidth"] > f["clientWidth"]:
            bad.append(
                f"{at}: horizontal overflow: scrollWidth {f['scrollWidth']} > clientWidth "
                f"{f['clientWidth']}; sticking out: {', '.join(f['wide']) or '?'}"
            )
        for img in f["images"]:
            if not (img["complete"] and img["naturalWidth"] > 0):
                bad.append(f"{at}: image {img['src']!r} does not load")
            elif img["shownWidth"] < 0.5 * img["naturalWidth"]:
                bad.append(f"{at}: image {img['src']!r} is shown {img['shownWidth']} px wide, "
                           f"under half its {img['naturalWidth']} px: its text is too small "
                           "to read")  # fmt: skip
            elif img["naturalHeight"] > MAX_SCREENS * f["size"][1]:
                bad.append(f"{at}: image {img['src']!r} is {img['naturalHeight']} px tall, "
                           f"more than {MAX_SCREENS} screens")  # fmt: skip
    first = findings[0]
    for img in first["images"]:
        if not img["caption"]:
            bad.append(f"image {img['src']!r} has no <figure> with a <figcaption>")
    ids = set(first["ids"])
    for ref in dict.fromkeys(first["refs"]):
        target, fragment = local_target(page, ref)
        if target is None:
            continue
        if target == page.resolve() or target == page:
            if fragment and fragment not in ids:
                bad.append(f"link {ref!r}: no element with id {fragment!r}")
        elif not target.exists():
            bad.append(f"link {ref!r}: {target} does not exist")
    m = REPR.search(first["text"])
    if m:
        start = max(0, m.start() - 30)
        bad.append(f"the text shows a Python repr: ...{first['text'][start : m.end() + 30]!r}")
    if first["pre"]:
        bad.append(f"the page has {first['pre']} <pre> block(s): show numbers in tables")
    return bad


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    if not m:
        raise argparse.ArgumentTypeError(
            f"a size is WIDTHxHEIGHT in px, e.g. 1366x768; got {text!r}"
        )
    return int(m.group(1)), int(m.group(2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("page", type=Path, help="the report's index.html")
    ap.add_argument("--size", type=_size, action="append", metavar="WxH",
                    help="window size(s) to check (default 1366x768 and 1024x768)")  # fmt: skip
    ap.add_argument("--chromium", help="the Chromium binary (default: $CHROMIUM or on PATH)")
    ap.add_argument("--screenshot", type=Path, metavar="PNG",
                    help="also save a full-page screenshot at the first size")  # fmt: skip
    ap.add_argument("--json", action="store_true", help="print the findings as JSON")
    args = ap.parse_args(argv)
    page: Path = args.page
    if not page.is_file():
        print(f"check_report: error: {page}: no such page", file=sys.stderr)
        return 2
    binary = find_chromium(args.chromium)
    if binary is None:
        print(
            "check_report: error: no Chromium found (tried "
            f"{', '.join(n for n in (args.chromium, '$CHROMIUM', *CHROMIUM_NAMES) if n)}); "
            "install it, e.g. `apt-get install chromium`",
            file=sys.stderr,
        )
        return 2
    sizes = args.size or list(DEFAULT_SIZES)
    try:
        findings = probe_page(page, sizes, binary, args.screenshot)
    except (CheckError, OSError) as exc:
        print(f"check_report: error: {page}: {exc}", file=sys.stderr)
        return 2
    failures = check(page, findings)
    if args.json:
        summary = [
            {k: f[k] for k in ("size", "scrollWidth", "clientWidth", "wide")}
            | {
                "images": len(f["images"]),
                "images_loaded": sum(i["complete"] and i["naturalWidth"] > 0 for i in f["images"]),
                "tables": f["tables"],
            }
            for f in findings
        ]
        print(json.dumps({"page": str(page), "ok": not failures, "failures": failures,
                          "findings": summary}, indent=1))  # fmt: skip
    else:
        for f in findings:
            ok = sum(i["complete"] and i["naturalWidth"] > 0 for i in f["images"])
            print(
                f"{f['size'][0]}x{f['size'][1]}: scrollWidth {f['scrollWidth']} <= clientWidth "
                f"{f['clientWidth']}: {'yes' if f['scrollWidth'] <= f['clientWidth'] else 'NO'}; "
                f"{ok}/{len(f['images'])} images load; {f['tables']} tables"
            )
        for line in failures:
            print(f"FAIL {line}")
        print(f"{page}: {'ok' if not failures else f'{len(failures)} failure(s)'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
