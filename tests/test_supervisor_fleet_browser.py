"""Issue 43 item 4, one picture, on the supervisor page in Debian's headless chromium with every request off
loopback refused: two vehicles of one mission report through the real HTTP API with their own tokens; the
page's fleet map shows each one's part, track and position in its colour (the exports' colours) and named
by its id, over the mission's merged coverage; the legend gives id, colour, state and coverage of the part;
and one queue holds the candidates of both vehicles, newest first, each naming the vehicle that sees it.
A decision from the queue reaches the vehicle's candidate. Select: -k fleet_browser.
"""

from __future__ import annotations

import base64
import re
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
from backend.config import AuthConfig, BackendConfig, SessionConfig, VerifierConfig
from cloudtrack.vehicle_colours import vehicle_colours
from sitl.simulated_detector import SimulatedPersonDetector
from tests import browser_pages
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "out" / "test-artifacts" / "supervisor-fleet.png"
MISSION = "m-43"
PROMPT = "a man in a gray shirt"
LAT, LON = 47.3977, 8.5456
D = 0.0009  # about 100 m of latitude
# The area split in two: drone-1 flies the western part, drone-2 the eastern (counter-clockwise rings).
PARTS = {
    "drone-1": [[LAT, LON], [LAT, LON + D], [LAT + D, LON + D], [LAT + D, LON]],
    "drone-2": [[LAT, LON + D], [LAT, LON + 2 * D], [LAT + D, LON + 2 * D], [LAT + D, LON + D]],
}
SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}


@pytest.fixture
def page() -> Iterator[Page]:
    with browser_pages.offline_page() as (page, outside):
        yield page
    assert outside == []  # vendored assets only: nothing but loopback was asked for


def _crop() -> str:
    picture = np.full((160, 90, 3), 90, np.uint8)
    cv2.rectangle(picture, (25, 30), (65, 140), (40, 40, 200), -1)
    return base64.b64encode(cv2.imencode(".jpg", picture)[1].tobytes()).decode()


def _status(url: str, vehicle: str, step: int, mode: str = "AUTO", **extra: Any) -> None:
    """`vehicle` at `step` of its lane up the middle of its part, the southern half of which it has covered."""
    part = PARTS[vehicle]
    west, east = part[0][1], part[1][1]
    covered = [[part[0], part[1], [LAT + D / 2, east], [LAT + D / 2, west]]]
    body = {
        "mission_id": MISSION,
        "state": "SEARCHING",
        "prompt": PROMPT,
        "position": [LAT + step * D / 10, (west + east) / 2],
        "heading_deg": 0.0,
        "search": {"area": part, "covered": covered, "coverage": 0.5, "mode": mode},
        **extra,
    }
    headers = {"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"}
    response = httpx.post(f"{url}/v1/vehicles/{vehicle}/status", json=body, headers=headers, timeout=10)
    assert response.status_code == 200, response.text


def _awaiting(url: str, vehicle: str, step: int, candidate: str) -> None:
    at = [LAT + step * D / 10 + 0.0001, (PARTS[vehicle][0][1] + PARTS[vehicle][1][1]) / 2 + 0.0001]
    awaiting = {
        "candidate_id": candidate,
        "box": [25.0, 30.0, 65.0, 140.0],
        "verdict": "uncertain",
        "justification": f"gray shirt seen by {vehicle}",
        "crop_jpeg_b64": _crop(),
        "position": at,
    }
    _status(url, vehicle, step, state="AWAITING_SUPERVISOR", awaiting=awaiting)


def _queue(page: Page) -> list[tuple[str | None, str | None]]:
    items = page.locator("#queue li.queued")
    return [
        (items.nth(i).get_attribute("data-vehicle"), items.nth(i).get_attribute("data-candidate"))
        for i in range(items.count())
    ]


def _rgb(colour: str) -> str:
    return f"rgb({int(colour[1:3], 16)}, {int(colour[3:5], 16)}, {int(colour[5:7], 16)})"


@pytest.mark.slow
def test_the_fleet_on_one_map_and_one_candidate_queue(page: Page) -> None:
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        verifier=VerifierConfig(kind="none"),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    colours = vehicle_colours(PARTS)
    assert colours["drone-1"] != colours["drone-2"]
    # No keyframe is analysed here: the detector is never asked.
    with serve(create_app(config, detector=SimulatedPersonDetector(lambda fid: None))) as url:
        for step in range(6):  # both fly up their lanes: a track each
            for vehicle in PARTS:
                _status(url, vehicle, step)
        _awaiting(url, "drone-1", 6, "c-west")
        time.sleep(1.2)  # drone-2's candidate waits from later: it is the newer
        _awaiting(url, "drone-2", 6, "c-east")

        page.goto(f"{url}/supervisor")
        page.fill("#token", SUPERVISOR_TOKEN)
        page.click("#login button[type=submit]")
        expect(page.locator("#connection")).to_have_text("live", timeout=15_000)
        figure = page.locator(f'figure.mission-map[data-mission="{MISSION}"]')
        expect(figure).to_be_visible(timeout=10_000)
        expect(figure.locator(".mission-title")).to_have_text(
            f"Mission {MISSION}: 2 vehicles · 50 % of the area covered"
        )
        the_map = figure.locator("svg.fleet-map")

        # Each vehicle's part, track and position: in its colour, and named by its id.
        for vehicle, colour in colours.items():
            part = the_map.locator(f'path.part[data-vehicle="{vehicle}"]')
            expect(part).to_have_count(1)
            assert part.get_attribute("stroke") == colour
            expect(part.locator("title")).to_have_text(f"{vehicle}'s part of the area")
            expect(the_map.locator(f'text.part-label[data-vehicle="{vehicle}"]')).to_have_text(
                f"{vehicle} part"
            )
            track = the_map.locator(f'path.fleet-track[data-vehicle="{vehicle}"]')
            expect(track).to_have_count(1)
            assert track.get_attribute("stroke") == colour
            expect(track.locator("title")).to_have_text(f"{vehicle}'s track")
            assert (track.get_attribute("d") or "").count("L") == 6  # 7 positions, 10 m apart
            mark = the_map.locator(f'path.fleet-vehicle[data-vehicle="{vehicle}"]')
            assert mark.get_attribute("fill") == colour
            expect(the_map.locator(f'text.vehicle-label[data-vehicle="{vehicle}"]')).to_have_text(
                f"{vehicle} · awaiting supervisor"
            )
            candidate = the_map.locator(f'circle.fleet-candidate[data-vehicle="{vehicle}"]')
            assert candidate.get_attribute("stroke") == colour
            # The legend: id, colour, state and the coverage of its part.
            item = figure.locator(f'.fleet-legend li[data-vehicle="{vehicle}"]')
            expect(item.locator(".legend-id")).to_have_text(vehicle)
            expect(item.locator(".legend-state")).to_have_text("awaiting supervisor")
            expect(item.locator(".legend-coverage")).to_have_text("50 % of its part covered")
            expect(item.locator(".chip")).to_have_css("background-color", _rgb(colour))
            # The vehicle's console carries the same chip beside its id.
            card = page.locator(f'section.vehicle[data-vehicle="{vehicle}"]')
            expect(card.locator(".vehicle-head .chip")).to_have_css("background-color", _rgb(colour))
            # ... and draws the mission's merged covered area under its part (its own is not sent twice).
            expect(card.locator(".map path.covered")).to_have_count(1)
        # The merged map under them: one covered area over both parts, the mission's area outlined.
        expect(the_map.locator("path.merged-covered")).to_have_count(1)
        expect(the_map.locator("path.merged-area")).to_have_count(1)
        # Every shape stays inside the map.
        inside = """el => {
            const b = el.getBoundingClientRect(), m = el.ownerSVGElement.getBoundingClientRect();
            return b.left >= m.left - 0.5 && b.top >= m.top - 0.5 && b.right <= m.right + 0.5
                && b.bottom <= m.bottom + 0.5;
        }"""
        shapes = the_map.locator("path.part, path.fleet-track, path.fleet-vehicle, text.vehicle-label").all()
        assert len(shapes) == 8 and all(shape.evaluate(inside) for shape in shapes)

        # The exports draw the vehicles in the same colours.
        exported = httpx.get(f"{url}/v1/missions/{MISSION}/finds.geojson", headers=SUPERVISOR, timeout=10)
        assert exported.status_code == 200, exported.text
        assert {v["vehicle_id"]: v["colour"] for v in exported.json()["vehicles"]} == colours

        # One queue, both vehicles' candidates, newest first, each naming its vehicle by id and colour.
        expect(page.locator("#queue li.queued")).to_have_count(2)
        assert _queue(page) == [("drone-2", "c-east"), ("drone-1", "c-west")]
        expect(page.locator("#queue-count")).to_have_text("(2)")
        for vehicle, cid in (("drone-2", "c-east"), ("drone-1", "c-west")):
            item = page.locator(f'#queue li.queued[data-vehicle="{vehicle}"]')
            expect(item.locator(".seen-by")).to_have_text(f"{vehicle} sees candidate {cid}")
            expect(item.locator(".chip")).to_have_css("background-color", _rgb(colours[vehicle]))
            expect(item.locator(".justification")).to_have_text(f"gray shirt seen by {vehicle}")
            expect(item.locator(".age")).to_contain_text("put to the supervisor")
            expect(item.locator("img.crop")).to_be_visible()

        # Rejected from the queue: the decision is drone-1's candidate's, on its card as well.
        west = page.locator('#queue li.queued[data-vehicle="drone-1"]')
        west.locator("button.reject").click()
        expect(west.locator(".status")).to_have_text("rejected by supervisor page", timeout=10_000)
        card = page.locator('section.vehicle[data-vehicle="drone-1"] article[data-candidate="c-west"]')
        expect(card.locator(".status")).to_have_text("rejected by supervisor page")
        decisions = httpx.get(  # what the vehicle picks up
            f"{url}/v1/vehicles/drone-1/decisions",
            headers={"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"},
            timeout=10,
        )
        assert decisions.status_code == 200, decisions.text
        assert [(d["candidate_id"], d["action"]) for d in decisions.json()] == [("c-west", "reject")]

        # drone-1 goes on and puts another candidate: the newest, on top.
        _awaiting(url, "drone-1", 7, "c-west-2")
        expect(page.locator('#queue li.queued[data-candidate="c-west-2"]')).to_have_count(1, timeout=10_000)
        assert _queue(page) == [("drone-1", "c-west-2"), ("drone-2", "c-east")]
        expect(page.locator("#queue li.queued").first.locator(".seen-by")).to_have_text(
            "drone-1 sees candidate c-west-2"
        )

        # A vehicle that goes home has left the search (the back-end says so): on the map and in the legend,
        # with the part of its area it leaves unflown (its northern half) in its colour, named.
        expect(the_map.locator("path.unflown")).to_have_count(0)
        _status(url, "drone-2", 7, mode="RTL")
        expect(the_map.locator('text.vehicle-label[data-vehicle="drone-2"]')).to_have_text(
            "drone-2 · left the search (mode RTL)", timeout=10_000
        )
        legend = figure.locator('.fleet-legend li[data-vehicle="drone-2"]')
        expect(legend.locator(".legend-state")).to_have_text("left the search (mode RTL)")
        expect(legend.locator(".legend-coverage")).to_have_text(
            re.compile(r"^50 % of its part covered · \d+ m² unflown$")
        )
        unflown = the_map.locator('path.unflown[data-vehicle="drone-2"]')
        expect(unflown).to_have_count(1)
        assert unflown.get_attribute("fill") == colours["drone-2"]
        expect(unflown.locator("title")).to_have_text(
            re.compile(r"^drone-2 left \d+ m² of its part unflown$")
        )
        expect(the_map.locator("path.unflown")).to_have_count(1)  # drone-1 searches on
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        page.goto("about:blank")  # close the live stream before the back-end stops
