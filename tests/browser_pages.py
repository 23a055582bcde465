"""Pages of Debian's chromium (driven by Playwright) for the browser tests: a plain one, and one whose every
request off 127.0.0.1 is refused (the supervisor page must run on vendored assets alone, as at an incident
command post without internet)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from playwright.sync_api import Locator, Page, Route, sync_playwright

CHROMIUM = "/usr/bin/chromium"
# Without the background-networking flags chromium floods the machine with refused connections.
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip


@contextmanager
def plain_page(width: int = 1280, height: int = 900) -> Iterator[Page]:
    assert Path(CHROMIUM).is_file(), f"{CHROMIUM} is missing: `make test` installs Debian's chromium"
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield browser.new_page(viewport={"width": width, "height": height})
        finally:
            browser.close()


@contextmanager
def offline_page(width: int = 1400, height: int = 1000) -> Iterator[tuple[Page, list[str]]]:
    """A page of that viewport, and the list of requests it tried off loopback (each refused)."""
    assert Path(CHROMIUM).is_file(), f"{CHROMIUM} is missing: `make test` installs Debian's chromium"
    outside: list[str] = []

    def only_loopback(route: Route) -> None:
        if route.request.url.startswith("http://127.0.0.1:"):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort("internetdisconnected")

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            context = browser.new_context(viewport={"width": width, "height": height})
            context.route("**/*", only_loopback)
            yield context.new_page(), outside
        finally:
            browser.close()


# Rects of several elements under `root`, read in one animation frame once two frames in a row agree: read
# one by one, a layout shift between the reads (a panel appearing above) set a box apart from its frame.
_SETTLED_RECTS = """async (root, selectors) => {
  const frame = () => new Promise((done) => requestAnimationFrame(done));
  const read = () => JSON.stringify(selectors.map((s) => {
    const r = root.querySelector(s).getBoundingClientRect();
    return {x: r.x, y: r.y, width: r.width, height: r.height};
  }));
  let last = read();
  for (let i = 0; i < 300; i++) {
    await frame();
    const now = read();
    if (now === last) return JSON.parse(now);
    last = now;
  }
  throw new Error("the layout did not settle in 300 frames");
}"""


def settled_boxes(root: Locator, *selectors: str) -> list[dict[str, float]]:
    """Each selector's box (viewport pixels, as Locator.bounding_box) under root, read together once the
    layout holds still."""
    boxes: list[dict[str, float]] = root.evaluate(_SETTLED_RECTS, list(selectors))
    return boxes
