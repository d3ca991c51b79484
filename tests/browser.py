"""The page checker of the tests that look at pictures and pages in headless Chromium."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

#: ``tools/check_report.py``, run as a command by the tests.
CHECKER = Path(__file__).resolve().parents[1] / "tools" / "check_report.py"


def chromium() -> str | None:
    """The Chromium binary the checker would use (None: none found)."""
    sys.path.insert(0, str(CHECKER.parent))
    try:
        from check_report import find_chromium
    finally:
        sys.path.remove(str(CHECKER.parent))
    return find_chromium()


#: Skip a test when there is no Chromium to check with.
needs_chromium = pytest.mark.skipif(
    chromium() is None,
    reason="no Chromium binary found (chromium, chromium-browser, google-chrome or "
    "$CHROMIUM); install it with `apt-get install chromium` to check pages in a browser",
)
