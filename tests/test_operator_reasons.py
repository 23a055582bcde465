"""Every refusal reaches the operator as a reason (issue 28): the start gate (MAV_RESULT_IN_PROGRESS, then
ACCEPTED or DENIED with a STATUSTEXT naming why), the back-end's prompt check, and the companion's notices
(waiting for the autopilot or the back-end, a refused token said as such). Select: -k reasons.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from behaviors.mission_commands import MissionCommand, StartMission
from cloudtrack.api_client import BackendClient, BackendError
from cloudtrack.gcs_protocol import (
    CMD_START,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_IN_PROGRESS,
    GcsProtocol,
    StartVerdict,
    encode_prompt,
)
from companion.cloud.start_check import StartCheck, verdict_for
from companion.operator_notices import OperatorNotices
from tests.backend_fixtures import SUPERVISOR, auth, backend_config
from tests.live_backend import serve

URL = "http://127.0.0.1:8080"


class _Replies:
    def __init__(self) -> None:
        self.delivered: list[MissionCommand] = []
        self.acks: list[int] = []
        self.texts: list[str] = []

    def deliver(self, command: MissionCommand) -> None:
        self.delivered.append(command)

    def ack(self, msg: Any, result: int) -> None:
        self.acks.append(result)

    def status(self, text: str, severity: int = 6) -> None:
        self.texts.append(text)

    def camera_information(self, image_size: tuple[int, int], component: int) -> None: ...

    def latest_status(self) -> None: ...


class _Msg:
    """A COMMAND_LONG as pymavlink decodes it."""

    def __init__(self, command: int, *params: float) -> None:
        self.command = command
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        self.param1, self.param2, self.param3, self.param4 = p[:4]
        self.target_system, self.target_component = 1, 191

    def get_type(self) -> str:
        return "COMMAND_LONG"

    def get_srcSystem(self) -> int:  # noqa: N802 - pymavlink's name
        return 255

    def get_srcComponent(self) -> int:  # noqa: N802
        return 190


class _Tunnel:
    def __init__(self, payload: bytes) -> None:
        self.payload_type, self.payload, self.payload_length = 49421, list(payload), len(payload)
        self.target_system, self.target_component = 1, 191

    def get_type(self) -> str:
        return "TUNNEL"

    def get_srcSystem(self) -> int:  # noqa: N802
        return 255


def _start(protocol: GcsProtocol, prompt: str, mission: int = 7) -> None:
    chunks = encode_prompt(mission, "", prompt)
    for chunk in chunks:
        protocol.handle(_Tunnel(chunk), time.monotonic())
    protocol.handle(
        _Msg(CMD_START, mission, len(chunks), 0, sum(len(c) - 4 for c in chunks)), time.monotonic()
    )


class _Gate:
    """A start gate whose verdict the test gives later."""

    def __init__(self) -> None:
        self.verdict: StartVerdict | None = None
        self.done: list[Callable[[], None]] = []

    def __call__(self, start: StartMission, done: Callable[[], None]) -> StartVerdict | None:
        if self.verdict is None and not self.done:
            self.done.append(done)
        return self.verdict


@pytest.mark.parametrize(
    ("verdict", "acks", "texts", "delivered"),
    [
        (StartVerdict(True), [MAV_RESULT_ACCEPTED], ["MISSION 7 STARTED: a man in a red cap"], 1),
        (
            StartVerdict(True, "waiting for the back-end at http://x: connection refused"),
            [MAV_RESULT_ACCEPTED],
            [
                "MISSION 7 STARTED: a man in a red cap",
                "waiting for the back-end at http://x: connection refused",
            ],
            1,
        ),
        (
            StartVerdict(False, "the back-end cannot search for this: no class 'buoy'"),
            [MAV_RESULT_DENIED],
            ["START REFUSED: the back-end cannot search for this: no class 'buoy'"],
            0,
        ),
    ],
)
def test_reasons_start_gate_answers_in_progress_then_the_verdict(
    verdict: StartVerdict, acks: list[int], texts: list[str], delivered: int
) -> None:
    replies, gate = _Replies(), _Gate()
    protocol = GcsProtocol(1, 191, 100, lambda: (640, 480), replies, start_gate=gate)
    _start(protocol, "a man in a red cap")
    _start(protocol, "a man in a red cap")  # the GCS's retry while the back-end is asked: one question
    assert replies.acks == [MAV_RESULT_IN_PROGRESS, MAV_RESULT_IN_PROGRESS] and replies.delivered == []
    assert len(gate.done) == 1
    gate.verdict = verdict
    gate.done[0]()
    assert replies.acks[2:] == acks and replies.texts == texts and len(replies.delivered) == delivered
    _start(protocol, "a man in a red cap")  # known now: answered at once
    assert replies.acks[-1] == acks[0]


class _Client:
    url = URL

    def __init__(self, error: Exception | None = None, delay_s: float = 0.0) -> None:
        self.error, self.delay_s, self.calls = error, delay_s, 0

    def check_prompt(self, prompt: str, superset: str | None = None) -> object:
        self.calls += 1
        time.sleep(self.delay_s)
        if self.error is not None:
            raise self.error
        return {"superset": "person"}


@pytest.mark.parametrize(
    ("error", "accepted", "words"),
    [
        (None, True, ""),
        (
            BackendError("HTTP 422", 422, detail="superset 'life buoy' has no COCO mapping"),
            False,
            "life buoy",
        ),
        (
            BackendError("HTTP 401", 401, detail="invalid bearer token"),
            False,
            "refused this vehicle's token (HTTP 401",
        ),
        (
            BackendError(f"back-end {URL} unreachable: connection refused", None, True, "connection refused"),
            True,
            "waiting for the back-end at",
        ),
        (BackendError("HTTP 503", 503, True, detail="busy"), True, "waiting for the back-end at"),
    ],
)
def test_reasons_start_check_verdicts(error: Exception | None, accepted: bool, words: str) -> None:
    verdict = verdict_for(error, URL)
    assert verdict.accepted is accepted and words in verdict.reason
    heard: list[StartVerdict] = []
    check = StartCheck(_Client(error, delay_s=0.3), on_verdict=heard.append)  # still asking at the 2nd call
    done = threading.Event()
    start = StartMission("an orange life buoy")
    assert check(start, done.set) is None and check(start, lambda: None) is None  # asked once
    assert done.wait(5)
    assert check(start, lambda: None) == verdict == heard[0]


def test_reasons_notices_say_each_change_once_most_pressing_first() -> None:
    notices = OperatorNotices("udpin:0.0.0.0:14550", URL)
    notices.autopilot_heard(False)
    notices.autopilot_heard(False)
    notices.backend_failed(
        BackendError(f"back-end {URL} unreachable: connection refused", None, True, "connection refused")
    )
    assert notices.current() == "waiting for the autopilot's HEARTBEAT on udpin:0.0.0.0:14550"
    notices.autopilot_heard(True)
    assert notices.current() == f"waiting for the back-end at {URL}: connection refused"
    notices.backend_failed(BackendError("HTTP 401", 401, detail="invalid bearer token"), "status")
    assert notices.current().startswith("the back-end refused this vehicle's token (HTTP 401: invalid bearer")
    notices.backend_answered()
    assert notices.current() == ""
    notices.backend_failed(BackendError("HTTP 422", 422, detail="no class 'buoy'"))
    assert notices.current() == "the back-end cannot search for this mission: no class 'buoy'"
    assert [topic for topic, _ in notices.changes()] == [
        "autopilot", "backend", "autopilot", "backend", "auth", "auth", "search",
    ]  # fmt: skip
    assert notices.changes() == []


@pytest.fixture(scope="module")
def backend_url(models_dir: Path) -> Iterator[str]:
    with serve(create_app(backend_config(models_dir))) as url:
        yield url


@pytest.mark.parametrize(
    ("prompt", "token", "accepted", "words"),
    [
        ("an injured man in a gray shirt", "drone-1-token-one", True, ""),
        ("an orange life buoy", "drone-1-token-one", False, "has no COCO mapping (nearest known classes"),
        (
            "an injured man in a gray shirt",
            "not-a-token-of-anyone",
            False,
            "refused this vehicle's token (HTTP 401",
        ),
    ],
)
def test_reasons_start_check_against_the_real_back_end(
    backend_url: str, prompt: str, token: str, accepted: bool, words: str
) -> None:
    done = threading.Event()
    check = StartCheck(BackendClient(backend_url, token, 5.0, vehicle_id="drone-1"))
    assert check(StartMission(prompt), done.set) is None and done.wait(10)
    verdict = check(StartMission(prompt), lambda: None)
    assert verdict is not None and verdict.accepted is accepted and words in verdict.reason


def test_reasons_prompt_check_endpoint(models_dir: Path) -> None:
    with TestClient(create_app(backend_config(models_dir))) as client:
        ok = client.post("/v1/prompts/check", json={"prompt": "a kayak"}, headers=auth())
        assert ok.status_code == 200 and ok.json()["superset"] == "boat"
        refused = client.post("/v1/prompts/check", json={"prompt": "an orange life buoy"}, headers=auth())
        assert refused.status_code == 422 and "nearest known classes" in refused.json()["detail"]
        assert client.post("/v1/prompts/check", json={"prompt": "a kayak"}).status_code == 401
        forced = client.post(
            "/v1/prompts/check", json={"prompt": "an orange thing", "superset": "boat"}, headers=auth()
        )
        assert forced.status_code == 200 and forced.json()["superset"] == "boat"
        # Words outside the given superset: searched, with a warning naming what they name.
        outside = client.post(
            "/v1/prompts/check", json={"prompt": "an orange life buoy", "superset": "person"}, headers=auth()
        )
        assert outside.status_code == 200 and outside.json()["superset"] == "person"
        assert outside.json()["warning"].startswith("the prompt's 'orange life buoy' is no person")
        fits = client.post(
            "/v1/prompts/check", json={"prompt": "a man in a kayak", "superset": "person"}, headers=auth()
        )
        assert fits.json()["warning"] is None and ok.json()["warning"] is None


def test_reasons_a_refused_vehicle_token_shows_on_the_page(models_dir: Path) -> None:
    with TestClient(create_app(backend_config(models_dir))) as client:
        wrong = {"Authorization": "Bearer not-the-token-of-drone-1"}
        assert (
            client.post("/v1/vehicles/drone-1/status", json={"state": "IDLE"}, headers=wrong).status_code
            == 401
        )
        # An unknown vehicle's name is not shown: anyone can make up one.
        assert (
            client.post("/v1/vehicles/drone-9/status", json={"state": "IDLE"}, headers=wrong).status_code
            == 401
        )
        supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
        (vehicle,) = client.get("/supervisor/api/state", headers=supervisor).json()["vehicles"]
        assert vehicle["id"] == "drone-1" and vehicle["state"] == "UNKNOWN"
        assert (
            vehicle["auth_error"] == "the back-end refused this vehicle's token (401: invalid bearer token)"
        )
