"""The supervisor's console in Debian's headless chromium with every request off loopback refused: a real
keyframe sent to /v1/detect shows live with its candidate boxes and the tracked box; the map is drawn from
the positions alone (track, search area, covered area, candidate, finds) or over tiles from a configured
loopback tile server; search progress and coverage, the reason for the state, the candidate's crop with
its box drawn and what the back-end could not judge of the description; a Confirm makes a find that stays
in the list and on the map after the vehicle moves on. A screenshot is kept in
out/test-artifacts/supervisor-console.png. Select: -k console.
"""

from __future__ import annotations

import base64
import http.server
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from playwright.sync_api import Page, expect

from backend.app import create_app
from backend.config import (
    AuthConfig,
    BackendConfig,
    DetectorConfig,
    SessionConfig,
    SupervisorConfig,
    VerifierConfig,
)
from tests import browser_pages
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "out" / "test-artifacts" / "supervisor-console.png"
PROMPT = "the man in the green-and-white striped shirt"
DRONE = {"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"}
HOME = (47.39770, 8.54560)
AREA = [[47.3972, 8.5449], [47.3972, 8.5465], [47.3984, 8.5465], [47.3984, 8.5449]]


@pytest.fixture
def offline_page() -> Iterator[tuple[Page, list[str]]]:
    with browser_pages.offline_page() as page_and_outside:
        yield page_and_outside


class TileServer:
    """A map tile server on loopback (a site's own, no internet): one 256-px PNG for every z/x/y, counted."""

    def __init__(self) -> None:
        tile = np.full((256, 256, 3), (205, 225, 200), np.uint8)
        cv2.line(tile, (0, 128), (255, 128), (160, 170, 150), 3)
        self.png = cv2.imencode(".png", tile)[1].tobytes()
        self.requests: list[str] = []
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - the standard library's name
                owner.requests.append(self.path)
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Content-Length", str(len(owner.png)))
                self.end_headers()
                self.wfile.write(owner.png)

            def log_message(self, *_: Any) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/tiles/{{z}}/{{x}}/{{y}}.png"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _backend(models_dir: Path, tiles: str = "") -> Any:
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        verifier=VerifierConfig(kind="local"),  # the default: it says what it could not judge
        sessions=SessionConfig(sqlite_path=":memory:"),
        supervisor=SupervisorConfig(map_tiles=tiles),
    )
    return serve(create_app(config))


def _fly(url: str, sequences_dir: Path) -> dict[str, Any]:
    """drone-1 searches: a real keyframe to /v1/detect, a short track over the search area, then it awaits
    the supervisor on the striped shirt with its crop; the candidate it reports."""
    seq = sequences_dir / "uav123_person12_1"
    frame = cv2.imread(str(seq / "frames" / "000001.jpg"))
    assert frame is not None
    keyframe = cv2.imencode(".jpg", frame, [int(cv2.IMWRITE_JPEG_QUALITY), 85])[1].tobytes()
    meta = {"vehicle_id": "drone-1", "mission_id": "m-12", "prompt": PROMPT, "frame_id": 41}
    with httpx.Client(base_url=url, timeout=60, headers=DRONE) as client:
        answer = client.post(
            "/v1/detect", files={"image": ("k.jpg", keyframe, "image/jpeg")}, data={"meta": json.dumps(meta)}
        )
        assert answer.status_code == 200, answer.text
        candidates = answer.json()["candidates"]
        best = max(candidates, key=lambda c: (c["verdict"] == "yes", c["score"]))
        x1, y1, x2, y2 = (int(v) for v in best["box"])
        crop = frame[max(0, y1 - 50) : y2 + 50, max(0, x1 - 50) : x2 + 50]
        crop_box = [x1 - max(0, x1 - 50), y1 - max(0, y1 - 50), x2 - max(0, x1 - 50), y2 - max(0, y1 - 50)]
        for i in range(12):  # a lawnmower survey's first lanes, 15 m apart
            lane, step = divmod(i, 4)
            lat = AREA[0][0] + 0.0001 + 0.00033 * (step if lane % 2 == 0 else 3 - step)
            lon = AREA[0][1] + 0.0002 + 0.0002 * lane
            status = {
                "mission_id": "m-12", "state": "SEARCHING", "prompt": PROMPT, "position": [lat, lon],
                "altitude_m": 30.0, "heading_deg": 10.0 * i, "reason": "searching along the mission, item 3",
                "progress": {"keyframes": 40 + i, "candidates": 3, "rejected": 1},
                "search": {
                    "area": AREA, "coverage": 0.02 * i, "mission_item": 3, "mission_items": 9, "mode": "AUTO",
                    "covered": [[[47.3972, 8.5449], [47.3984, 8.5449],
                                 [47.3984, 8.5449 + 0.0002 * (lane + 1)], [47.3972, 8.5449 + 0.0002 * (lane + 1)]]],
                },
            }  # fmt: skip
            assert client.post("/v1/vehicles/drone-1/status", json=status).status_code == 200
        awaiting = {
            "candidate_id": best["candidate_id"], "box": best["box"], "verdict": best["verdict"],
            "justification": best["justification"], "unjudged": best["unjudged"], "alike": 2,
            "position": [47.39808, 8.54598], "crop_box": crop_box,
            "crop_jpeg_b64": base64.b64encode(cv2.imencode(".jpg", crop)[1].tobytes()).decode(),
        }  # fmt: skip
        status.update(
            state="AWAITING_SUPERVISOR", reason="awaiting supervisor", awaiting=awaiting,
            track_box=best["box"], frame_id=41, awaiting_more=["c-91", "c-92"], dropped_undecided=["c-90"],
        )  # fmt: skip
        assert client.post("/v1/vehicles/drone-1/status", json=status).status_code == 200
    return awaiting


def _log_in(page: Page, url: str) -> None:
    page.goto(f"{url}/supervisor")
    page.fill("#token", SUPERVISOR_TOKEN)
    page.click("#login button[type=submit]")
    expect(page.locator("#connection")).to_have_text("live", timeout=15_000)


def _loaded(page: Page, selector: str) -> None:
    page.wait_for_function(
        "s => { const el = document.querySelector(s); return el && el.complete && el.naturalWidth > 0; }",
        arg=selector,
        timeout=15_000,
    )


@pytest.mark.slow
def test_console_shows_live_keyframe_map_and_finds_offline(
    offline_page: tuple[Page, list[str]], models_dir: Path, sequences_dir: Path
) -> None:
    page, outside = offline_page
    with _backend(models_dir) as url:
        awaiting = _fly(url, sequences_dir)
        _log_in(page, url)
        card = page.locator('section[data-vehicle="drone-1"]')
        expect(card.locator(".state")).to_have_text("AWAITING_SUPERVISOR")
        expect(card.locator(".reason")).to_have_text("awaiting supervisor")
        # The live keyframe, decoded, with the answer's boxes and the tracked box drawn over it.
        _loaded(page, 'section[data-vehicle="drone-1"] img.keyframe')
        assert card.locator("img.keyframe").evaluate("el => el.naturalWidth") == 1280
        boxes = card.locator(".overlay rect")
        assert boxes.count() >= 2 and card.locator(".overlay rect.track").count() == 1
        # Progress, coverage and the autopilot's mission.
        expect(card.locator(".progress")).to_have_text(
            "51 keyframes checked · 3 put to the supervisor · 1 rejected"
        )
        expect(card.locator(".coverage")).to_have_text("22 % of the area seen")
        expect(card.locator(".mission-item")).to_have_text("mission item 3 of 9 · mode AUTO")
        # The map from the positions alone: area, covered, track, the vehicle and the candidate.
        the_map = card.locator("svg.map")
        for mark in ("path.area", "path.covered", "path.track", "path.vehicle-mark", "circle.candidate-mark"):
            assert the_map.locator(mark).count() >= 1, mark
        assert the_map.locator("image").count() == 0  # no tiles configured: none asked for
        # The candidate's crop with its box drawn on it.
        candidate = card.locator(f'article[data-candidate="{awaiting["candidate_id"]}"]')
        _loaded(page, f'article[data-candidate="{awaiting["candidate_id"]}"] img.crop')
        assert candidate.locator(".crop-overlay rect").count() == 1
        # What the back-end could not judge of the description ("striped": no pattern is judged at this
        # size; "man": the detector judged a person, not a man): the supervisor is told to check it.
        assert {"striped", "man"} <= set(awaiting["unjudged"]), awaiting["unjudged"]
        expect(candidate.locator(".unjudged")).to_be_visible()
        expect(candidate.locator(".unjudged")).to_contain_text("Not checked by the machine")
        expect(candidate.locator(".unjudged-words")).to_have_text("; ".join(awaiting["unjudged"]))
        # Chosen among others that fit as well (the mission counts them; two here): said, not hidden.
        expect(candidate.locator(".alike")).to_have_text(
            "2 other candidates in that view fit what was checked as well: this one was chosen by the "
            "detector's score alone."
        )
        # The others waiting behind it (a supervisor slower than the survey), and one dropped undecided.
        expect(card.locator(".queue")).to_have_text(
            "2 more awaiting a decision, each shown once the one above is decided: c-91, c-92"
        )
        expect(card.locator(".dropped")).to_contain_text(
            "Dropped undecided (too many awaited a decision): c-90."
        )
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT.with_name("supervisor-console-awaiting.png")), full_page=True)
        # Confirm: the find is listed, with its crop, and marked on the map ...
        candidate.locator("button.confirm").click()
        expect(candidate.locator(".status")).to_have_text("confirmed by supervisor page", timeout=10_000)
        find = card.locator("li.find")
        expect(find).to_have_count(1)
        expect(find.locator(".where")).to_contain_text("47.398080, 8.545980")
        expect(find.locator(".who")).to_have_text("confirmed by supervisor page")
        expect(find.locator(".seen")).to_have_text("when the position was seen is not known")  # made here
        _loaded(page, 'section[data-vehicle="drone-1"] li.find img.crop')
        # ... and stays when the vehicle has moved on to its next candidate's search, its own find (seen 45 s
        # before the confirmation: the survey had flown on) replacing the page's.
        now = time.time()
        own = {
            "candidate_id": awaiting["candidate_id"],
            "position": [47.39808, 8.54598],
            "sigma_m": 1.5,
            "time": now,
            "seen_at": now - 45.0,
            "prompt": PROMPT,
            "confirmed_by": "supervisor page",
        }
        moved = {"mission_id": "m-12", "state": "SEARCHING", "prompt": PROMPT, "position": [47.3981, 8.5462],
                 "reason": "survey resumed at item 4", "find": own}  # fmt: skip
        assert (
            httpx.post(f"{url}/v1/vehicles/drone-1/status", json=moved, headers=DRONE, timeout=10).status_code
            == 200
        )
        expect(card.locator(".state")).to_have_text("SEARCHING")
        expect(card.locator("article.candidate")).to_have_count(0)
        expect(card.locator(".queue")).to_be_hidden()
        expect(card.locator(".dropped")).to_be_hidden()
        expect(find).to_have_count(1)
        expect(find.locator(".seen")).to_contain_text("45 s before the confirmation")
        assert the_map.locator("path.find-mark").count() == 1
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        print(f"screenshot: {SCREENSHOT}")
        page.goto("about:blank")  # close the live stream before the back-end stops
    assert outside == []  # nothing but loopback was asked for
    assert SCREENSHOT.stat().st_size > 20_000


@pytest.mark.slow
def test_console_map_draws_over_tiles_from_the_configured_server(
    offline_page: tuple[Page, list[str]], models_dir: Path, sequences_dir: Path
) -> None:
    page, outside = offline_page
    tiles = TileServer()
    try:
        with _backend(models_dir, tiles.url) as url:
            _fly(url, sequences_dir)
            _log_in(page, url)
            the_map = page.locator('section[data-vehicle="drone-1"] svg.map')
            expect(the_map.locator("image").first).to_be_attached(timeout=15_000)
            page.wait_for_function("() => document.querySelectorAll('svg.map image').length > 0")
            expect(page.locator('section[data-vehicle="drone-1"] .map-info')).to_contain_text("tile server")
            page.wait_for_timeout(1000)
            page.screenshot(path=str(SCREENSHOT.with_name("supervisor-console-tiles.png")), full_page=True)
            page.goto("about:blank")
    finally:
        tiles.close()
    assert outside == []
    zooms = {int(p.split("/")[2]) for p in tiles.requests}
    assert tiles.requests and zooms and min(zooms) >= 15  # a site-sized area: street-level tiles
