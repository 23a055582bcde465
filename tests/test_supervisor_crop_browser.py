"""The candidate's crop on the supervisor page, in a real headless browser (Debian's chromium): a person
12 px tall in the 640-px keyframe (24 px in the 1280-px native frame the companion crops from) stands at
least 160 px tall on the card, its box drawn; a click shows the whole crop larger. Select: -k crop_browser.
"""

from __future__ import annotations

import base64
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from playwright.sync_api import Page, expect

from behaviors.geometry import Box
from companion.cloud.candidate_crop import KEYFRAME_WIDTH, candidate_crop
from tests import browser_pages
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, live_backend

SHOT = Path(__file__).resolve().parents[1] / "out" / "test-artifacts" / "supervisor-crop.png"


@pytest.fixture
def browser_page() -> Iterator[Page]:
    with browser_pages.plain_page() as page:
        yield page


def _native_frame_with_a_small_person(sequences_dir: Path) -> tuple[np.ndarray, Box]:
    """A real 1280x720 frame with a real person scaled to 24 px tall in it: 12 px in the keyframe."""
    person_seq = sequences_dir / "uav123_person12_1"
    source = cv2.imread(str(person_seq / "frames" / "000001.jpg"))
    ground = cv2.imread(str(sequences_dir / "uav123_bike1" / "frames" / "000001.jpg"))
    assert source is not None and ground is not None and ground.shape[:2] == (720, 1280)
    x, y, w, h = (
        int(float(v)) for v in (person_seq / "groundtruth.txt").read_text().splitlines()[0].split(",")
    )
    person = cv2.resize(source[y : y + h, x : x + w], (10, 24), interpolation=cv2.INTER_AREA)
    ground[300:324, 200:210] = person
    return ground, Box(200, 300, 10, 24)


@pytest.mark.slow
def test_crop_browser_card_shows_a_12px_person_160px_tall_and_larger_on_click(
    models_dir: Path, sequences_dir: Path, browser_page: Page
) -> None:
    page = browser_page
    frame, box = _native_frame_with_a_small_person(sequences_dir)
    assert box.h * KEYFRAME_WIDTH / 1280 == 12
    crop = candidate_crop(frame, box)
    assert crop is not None
    with live_backend(models_dir) as backend:
        body = {
            "mission_id": "m-1",
            "state": "AWAITING_SUPERVISOR",
            "prompt": "an injured man in a gray shirt",
            "awaiting": {"candidate_id": "c-small", "box": [100, 150, 105, 162], "verdict": "yes", **crop},
        }
        headers = {"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"}
        answer = httpx.post(
            f"{backend.url}/v1/vehicles/drone-1/status", json=body, headers=headers, timeout=10
        )
        assert answer.status_code == 200, answer.text
        page.goto(f"{backend.url}/supervisor")
        page.fill("#token", SUPERVISOR_TOKEN)
        page.click("#login button[type=submit]")
        card = page.locator('article.candidate[data-candidate="c-small"]')
        rect = card.locator(".crop-overlay rect")
        expect(rect).to_have_count(1)
        frame_box, image_box, person = browser_pages.settled_boxes(
            card, ".crop-box", "img.crop", ".crop-overlay rect"
        )
        # The person (its box) at least 160 px tall on screen, inside the card's visible frame.
        assert person["height"] >= 160, person
        assert frame_box["height"] >= 160 and image_box["height"] >= 160, (frame_box, image_box)
        assert (
            frame_box["y"] - 1 <= person["y"]
            and person["y"] + person["height"] <= frame_box["y"] + frame_box["height"] + 1
        )
        assert (
            frame_box["x"] - 1 <= person["x"]
            and person["x"] + person["width"] <= frame_box["x"] + frame_box["width"] + 1
        )
        SHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOT))
        # A click: the whole crop, larger than the card, the box drawn on it.
        card.locator(".crop-box").click()
        dialog = page.locator("#crop-dialog")
        expect(dialog).to_be_visible()
        expect(dialog.locator(".crop-caption")).to_contain_text("candidate c-small")
        large, large_rect = browser_pages.settled_boxes(dialog, "img.crop", ".crop-overlay rect")
        assert large["height"] > frame_box["height"] * 2 and large["width"] > frame_box["width"] * 2, large
        decoded = cv2.imdecode(
            np.frombuffer(base64.b64decode(crop["crop_jpeg_b64"]), np.uint8), cv2.IMREAD_COLOR
        )
        crop_height = decoded.shape[0]
        assert (
            abs(
                large["height"] / crop_height * (crop["crop_box"][3] - crop["crop_box"][1])
                - large_rect["height"]
            )
            < 3
        )
        page.screenshot(path=str(SHOT.with_name("supervisor-crop-large.png")))
        dialog.locator("button").click()
        expect(dialog).to_be_hidden()
        page.goto("about:blank")  # close the live stream before the back-end stops
