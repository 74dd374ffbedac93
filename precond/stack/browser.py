"""A real headless browser for the review page's tests and benchmark: the system's Chromium (Debian's
`chromium`, installed by scripts/install.sh) driven by Playwright. Playwright's own browser download is not
used: the system browser is the one a deployment's users have, and the only one an offline machine can get.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from playwright.sync_api import Browser

CANDIDATES = ("chromium", "chromium-browser", "google-chrome")


def executable() -> str | None:
    """The browser to drive: `PRECOND_BROWSER`, else the first of CANDIDATES on PATH."""
    named = os.environ.get("PRECOND_BROWSER")
    if named:
        return named if os.access(named, os.X_OK) else None
    return next((found for name in CANDIDATES if (found := shutil.which(name))), None)


def missing() -> str | None:
    """Why no browser test can run here (None: one can)."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[dev]')"
    if executable() is None:
        return "no Chromium found (apt-get install chromium, or set PRECOND_BROWSER)"
    return None


@contextmanager
def chromium() -> Iterator[Browser]:
    from playwright.sync_api import sync_playwright

    path = executable()
    if path is None:
        raise RuntimeError(missing())
    # Chromium's own sandbox needs user namespaces, which root in a container does not get
    args = ["--no-sandbox"] if os.geteuid() == 0 else []
    with sync_playwright() as driver:
        browser = driver.chromium.launch(executable_path=path, args=args)
        try:
            yield browser
        finally:
            browser.close()
