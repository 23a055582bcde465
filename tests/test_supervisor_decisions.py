"""The first decision on a candidate stands: Confirm and Reject sent at the same moment, 20 times, over real
HTTP to the real back-end on SQLite and on Redis. Exactly one is stored (201), the other is refused (409)
naming the one that stands; the vehicle (the companion's own session polling its decisions), the store and
the page's snapshot all hold the same decision. Select: -k decisions.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from backend_tools.fleet_services import RedisServer
from behaviors.mission_commands import ConfirmCandidate, RejectCandidate
from cloudtrack.api_client import BackendClient
from companion.cloud.backend_session import BackendSession
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve

SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}
ROUNDS = 20


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer() as server:
        yield server


@pytest.fixture(params=["sqlite", "redis"])
def backend(
    request: pytest.FixtureRequest, models_dir: Path, tmp_path: Path, redis_server: RedisServer
) -> Iterator[tuple[str, object]]:
    if request.param == "redis":
        sessions = SessionConfig(store="redis", redis_url=redis_server.url)
        import redis

        redis.Redis.from_url(redis_server.url).flushdb()
    else:
        sessions = SessionConfig(sqlite_path=str(tmp_path / "sessions.sqlite3"))
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        verifier=VerifierConfig(kind="none"),
        sessions=sessions,
    )
    app = create_app(config)
    with serve(app) as url:
        yield url, app


def test_decisions_confirm_and_reject_at_once_first_stands_everywhere(backend: tuple[str, object]) -> None:
    url, app = backend
    client = BackendClient(url, VEHICLE_TOKENS["drone-1"], vehicle_id="drone-1", mission_id="m-race")
    session = BackendSession(client, period_s=0.05).start()
    try:
        _race(url, app, client, session)
    finally:
        session.close()


def _race(url: str, app: object, client: BackendClient, session: BackendSession) -> None:
    """`session` only polls the decisions here, as the companion's does."""
    winners: dict[str, str] = {}
    with httpx.Client(base_url=url, timeout=10, headers=SUPERVISOR) as supervisor:
        for i in range(ROUNDS):
            candidate = f"c-{i}"
            # Each candidate another person, 111 m from the last (one person seen again is one find).
            awaiting = {
                "candidate_id": candidate,
                "box": [10.0, 10.0, 40.0, 90.0],
                "position": [47.39 + 0.001 * i, 8.54],
            }
            # The status goes out here, in order (the session's own reports would race this loop's).
            client.report_status("AWAITING_SUPERVISOR", awaiting=awaiting)
            answers: dict[str, httpx.Response] = {}
            barrier = threading.Barrier(2)

            def decide(
                action: str,
                candidate: str = candidate,
                barrier: threading.Barrier = barrier,
                answers: dict[str, httpx.Response] = answers,
            ) -> None:
                barrier.wait()
                answers[action] = supervisor.post(
                    "/v1/vehicles/drone-1/decisions",
                    params={"require_awaiting": "true"},
                    json={
                        "candidate_id": candidate,
                        "action": action,
                        "operator": "supervisor page",
                        "via": "supervisor page",
                    },
                )

            threads = [threading.Thread(target=decide, args=(a,)) for a in ("confirm", "reject")]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            codes = sorted(r.status_code for r in answers.values())
            assert codes == [201, 409], {a: (r.status_code, r.text) for a, r in answers.items()}
            (won,) = [a for a, r in answers.items() if r.status_code == 201]
            (lost,) = [a for a, r in answers.items() if r.status_code == 409]
            done = {"confirm": "confirmed", "reject": "rejected"}[won]
            detail = answers[lost].json()["detail"]
            assert f"already {done} by supervisor page" in detail and "stands" in detail, detail
            winners[candidate] = won
            # A repeat of the standing decision changes nothing (200); the other stays refused.
            again = supervisor.post(
                "/v1/vehicles/drone-1/decisions", json={"candidate_id": candidate, "action": won}
            )
            assert again.status_code == 200 and again.json() == answers[won].json()

    # The vehicle: exactly one command per candidate, the one that stood.
    heard: dict[str, str] = {}
    deadline = time.monotonic() + 10
    while len(heard) < ROUNDS and time.monotonic() < deadline:
        for command in session.commands():
            assert isinstance(command, (ConfirmCandidate, RejectCandidate))
            assert command.candidate_id not in heard, f"{command.candidate_id} decided twice"
            heard[command.candidate_id] = "confirm" if isinstance(command, ConfirmCandidate) else "reject"
        time.sleep(0.05)
    assert heard == winners
    # The store: one decision per candidate, the standing one.
    sessions = app.state.sessions  # type: ignore[attr-defined]
    stored = sessions.decisions("drone-1")
    assert {d.candidate_id: d.action for d in stored} == winners and len(stored) == ROUNDS
    # The page: the snapshot it renders shows the standing decision on the candidate still awaited, and
    # every confirmed candidate as a find.
    with httpx.Client(base_url=url, timeout=10, headers=SUPERVISOR) as supervisor:
        (vehicle,) = supervisor.get("/supervisor/api/state").json()["vehicles"]
        last = f"c-{ROUNDS - 1}"
        (shown,) = vehicle["candidates"]
        assert (
            shown["id"] == last
            and shown["status"] == {"confirm": "confirmed", "reject": "rejected"}[winners[last]]
        )
        assert shown["decided_by"] == "supervisor page"
        confirmed = sorted(c for c, a in winners.items() if a == "confirm")
        assert sorted(f["candidate_id"] for f in vehicle["finds"]) == confirmed
        assert all(f["confirmed_by"] == "supervisor page" for f in vehicle["finds"])
    print(json.dumps({"confirm wins": len(confirmed), "reject wins": ROUNDS - len(confirmed)}))


def test_the_session_says_which_rejections_the_back_end_took(
    backend: tuple[str, object], sequences_dir: Path
) -> None:
    """The companion's position rule for a rejection gives way once the back-end holds it (its verifier then
    judges every candidate's appearance against it: `behaviors.rejection_memory`), so the session says which
    rejections the back-end stored: one of a candidate it answered, not an id it never gave (refused)."""
    import cv2

    url, _ = backend
    client = BackendClient(url, VEHICLE_TOKENS["drone-1"], vehicle_id="drone-1", mission_id="m-shared")
    frame = sorted((sequences_dir / "uav123_group1_1" / "frames").iterdir())[0]
    found = client.detect(cv2.imread(str(frame)), "a person")
    assert found and found[0].candidate_id
    session = BackendSession(client, period_s=0.05).start()
    try:
        session.update({"state": "AWAITING_SUPERVISOR", "mission_id": "m-shared"})
        session.reject("never-given", None)
        session.reject(found[0].candidate_id, (47.39, 8.54))
        shared: list[str] = []
        deadline = time.monotonic() + 10
        while not shared and time.monotonic() < deadline:
            shared += session.shared_rejections()
            time.sleep(0.05)
        time.sleep(0.2)  # a second round: nothing more
        assert shared + session.shared_rejections() == [found[0].candidate_id]
    finally:
        session.close()
