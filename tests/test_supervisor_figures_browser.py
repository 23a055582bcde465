"""Issue 45 on the supervisor page, in Debian's headless chromium with every request off loopback refused:
one id per candidate (the card, the live view's box over two keyframes whose answers name the person anew,
the find and its GeoJSON name the candidate as the GCS does), the confirmed person labelled confirmed in
the live view, counters that say what they count, no area figure without a search area, the live view's
age written on it, and a find's pin inside the map. Real keyframes go through /v1/detect (YOLOX-nano, the
local verifier); the companion's status reports are posted as it sends them. Select: -k figures.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import pytest
from playwright.sync_api import Locator, Page, expect

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from tests import browser_pages
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "out" / "test-artifacts" / "supervisor-figures.png"
PROMPT = "the man in the green-and-white striped shirt"
DRONE = {"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"}
SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}
MISSION = "m-45"
# The vehicle flew 100 m north; the person was found 25 m north-east of where it is: the northernmost and
# easternmost point on the map, where a pin drawn above its point used to be clipped.
TRACK = [[47.39770 + 0.0000899 * i, 8.54560] for i in range(11)]
FIND_AT = [47.39770 + 0.0000899 * 12.5, 8.54560 + 0.00020]


@pytest.fixture
def page() -> Iterator[Page]:
    with browser_pages.offline_page() as (page, outside):
        yield page
    assert outside == []  # vendored assets only: nothing but loopback was asked for


def _detect(client: httpx.Client, keyframe: bytes, frame_id: int) -> list[dict[str, Any]]:
    meta = {"vehicle_id": "drone-1", "mission_id": MISSION, "prompt": PROMPT, "frame_id": frame_id}
    answer = client.post(
        "/v1/detect", files={"image": ("k.jpg", keyframe, "image/jpeg")}, data={"meta": json.dumps(meta)}
    )
    assert answer.status_code == 200, answer.text
    candidates: list[dict[str, Any]] = answer.json()["candidates"]
    assert candidates
    return candidates


def _status(client: httpx.Client, body: dict[str, Any]) -> None:
    full = {"mission_id": MISSION, "prompt": PROMPT, "position": TRACK[-1], **body}
    response = client.post("/v1/vehicles/drone-1/status", json=full)
    assert response.status_code == 200, response.text


def _labels(card: Locator) -> list[str]:
    return [t.strip() for t in card.locator(".overlay text").all_text_contents()]


@pytest.mark.slow
def test_figures_ids_and_labels_on_the_page(page: Page, models_dir: Path, sequences_dir: Path) -> None:
    frame = cv2.imread(str(sequences_dir / "uav123_person12_1" / "frames" / "000001.jpg"))
    assert frame is not None
    keyframe = cv2.imencode(".jpg", frame, [int(cv2.IMWRITE_JPEG_QUALITY), 85])[1].tobytes()
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        verifier=VerifierConfig(kind="local"),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    with serve(create_app(config)) as url, httpx.Client(base_url=url, timeout=60, headers=DRONE) as client:
        # The keyframe that proposes the person: the candidate's id is its answer's id for them.
        first = _detect(client, keyframe, 41)
        best = max(first, key=lambda c: (c["verdict"] == "yes", c["score"]))
        cid = best["candidate_id"]
        awaiting = {"candidate_id": cid, "box": best["box"], "verdict": best["verdict"], "position": FIND_AT}
        tracked = {"track_box": best["box"], "track_id": cid}
        # A follow with no search area: 2 keyframes, 9 boxes in their answers, 1 put to the supervisor.
        progress = {"keyframes": 2, "detections": 9, "candidates": 1, "rejected": 0}
        for position in TRACK:
            _status(client, {"state": "FOLLOWING", "position": position, "progress": progress})
        _status(
            client,
            {
                "state": "AWAITING_SUPERVISOR",
                "awaiting": awaiting,
                "frame_id": 41,
                **tracked,
                "progress": progress,
            },
        )
        page.goto(f"{url}/supervisor")
        page.fill("#token", SUPERVISOR_TOKEN)
        page.click("#login button[type=submit]")
        expect(page.locator("#connection")).to_have_text("live", timeout=15_000)
        card = page.locator('section[data-vehicle="drone-1"]')

        # One id: the card names the candidate as the GCS does, and so does its box in the live view.
        candidate = card.locator(f'article[data-candidate="{cid}"]')
        expect(candidate.locator(".candidate-id")).to_have_text(f"candidate {cid}")
        expect(card.locator(".overlay text").first).to_be_attached(timeout=15_000)
        labels = _labels(card)
        # Named once: the answer's box over the track carries the id, the tracked box no second label.
        assert sum(cid in label for label in labels) == 1 and f"awaiting {cid}" in labels, labels
        others = [c for c in first if c["candidate_id"] != cid]
        for other in others:  # boxes put to no one: the verdict alone, never the answer's own id
            assert not any(other["candidate_id"] in label for label in labels), labels
        assert sorted(labels) == sorted([f"awaiting {cid}", *(c["verdict"] for c in others)])

        # Counters say what they count; a follow without a search area shows no area figure.
        expect(card.locator(".progress")).to_have_text(
            "2 keyframes checked · 9 detections · 1 put to the supervisor · 0 rejected"
        )
        expect(card.locator(".coverage")).to_have_text("no search area")
        expect(card.locator(".coverage-bar")).to_be_hidden()

        # The live view says how old it is, in seconds, on the picture (marked once past 2 s).
        badge = card.locator(".keyframe-age")
        expect(badge).to_be_visible()
        expect(badge).to_have_text(re.compile(r"^(not live: )?\d+ s old$"))
        text, stale = badge.text_content() or "", badge.get_attribute("data-stale")
        seconds = int(re.findall(r"\d+", text)[0])
        assert (stale == "1") == text.startswith("not live") and (seconds > 2) <= (stale == "1"), (
            text,
            stale,
        )
        expect(card.locator(".keyframe-info")).to_contain_text(
            re.compile(r"keyframe 41 · received \d+ s ago")
        )
        # A report that changes nothing renews "last report", never the keyframe's age.
        expect(badge).to_have_attribute("data-stale", "1", timeout=15_000)
        before = int(re.findall(r"\d+", badge.text_content() or "")[0])
        waiting = {"state": "AWAITING_SUPERVISOR", "awaiting": awaiting, "frame_id": 41, **tracked}
        _status(client, {**waiting, "progress": progress})
        expect(card.locator(".vehicle-head .seen")).to_have_text(re.compile(r"last report [01] s ago"))
        assert int(re.findall(r"\d+", badge.text_content() or "")[0]) >= before >= 2

        # The next keyframe's answer names the person anew: the live view keeps the candidate's id.
        second = _detect(client, keyframe, 42)
        assert cid not in {c["candidate_id"] for c in second}
        _status(
            client,
            {
                "state": "AWAITING_SUPERVISOR",
                "awaiting": awaiting,
                "frame_id": 42,
                **tracked,
                "progress": progress,
            },
        )
        # (the keyframe may show before the status that names its tracked box: the label is waited for)
        expect(card.locator(".keyframe-info")).to_contain_text("keyframe 42", timeout=15_000)
        expect(card.locator(".overlay text", has_text=f"awaiting {cid}")).to_have_count(1)
        labels = _labels(card)
        assert f"awaiting {cid}" in labels, labels
        assert not any(c["candidate_id"] in label for c in second for label in labels), labels

        # Confirmed on the page; the vehicle reports the find and goes on sending keyframes, whose verifier
        # may still say "uncertain": the live view labels the person confirmed, by the same id.
        candidate.locator("button.confirm").click()
        expect(candidate.locator(".status")).to_have_text("confirmed by supervisor page", timeout=10_000)
        _detect(client, keyframe, 43)
        find = {"candidate_id": cid, "position": FIND_AT, "sigma_m": 6.0, "time": time.time(),
                "prompt": PROMPT, "confirmed_by": "supervisor page"}  # fmt: skip
        _status(client, {"state": "CONFIRMED", "frame_id": 43, **tracked, "find": find, "progress": progress})
        expect(card.locator(".keyframe-info")).to_contain_text("keyframe 43", timeout=15_000)
        expect(card.locator(".overlay text", has_text=f"confirmed {cid}")).to_have_count(1)
        labels = _labels(card)
        assert f"confirmed {cid}" in labels, labels
        assert not any(label.startswith("uncertain") and cid in label for label in labels), labels
        # A keyframe whose answer has no box on the track (the detector missed the person): the tracked box
        # itself is named, confirmed.
        _detect(client, keyframe, 44)
        elsewhere = {"track_box": [4.0, 4.0, 24.0, 60.0], "track_id": cid}
        _status(
            client, {"state": "CONFIRMED", "frame_id": 44, **elsewhere, "find": find, "progress": progress}
        )
        expect(card.locator(".keyframe-info")).to_contain_text("keyframe 44", timeout=15_000)
        expect(card.locator(".overlay text", has_text=f"confirmed {cid}")).to_have_count(1)
        assert [label for label in _labels(card) if cid in label] == [f"confirmed {cid}"]
        found = card.locator("li.find")
        expect(found).to_have_count(1)
        expect(found.locator(".find-id")).to_have_text(f"candidate {cid}")
        exported = httpx.get(
            f"{url}/v1/missions/{MISSION}/finds.geojson", params={"vehicle_id": "drone-1"}, headers=SUPERVISOR
        )
        assert exported.status_code == 200, exported.text
        assert cid in {f["properties"].get("candidate_id") for f in exported.json()["features"]}

        # The find's pin and its uncertainty circle inside the map, at the drawn area's north-east corner.
        the_map = card.locator("svg.map")
        expect(the_map.locator("path.find-mark")).to_have_count(1)
        for mark in ("path.find-mark", "circle.sigma"):
            box = the_map.locator(mark).evaluate(
                "el => { const b = el.getBBox(); return [b.x, b.y, b.width, b.height]; }"
            )
            x, y, w, h = box
            assert x >= 0 and y >= 0 and x + w <= 400 and y + h <= 300, (mark, box)
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        page.goto("about:blank")  # close the live stream before the back-end stops
