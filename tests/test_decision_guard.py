"""A GCS decision naming no candidate (candidate 0, QGroundControl's buttons) pressed for the candidate before
is refused when another came to await a moment before it arrived (`behaviors.decision_guard`); decisions
naming a candidate (the supervisor page) and a candidate seen again are never refused. The mission tests
drive the real state machine with the default guard ([safety] gcs_decision_guard_s)."""

from __future__ import annotations

import pytest

from behaviors.actions import GcsMessage, ReportCandidate
from behaviors.decision_guard import DecisionGuard, observe, too_new
from behaviors.events import BackendAnswer, TimerTick
from behaviors.mission import MissionState, State, step, undirected_candidate
from behaviors.mission_commands import ConfirmCandidate, RejectCandidate
from behaviors.mission_config import MissionConfig
from cloudtrack.vehicle_config import SafetyConfig
from tests.test_mission import AT_STANDOFF, FAR, candidate, cmd, kinds, tracked
from tests.test_mission import reach as spot_reach
from tests.test_mission_survey import ELSEWHERE, run
from tests.test_mission_survey import reach as survey_reach

S = MissionState
GUARDED = MissionConfig()
GUARD_S = GUARDED.gcs_decision_guard_s


@pytest.mark.parametrize(
    ("guard", "candidate_id", "now_s", "expected"),
    [
        (DecisionGuard(), "", 5.0, DecisionGuard()),
        (DecisionGuard(), "c1", 5.0, DecisionGuard("c1", 5.0)),
        (DecisionGuard("c1", 2.0), "c1", 5.0, DecisionGuard("c1", 2.0)),  # the same one: its time stays
        (DecisionGuard("c1", 2.0), "c2", 5.0, DecisionGuard("c2", 5.0)),
        (DecisionGuard("c1", 2.0), "", 5.0, DecisionGuard("", 5.0)),
    ],
)
def test_observe(guard: DecisionGuard, candidate_id: str, now_s: float, expected: DecisionGuard) -> None:
    assert observe(guard, candidate_id, now_s) == expected


@pytest.mark.parametrize(
    ("guard", "now_s", "guard_s", "expected"),
    [
        (DecisionGuard("c2", 5.0), 5.0, 0.75, True),
        (DecisionGuard("c2", 5.0), 5.74, 0.75, True),
        (DecisionGuard("c2", 5.0), 5.75, 0.75, False),
        (DecisionGuard("c2", 5.0), 9.0, 0.75, False),
        (DecisionGuard("", 5.0), 5.1, 0.75, False),  # nothing to decide: the mission says so
        (DecisionGuard("c2", 5.0), 5.0, 0.0, False),  # guard off
    ],
)
def test_too_new(guard: DecisionGuard, now_s: float, guard_s: float, expected: bool) -> None:
    assert too_new(guard, now_s, guard_s) is expected


def _next_candidate_awaiting(state: State, t: float, cid: str = "c2") -> State:
    """The back-end's next candidate (answer at t - 0.3), tracked, and at the standoff at `t`: awaiting. It is
    another person, not where the rejected one was proposed (a rejection holds there too)."""
    assert state.queries, "the search asks the back-end"
    answer = BackendAnswer(t - 0.3, state.queries[-1][0], 90, (candidate(ELSEWHERE, cid),))
    state, _ = run(state, [answer, tracked(t - 0.2, ELSEWHERE), tracked(t, AT_STANDOFF)], GUARDED)
    assert state.mode is S.AWAITING_SUPERVISOR and state.target is not None
    assert state.target.candidate_id == cid
    return state


def _rejected_on_the_page_then_next(t: float) -> State:
    """c1 awaits; the page rejects it (naming it); the search finds c2, awaiting from `t`."""
    state = spot_reach(S.AWAITING_SUPERVISOR, GUARDED)
    state, _ = run(state, [cmd(1.3, RejectCandidate("c1")), TimerTick(1.4), TimerTick(t - 0.5)], GUARDED)
    assert state.mode is S.SEARCHING
    return _next_candidate_awaiting(state, t)


@pytest.mark.parametrize("decision", [ConfirmCandidate(by="gcs"), RejectCandidate()])
def test_a_press_arriving_just_after_the_next_candidate_came_is_refused(
    decision: ConfirmCandidate | RejectCandidate,
) -> None:
    """The page rejected c1 while the GCS operator pressed for c1; the press arrives after c2 came: it must
    not decide c2. After the guard time the same press decides c2. (On the spot c2 is candidate 0 from its
    acquisition, the back-end's answer at 4.7, as the companion flies to it.)"""
    state = _rejected_on_the_page_then_next(5.0)
    assert state.undirected == DecisionGuard("c2", 4.7)
    verb = "CONFIRM" if isinstance(decision, ConfirmCandidate) else "REJECT"
    refused, actions = step(state, cmd(4.7 + GUARD_S - 0.05, decision), GUARDED)
    assert refused.mode is S.AWAITING_SUPERVISOR and refused.target == state.target
    assert refused.rejections == state.rejections and refused.found == state.found
    assert actions == (GcsMessage(f"{verb} REFUSED: c2 is new, press again", "warning"),)
    decided, actions = step(refused, cmd(4.7 + GUARD_S + 0.05, decision), GUARDED)
    if isinstance(decision, ConfirmCandidate):
        assert decided.mode is S.CONFIRMED and decided.target is not None
        assert decided.target.candidate_id == "c2" and decided.target.confirmed_by == "gcs"
    else:
        assert decided.mode is S.REJECTED and decided.rejections.entries[-1].candidate_id == "c2"


def test_a_decision_naming_its_candidate_is_never_held_back() -> None:
    state = _rejected_on_the_page_then_next(5.0)
    state, actions = step(state, cmd(5.05, ConfirmCandidate("c2", by="supervisor page")), GUARDED)
    assert state.mode is S.CONFIRMED and "ReportCandidate" in kinds(actions)


def test_the_same_candidate_seen_again_is_decided_at_once() -> None:
    """A short loss and the track back on the same candidate: the operator was shown it; no refusal."""
    state = spot_reach(S.AWAITING_SUPERVISOR, GUARDED)
    state, _ = run(state, [tracked(2.0, None, ok=False, reason="score"), tracked(2.1, AT_STANDOFF)], GUARDED)
    assert state.mode is S.AWAITING_SUPERVISOR
    state, actions = step(state, cmd(2.15, ConfirmCandidate(by="gcs")), GUARDED)
    assert state.mode is S.CONFIRMED and "ReportCandidate" in kinds(actions)


def test_the_first_candidate_of_a_mission_is_guarded_too() -> None:
    """A press meant for an earlier mission's candidate (or for nothing) is no decision on one just shown."""
    state = spot_reach(S.FOLLOWING, GUARDED)  # c1 tracked from t = 1.0
    _, actions = step(state, cmd(1.2, ConfirmCandidate(by="gcs")), GUARDED)
    assert actions == (GcsMessage("CONFIRM REFUSED: c1 is new, press again", "warning"),)


def test_looking_only_a_press_for_the_candidate_left_behind_is_not_applied_to_the_next() -> None:
    """Looking only, the survey flew past c1 (still awaiting a decision) and the next candidate c2 is
    tracked: candidate 0 means c1, the one awaiting, until c2 is put to the supervisor; a press arriving
    just after that is refused, and the one after the guard time decides c2, with c1 still awaiting."""
    state = survey_reach(S.AWAITING_SUPERVISOR, engage=False, config=GUARDED)
    state, _ = run(
        state, [tracked(1.3, None, ok=False), TimerTick(1.3 + GUARDED.lost_looking_s + 0.1)], GUARDED
    )
    assert state.mode is S.SEARCHING and [p.candidate_id for p in state.pending] == ["c1"]
    before = _next_candidate_awaiting(state, 5.0)
    assert before.undirected == DecisionGuard("c2", 4.8)  # looking only: put to the supervisor once tracked
    # While c2 is only being acquired, candidate 0 is still c1.
    acquiring, _ = run(
        state, [BackendAnswer(4.7, state.queries[-1][0], 90, (candidate(FAR, "c2"),))], GUARDED
    )
    pending = undirected_candidate(acquiring)
    assert acquiring.mode is S.ACQUIRING and pending is not None and pending.candidate_id == "c1"
    _, actions = step(acquiring, cmd(4.8, ConfirmCandidate(by="gcs")), GUARDED)
    report = [a for a in actions if isinstance(a, ReportCandidate)]
    assert report and report[0].candidate_id == "c1" and report[0].status == "confirmed"
    # c2 put to the supervisor at 4.8: the press for c1 arriving at 5.2 decides nothing.
    refused, actions = step(before, cmd(5.2, ConfirmCandidate(by="gcs")), GUARDED)
    assert kinds(actions) == ["GcsMessage"] and "c2 is new" in actions[0].text  # type: ignore[attr-defined]
    assert refused.pending == before.pending and refused.mode is S.AWAITING_SUPERVISOR
    decided, _ = step(refused, cmd(4.8 + GUARD_S, ConfirmCandidate(by="gcs")), GUARDED)
    assert decided.target is not None and decided.target.confirmed_by == "gcs"
    assert [p.candidate_id for p in decided.pending] == ["c1"]


def test_the_guard_is_a_safety_setting_with_the_schema_default() -> None:
    config = MissionConfig.from_sections(
        behavior={}, control={}, camera={}, backend={}, safety={"gcs_decision_guard_s": 2.0}
    )
    assert config.gcs_decision_guard_s == 2.0
    assert SafetyConfig().gcs_decision_guard_s == GUARD_S == 0.75
    with pytest.raises(ValueError, match="gcs_decision_guard_s"):
        SafetyConfig(gcs_decision_guard_s=11.0)
