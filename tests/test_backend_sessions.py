"""Session state: rejection memory per mission, statuses and decisions, fair queueing, configuration."""

from __future__ import annotations

import asyncio
import base64
from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.appearance import descriptor
from backend.config import ENV_PREFIX, BackendConfig, load_backend_config
from backend.fair_queue import FairScheduler, QueueFullError
from backend.schemas import AwaitingCandidate, DecisionIn, RejectionIn, VehicleStatusIn
from backend.sessions import QuotaExceededError, SessionStore, UnknownCandidateError, distance_m
from behaviors.geometry import Box
from cloudtrack.config_files import ConfigError, load_config

REPO = Path(__file__).resolve().parents[1]


def _person(colour: tuple[int, int, int], seed: int = 0) -> np.ndarray:
    """A 120x60 'person' patch of one clothing colour with some texture."""
    rng = np.random.default_rng(seed)
    patch = np.zeros((120, 60, 3), np.uint8)
    patch[:] = colour
    noise = rng.integers(-12, 12, patch.shape)
    return np.clip(patch.astype(int) + noise, 0, 255).astype(np.uint8)


RED, BLUE = _person((40, 40, 200)), _person((200, 80, 30))
WHOLE = Box(0, 0, 60, 120)


def test_rejected_candidate_by_id_is_recognised_and_others_are_not() -> None:
    store = SessionStore()
    store.remember_candidates(
        "d1", "m1", [("c-red", descriptor(RED, WHOLE)), ("c-blue", descriptor(BLUE, WHOLE))]
    )
    store.add_rejection("m1", RejectionIn(vehicle_id="d1", candidate_id="c-red", reason="wrong person"))
    check = store.rejection_check("d1", "m1", None)
    reason = check(descriptor(_person((40, 40, 200), seed=5), WHOLE))  # same look, new pixels
    assert reason is not None and "c-red" in reason
    assert check(descriptor(BLUE, WHOLE)) is None
    assert (
        store.rejection_check("d1", "m2", None)(descriptor(RED, WHOLE)) is None
    )  # other missions unaffected
    assert [r.candidate_id for r in store.rejections("d1", "m1")] == ["c-red"]


def test_rejection_needs_a_known_id_or_a_crop() -> None:
    store = SessionStore()
    with pytest.raises(UnknownCandidateError, match="send crop_jpeg_b64"):
        store.add_rejection("m1", RejectionIn(vehicle_id="d1", candidate_id="nope"))
    crop = base64.b64encode(cv2.imencode(".jpg", RED)[1].tobytes()).decode()
    store.add_rejection("m1", RejectionIn(vehicle_id="d1", crop_jpeg_b64=crop))
    assert store.rejection_check("d1", "m1", None)(descriptor(RED, WHOLE)) is not None
    with pytest.raises(ValueError, match="base64"):
        store.add_rejection("m1", RejectionIn(vehicle_id="d1", crop_jpeg_b64="%%%"))
    with pytest.raises(ValueError, match="JPEG or PNG"):
        store.add_rejection(
            "m1", RejectionIn(vehicle_id="d1", crop_jpeg_b64=base64.b64encode(b"text").decode())
        )


def test_position_limits_a_rejection_to_its_place() -> None:
    store = SessionStore(radius_m=100)
    store.remember_candidates("d1", "m1", [("c", descriptor(RED, WHOLE))])
    store.add_rejection("m1", RejectionIn(vehicle_id="d1", candidate_id="c", position=[47.0, 8.0]))
    look = descriptor(RED, WHOLE)
    assert store.rejection_check("d1", "m1", [47.0005, 8.0])(look) is not None  # about 56 m away
    assert store.rejection_check("d1", "m1", [47.01, 8.0])(look) is None  # about 1.1 km away: a look-alike
    assert store.rejection_check("d1", "m1", None)(look) is not None
    assert 1100 < distance_m([47.0, 8.0], [47.01, 8.0]) < 1125


def test_missions_expire_and_rejections_are_bounded_by_a_quota() -> None:
    now = [1000.0]
    store = SessionStore(mission_ttl_s=60, max_rejections=3, clock=lambda: now[0])
    store.open_mission("d1", "old")
    store.remember_candidates("d1", "old", [(f"c{i}", descriptor(RED, WHOLE)) for i in range(5)])
    for i in range(3):
        store.add_rejection("old", RejectionIn(vehicle_id="d1", candidate_id=f"c{i}"))
    with pytest.raises(QuotaExceededError):  # refused, not silently forgetting the oldest rejection
        store.add_rejection("old", RejectionIn(vehicle_id="d1", candidate_id="c3"))
    assert [r.candidate_id for r in store.rejections("d1", "old")] == ["c0", "c1", "c2"]
    now[0] += 120
    store.open_mission("d1", "new")
    assert store.rejections("d1", "old") == []


def test_supervisor_reject_decision_enters_the_rejection_memory() -> None:
    store = SessionStore()
    store.remember_candidates("d1", "m1", [("c1", descriptor(RED, WHOLE))])
    awaiting = AwaitingCandidate(candidate_id="c1", box=[0, 0, 60, 120], justification="red shirt")
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="AWAIT_SUPERVISOR", awaiting=awaiting))
    reject, _ = store.add_decision("d1", DecisionIn(candidate_id="c1", action="reject", note="not him"))
    assert [r.reason for r in store.rejections("d1", "m1")] == ["not him"]
    # The first decision stands: a later confirm changes nothing and enters nothing.
    standing, created = store.add_decision("d1", DecisionIn(candidate_id="c1", action="confirm"))
    assert not created and standing == reject and store.finds("d1") == []
    assert store.decisions("d1") == [reject] and store.decisions("d1", after=reject.decision_id) == []
    assert store.decisions("d2") == []
    # A reject for a candidate the back-end never saw still reaches the companion.
    store.add_decision("d1", DecisionIn(candidate_id="unknown", action="reject"))
    assert store.decisions("d1")[-1].candidate_id == "unknown"
    assert store.status("d1") is not None and [s.vehicle_id for s in store.statuses()] == ["d1"]


def test_fair_scheduler_serves_vehicles_in_turn() -> None:
    async def scenario() -> tuple[list[str], bool]:
        scheduler = FairScheduler(slots=1, max_queued_per_key=10)
        order: list[str] = []
        gate = asyncio.Event()

        async def request(vehicle: str) -> None:
            async with scheduler.slot(vehicle):
                order.append(vehicle)
                await gate.wait()

        first = asyncio.create_task(request("flood"))
        await asyncio.sleep(0)
        tasks = [asyncio.create_task(request("flood")) for _ in range(4)]
        await asyncio.sleep(0)
        tasks += [asyncio.create_task(request("quiet")), asyncio.create_task(request("other"))]
        await asyncio.sleep(0)
        gate.set()
        await asyncio.gather(first, *tasks)
        return order, scheduler.running == 0 and scheduler.queued == 0

    order, drained = asyncio.run(scenario())
    # FIFO would serve all five flood requests first; round-robin lets quiet and other in early.
    assert order[:4] == ["flood", "flood", "quiet", "other"] and order.count("flood") == 5 and drained


def test_fair_scheduler_refuses_a_full_vehicle_queue_and_survives_cancellation() -> None:
    async def scenario() -> None:
        scheduler = FairScheduler(slots=1, max_queued_per_key=1)
        gate = asyncio.Event()

        async def request(vehicle: str) -> None:
            async with scheduler.slot(vehicle):
                await gate.wait()

        holder = asyncio.create_task(request("a"))
        await asyncio.sleep(0)
        waiting = asyncio.create_task(request("a"))
        await asyncio.sleep(0)
        with pytest.raises(QueueFullError):
            async with scheduler.slot("a"):
                pass
        waiting.cancel()
        await asyncio.sleep(0)
        assert scheduler.queued == 0
        gate.set()
        await holder
        async with scheduler.slot("b"):
            assert scheduler.running == 1

    asyncio.run(scenario())


def test_default_file_matches_schema_defaults() -> None:
    assert load_config(BackendConfig, REPO / "config" / "backend.toml", environ={}) == BackendConfig()


def test_environment_prefix_is_the_backends_own() -> None:
    environ = {
        f"{ENV_PREFIX}SERVER__PORT": "9000",
        f"{ENV_PREFIX}AUTH__TOKENS": '{"d1": "s3cret-vehicle-token"}',
        "CLOUDTRACK_BACKEND__TOKEN": "companion-setting",
        "CLOUDTRACK_SAFETY__MAX_SPEED_M_S": "2",
    }
    config = load_backend_config(None, environ=environ)
    assert config.server.port == 9000 and config.auth.tokens == {"d1": "s3cret-vehicle-token"}


def test_bad_backend_config_is_named(tmp_path: Path) -> None:
    path = tmp_path / "b.toml"
    path.write_text('[detector]\nkind = "yolo9000"\n[verifier]\ntimeout = 3\n')
    with pytest.raises(ConfigError) as info:
        load_config(BackendConfig, path, environ={})
    assert (
        "detector.kind" in str(info.value)
        and "verifier.timeout" in str(info.value)
        and "timeout_s" in str(info.value)
    )


def test_status_keeps_a_candidates_crop_but_never_gives_it_to_another() -> None:
    store = SessionStore()
    crop = base64.b64encode(cv2.imencode(".jpg", RED)[1].tobytes()).decode()
    first = AwaitingCandidate(
        candidate_id="c1", box=[0, 0, 60, 120], crop_jpeg_b64=crop, crop_box=[5, 5, 65, 125]
    )
    store.set_status("drone-1", VehicleStatusIn(mission_id="m1", state="AWAITING_SUPERVISOR", awaiting=first))
    later = AwaitingCandidate(candidate_id="c1", box=[2, 0, 62, 120])
    kept = store.set_status(
        "drone-1", VehicleStatusIn(mission_id="m1", state="AWAITING_SUPERVISOR", awaiting=later)
    )
    assert (
        kept.awaiting is not None
        and kept.awaiting.crop_jpeg_b64 == crop
        and kept.awaiting.crop_box == [5, 5, 65, 125]
    )
    assert kept.awaiting.box == [2, 0, 62, 120]  # everything else is the new report's
    other = AwaitingCandidate(candidate_id="c2", box=[0, 0, 60, 120])
    fresh = store.set_status(
        "drone-1", VehicleStatusIn(mission_id="m1", state="AWAITING_SUPERVISOR", awaiting=other)
    )
    assert fresh.awaiting is not None and fresh.awaiting.crop_jpeg_b64 is None


def test_a_mission_opened_moments_ago_is_not_written_again() -> None:
    """Every keyframe and status report opens its mission; within touch_interval_s only the first writes
    (a commit with an fsync), a new mission always reaches the store (and its quota)."""
    now = [1000.0]
    store = SessionStore(mission_ttl_s=6 * 3600, max_missions=2, clock=lambda: now[0])
    writes: list[str] = []
    touch = store.state.touch_mission
    store.state.touch_mission = lambda v, m, *a: (writes.append(m), touch(v, m, *a))[1]  # type: ignore[method-assign]
    for _ in range(5):
        store.open_mission("v1", "m1")
        now[0] += 1
    assert writes == ["m1"] and store.touch_interval_s == 60
    now[0] += 60
    store.open_mission("v1", "m1")
    store.open_mission("v1", "m2")
    assert writes == ["m1", "m1", "m2"]
    with pytest.raises(QuotaExceededError):
        store.open_mission("v1", "m3")  # never cached: the quota still holds
