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
from pydantic import ValidationError

from behaviors.actions import ReportCandidate
from behaviors.detection import Verdict
from behaviors.geolocation import GeoEstimate
from behaviors.geometry import Box
from behaviors.mission import MissionState, Target, awaiting_decision, initial_state, step
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.track_result import TrackResult
from cloudtrack.api_models import AwaitingCandidate
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
