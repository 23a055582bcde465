"""The session stores behind one interface: SQLite (a real file, WAL) and Redis (Debian's real redis-server
started here), the same tests for both, plus what only sharing gives: two replicas on one Redis see one
fleet and one rejection memory, and a change made through one wakes the other's watcher (pub/sub).
Select with -k store.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from backend.redis_store import RedisStore
from backend.schemas import KeyframeCandidate, KeyframeRecord, MissionMap, StoredFind
from backend.sessions import SessionStore
from backend.state_store import (
    DECISIONS_KEPT_PER_VEHICLE,
    FINDS_PER_MISSION,
    QuotaExceededError,
    SqliteStore,
    StateStore,
    vector_bytes,
    vector_from,
)
from backend_tools.fleet_services import RedisServer
from cloudtrack.api_models import DecisionIn, Rejection, RejectionIn, VehicleStatus


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer() as server:
        yield server


@pytest.fixture(params=["sqlite", "redis"])
def state(request: pytest.FixtureRequest, tmp_path: Path, redis_server: RedisServer) -> Iterator[StateStore]:
    if request.param == "sqlite":
        store: StateStore = SqliteStore(tmp_path / "sessions.sqlite3")
    else:
        store = RedisStore(redis_server.url)
        store._redis.flushdb()  # type: ignore[attr-defined]
    yield store
    store.close()


def _rejection(vehicle: str, mission: str, candidate: str) -> Rejection:
    return Rejection(
        rejection_id=0,
        mission_id=mission,
        vehicle_id=vehicle,
        candidate_id=candidate,
        position=None,
        reason="",
        created_at=1.0,
    )


def test_store_missions_are_per_vehicle_capped_and_expire(state: StateStore) -> None:
    for i in range(3):
        state.touch_mission("d1", f"m{i}", 100.0 + i, 60, 3)
    state.touch_mission("d1", "m0", 110.0, 60, 3)  # a known mission is always allowed
    state.touch_mission("d2", "m0", 110.0, 60, 3)  # another vehicle's quota is its own
    with pytest.raises(QuotaExceededError) as info:
        state.touch_mission("d1", "m3", 120.0, 60, 3)
    assert info.value.retry_after_s == 41  # m1, the oldest live one, expires at 161
    assert state.expire(105.0) == 2  # m1 and m2 of d1; m0 of both was seen at 110
    state.touch_mission("d1", "m3", 151.0, 60, 3)


def test_store_candidates_rejections_and_vectors_as_bytes(state: StateStore) -> None:
    state.touch_mission("d1", "m1", 100.0, 60, 10)
    vector = np.linspace(0, 1, 128).tolist()
    state.put_candidates("d1", "m1", [("c1", vector_bytes(vector))])
    blob = state.candidate("d1", "m1", "c1")
    assert isinstance(blob, bytes) and len(blob) == 128 * 4
    assert np.allclose(vector_from(blob), vector)
    assert state.candidate("d2", "m1", "c1") is None
    first = state.add_rejection("d1", "m1", _rejection("d1", "m1", "c1"), blob, limit=2)
    second = state.add_rejection("d1", "m1", _rejection("d1", "m1", "c2"), blob, limit=2)
    assert second.rejection_id > first.rejection_id > 0
    with pytest.raises(QuotaExceededError):
        state.add_rejection("d1", "m1", _rejection("d1", "m1", "c3"), blob, limit=2)
    assert [(r.candidate_id, a) for r, a in state.rejections("d1", "m1")] == [("c1", blob), ("c2", blob)]
    assert state.rejections("d2", "m1") == []
    state.expire(float("inf"))
    assert state.rejections("d1", "m1") == [] and state.candidate("d1", "m1", "c1") is None


def test_store_statuses_decisions_version_and_rate(state: StateStore) -> None:
    v0 = state.version()
    state.set_status(VehicleStatus(vehicle_id="d2", updated_at=1.0, state="SEARCH"))
    state.set_status(VehicleStatus(vehicle_id="d1", updated_at=2.0, state="TRACK"))
    assert [s.vehicle_id for s in state.statuses()] == ["d1", "d2"] and state.status("d1").state == "TRACK"  # type: ignore[union-attr]
    a, created_a = state.add_decision("d1", "m1", DecisionIn(candidate_id="c1", action="reject"), 3.0)
    b, created_b = state.add_decision("d1", "m1", DecisionIn(candidate_id="c2", action="confirm"), 4.0)
    assert created_a and created_b
    assert state.decisions("d1") == [a, b] and state.decisions("d1", after=a.decision_id) == [b]
    assert state.decisions("d2") == []
    assert state.version() >= v0 + 4
    assert [state.rate_hit("d1", 1000.5, 2, 10.0) for _ in range(3)][:2] == [None, None]
    assert state.rate_hit("d1", 1001.0, 2, 10.0) == pytest.approx(9.0)
    assert state.rate_hit("d1", 1010.0, 2, 10.0) is None  # a new window


def test_store_first_decision_on_a_candidate_stands(state: StateStore) -> None:
    confirm, created = state.add_decision("d1", "m1", DecisionIn(candidate_id="c1", action="confirm"), 1.0)
    reject, again = state.add_decision("d1", "m1", DecisionIn(candidate_id="c1", action="reject"), 2.0)
    assert created and not again and reject == confirm  # the standing one comes back, nothing new stored
    assert state.decisions("d1") == [confirm] and state.standing_decision("d1", "m1", "c1") == confirm
    # Another mission's candidate of the same id, another vehicle's: decided on their own.
    assert state.add_decision("d1", "m2", DecisionIn(candidate_id="c1", action="reject"), 3.0)[1]
    assert state.add_decision("d2", "m1", DecisionIn(candidate_id="c1", action="reject"), 3.0)[1]
    assert state.standing_decision("d1", "m3", "c1") is None


def test_store_first_decision_wins_when_twenty_pairs_race(state: StateStore) -> None:
    """Confirm and reject of each candidate from two threads at once: exactly one is stored, and both callers
    are answered with it."""
    for i in range(20):
        answers: list[tuple[object, bool]] = []
        barrier = threading.Barrier(2)

        def decide(
            action: str,
            candidate: str = f"c{i}",
            barrier: threading.Barrier = barrier,
            answers: list = answers,
        ) -> None:
            barrier.wait()
            decision = DecisionIn(candidate_id=candidate, action=action)  # type: ignore[arg-type]
            answers.append(state.add_decision("d1", "m1", decision, 1.0))

        threads = [threading.Thread(target=decide, args=(a,)) for a in ("confirm", "reject")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(created for _, created in answers) == [False, True]
        assert answers[0][0] == answers[1][0] == state.standing_decision("d1", "m1", f"c{i}")
    assert len(state.decisions("d1")) == 20


def _find(
    candidate: str, source: str = "vehicle", mission: str = "m1", sigma: float | None = 2.0
) -> StoredFind:
    return StoredFind(
        candidate_id=candidate, position=[47.0, 8.0], sigma_m=sigma, time=10.0, prompt="a man in red",
        confirmed_by="gcs", vehicle_id="d1", mission_id=mission, received_at=10.0, source=source,  # type: ignore[arg-type]
    )  # fmt: skip


def test_store_finds_once_maps_and_keyframes(state: StateStore) -> None:
    state.touch_mission("d1", "m1", 1.0, 1e9, 10)
    state.touch_mission("d1", "m2", 1.0, 1e9, 10)
    made, changed = state.put_find(_find("c1", "supervisor", sigma=None))
    assert changed and state.finds("d1", "m1") == [made]
    better, replaced = state.put_find(_find("c1"), replace_source="supervisor")  # the vehicle's own, once
    assert replaced and state.finds("d1", "m1") == [better]
    kept, again = state.put_find(_find("c1", sigma=9.0), replace_source="supervisor")
    assert not again and kept == better
    state.put_find(_find("c2", mission="m2"))
    assert [f.candidate_id for f in state.finds("d1")] == ["c1", "c2"] and state.finds("d2") == []
    for i in range(3, 3 + FINDS_PER_MISSION - 1):
        state.put_find(_find(f"c{i}"))
    with pytest.raises(QuotaExceededError):
        state.put_find(_find("one-too-many"))
    area = MissionMap(track=[[47.0, 8.0, 1.0]], area=[[47.0, 8.0], [47.1, 8.0], [47.1, 8.1]], coverage=0.25)
    state.set_mission_map("d1", "m1", area)
    assert state.mission_map("d1", "m1") == area and state.mission_map("d1", "m2") is None
    record = KeyframeRecord(
        frame_id=7, mission_id="m1", width=64, height=48, received_at=5.0,
        candidates=[KeyframeCandidate(id="c1", box=[1, 2, 3, 4], verdict="yes")],
    )  # fmt: skip
    before = state.version()
    state.set_keyframe("d1", record, b"\xff\xd8jpeg")
    assert state.version() > before  # the page's live view is woken by a new keyframe
    assert state.keyframe("d1") == record and state.keyframe_jpeg("d1") == (record, b"\xff\xd8jpeg")
    assert state.keyframe("d2") is None
    state.expire(float("inf"))  # finds, decisions on candidates and maps go with their mission
    assert state.finds("d1") == [] and state.mission_map("d1", "m1") is None


def test_store_sqlite_keeps_everything_across_a_reopen(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    first = SessionStore(SqliteStore(path))
    first.state.set_status(VehicleStatus(vehicle_id="d1", updated_at=1.0, state="AWAIT", mission_id="m1"))
    first.open_mission("d1", "m1")
    first.remember_candidates("d1", "m1", [("c1", [0.5] * 128)])
    decision, _ = first.add_decision("d1", DecisionIn(candidate_id="c1", action="reject"))
    first.state.put_find(_find("c2"))
    # No close(): what a SIGKILL leaves behind.
    again = SessionStore(SqliteStore(path))
    assert again.decisions("d1") == [decision] and again.state.finds("d1", "m1") == [_find("c2")]
    assert again.standing_decision("d1", "m1", "c1") == decision
    assert [r.candidate_id for r in again.rejections("d1", "m1")] == ["c1"]
    assert again.rejection_check("d1", "m1", None)([0.5] * 127 + [0.6]) is not None


def test_store_two_replicas_on_one_redis_share_fleet_and_memory(redis_server: RedisServer) -> None:
    a, b = SessionStore(RedisStore(redis_server.url)), SessionStore(RedisStore(redis_server.url))
    a.state._redis.flushdb()  # type: ignore[attr-defined]
    a.open_mission("d1", "m1")
    a.remember_candidates("d1", "m1", [("c1", [1.0] + [0.0] * 127)])
    b.add_rejection("m1", RejectionIn(vehicle_id="d1", candidate_id="c1"))  # known through a's candidates
    assert a.rejection_check("d1", "m1", None)([1.0] + [0.0] * 127) is not None
    b.state.set_status(VehicleStatus(vehicle_id="d9", updated_at=1.0, state="SEARCH"))
    assert [s.vehicle_id for s in a.statuses()] == ["d9"]


def test_store_redis_change_wakes_another_replicas_watcher(redis_server: RedisServer) -> None:
    watcher, writer = RedisStore(redis_server.url), RedisStore(redis_server.url)
    last = watcher.version()
    woke: list[float] = []

    def watch() -> None:
        started = time.monotonic()
        watcher.wait_change(last, 10.0)
        woke.append(time.monotonic() - started)

    thread = threading.Thread(target=watch)
    thread.start()
    time.sleep(0.3)  # the watcher is subscribed and blocked
    writer.set_status(VehicleStatus(vehicle_id="d1", updated_at=1.0, state="TRACK"))
    thread.join(timeout=10)
    assert woke and woke[0] < 5.0  # woken by the publication, not by its 10 s timeout
    assert watcher.version() > last


def test_store_a_vehicles_report_is_kept_apart_and_never_stands(state: StateStore) -> None:
    """Issue 44: what the vehicle reports was decided at its GCS is its report, not the standing decision."""
    gcs = DecisionIn(candidate_id="c1", action="confirm", operator="supervisor page")
    reported, created = state.add_decision("d1", "m1", gcs, 1.0, source="vehicle")
    assert created and reported.source == "vehicle"
    assert state.add_decision("d1", "m1", gcs, 2.0, source="vehicle") == (reported, False)  # once
    assert state.standing_decision("d1", "m1", "c1") is None
    assert state.reported_decision("d1", "m1", "c1") == reported
    reject, created = state.add_decision("d1", "m1", DecisionIn(candidate_id="c1", action="reject"), 3.0)
    assert created and state.standing_decision("d1", "m1", "c1") == reject
    assert state.decisions("d1") == [reported, reject]


def test_store_the_decision_list_says_which_it_dropped(state: StateStore) -> None:
    """Past DECISIONS_KEPT_PER_VEHICLE the oldest leave the list, the highest id dropped is kept, and every
    standing decision still stands."""
    extra = 3
    made = [
        state.add_decision("d1", "m1", DecisionIn(candidate_id=f"c{i}", action="reject"), float(i))[0]
        for i in range(DECISIONS_KEPT_PER_VEHICLE + extra)
    ]
    assert state.decisions_dropped("d1") == made[extra - 1].decision_id and state.decisions_dropped("d2") == 0
    assert state.decisions("d1") == made[extra:]
    assert state.standing_decision("d1", "m1", "c0") == made[0]
