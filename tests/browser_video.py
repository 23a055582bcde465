"""Load an MP4 in a `<video>` element of headless chromium (Debian's, driven by Playwright) and read it back.

What a supervisor or a developer opening `out/demo.mp4` in a browser gets: the duration and size the
browser decoded, or the browser's media error code (4: format not supported, e.g. OpenCV's mp4v).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--allow-file-access-from-files", "--autoplay-policy=no-user-gesture-required",
]  # fmt: skip

_READ_BACK = """
() => new Promise((resolve) => {
  const video = document.querySelector("video");
  const done = () => resolve({duration: video.duration, width: video.videoWidth, height: video.videoHeight,
                              readyState: video.readyState, error: video.error ? video.error.code : null});
  if (video.readyState >= 2 || video.error) { done(); return; }
  video.addEventListener("loadeddata", done);
  video.addEventListener("error", done);
  setTimeout(done, 20000);
})
"""


def play_in_chromium(video: Path) -> dict[str, Any]:
    """{duration (s), width, height, readyState, error}; readyState >= 2 means a frame was decoded."""
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).is_file(), f"{CHROMIUM} is missing: `make test` installs Debian's chromium"
    with tempfile.TemporaryDirectory(prefix="cloudtrack-video-") as folder:
        shutil.copyfile(video, Path(folder) / "video.mp4")
        page_path = Path(folder) / "index.html"
        page_path.write_text('<!doctype html><video src="video.mp4" preload="auto" muted></video>')
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page()
                page.goto(page_path.as_uri())
                result: dict[str, Any] = page.evaluate(_READ_BACK)
            finally:
                browser.close()
    return result
