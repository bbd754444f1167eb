"""Headless Chromium for the browser tests (Debian's chromium + chromedriver, driven by selenium)."""

from __future__ import annotations

import importlib.util
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

CHROMIUM = Path(os.environ.get("MORPHEUS_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("MORPHEUS_CHROMEDRIVER", "/usr/bin/chromedriver"))
# This machine's closed network refuses Chromium's background connections, many at a time, without these.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage")


def missing_browser_parts() -> list[str]:
    missing = [str(path) for path in (CHROMIUM, CHROMEDRIVER) if not os.access(path, os.X_OK)]
    if importlib.util.find_spec("selenium") is None:
        missing.append("the selenium package (pip install -e '.[dev]')")
    return missing


_MISSING = missing_browser_parts()
needs_browser = pytest.mark.skipif(
    bool(_MISSING),
    reason=f"headless Chromium unavailable, missing: {', '.join(_MISSING)}; "
    "`make browser` installs the Debian packages chromium and chromium-driver",
)


@contextmanager
def chromium(viewport: tuple[int, int] = (1400, 1000)) -> Iterator:
    """A selenium driver whose page area is ``viewport`` (a fresh profile, quit on exit)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    with tempfile.TemporaryDirectory(prefix="morpheus-chromium-") as profile:
        options.add_argument(f"--user-data-dir={profile}")
        options.add_argument(f"--window-size={viewport[0]},{viewport[1]}")
        driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
        try:
            driver.set_page_load_timeout(60)
            # --window-size is the outer size: grow the window so that the page itself gets the viewport.
            dw, dh = driver.execute_script("return [outerWidth - innerWidth, outerHeight - innerHeight]")
            driver.set_window_size(viewport[0] + dw, viewport[1] + dh)
            yield driver
        finally:
            driver.quit()
