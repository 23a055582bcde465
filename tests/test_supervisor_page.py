"""The supervisor page's API on the real back-end over loopback HTTP: auth, snapshot, crop, SSE, decisions."""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from fastapi import FastAPI

from backend.change_feed import ChangeFeed
from backend.config import AuthConfig, BackendConfig
from backend.dependencies import EventStreamLimits, get_event_stream_limits
from backend.routers import supervisor
from backend.sessions import SessionStore
from backend.supervisor_view import SupervisorView
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, LiveBackend, live_backend, serve

SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}
DRONE = {"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"}


@pytest.fixture(scope="module")
def backend(models_dir: Path) -> Iterator[LiveBackend]:
    with live_backend(models_dir) as live:
        yield live


@pytest.fixture(scope="module")
def crop_b64(sequences_dir: Path) -> str:
    """A real crop of the person in a real frame, with the 50 px margin, as the companion sends it."""
    seq = sequences_dir / "uav123_person12_1"
    frame = cv2.imread(str(seq / "frames" / "000001.jpg"))
    x, y, w, h = (int(float(v)) for v in (seq / "groundtruth.txt").read_text().splitlines()[0].split(","))
    crop = frame[max(0, y - 50) : y + h + 50, max(0, x - 50) : x + w + 50]
    ok, data = cv2.imencode(".jpg", crop)
    assert ok
    return base64.b64encode(data.tobytes()).decode()


def report(
    client: httpx.Client, state: str, awaiting: dict[str, Any] | None, vehicle: str = "drone-1"
) -> None:
    body = {
        "mission_id": "m-1",
        "state": state,
        "prompt": "a man in a red shirt",
        "position": [47.3977, 8.5456],
        "awaiting": awaiting,
    }
    response = client.post(
        f"/v1/vehicles/{vehicle}/status",
        json=body,
        headers={"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"},
    )
    assert response.status_code == 200, response.text


def candidate(crop_b64: str, candidate_id: str = "c-17") -> dict[str, Any]:
    return {
        "candidate_id": candidate_id,
        "box": [100.0, 80.0, 140.0, 180.0],
        "justification": "red shirt, lying on the ground",
        "crop_jpeg_b64": crop_b64,
        "position": [47.39781, 8.54567],
    }


def test_page_and_assets_are_served_without_data(backend: LiveBackend) -> None:
    with httpx.Client(base_url=backend.url, timeout=10) as client:
        page = client.get("/supervisor")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "Confirm" in page.text and "/supervisor/static/supervisor.js" in page.text
        script = client.get("/supervisor/static/supervisor.js")
        assert script.status_code == 200 and "javascript" in script.headers["content-type"]
        assert "Authorization" in script.text and "textContent" in script.text
        assert client.get("/supervisor/static/supervisor.css").headers["content-type"].startswith("text/css")
        assert client.get("/supervisor/static/..%2Fapp.py").status_code == 404
        assert client.get("/supervisor/static/secrets.txt").status_code == 404


def test_everything_with_data_needs_the_supervisor_token(backend: LiveBackend, crop_b64: str) -> None:
    with httpx.Client(base_url=backend.url, timeout=10) as client:
        report(client, "AWAITING_SUPERVISOR", candidate(crop_b64))
        decision_url = "/v1/vehicles/drone-1/decisions?require_awaiting=true"
        for method, url in (
            ("GET", "/supervisor/api/state"),
            ("GET", "/supervisor/events"),
            ("GET", "/supervisor/api/vehicles/drone-1/candidates/c-17/crop.jpg"),
            ("POST", decision_url),
        ):
            body = {"candidate_id": "c-17", "action": "confirm"} if method == "POST" else None
            assert client.request(method, url, json=body).status_code == 401, url
            wrong = {"Authorization": "Bearer not-a-token"}
            assert client.request(method, url, json=body, headers=wrong).status_code == 401, url
            # A vehicle's token is valid for the API but is not the supervisor's.
            assert client.request(method, url, json=body, headers=DRONE).status_code == 403, url
        decisions = client.get("/v1/vehicles/drone-1/decisions", headers=DRONE).json()
        assert all(d["candidate_id"] != "c-17" for d in decisions)  # nothing got through


def test_snapshot_crop_and_decision_reach_the_vehicle(backend: LiveBackend, crop_b64: str) -> None:
    with httpx.Client(base_url=backend.url, timeout=10) as client:
        report(client, "AWAITING_SUPERVISOR", candidate(crop_b64, "c-21"))
        report(client, "SEARCHING", None, vehicle="drone-2")
        snapshot = client.get("/supervisor/api/state", headers=SUPERVISOR).json()
        vehicles = {v["id"]: v for v in snapshot["vehicles"]}
        assert vehicles["drone-2"]["state"] == "SEARCHING" and vehicles["drone-2"]["candidates"] == []
        one = vehicles["drone-1"]
        assert one["state"] == "AWAITING_SUPERVISOR" and one["prompt"] == "a man in a red shirt"
        (cand,) = one["candidates"]
        assert cand["id"] == "c-21" and cand["status"] == "awaiting"
        assert cand["justification"] == "red shirt, lying on the ground"
        assert cand["position"] == {"lat": 47.39781, "lon": 8.54567}
        assert cand["verdict"] in ("yes", "uncertain") and 0 <= cand["age_s"] < 60

        crop = client.get(cand["crop_url"], headers=SUPERVISOR)
        assert crop.status_code == 200 and crop.headers["content-type"] == "image/jpeg"
        assert crop.content == base64.b64decode(crop_b64)
        assert cv2.imdecode(np.frombuffer(crop.content, np.uint8), cv2.IMREAD_COLOR) is not None

        url = "/v1/vehicles/drone-1/decisions?require_awaiting=true"
        c21 = {"candidate_id": "c-21"}
        assert client.post(url, json={**c21, "action": "maybe"}, headers=SUPERVISOR).status_code == 422
        assert (
            client.post(url, json={**c21, "action": "confirm", "x": 1}, headers=SUPERVISOR).status_code == 422
        )
        stale = client.post(url, json={"candidate_id": "c-20", "action": "confirm"}, headers=SUPERVISOR)
        assert stale.status_code == 409 and "no longer waiting" in stale.json()["detail"]
        unknown = client.post(
            "/v1/vehicles/drone-9/decisions?require_awaiting=true",
            json={**c21, "action": "reject"},
            headers=SUPERVISOR,
        )
        assert unknown.status_code == 404
        # The page's own decision path is gone: the API's endpoint above is the only one.
        gone = "/supervisor/api/vehicles/drone-1/candidates/c-21/decision"
        assert client.post(gone, json={"decision": "confirm"}, headers=SUPERVISOR).status_code in (404, 405)

        posted = client.post(url, json={**c21, "action": "confirm"}, headers=SUPERVISOR)
        assert posted.status_code == 201, posted.text
        # The companion polls its session exactly as it does for a decision made anywhere else.
        polled = client.get("/v1/vehicles/drone-1/decisions", params={"after": 0}, headers=DRONE).json()
        assert [(d["candidate_id"], d["action"]) for d in polled][-1] == ("c-21", "confirm")
        after = client.get("/supervisor/api/state", headers=SUPERVISOR).json()
        assert (
            next(v for v in after["vehicles"] if v["id"] == "drone-1")["candidates"][0]["status"]
            == "confirmed"
        )


def read_events(
    lines: Iterator[str], count: int, timeout_s: float = 15.0, kinds: tuple[str, ...] = ("state", "vehicle")
) -> list[dict[str, Any]]:
    """The snapshot after each of the next `count` `state` or `vehicle` events (a `vehicle` event replaces
    that vehicle in the last snapshot, as the page does) from an open Server-Sent Events response."""
    found: list[dict[str, Any]] = []
    kind, data = "", []
    deadline = time.monotonic() + timeout_s
    for line in lines:
        assert time.monotonic() < deadline, "no event in time"
        if line.startswith("event:"):
            kind = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].strip())
        elif line == "" and data:
            body = json.loads("\n".join(data))
            if kind == "state":
                read_events.snapshot = body  # type: ignore[attr-defined]
            elif kind == "vehicle":
                last = read_events.snapshot  # type: ignore[attr-defined]
                last["vehicles"] = [body if v["id"] == body["id"] else v for v in last["vehicles"]]
            if kind in kinds:
                found.append(json.loads(json.dumps(read_events.snapshot if kind != "ages" else body)))  # type: ignore[attr-defined]
                if len(found) == count:
                    return found
            kind, data = "", []
    raise AssertionError("stream ended")


def test_a_report_that_changes_nothing_still_renews_the_vehicles_age(backend: LiveBackend) -> None:
    """The companion reports every second; "last report" must say so even when nothing else changed."""
    with httpx.Client(base_url=backend.url, timeout=15) as client:
        report(client, "SEARCHING", None, vehicle="drone-2")
        with client.stream("GET", "/supervisor/events", headers=SUPERVISOR) as stream:
            lines = stream.iter_lines()
            read_events(lines, 1, kinds=("state",))
            time.sleep(1.5)
            report(client, "SEARCHING", None, vehicle="drone-2")
            (ages,) = read_events(lines, 1, kinds=("ages",))
            assert ages["drone-2"] < 1.0


def test_live_updates_arrive_as_server_sent_events(backend: LiveBackend, crop_b64: str) -> None:
    with httpx.Client(base_url=backend.url, timeout=15) as client:
        report(client, "FOLLOWING", None)
        with client.stream("GET", "/supervisor/events", headers=SUPERVISOR) as stream:
            assert stream.status_code == 200
            assert stream.headers["content-type"].startswith("text/event-stream")
            lines = stream.iter_lines()
            (first,) = read_events(lines, 1)
            assert next(v for v in first["vehicles"] if v["id"] == "drone-1")["state"] == "FOLLOWING"
            report(client, "AWAITING_SUPERVISOR", candidate(crop_b64, "c-30"))
            (second,) = read_events(lines, 1)
            one = next(v for v in second["vehicles"] if v["id"] == "drone-1")
            assert one["state"] == "AWAITING_SUPERVISOR" and one["candidates"][0]["id"] == "c-30"


def test_a_crop_that_is_not_a_jpeg_is_refused_when_reported(backend: LiveBackend) -> None:
    """Only real JPEG bytes are ever served as image/jpeg: anything else is refused on the way in."""
    with httpx.Client(base_url=backend.url, timeout=10) as client:
        for bad in (
            "***not base64***",
            base64.b64encode(b"<script>alert(1)</script>").decode(),
            base64.b64encode(b"\xff\xd8\xff\xe0" + bytes(64)).decode(),
        ):
            body = {
                "mission_id": "m-1",
                "state": "AWAITING_SUPERVISOR",
                "awaiting": {**candidate("", "c-40"), "crop_jpeg_b64": bad},
            }
            response = client.post("/v1/vehicles/drone-1/status", json=body, headers=DRONE)
            assert response.status_code == 422, (bad, response.text)
        missing = client.get("/supervisor/api/vehicles/drone-1/candidates/c-39/crop.jpg", headers=SUPERVISOR)
        assert missing.status_code == 404


def test_an_event_stream_ends_after_its_lifetime_so_shutdowns_are_never_held() -> None:
    """uvicorn waits for open responses when it stops; the page reconnects when a stream ends."""
    app = FastAPI()
    app.state.config = BackendConfig(auth=AuthConfig(supervisor_token=SUPERVISOR_TOKEN))
    store = SessionStore()
    feed = ChangeFeed(store.state).start()
    app.state.sessions, app.state.feed, app.state.supervisor_view = store, feed, SupervisorView(store)
    app.include_router(supervisor.router)
    app.dependency_overrides[get_event_stream_limits] = lambda: EventStreamLimits(max_stream_s=1.0)
    try:
        with serve(app) as url, httpx.Client(base_url=url, timeout=15) as client:
            started = time.monotonic()
            with client.stream("GET", "/supervisor/events", headers=SUPERVISOR) as stream:
                lines = list(stream.iter_lines())  # returns only when the server ends the stream
            took = time.monotonic() - started
    finally:
        feed.stop()
    assert "event: state" in lines
    assert 1.0 <= took < 10.0, took


def test_reject_reaches_the_vehicle_and_the_missions_rejection_memory(
    backend: LiveBackend, crop_b64: str
) -> None:
    with httpx.Client(base_url=backend.url, timeout=10) as client:
        report(client, "AWAITING_SUPERVISOR", candidate(crop_b64, "c-50"))
        url = "/v1/vehicles/drone-1/decisions?require_awaiting=true"
        posted = client.post(
            url, json={"candidate_id": "c-50", "action": "reject", "note": "wrong shirt"}, headers=SUPERVISOR
        )
        assert posted.status_code == 201, posted.text
        polled = client.get("/v1/vehicles/drone-1/decisions", headers=DRONE).json()
        assert (polled[-1]["candidate_id"], polled[-1]["action"], polled[-1]["note"]) == (
            "c-50",
            "reject",
            "wrong shirt",
        )
        # The back-end remembers it (with the crop the vehicle sent) so look-alikes are answered "no".
        rejections = client.get("/v1/missions/m-1/rejections", headers=DRONE).json()
        assert (
            client.get("/v1/missions/m-1/rejections", headers=SUPERVISOR).status_code == 422
        )  # name the vehicle
        assert (
            client.get(
                "/v1/missions/m-1/rejections", params={"vehicle_id": "drone-1"}, headers=SUPERVISOR
            ).json()
            == rejections
        )
        assert any(r["candidate_id"] == "c-50" and r["reason"] == "wrong shirt" for r in rejections)
        state = client.get("/supervisor/api/state", headers=SUPERVISOR).json()
        cand = next(v for v in state["vehicles"] if v["id"] == "drone-1")["candidates"][0]
        assert cand["id"] == "c-50" and cand["status"] == "rejected"
