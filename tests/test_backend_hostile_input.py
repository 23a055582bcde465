"""Issue 31's faults of the HTTP API, each tried the way a hostile or broken client would (select: -k hostile).

Work per request is bounded before any validation (body size per route, JSON values, keys, depth), a 422
lists the first few errors and how many there were, the rate limit counts a request before its body is
read (so invalid posts count too), positions and integers are range-checked (422, never 500), and a
client that trickles its header lines is cut off.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import requests
from fastapi.testclient import TestClient

from backend import request_limits
from backend.app import create_app
from backend.serving import BackgroundServer
from cloudtrack.api_models import Rejection
from tests.backend_fixtures import SUPERVISOR, auth, backend_config, detect_parts, frame, jpeg

SUP = {"Authorization": f"Bearer {SUPERVISOR}"}


@pytest.fixture(scope="module")
def client(models_dir: Path) -> Iterator[TestClient]:
    app = create_app(backend_config(models_dir, "sessions.rate_limit_requests=100000"))
    with TestClient(app) as test_client:
        yield test_client


def _status(client: TestClient, body: bytes | dict[str, Any], vehicle: str = "drone-1") -> Any:
    content = body if isinstance(body, bytes) else json.dumps(body).encode()
    return client.post(
        f"/v1/vehicles/{vehicle}/status",
        content=content,
        headers={**auth(vehicle), "Content-Type": "application/json"},
    )


# Bounded work before validation


def test_hostile_status_of_150000_unknown_keys_is_refused_by_its_size(client: TestClient) -> None:
    body = json.dumps({f"k{i}": 0 for i in range(150_000)}).encode()  # 1.7 MB, as reported
    assert len(body) > 1_500_000
    answer = _status(client, body)
    assert answer.status_code == 413 and len(answer.content) < 1000, answer.text[:300]


@pytest.mark.parametrize(("keys", "problem"), [(60_000, "values"), (5_000, "keys")])
def test_hostile_unknown_keys_within_the_size_are_refused_before_validation(
    client: TestClient, keys: int, problem: str
) -> None:
    body = json.dumps({"state": "SEARCH", **{f"k{i}": 0 for i in range(keys)}}).encode()
    assert len(body) < 900_000  # under the status route's size: the count of values or keys refuses it
    answer = _status(client, body)
    assert answer.status_code == 413 and len(answer.content) < 1000, answer.text[:300]
    assert problem in answer.json()["detail"]


@pytest.mark.parametrize(
    ("document", "problem"),
    [
        ({"a": json.loads("[" * 20 + "1" + "]" * 20)}, "nested deeper"),
        ({"area": list(range(20_000))}, "values"),
        ({f"k{i}": 1 for i in range(200)}, "keys"),
        ({"state": "SEARCH", "position": [1, 2]}, None),
    ],
)
def test_hostile_json_shape_table(document: Any, problem: str | None) -> None:
    from backend.request_limits import JsonLimits, json_shape_problem

    found = json_shape_problem(json.dumps(document).encode(), JsonLimits())
    assert (found is None) if problem is None else (found is not None and problem in found), found


def test_hostile_a_status_within_the_contract_fits_the_json_limits() -> None:
    """A status at every bound of the contract (search area, covered area, two crops) is not refused."""
    from backend.request_limits import json_shape_problem, route_limit

    area = [[47.0 + i * 1e-4, 8.0] for i in range(200)]
    covered = [[[47.0 + i * 1e-4, 8.0 + r * 1e-4] for i in range(25)] for r in range(20)]
    crop = "A" * 400_000
    status = {
        "mission_id": "m-1",
        "state": "SEARCH",
        "search": {"area": area, "covered": covered, "coverage": 0.5},
        "awaiting": {"candidate_id": "c1", "box": [0, 0, 1, 1], "crop_jpeg_b64": crop},
        "find": {"candidate_id": "c1", "position": [47, 8], "sigma_m": 3, "time": 1, "confirmed_by": "gcs",
                 "crop_jpeg_b64": crop},
    }  # fmt: skip
    body = json.dumps(status).encode()
    limit = route_limit("POST", "/v1/vehicles/drone-1/status")
    assert len(body) <= limit.max_bytes and json_shape_problem(body, limit.json) is None


def test_hostile_validation_errors_are_summarised(client: TestClient) -> None:
    body = {"state": 7, "prompt": 8, "altitude_m": "x", "heading_deg": "y", "reason": 9, "mission_id": "a b"}
    body.update({f"extra_{i}": i for i in range(40)})
    answer = _status(client, body)
    assert answer.status_code == 422
    reply = answer.json()
    assert len(reply["detail"]) == 5 and reply["error_count"] == 46, reply
    assert all(set(e) == {"type", "loc", "msg"} for e in reply["detail"])


def test_hostile_detect_meta_errors_are_summarised(client: TestClient, sequences_dir: Path) -> None:
    meta = {"vehicle_id": "drone-1", "mission_id": "m", "prompt": "a man", **{f"x{i}": 0 for i in range(25)}}
    parts = detect_parts(jpeg(frame(sequences_dir)))
    parts["data"] = {"meta": json.dumps(meta)}
    answer = client.post("/v1/detect", headers=auth(), **parts)
    assert answer.status_code == 422 and len(answer.json()["detail"]) == 5, answer.text[:300]
    assert answer.json()["error_count"] == 25


def test_hostile_validation_failures_count_towards_the_rate_limit(
    models_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The quota counts per fixed window of the wall clock: eight requests that straddle a window's edge
    # would start a fresh count half-way. The clock stands still here, at a window's start.
    monkeypatch.setattr(request_limits, "time", SimpleNamespace(time=lambda: 120.0, monotonic=time.monotonic))
    app = create_app(
        backend_config(models_dir, "sessions.rate_limit_requests=5", "sessions.rate_limit_window_s=60")
    )
    with TestClient(app) as client:
        codes = [_status(client, {"state": ["not", "text"]}).status_code for _ in range(8)]
        assert codes == [422] * 5 + [429] * 3, codes
        refused = _status(client, {"state": "SEARCH"})
        assert refused.status_code == 429 and int(refused.headers["Retry-After"]) > 0
        assert _status(client, {"state": "SEARCH"}, "drone-2").status_code == 200  # per vehicle


def test_hostile_an_unknown_token_is_refused_before_its_body_is_read(client: TestClient) -> None:
    body = json.dumps({f"k{i}": 0 for i in range(60_000)}).encode()
    answer = client.post(
        "/v1/vehicles/drone-1/status",
        content=body,
        headers={"Authorization": "Bearer not-a-token-of-anyone", "Content-Type": "application/json"},
    )
    assert answer.status_code == 401 and answer.headers["www-authenticate"] == "Bearer"


def test_hostile_route_limits_table() -> None:
    from backend.request_limits import route_limit

    assert route_limit("POST", "/v1/detect").max_bytes == 2_000_000  # server.max_request_bytes
    assert route_limit("POST", "/v1/vehicles/d-1/status").max_bytes >= 900_000  # two 400 kB crops
    assert route_limit("POST", "/v1/missions/m/rejections").max_bytes < 900_000
    assert route_limit("POST", "/v1/vehicles/d-1/decisions").max_bytes <= 16_384
    assert route_limit("GET", "/v1/vehicles").max_bytes <= 16_384


# Range-checked positions and integers: 422, never 500


def test_hostile_a_position_off_the_globe_is_422_everywhere(client: TestClient) -> None:
    rejection = client.post(
        "/v1/missions/m-geo/rejections",
        json={"vehicle_id": "drone-1", "candidate_id": "c1", "position": [135, 0]},
        headers=auth(),
    )
    assert rejection.status_code == 422, rejection.text
    awaiting = {"candidate_id": "c1", "box": [0, 0, 10, 10], "position": [1e308, -1e308]}
    status = _status(client, {"mission_id": "m-geo", "state": "AWAIT", "awaiting": awaiting})
    assert status.status_code == 422, status.text
    assert _status(client, {"state": "SEARCH", "position": [1e308, -1e308]}).status_code == 422


def test_hostile_a_stored_position_off_the_globe_never_makes_a_500(
    client: TestClient, sequences_dir: Path
) -> None:
    """A rejection stored before positions were checked ([135, 0]) and a detect at [45, 180]: the reported
    math domain error in sessions.distance_m."""
    sessions = client.app.state.sessions  # type: ignore[attr-defined]
    sessions.open_mission("drone-1", "m-old")
    record = Rejection(rejection_id=0, mission_id="m-old", vehicle_id="drone-1", candidate_id="c0",
                       position=[135.0, 0.0], reason="", created_at=1.0)  # fmt: skip
    sessions.state.add_rejection("drone-1", "m-old", record, bytes(128 * 4), 200)
    answer = client.post(
        "/v1/detect",
        headers=auth(),
        **detect_parts(jpeg(frame(sequences_dir)), mission_id="m-old", vehicle_position=[45, 180]),
    )
    assert answer.status_code == 200, answer.text[:300]


@pytest.mark.parametrize("after", ["9223372036854775808", "-1", "1e3", str(2**70)])
def test_hostile_decision_polling_after_out_of_range_is_422(client: TestClient, after: str) -> None:
    answer = client.get(f"/v1/vehicles/drone-1/decisions?after={after}", headers=auth())
    assert answer.status_code == 422, answer.text


EXTREMES: list[Any] = [1e308, -1e308, 2**64, -(2**64), 2**63, -1, 0]


@pytest.mark.parametrize("value", EXTREMES)
def test_hostile_extreme_numbers_in_every_field_never_make_a_5xx(
    client: TestClient, sequences_dir: Path, value: Any
) -> None:
    keyframe = jpeg(frame(sequences_dir))
    answers = [
        _status(client, {"state": "SEARCH", "altitude_m": value, "heading_deg": value}),
        _status(client, {"state": "SEARCH", "track_box": [value, value, value, value], "frame_id": value}),
        _status(client, {"state": "SEARCH", "progress": {"keyframes": value, "candidates": value}}),
        _status(client, {"state": "SEARCH", "search": {"mission_item": value, "coverage": value}}),
        _status(client, {"mission_id": "m-x", "state": "AWAIT",
                         "awaiting": {"candidate_id": "c", "box": [value] * 4, "crop_box": [value] * 4}}),
        client.post("/v1/missions/m-x/rejections", headers=auth(),
                    json={"vehicle_id": "drone-1", "candidate_id": "c", "crop_box": [value] * 4}),
        client.post("/v1/detect", headers=auth(),
                    **detect_parts(keyframe, frame_id=value, capture_time=value, roi=[0, 0, value, value])),
        client.post("/v1/detect", headers=auth(),
                    **detect_parts(keyframe, roi=[value, value, 10, 10])),
        client.get(f"/v1/vehicles/drone-1/decisions?after={value}", headers=auth()),
    ]  # fmt: skip
    assert [a.status_code for a in answers if a.status_code >= 500] == [], [a.text[:200] for a in answers]


# Slow headers


def _trickle(port: int, stop: threading.Event, closed: list[float], started: float) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as conn:
        conn.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
        try:
            while not stop.is_set():
                conn.sendall(b"X-Trickle: 1\r\n")  # a header line now and then, never the blank line
                conn.settimeout(0.3)
                try:
                    if conn.recv(4096) == b"":
                        break
                except TimeoutError:
                    continue
                else:
                    break  # an answer (408), then the close
        except OSError:
            pass
    closed.append(time.monotonic() - started)


def test_hostile_clients_trickling_header_lines_are_cut_off(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir, "server.header_timeout_s=1.0"))
    with BackgroundServer(app) as server:  # the server's header timeout comes from the app's config
        port = int(server.url.rsplit(":", 1)[1])
        stop, closed = threading.Event(), []  # type: ignore[var-annotated]
        started = time.monotonic()
        threads = [threading.Thread(target=_trickle, args=(port, stop, closed, started)) for _ in range(90)]
        for t in threads:
            t.start()
        try:
            # Meanwhile a real client is served.
            assert requests.get(server.url + "/health", timeout=10).status_code == 200
            deadline = time.monotonic() + 20
            while len(closed) < 90 and time.monotonic() < deadline:
                time.sleep(0.1)
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=10)
    assert len(closed) == 90 and max(closed) < 15, sorted(closed)[-3:]


def test_hostile_a_slow_but_complete_request_is_still_served(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir, "server.header_timeout_s=2.0"))
    with BackgroundServer(app) as server:
        port = int(server.url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
            for line in (b"GET /health HTTP/1.1\r\n", b"Host: x\r\n", b"Connection: close\r\n", b"\r\n"):
                conn.sendall(line)
                time.sleep(0.2)
            answer = b""
            while chunk := conn.recv(4096):
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 200"), answer[:100]


# Hostile load beside a vehicle's search (the bench's figures: docs/benchmarks.md, "Back-end under hostile load")


@pytest.mark.slow
def test_hostile_load_beside_a_search_answers_every_kind_without_a_5xx(
    models_dir: Path, sequences_dir: Path
) -> None:
    """`cloudtrack-backend bench --hostile` in small: every hostile kind gets its refusal (issue 44's duplicate
    headers a 400, also in the attack phase), the searching vehicle every answer, the slow clients are cut by
    the server. No timing is asserted."""
    from backend_tools.hostile_bench import hostile_kinds, hostile_run

    kinds = hostile_kinds()
    report = hostile_run(models_dir, sequences_dir, 4 * len(kinds), 6, 3.0, lambda _: None,
                         ("server.header_timeout_s=1.0",))  # fmt: skip
    assert report["server_errors"] == 0, report["by_kind"]
    refusals = {kind: set(codes) for kind, codes in report["by_kind"].items()}
    assert set(refusals) == {k.kind for k in kinds}
    for kind, codes in refusals.items():
        expected = {"200", "429"} if kind.startswith("a new mission") else {"413", "422"}
        expected = {"400"} if kind.startswith("duplicate") else expected
        assert codes <= expected, (kind, codes)
    assert set(report["vehicle_a"]["codes"]) == {"A 200", "A status 200"}
    assert report["vehicle_a"]["beside"]["keyframes"] > 0
    attack = report["duplicate_header_attack"]
    assert set(attack["answers"]) == {"400"} and set(attack["codes"]) == {"A 200", "A status 200"}, attack
    assert attack["vehicle_a"]["keyframes"] > 0 and attack["vehicle_a"]["statuses"] > 0
    assert report["slow_clients_closed"] == 6  # by the server: the clients never stop on their own
