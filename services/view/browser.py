"""Headless Chromium for the view: a page, a screenshot once the scene has settled.

Drives Debian's `chromium` through Playwright (`executable_path`), since Playwright's own
browser download needs the internet. WebGL then renders in software (SwiftShader).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from playwright.sync_api import Locator, Page

CHROMIUM_NAMES = ("chromium", "chromium-browser")
CHROMIUM_ARGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync")
"""No sandbox (containers and root), no GPU, and nothing that reaches out to the network."""
HIDE_NOTICES_CSS = ".mantine-Notifications-root { display: none !important; }"
"""viser warns about software WebGL in a corner notification; pictures are better without it."""
SETTLE_INTERVAL_S = 0.5


class BrowserUnavailable(RuntimeError):
    """Chromium or Playwright is not installed."""


def find_chromium() -> str | None:
    """Path of a Chromium executable on PATH, or None."""
    return next((path for name in CHROMIUM_NAMES if (path := shutil.which(name))), None)


@contextmanager
def open_page(url: str, *, width: int = 1280, height: int = 800, timeout_s: float = 60.0,
              before_load: Callable[[Page], None] | None = None) -> Iterator[Page]:
    """A headless Chromium page (fresh profile) showing `url` once its 3D canvas exists.

    `before_load` runs on the page before it navigates (e.g. to listen to its websockets).

    Raises:
        BrowserUnavailable: no Chromium on PATH or no Playwright package.
    """
    executable = find_chromium()
    if executable is None:
        raise BrowserUnavailable("no Chromium found on PATH (Debian: `apt-get install chromium`)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        raise BrowserUnavailable("the Python package playwright is missing (`pip install robonav-arm[view]`)") from exc
    with tempfile.TemporaryDirectory(prefix="robonav-chromium-") as profile, sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            profile, executable_path=executable, headless=True, args=list(CHROMIUM_ARGS),
            viewport={"width": width, "height": height})
        try:
            page = context.pages[0] if context.pages else context.new_page()
            page.set_default_timeout(timeout_s * 1e3)
            if before_load is not None:
                before_load(page)
            page.goto(url)
            page.wait_for_selector("canvas")
            page.add_style_tag(content=HIDE_NOTICES_CSS)
            yield page
        finally:
            context.close()


def stable_screenshot(page: Page, target: Locator | None = None, *, timeout_s: float = 60.0,
                      interval_s: float = SETTLE_INTERVAL_S) -> bytes:
    """A PNG of `target` (default the whole page) once two screenshots in a row are identical.

    Raises:
        TimeoutError: the picture still changed after `timeout_s`.
    """
    deadline = time.monotonic() + timeout_s
    # A page clip, not an element screenshot: Playwright waits for an element to be "stable"
    # over two animation frames, which a page busy rendering in software may not give it.
    clip = None if target is None else target.bounding_box()
    previous = None
    while True:
        # The first picture waits for SwiftShader to compile every shader: allow it the whole budget.
        shot = page.screenshot(clip=clip, timeout=max(deadline - time.monotonic(), 10.0) * 1e3)
        if shot == previous:
            return shot
        if time.monotonic() > deadline:
            raise TimeoutError(f"the page still changed after {timeout_s:.0f} s")
        previous = shot
        page.wait_for_timeout(interval_s * 1e3)


def page_url(url: str) -> str:
    """`url` with viser's fixed device-pixel ratio: its adaptive one lowers the resolution
    while software rendering is slow, so two pictures of a still scene could differ."""
    return url + ("&" if "?" in url else "?") + "fixedDpr=1"


def capture_page(url: str, *, width: int = 1280, height: int = 800, timeout_s: float = 180.0) -> bytes:
    """A PNG of the whole page at `url` once its 3D view has settled.

    Stability is judged on the canvas alone: the control panel has widgets that animate.
    """
    with open_page(page_url(url), width=width, height=height, timeout_s=timeout_s) as page:
        stable_screenshot(page, page.locator("canvas").first, timeout_s=timeout_s)
        return page.screenshot(timeout=timeout_s * 1e3)
