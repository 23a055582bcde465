"""Issue 44 on the supervisor page, in Debian's headless chromium against a real back-end on loopback.

- A find whose prompt holds markup and whose `confirmed_by` holds "&" (items 1, 2): the page shows the
  words as text and its KML button downloads a file a strict XML parser reads, the words as text in it;
  with the back-end gone, the button says the download failed instead of doing nothing.
- A vehicle that reports "supervisor page" confirmed its find (item 6): the page labels it the vehicle's
  report, and the supervisor's own Reject is taken (no 409).
Select: -k hostile.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from lxml import etree
from playwright.sync_api import Page, expect

from tests.test_supervisor_console_browser import DRONE, _backend, _log_in, offline_page  # noqa: F401

INJECTION = (
    "<![CDATA[<img src=x onerror=alert(1)><a href=http://evil.example/>x</a>]]>"
    "<name>FAKE</name><Point><coordinates>0,0</coordinates></Point>"
)
KML = "{http://www.opengis.net/kml/2.2}"


def _status(url: str, body: dict[str, object]) -> None:
    answer = httpx.post(f"{url}/v1/vehicles/drone-1/status", json=body, headers=DRONE, timeout=10)
    assert answer.status_code == 200, answer.text


@pytest.fixture
def page(offline_page: tuple[Page, list[str]]) -> Iterator[Page]:  # noqa: F811 - the console's fixture
    yield offline_page[0]
    assert offline_page[1] == []  # nothing but loopback was asked for


@pytest.mark.slow
def test_hostile_find_text_stays_text_and_the_kml_button_says_when_it_fails(
    page: Page, models_dir: Path, tmp_path: Path
) -> None:
    find = {"candidate_id": "c-1", "position": [47.3978, 8.5456], "sigma_m": 2.0, "time": 1732200000.0,
            "prompt": INJECTION, "confirmed_by": "Smith & Jones"}  # fmt: skip
    with _backend(models_dir) as url:
        _status(url, {"mission_id": "m-44", "state": "CONFIRMED", "prompt": INJECTION, "find": find})
        _log_in(page, url)
        card = page.locator('section[data-vehicle="drone-1"]')
        item = card.locator("li.find")
        expect(item).to_have_count(1)
        expect(item.locator(".what")).to_have_text(f"{INJECTION} (mission m-44)")
        assert card.locator("img[src='x'], a[href^='http://evil']").count() == 0
        with page.expect_download() as download:
            card.locator(".downloads button", has_text="KML").click()
        saved = tmp_path / "finds.kml"
        download.value.save_as(saved)
        document = etree.fromstring(saved.read_bytes(), etree.XMLParser(recover=False))
        (placemark,) = [p for p in document.iter(f"{KML}Placemark") if p.find(f"{KML}Point") is not None]
        assert placemark.findtext(f"{KML}ExtendedData/{KML}Data[@name='prompt']/{KML}value") == INJECTION
        assert [n.text for n in placemark.iter(f"{KML}name")] == [placemark.findtext(f"{KML}name")]
        expect(card.locator(".download-error")).to_be_hidden()
    # The back-end is gone (stopped, unreachable): the button says so.
    card.locator(".downloads button", has_text="KML").click()
    expect(card.locator(".download-error")).to_have_text(
        "KML of mission m-44 not downloaded: the back-end did not answer"
    )
    page.goto("about:blank")


@pytest.mark.slow
def test_hostile_a_vehicles_claimed_confirmation_leaves_the_supervisors_reject_open(
    page: Page, models_dir: Path
) -> None:
    claim = '"supervisor page" at the GCS, as reported by drone-1'
    find = {"candidate_id": "c-6", "position": [47.3978, 8.5456], "sigma_m": 2.0, "time": 1732200000.0,
            "prompt": "a man in red", "confirmed_by": "supervisor page"}  # fmt: skip
    awaiting = {"candidate_id": "c-6", "box": [0, 0, 10, 10], "position": [47.3978, 8.5456]}
    with _backend(models_dir) as url:
        _status(url, {"mission_id": "m-6", "state": "AWAITING_SUPERVISOR", "prompt": "a man in red",
                      "awaiting": awaiting, "find": find})  # fmt: skip
        _log_in(page, url)
        card = page.locator('section[data-vehicle="drone-1"]')
        candidate = card.locator('article[data-candidate="c-6"]')
        expect(candidate.locator(".status")).to_have_text(
            f"awaiting (the vehicle's report: confirmed by {claim})"
        )
        expect(card.locator("li.find .who")).to_have_text(f"confirmed by {claim}")
        expect(candidate.locator("button.reject")).to_be_enabled()
        candidate.locator("button.reject").click()
        expect(candidate.locator(".status")).to_have_text(
            f"rejected by supervisor page (the vehicle's report: confirmed by {claim})", timeout=10_000
        )
        expect(candidate.locator(".decision")).not_to_contain_text("not sent")
        expect(card.locator("li.find .who")).to_have_text(
            f"confirmed by {claim}; rejected by supervisor page"
        )
        page.goto("about:blank")
