"""A search that moves on the back-end's fast stage: the early answer starts a provisional track, and the
final verdicts on the same keyframe confirm it, move it to the candidate they prefer, or end it."""

from __future__ import annotations

from dataclasses import replace

import pytest

from behaviors.actions import BackendQuery, GcsMessage, QueryPurpose, SendSetpoint, TrackerInit, TrackerStop
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, TimerTick
from behaviors.geometry import Box
from behaviors.mission import MissionState, State, initial_state, step
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.setpoint import Setpoint
from tests.test_mission import AT_STANDOFF, CFG, FAR, PROMPT, box_at, candidate, cmd, run, telemetry, tracked

S = MissionState
OTHER = box_at(25.0, u=150)


def searching(config: MissionConfig = CFG) -> tuple[State, BackendQuery]:
    state, _ = run(initial_state(config), [telemetry(0.0)], config)
    state, actions = step(state, cmd(0.1, StartMission(PROMPT)), config)
    query = [a for a in actions if isinstance(a, BackendQuery)][-1]
    return state, query


def early(query: BackendQuery, *found: Detection) -> BackendAnswer:
    return BackendAnswer(0.4, query.query_id, 30, found, final=False)


def final(query: BackendQuery, *found: Detection, t: float = 2.1) -> BackendAnswer:
    return BackendAnswer(t, query.query_id, 30, found)


def started_early() -> tuple[State, BackendQuery]:
    state, query = searching()
    state, actions = step(state, early(query, candidate(FAR, "fast1")), CFG)
    assert state.mode is S.ACQUIRING and state.target is not None and state.target.early is not None
    inits = [a for a in actions if isinstance(a, TrackerInit)]
    assert [(i.box, i.keyframe_id) for i in inits] == [(FAR, 30)]
    return state, query


def test_a_search_asks_for_the_early_answer_only_when_configured() -> None:
    assert searching()[1].early_answer and searching()[1].purpose is QueryPurpose.SEARCH
    assert not searching(replace(CFG, early_answer=False))[1].early_answer


def test_the_same_final_choice_keeps_the_track_with_the_final_verdict() -> None:
    state, query = started_early()
    state, _ = step(state, tracked(0.5, FAR), CFG)
    assert state.mode is S.FOLLOWING
    slightly_moved = replace(candidate(FAR, "vlm1"), box=Box(FAR.x + 1.0, FAR.y, FAR.w, FAR.h))
    state, actions = step(state, final(query, slightly_moved), CFG)
    assert state.mode is S.FOLLOWING and state.target is not None
    assert state.target.early is None and state.target.candidate_id == "vlm1"
    assert not any(isinstance(a, (TrackerInit, TrackerStop)) for a in actions)
    assert any(isinstance(a, GcsMessage) and "verified" in a.text for a in actions)
    # The query is closed: a repeat of the answer changes nothing.
    assert step(state, final(query, candidate(OTHER, "x")), CFG)[1] == ()


def test_another_candidate_the_final_verdicts_also_accept_is_no_reason_to_switch() -> None:
    """A lenient VLM ("if in doubt, rather say yes") may accept a bystander too, and rank them first."""
    state, query = started_early()
    state, _ = step(state, tracked(0.5, FAR), CFG)
    both = final(query, candidate(OTHER, "bystander", score=0.99), candidate(FAR, "vlm1", score=0.5))
    state, actions = step(state, both, CFG)
    assert state.mode is S.FOLLOWING and state.target is not None
    assert state.target.candidate_id == "vlm1" and state.target.early is None
    assert not any(isinstance(a, TrackerInit) for a in actions)
    assert state.target.alike == 1  # the bystander fits what was judged as well: the supervisor is told


def test_another_final_choice_restarts_the_track_on_it_from_the_keyframe() -> None:
    state, query = started_early()
    state, _ = step(state, tracked(0.5, FAR), CFG)
    state, actions = step(state, final(query, candidate(FAR, "a", Verdict.NO), candidate(OTHER, "b")), CFG)
    assert state.mode is S.ACQUIRING and state.target is not None
    assert state.target.candidate_id == "b" and state.target.early is None and state.target.alike == 0
    assert [(a.box, a.keyframe_id) for a in actions if isinstance(a, TrackerInit)] == [(OTHER, 30)]
    assert isinstance(actions[0], SendSetpoint) and actions[0].setpoint == Setpoint.zero()


def test_no_verified_candidate_ends_the_track_and_later_searches_wait_for_final_verdicts() -> None:
    state, query = started_early()
    state, _ = step(state, tracked(0.5, FAR), CFG)
    state, actions = step(state, final(query, candidate(FAR, "a", Verdict.NO)), CFG)
    assert state.mode is S.SEARCHING and state.target is None
    assert any(isinstance(a, TrackerStop) for a in actions)
    again = [a for a in actions if isinstance(a, BackendQuery)]
    assert again and not again[-1].early_answer  # the fast stage would pick the same person again
    # A verified track lets searches move early again (after the next track is confirmed).
    state, actions = step(state, final(again[-1], candidate(OTHER, "b")), CFG)
    assert state.mode is S.ACQUIRING and state.target is not None and state.target.early is None


def test_a_provisional_track_is_never_put_to_the_supervisor() -> None:
    state, query = started_early()
    for i in range(5):
        state, _ = step(state, tracked(0.5 + 0.1 * i, AT_STANDOFF), CFG)
    assert state.mode is S.FOLLOWING  # at the standoff, but the final verdicts are not in yet
    state, _ = step(state, final(query, candidate(AT_STANDOFF, "v")), CFG)
    state, _ = step(state, tracked(2.2, AT_STANDOFF), CFG)
    assert state.mode is S.AWAITING_SUPERVISOR


@pytest.mark.parametrize("verdict", [Verdict.YES, Verdict.NO])
def test_early_answers_only_start_a_search(verdict: Verdict) -> None:
    """Two searches out: the first one's early answer starts the track; the second one's early answer,
    whatever it says, moves nothing (only final verdicts are evidence about a track)."""
    state, first = searching()
    state, actions = step(state, TimerTick(0.6), CFG)
    second = [a for a in actions if isinstance(a, BackendQuery)][-1]
    assert second.query_id != first.query_id and second.early_answer
    state, _ = step(state, early(first, candidate(FAR, "fast1")), CFG)
    state, _ = step(state, tracked(0.7, FAR), CFG)
    late = BackendAnswer(0.8, second.query_id, 45, (candidate(OTHER, "o", verdict),), final=False)
    new, actions = step(state, late, CFG)
    assert actions == () and new.target == state.target and new.mode is S.FOLLOWING
    assert second.query_id in dict(new.queries)  # its final answer is still to come


def test_a_provisional_track_whose_final_verdicts_never_come_ends() -> None:
    """The full request failed (the VLM is down, a timeout): a failed verification is not a verified
    target. After [backend] timeout_s twice the track ends and searches wait for final answers."""
    config = MissionConfig.from_sections(
        behavior={}, control={}, safety={}, camera={}, backend={"timeout_s": 4.0}
    )
    assert config.final_answer_timeout_s == 8.0
    state, query = searching(config)
    state, _ = step(state, early(query, candidate(FAR, "fast1")), config)
    for i in range(40):
        state, actions = step(state, tracked(0.5 + 0.25 * i, FAR), config)
        state, actions = step(state, TimerTick(0.5 + 0.25 * i), config)
        if state.mode is S.SEARCHING:
            break
    assert state.mode is S.SEARCHING and 0.4 + 8.0 < state.now_s <= 0.4 + 8.25
    assert any(isinstance(a, TrackerStop) for a in actions)
    assert not [a for a in actions if isinstance(a, BackendQuery)][-1].early_answer
