"""Headless Chromium (Debian's, driven by the playwright package of the test extra) for the tests
that draw a page: report.html and the live page."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 # WebGL in software (SwiftShader): without a GPU, newer Chromium builds offer it only on request
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def playwright_chromium():
    """(playwright's sync_playwright, the Chromium executable), or the test skipped with what to install."""
    if not Path(CHROMIUM).exists() and shutil.which("chromium") is None:
        pytest.skip("no Chromium (apt-get install chromium; .ci/run installs it)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("no playwright (pip install -e '.[test]')")
    return sync_playwright, Path(CHROMIUM) if Path(CHROMIUM).exists() else Path(shutil.which("chromium"))
