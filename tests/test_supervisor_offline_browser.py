"""/docs and the supervisor page in Debian's headless chromium with no network but the back-end's loopback
port: Swagger UI renders from the package's own files (with its Authorize button), and with the default
configuration the supervisor page says it is off instead of asking for a token. Select: -k offline.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from backend.app import create_app
from backend.config import load_backend_config
from tests import browser_pages
from tests.live_backend import live_backend, serve

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "out" / "test-artifacts" / "docs-offline.png"


@pytest.fixture
def offline_page() -> Iterator[tuple[Page, list[str]]]:
    with browser_pages.offline_page(1280, 900) as page_and_outside:
        yield page_and_outside


@pytest.mark.slow
def test_offline_docs_show_swagger_ui_with_authorize(
    offline_page: tuple[Page, list[str]], models_dir: Path
) -> None:
    page, outside = offline_page
    with live_backend(models_dir) as backend:
        page.goto(f"{backend.url}/docs")
        expect(page.locator(".swagger-ui .info .title")).to_contain_text(
            "CloudTrack back-end", timeout=20_000
        )
        expect(page.locator(".opblock-summary-path", has_text="/v1/detect")).to_be_visible()
        authorize = page.locator("button.authorize")
        expect(authorize).to_be_visible()
        authorize.click()
        expect(page.locator(".auth-container")).to_contain_text("bearer")
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT), full_page=False)
    assert outside == []  # nothing was even tried off the machine


@pytest.mark.slow
def test_offline_default_supervisor_page_says_it_is_off(
    offline_page: tuple[Page, list[str]], models_dir: Path
) -> None:
    page, outside = offline_page
    config = load_backend_config(
        None, [f'detector.model_dir="{models_dir}"', 'sessions.sqlite_path=":memory:"'], environ={}
    )
    with serve(create_app(config)) as url:
        page.goto(f"{url}/supervisor")
        expect(page.locator("#disabled")).to_be_visible(timeout=20_000)
        expect(page.locator("#disabled")).to_contain_text("auth.supervisor_token")
        expect(page.locator("#login")).to_be_hidden()
    assert outside == []
