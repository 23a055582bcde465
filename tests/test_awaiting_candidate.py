"""A candidate never vanishes while the vehicle awaits the supervisor's decision: the behaviour says which
candidate waits whatever happens to the track (`awaiting_decision`), a re-acquisition reports it again, and
every status report of the main loop carries it (with its crop, encoded once). Select: -k awaiting.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import requests
from pydantic import ValidationError

from behaviors.actions import BackendQuery, QueryPurpose, ReportCandidate
from behaviors.detection import Verdict
from behaviors.geolocation import GeoEstimate
from behaviors.geometry import Box
from behaviors.mission import MissionState, Target, awaiting_decision, initial_state, step
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.track_result import TrackResult
from cloudtrack.api_models import AwaitingCandidate
from companion.cloud.candidate_crop import candidate_crop
from companion.mission_runner import MissionRunner
from companion.vision.frame_sources import Frame

CONFIG = MissionConfig()
TARGET = Target("c-17", "gray shirt", Verdict.YES, Box(300, 200, 30, 70), 5, 1.0)
MISSION = StartMission("an injured man in a gray shirt", mission_id="m1")


def _state(
    mode: MissionState, resume: MissionState = MissionState.FOLLOWING, target: Target | None = TARGET
) -> Any:
    return replace(initial_state(CONFIG), mode=mode, resume=resume, target=target, mission=MISSION, now_s=2.0)


@pytest.mark.parametrize(
    ("mode", "resume", "waiting"),
    [
        (MissionState.AWAITING_SUPERVISOR, MissionState.FOLLOWING, True),
        (MissionState.LOST, MissionState.AWAITING_SUPERVISOR, True),  # a short loss while it waits
        (MissionState.LOST, MissionState.FOLLOWING, False),
        (MissionState.LOST, MissionState.CONFIRMED, False),  # decided
        (MissionState.FOLLOWING, MissionState.FOLLOWING, False),
        (MissionState.CONFIRMED, MissionState.FOLLOWING, False),
        (MissionState.SEARCHING, MissionState.AWAITING_SUPERVISOR, False),
        (MissionState.ABORTED, MissionState.AWAITING_SUPERVISOR, False),
    ],
)
def test_awaiting_decision_by_state(mode: MissionState, resume: MissionState, waiting: bool) -> None:
    assert (awaiting_decision(_state(mode, resume)) is TARGET) is waiting


def test_awaiting_decision_reacquisition_reports_the_candidate_again() -> None:
    lost = _state(MissionState.LOST, MissionState.AWAITING_SUPERVISOR)
    found = TrackResult(9, 3.0, Box(302, 201, 30, 70), 0.9, True)
    state, actions = step(lost, found, CONFIG)
    assert state.mode is MissionState.AWAITING_SUPERVISOR
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert (report.candidate_id, report.status) == ("c-17", "awaiting")


def test_awaiting_every_status_carries_the_candidate_through_a_loss() -> None:
    none: Any = None
    runner = MissionRunner(CONFIG, none, none, none, none)
    image = np.random.default_rng(3).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    runner._latest = Frame(7, time.monotonic(), image)
    runner.state = _state(MissionState.AWAITING_SUPERVISOR)
    waiting = runner._status()["awaiting"]
    assert waiting["candidate_id"] == "c-17" and waiting["crop_jpeg_b64"] and waiting["verdict"] == "yes"
    runner._latest = Frame(8, time.monotonic(), np.zeros_like(image))  # the camera saw nothing useful
    runner.state = _state(MissionState.LOST, MissionState.AWAITING_SUPERVISOR)
    lost = runner._status()
    assert lost["state"] == "LOST" and lost["awaiting"]["candidate_id"] == "c-17"
    assert lost["awaiting"]["crop_jpeg_b64"] is waiting["crop_jpeg_b64"]  # encoded once, kept
    runner.state = _state(MissionState.CONFIRMED)
    assert "awaiting" not in runner._status()
    runner.state = _state(MissionState.SEARCHING, target=None)
    assert "awaiting" not in runner._status()


def test_awaiting_a_candidate_seen_beside_the_tracked_one_is_cropped_from_its_keyframe() -> None:
    """Looking only, the search proposes a person seen beside the tracked one (`behaviors.mission`,
    `_propose_other`): the GCS hears it, and its crop is cut from the keyframe the back-end found it in (the
    newest frame has moved on), kept until it is the one shown."""
    none: Any = None
    sent: list[int] = []
    said: list[str] = []

    class Backend:
        def submit(self, frame_id: int, *args: Any, **fields: Any) -> None:
            sent.append(frame_id)

    class Vehicle:
        def send_status(self, text: str, severity: int) -> None:
            said.append(text)

    backend: Any = Backend()
    vehicle: Any = Vehicle()
    runner = MissionRunner(CONFIG, none, none, vehicle, backend)
    keyframe = np.random.default_rng(5).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    runner._latest = Frame(7, time.monotonic(), keyframe)
    runner.state = _state(MissionState.AWAITING_SUPERVISOR)
    runner._submit(BackendQuery(3, QueryPurpose.SEARCH, MISSION.prompt, "", None))
    runner._latest = Frame(12, time.monotonic(), np.zeros_like(keyframe))  # the survey flew on
    beside = Box(420, 180, 30, 70)
    runner._report_candidate(
        ReportCandidate("c-21", "green shirt", Verdict.YES, None, beside, "queued", keyframe_id=7)
    )
    assert sent == [7] and said == ["CANDIDATE QUEUED c-21"]
    other = replace(TARGET, candidate_id="c-21", box=beside)
    runner.state = replace(runner.state, pending=(other,))
    assert runner._status()["awaiting_more"] == ["c-21"]
    runner.state = replace(_state(MissionState.SEARCHING, target=None), pending=(other,))  # c-17 decided
    shown = runner._status()["awaiting"]
    expected = candidate_crop(keyframe, beside)
    assert expected is not None and shown["candidate_id"] == "c-21"
    assert shown["crop_jpeg_b64"] == expected["crop_jpeg_b64"]


def test_a_rejection_the_back_end_took_reaches_the_rejection_memory() -> None:
    """The session's word that the back-end holds a rejection becomes a `RejectionShared` event: the memory
    entry then matches by place only within the estimates' own uncertainty (`behaviors.rejection_memory`)."""
    from behaviors.mission_commands import RejectCandidate
    from behaviors.rejection_memory import RejectedTarget

    none: Any = None

    class Vehicle:
        def commands(self) -> list[Any]:
            return []

    class Session:
        def commands(self) -> list[Any]:
            return [RejectCandidate("c-5")]

        def shared_rejections(self) -> list[str]:
            return ["c-17"]

        def fleet_order(self) -> None:
            return None

    vehicle: Any = Vehicle()
    session: Any = Session()
    runner = MissionRunner(CONFIG, none, none, vehicle, none, session=session)
    state = _state(MissionState.SEARCHING, target=None)
    runner.state = replace(
        state, rejections=state.rejections.remember(RejectedTarget("c-17")), next_query_id=9
    )
    events = runner._ground_events(3.0)
    assert [type(e).__name__ for e in events] == ["GcsCommand", "RejectionShared"]
    runner._handle(events[1])
    assert runner.state.rejections.entries[0].shared_from_query == 9


def test_awaiting_candidate_says_how_old_its_position_is() -> None:
    """The page's Confirm makes the find from the awaiting candidate before the vehicle's own arrives: it
    carries when its position was seen (tracked: the latest; out of view: the kept fix)."""
    none: Any = None
    runner = MissionRunner(CONFIG, none, none, none, none, wall_clock=lambda: 1_000.0)
    runner._latest = Frame(7, time.monotonic(), np.zeros((480, 640, 3), dtype=np.uint8))
    seen = GeoEstimate(47.0, 8.0, 10.0, 0.0, 10.0, 14.0, 1.0)
    target = replace(TARGET, position=seen, position_s=0.5)
    runner.state = _state(MissionState.AWAITING_SUPERVISOR, target=target)  # now_s 2.0
    awaiting = runner._status()["awaiting"]
    assert awaiting["position"] == [47.0, 8.0] and awaiting["seen_at"] == 998.5
    assert AwaitingCandidate.model_validate(awaiting).seen_at == 998.5
    runner.state = _state(MissionState.AWAITING_SUPERVISOR, target=replace(TARGET, position=seen))
    assert "seen_at" not in runner._status()["awaiting"]  # observed when is not known: not said


@pytest.mark.parametrize("seen_at", [-1.0, 2.0**35, float("nan"), float("inf")])
def test_awaiting_candidate_refuses_a_seen_at_no_clock_gives(seen_at: float) -> None:
    with pytest.raises(ValidationError, match="seen_at"):
        AwaitingCandidate.model_validate({"candidate_id": "c-1", "box": [1, 2, 3, 4], "seen_at": seen_at})


def test_awaiting_status_says_who_waits_behind_the_one_shown_and_who_was_dropped() -> None:
    """A supervisor slower than the survey: the page shows one candidate, and the status says the others
    waiting behind it (oldest first) and which were dropped undecided; the API takes it, the page's
    snapshot carries it."""
    from cloudtrack.api_models import QUEUE_IDS_MAX, VehicleStatusIn

    none: Any = None
    runner = MissionRunner(CONFIG, none, none, none, none)
    runner._latest = Frame(7, time.monotonic(), np.zeros((480, 640, 3), dtype=np.uint8))
    left = tuple(replace(TARGET, candidate_id=f"c-{k}") for k in (3, 5, 8))
    runner.state = replace(
        _state(MissionState.SEARCHING, target=None), pending=left, dropped_undecided=("c-1",)
    )
    status = runner._status()
    assert status["awaiting"]["candidate_id"] == "c-8"
    assert status["awaiting_more"] == ["c-3", "c-5"] and status["dropped_undecided"] == ["c-1"]
    runner.state = replace(runner.state, mode=MissionState.AWAITING_SUPERVISOR, target=TARGET)  # in view
    status = runner._status()
    assert status["awaiting"]["candidate_id"] == "c-17" and status["awaiting_more"] == ["c-3", "c-5", "c-8"]
    runner.state = _state(MissionState.AWAITING_SUPERVISOR)
    assert {"awaiting_more", "dropped_undecided"}.isdisjoint(runner._status())  # none waits, none dropped
    fields = {k: v for k, v in status.items() if k != "awaiting"}
    checked = VehicleStatusIn.model_validate(fields)
    assert checked.awaiting_more == ["c-3", "c-5", "c-8"] and checked.dropped_undecided == ["c-1"]
    for bad in (["c/1"], ["x" * 65], [f"c-{k}" for k in range(QUEUE_IDS_MAX + 1)]):
        with pytest.raises(ValidationError, match="awaiting_more"):
            VehicleStatusIn.model_validate({**fields, "awaiting_more": bad})
    # Through the real API to the page's snapshot.
    snapshot = _on_the_page({**fields, "awaiting": {"candidate_id": "c-17", "box": [300, 200, 330, 270]}})
    (vehicle,) = snapshot["vehicles"]
    assert [c["id"] for c in vehicle["candidates"]] == ["c-17"]
    assert vehicle["awaiting_more"] == ["c-3", "c-5", "c-8"] and vehicle["dropped_undecided"] == ["c-1"]


def test_what_the_back_end_could_not_judge_reaches_the_gcs_and_the_supervisor_page() -> None:
    """The candidate's unjudged words (a kind of car, a place nothing located) are what the supervisor must
    check by eye, and how many others it was chosen from by score alone says the choice was no judgement:
    the GCS line names both (the words shortened past their bound) and the status carries them, through the
    real API, to the page's snapshot. The API bounds them; a candidate with neither adds nothing."""
    said: list[str] = []

    class Vehicle:
        def send_status(self, text: str, severity: int) -> None:
            said.append(text)

    none: Any = None
    vehicle: Any = Vehicle()
    runner = MissionRunner(CONFIG, none, none, vehicle, none)
    runner._latest = Frame(7, time.monotonic(), np.zeros((480, 640, 3), dtype=np.uint8))
    unsure = ("minivan", "at the far crosswalk (the crosswalk: not located)")
    report = ReportCandidate("c-17", "white", Verdict.YES, None, TARGET.box, "awaiting")
    runner._report_candidate(replace(report, unjudged=unsure, alike=2))
    runner._report_candidate(report)
    runner._report_candidate(replace(report, unjudged=("x" * 40,) * 6))
    assert said[0] == (
        "CANDIDATE AWAITING c-17; 2 others alike; not checked: minivan; at the far crosswalk "
        "(the crosswalk: not located)"
    )
    assert said[1] == "CANDIDATE AWAITING c-17"
    assert len(said[2]) == len("CANDIDATE AWAITING c-17; not checked: ") + 150 and said[2].endswith("...")
    runner.state = _state(MissionState.AWAITING_SUPERVISOR, target=replace(TARGET, unjudged=unsure, alike=2))
    awaiting = runner._status()["awaiting"]
    assert awaiting["unjudged"] == list(unsure) and awaiting["alike"] == 2
    for field, bad in (
        ("unjudged", ["x" * 201]),
        ("unjudged", ["minivan"] * 33),
        ("alike", -1),
        ("alike", 1001),
    ):
        with pytest.raises(ValidationError, match=field):
            AwaitingCandidate.model_validate({**awaiting, field: bad})
    ((candidate,),) = [v["candidates"] for v in _on_the_page(runner._status())["vehicles"]]
    assert candidate["id"] == "c-17" and candidate["unjudged"] == list(unsure) and candidate["alike"] == 2


def _on_the_page(status: dict[str, Any]) -> Any:
    """`status` posted by drone-1 to a real back-end on loopback, and the supervisor page's snapshot after it."""
    from backend.app import create_app
    from backend.config import AuthConfig, BackendConfig, SessionConfig
    from backend.serving import BackgroundServer
    from sitl.simulated_detector import SimulatedPersonDetector

    config = BackendConfig(
        auth=AuthConfig(tokens={"drone-1": "drone-1-token-0001"}, supervisor_token="supervisor-token-0001"),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    with BackgroundServer(create_app(config, detector=SimulatedPersonDetector(lambda fid: None))) as server:
        posted = requests.post(
            f"{server.url}/v1/vehicles/drone-1/status",
            json=status,
            headers={"Authorization": "Bearer drone-1-token-0001"},
            timeout=5,
        )
        assert posted.status_code == 200, posted.text
        return requests.get(
            f"{server.url}/supervisor/api/state",
            headers={"Authorization": "Bearer supervisor-token-0001"},
            timeout=5,
        ).json()
