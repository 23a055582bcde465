"""Issue 14's defects, each tried the way a hostile vehicle or a careless operator would (select: -k hostile).

Isolation of missions between vehicles, decompression bombs (header checked before any decode, decoding
inside the vehicle's queue), quotas with 429 + Retry-After, decisions never lost, secrets never printed,
weak configurations refused, the supervisor page's hardening, and a body that never completes.
"""

from __future__ import annotations

import base64
import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

import backend.images
import backend.routers.detection
from backend import request_limits
from backend.app import create_app
from backend.config import load_backend_config
from backend.serving import BackgroundServer
from backend.sessions import SessionStore
from cloudtrack.api_models import AwaitingCandidate, DecisionIn, VehicleStatus
from cloudtrack.config_files import ConfigError
from tests.backend_fixtures import SUPERVISOR, TOKENS, auth, backend_config, detect_parts, frame, jpeg

SUP = {"Authorization": f"Bearer {SUPERVISOR}"}
PROMPT = "the man in the green-and-white striped shirt"


def header_bomb(width: int, height: int) -> bytes:
    """A real small JPEG whose frame header claims width x height (what a bomb's header says)."""
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 7] = height.to_bytes(2, "big")
    data[sof + 7 : sof + 9] = width.to_bytes(2, "big")
    return bytes(data)


@pytest.fixture(scope="module")
def client(models_dir: Path) -> Iterator[TestClient]:
    app = create_app(backend_config(models_dir, "sessions.max_missions_per_vehicle=4"))
    with TestClient(app) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def person_crop_b64(sequences_dir: Path) -> str:
    """The person of uav123_person12_1 frame 1 at its ground-truth box, in the 640x360 keyframe's pixels."""
    seq = sequences_dir / "uav123_person12_1"
    full = cv2.imread(str(seq / "frames" / "000001.jpg"))
    x, y, w, h = (float(v) for v in (seq / "groundtruth.txt").read_text().splitlines()[0].split(","))
    sx, sy = 640 / full.shape[1], 360 / full.shape[0]
    small = frame(sequences_dir)
    crop = small[int(y * sy) : int((y + h) * sy), int(x * sx) : int((x + w) * sx)]
    return base64.b64encode(jpeg(crop, 90)).decode()


def _detect(client: TestClient, keyframe: bytes, vehicle: str, mission: str) -> list[dict[str, Any]]:
    response = client.post(
        "/v1/detect",
        headers=auth(vehicle),
        **detect_parts(keyframe, vehicle_id=vehicle, mission_id=mission, prompt=PROMPT),
    )
    assert response.status_code == 200, response.text
    candidates: list[dict[str, Any]] = response.json()["candidates"]
    return candidates


def test_hostile_rejection_in_one_vehicles_mission_never_touches_another_vehicle(
    client: TestClient, sequences_dir: Path, person_crop_b64: str
) -> None:
    keyframe = jpeg(frame(sequences_dir))
    body = {"vehicle_id": "drone-1", "crop_jpeg_b64": person_crop_b64, "reason": "not him"}
    assert client.post("/v1/missions/7/rejections", json=body, headers=auth("drone-1")).status_code == 201
    mine = _detect(client, keyframe, "drone-1", "7")
    assert any(c["verifier"] == "rejection-memory" and c["verdict"] == "no" for c in mine)  # the memory works
    theirs = _detect(client, keyframe, "drone-2", "7")
    assert theirs and not any(c["verifier"] == "rejection-memory" or c["previously_rejected"] for c in theirs)
    assert client.get("/v1/missions/7/rejections", headers=auth("drone-2")).json() == []
    assert len(client.get("/v1/missions/7/rejections", headers=auth("drone-1")).json()) == 1


def test_hostile_bomb_keyframe_is_refused_from_its_header_without_decoding(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    decoded: list[int] = []
    real = backend.images.cv2.imdecode
    monkeypatch.setattr(backend.images.cv2, "imdecode", lambda *a: decoded.append(1) or real(*a))
    response = client.post("/v1/detect", headers=auth(), **detect_parts(header_bomb(16000, 16000)))
    assert response.status_code == 413 and "16000x16000" in response.json()["detail"]
    assert decoded == []


def test_hostile_keyframes_are_decoded_inside_the_vehicles_queue(
    client: TestClient, sequences_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    running: list[int] = []
    real = backend.routers.detection.decode_image

    def watched(data: bytes, max_pixels: int) -> np.ndarray:
        running.append(client.app.state.scheduler.running)  # type: ignore[attr-defined]
        return real(data, max_pixels)

    monkeypatch.setattr("backend.routers.detection.decode_image", watched)
    _detect(client, jpeg(frame(sequences_dir)), "drone-1", "queue")
    assert running == [1]  # the slot was held while decoding


def test_hostile_bomb_crops_are_refused_on_every_route(client: TestClient) -> None:
    bomb = base64.b64encode(header_bomb(8700, 8700)).decode()
    rejection = client.post(
        "/v1/missions/m-b/rejections", json={"vehicle_id": "drone-1", "crop_jpeg_b64": bomb}, headers=auth()
    )
    assert rejection.status_code == 413 and "8700x8700" in rejection.json()["detail"]
    awaiting = {"candidate_id": "c-bomb", "box": [0, 0, 10, 10], "crop_jpeg_b64": bomb}
    status = client.post(
        "/v1/vehicles/drone-1/status",
        json={"mission_id": "m-b", "state": "AWAIT", "awaiting": awaiting},
        headers=auth(),
    )
    assert status.status_code == 422, status.text  # never stored, so the supervisor's Reject never decodes it


def test_hostile_mission_flood_hits_the_quota_with_retry_after(client: TestClient) -> None:
    answers = [
        client.post(
            "/v1/vehicles/drone-2/status",
            json={"mission_id": f"flood-{i}", "state": "SEARCH"},
            headers=auth("drone-2"),
        )
        for i in range(8)
    ]
    codes = [a.status_code for a in answers]
    assert 429 in codes and codes.count(200) <= 4, codes
    refused = next(a for a in answers if a.status_code == 429)
    assert int(refused.headers["Retry-After"]) > 0 and "live missions" in refused.json()["detail"]


def test_hostile_request_rate_quota_answers_429_with_retry_after(
    models_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The quota counts per fixed window of the wall clock: eight requests that straddle a window's edge
    # would start a fresh count half-way. The clock stands still here, at a window's start.
    monkeypatch.setattr(request_limits, "time", SimpleNamespace(time=lambda: 120.0, monotonic=time.monotonic))
    app = create_app(
        backend_config(models_dir, "sessions.rate_limit_requests=5", "sessions.rate_limit_window_s=60")
    )
    with TestClient(app) as client:
        codes = [client.get("/v1/vehicles/drone-1/decisions", headers=auth()).status_code for _ in range(8)]
        assert codes[:5] == [200] * 5 and codes[5:] == [429] * 3
        refused = client.get("/v1/vehicles/drone-1/decisions", headers=auth())
        assert 0 < int(refused.headers["Retry-After"]) <= 60
        assert (
            client.get("/v1/vehicles/drone-2/decisions", headers=auth("drone-2")).status_code == 200
        )  # per vehicle
        assert client.get("/v1/vehicles", headers=SUP).status_code == 200  # the supervisor has no rate quota


def test_hostile_expiry_reads_only_the_expired_missions() -> None:
    """Expiry is an index range on last_seen (O(expired)), not a sweep of every mission under a lock."""
    now = [1000.0]
    store = SessionStore(mission_ttl_s=60, max_missions=10_000, clock=lambda: now[0])
    for i in range(300):
        store.open_mission(f"v{i % 3}", f"m{i}")
    db = store.state._db  # type: ignore[attr-defined]
    plan = " ".join(
        str(row)
        for row in db.execute(
            "EXPLAIN QUERY PLAN SELECT vehicle, mission FROM missions WHERE last_seen < ?", (0.0,)
        )
    )
    assert "missions_by_age" in plan, plan
    now[0] += 30
    store.open_mission("v0", "fresh")
    assert db.execute("SELECT count(*) FROM missions").fetchone()[0] == 301
    now[0] += 45  # the 300 are 75 s old, "fresh" 45 s
    assert store.state.expire(now[0] - 60) == 300
    assert db.execute("SELECT mission FROM missions").fetchall() == [("fresh",)]


def test_hostile_reject_with_an_undecodable_stored_crop_still_records_the_decision() -> None:
    store = SessionStore()
    garbage = base64.b64encode(b"\xff\xd8\xff" + b"\x00" * 40).decode()
    awaiting = AwaitingCandidate(candidate_id="c1", box=[0, 0, 10, 10], crop_jpeg_b64=garbage)
    # Written straight to the state: e.g. kept from a version that did not check crops.
    store.state.set_status(
        VehicleStatus(vehicle_id="d1", updated_at=1.0, mission_id="m1", state="AWAIT", awaiting=awaiting)
    )
    decision, _ = store.add_decision("d1", DecisionIn(candidate_id="c1", action="reject"))
    assert store.decisions("d1") == [decision] and decision.action == "reject"


def test_hostile_supervisor_note_over_the_limit_is_422_and_at_the_limit_201(client: TestClient) -> None:
    crop = base64.b64encode(jpeg(np.full((40, 20, 3), 90, np.uint8))).decode()
    awaiting = {"candidate_id": "c-note", "box": [0, 0, 10, 10], "crop_jpeg_b64": crop}
    assert (
        client.post(
            "/v1/vehicles/drone-1/status",
            json={"mission_id": "m-note", "state": "AWAIT", "awaiting": awaiting},
            headers=auth(),
        ).status_code
        == 200
    )
    url = "/v1/vehicles/drone-1/decisions?require_awaiting=true"  # as the supervisor page sends it
    page = {"candidate_id": "c-note", "action": "reject"}
    assert client.post(url, json={**page, "note": "x" * 501}, headers=SUP).status_code == 422
    assert client.post(url, json={**page, "note": "x" * 500}, headers=SUP).status_code == 201
    api = client.post(
        "/v1/vehicles/drone-1/decisions",
        json={"candidate_id": "c-note", "action": "confirm", "note": "y" * 501},
        headers=SUP,
    )
    assert api.status_code == 422


def test_hostile_candidate_ids_cannot_become_paths(client: TestClient) -> None:
    evil = "../../../../../v1/vehicles?"
    awaiting = {"candidate_id": evil, "box": [0, 0, 10, 10]}
    status = client.post(
        "/v1/vehicles/drone-1/status",
        json={"mission_id": "m-p", "state": "AWAIT", "awaiting": awaiting},
        headers=auth(),
    )
    assert status.status_code == 422
    decision = client.post(
        "/v1/vehicles/drone-1/decisions", json={"candidate_id": evil, "action": "reject"}, headers=SUP
    )
    assert decision.status_code == 422
    rejection = client.post(
        "/v1/missions/m-p/rejections", json={"vehicle_id": "drone-1", "candidate_id": evil}, headers=auth()
    )
    assert rejection.status_code == 422


def test_hostile_responses_carry_browser_hardening_headers(client: TestClient) -> None:
    for path in ("/supervisor", "/health", "/docs", "/v1/vehicles"):
        headers = client.get(path, headers=SUP).headers
        assert (
            "frame-ancestors 'none'" in headers["content-security-policy"]
            and "script-src 'self'" in headers["content-security-policy"]
        ), path
        assert headers["x-frame-options"] == "DENY" and headers["x-content-type-options"] == "nosniff", path


def test_hostile_openapi_declares_bearer_and_docs_need_no_cdn(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    assert schema["components"]["securitySchemes"]["bearer"] == {
        "type": "http",
        "scheme": "bearer",
        "description": "A vehicle's token (auth.tokens) or the supervisor's (auth.supervisor_token).",
    }
    assert {"bearer": []} in schema["paths"]["/v1/detect"]["post"]["security"]
    page = client.get("/docs").text
    assert "cdn" not in page.lower() and "http" not in page.replace("http-equiv", "")
    script = client.get("/docs/assets/swagger-ui-bundle.js")
    assert script.status_code == 200 and len(script.content) > 500_000 and "SwaggerUIBundle" in script.text
    assert client.get("/docs/assets/swagger-ui.css").status_code == 200
    assert client.get("/docs/assets/..%2F..%2Fapp.py").status_code == 404


def test_hostile_default_config_turns_the_supervisor_page_off_instead_of_asking(models_dir: Path) -> None:
    app = create_app(
        load_backend_config(
            None, [f'detector.model_dir="{models_dir}"', 'sessions.sqlite_path=":memory:"'], environ={}
        )
    )
    with TestClient(app) as client:
        assert client.get("/supervisor/api/enabled").json() == {"enabled": False}
        assert (
            client.get(
                "/supervisor/api/state", headers={"Authorization": "Bearer anything-at-all-here"}
            ).status_code
            == 401
        )


def test_hostile_body_that_never_completes_is_cut_off(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir, "server.body_timeout_s=1.0"))
    with BackgroundServer(app) as server:
        host, port = server.url.removeprefix("http://").split(":")
        with socket.create_connection((host, int(port)), timeout=10) as conn:
            conn.sendall(
                b"POST /v1/missions/m/rejections HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                + TOKENS["drone-1"].encode()
                + b"\r\nContent-Type: application/json\r\n"
                b'Content-Length: 1000\r\n\r\n{"vehicle_id": '
            )
            started = time.monotonic()
            answer = b""
            while chunk := conn.recv(4096):  # until the server closes the connection
                answer += chunk
            took = time.monotonic() - started
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert took < 5.0, took


# Secrets and weak configurations


def _load(environ: dict[str, str]) -> str:
    try:
        load_backend_config(None, environ=environ)
    except ConfigError as exc:
        return str(exc)
    return ""


def test_hostile_config_errors_never_echo_tokens() -> None:
    secret = "very-secret-token-0001"
    malformed = _load({"CLOUDTRACK_BACKEND_AUTH__TOKENS": f'{{"drone-1": "{secret}", "drone-2": '})
    assert malformed and secret not in malformed and "auth.tokens" in malformed
    wrong_type = _load({"CLOUDTRACK_BACKEND_AUTH__TOKENS": f'["{secret}"]'})
    assert wrong_type and secret not in wrong_type


def test_hostile_all_digit_tokens_are_tokens() -> None:
    config = load_backend_config(
        None,
        environ={
            "CLOUDTRACK_BACKEND_AUTH__TOKENS": '{"drone-1": 12345678901234567890}',
            "CLOUDTRACK_BACKEND_AUTH__SUPERVISOR_TOKEN": "98765432109876543210",
        },
    )
    assert config.auth.tokens == {"drone-1": "12345678901234567890"}
    assert config.auth.supervisor_token == "98765432109876543210"


@pytest.mark.parametrize(
    ("tokens", "supervisor", "problem"),
    [
        ({"drone-1": "x"}, "", "shorter than 16"),
        ({"drone-1": "shared-token-000001", "drone-2": "shared-token-000001"}, "", "share one token"),
        ({"drone-1": "same-as-supervisor-01"}, "same-as-supervisor-01", "equals supervisor_token"),
        ({}, "short", "supervisor_token is shorter"),
    ],
)
def test_hostile_weak_auth_configurations_are_refused(
    tokens: dict[str, str], supervisor: str, problem: str
) -> None:
    message = _load(
        {
            "CLOUDTRACK_BACKEND_AUTH__TOKENS": json.dumps(tokens),
            "CLOUDTRACK_BACKEND_AUTH__SUPERVISOR_TOKEN": supervisor,
        }
    )
    assert problem in message
    for token in [*tokens.values(), supervisor]:
        assert len(token) < 3 or f"'{token}'" not in message and f'"{token}"' not in message


def test_hostile_config_show_hides_tokens_and_keys() -> None:
    token, key = "companion-token-abcdef-0001", "ab" * 32
    env = {
        "CLOUDTRACK_BACKEND__TOKEN": token,
        "CLOUDTRACK_MAVLINK__SIGNING_KEY": key,
        "PATH": "/usr/bin:/bin",
    }
    shown = subprocess.run(
        [sys.executable, "-m", "companion.cli", "config", "show"],
        capture_output=True,
        text=True,
        env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        timeout=60,
    )
    assert shown.returncode == 0, shown.stderr
    assert token not in shown.stdout and key not in shown.stdout
    assert 'token = "<hidden>"' in shown.stdout and 'signing_key = "<hidden>"' in shown.stdout


def test_hostile_rejection_flood_hits_the_missions_quota_with_retry_after(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir, "sessions.max_rejections_per_mission=2"))
    crop = base64.b64encode(jpeg(np.full((40, 20, 3), 90, np.uint8))).decode()
    body = {"vehicle_id": "drone-1", "crop_jpeg_b64": crop}
    with TestClient(app) as client:
        answers = [client.post("/v1/missions/m-r/rejections", json=body, headers=auth()) for _ in range(3)]
        assert [a.status_code for a in answers] == [201, 201, 429]
        assert (
            int(answers[2].headers["Retry-After"]) > 0
            and "rejections (the limit)" in answers[2].json()["detail"]
        )
        assert len(client.get("/v1/missions/m-r/rejections", headers=auth()).json()) == 2  # none forgotten
