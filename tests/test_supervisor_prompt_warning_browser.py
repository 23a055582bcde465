"""The prompt warning on the supervisor page, in a real headless browser (Debian's chromium): a vehicle
searching "an orange life buoy" under the superset person shows the warning beside its prompt; one whose
words fit its superset shows none. Select: -k prompt_warning.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Page, expect

from tests import browser_pages
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, live_backend


@pytest.fixture
def browser_page() -> Iterator[Page]:
    with browser_pages.plain_page() as page:
        yield page


def _status(url: str, vehicle: str, prompt: str, superset: str) -> None:
    body = {"mission_id": "m-1", "state": "SEARCHING", "prompt": prompt, "superset": superset}
    headers = {"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"}
    response = httpx.post(f"{url}/v1/vehicles/{vehicle}/status", json=body, headers=headers, timeout=10)
    assert response.status_code == 200, response.text


@pytest.mark.slow
def test_supervisor_page_shows_a_prompt_warning(models_dir: Path, browser_page: Page) -> None:
    page = browser_page
    with live_backend(models_dir) as backend:
        _status(backend.url, "drone-1", "an orange life buoy", "person")
        _status(backend.url, "drone-2", "a man in a red coat", "person")
        page.goto(f"{backend.url}/supervisor")
        page.fill("#token", SUPERVISOR_TOKEN)
        page.click("#login button[type=submit]")
        warned = page.locator('section.vehicle[data-vehicle="drone-1"] .mission')
        expect(warned).to_contain_text("Looking for: an orange life buoy (mission m-1)")
        expect(warned.locator(".prompt-warning")).to_contain_text(
            "Warning: the prompt's 'orange life buoy' is no person (nor any COCO class)"
        )
        fits = page.locator('section.vehicle[data-vehicle="drone-2"] .mission')
        expect(fits).to_contain_text("Looking for: a man in a red coat")
        expect(fits.locator(".prompt-warning")).to_have_count(0)
        page.goto("about:blank")  # close the live stream before the back-end stops
