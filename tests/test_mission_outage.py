"""Answers to keyframes the companion kept through a back-end outage (`BackendAnswer.stored`), table-driven
through real `step` calls: never a track's start (the person is long out of view); a verified candidate
not rejected, found, already awaiting or tracked is placed from the keyframe's own pose and awaits the
supervisor out of view, reported with when it was seen; the supervisor decides on it as on any other.
Select: -k outage."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from behaviors.actions import ReportCandidate, TrackerInit
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, BackendUnreachable, TimerTick
from behaviors.geolocation import locate_box
from behaviors.mission import MissionState, State, awaiting_after, awaiting_decision, initial_state, step
from behaviors.mission_commands import AbortMission, ConfirmCandidate, RejectCandidate, StartMission
from behaviors.telemetry import Telemetry
from tests.test_mission import AT_STANDOFF, CAM, CFG, FAR, PROMPT, box_at, candidate, cmd
from tests.test_mission_survey import _seen_and_left, auto, reach, run

S = MissionState
SEEN_S = 3.0  # the stored keyframe's capture: the survey was 200 m back along its lane then
NOW_S = 40.0  # its answer, once the back-end is back
ELSEWHERE = box_at(18.0, u=CAM.cx - 150.0)  # nobody any test put to the supervisor stands there


def stored(
    state: State, *dets: Detection, pose: Telemetry | None = None, query_id: int = 1, t: float = NOW_S
) -> BackendAnswer:
    """The answer to a keyframe captured at SEEN_S, sent from the store once the link returned."""
    at = pose if pose is not None else auto(SEEN_S, north_m=0.0)
    return BackendAnswer(t, query_id, 90, dets, pose=at, stored=True)


def _down_and_back(state: State) -> State:
    """The back-end went away during the search (its queries forgotten) and answers again."""
    state, _ = run(state, [auto(NOW_S - 1.0, north_m=200.0), BackendUnreachable(NOW_S - 0.9, "no answer")])
    assert state.backend_down and state.queries == ()
    return state


def _searching() -> State:
    return _down_and_back(reach(S.SEARCHING, engage=False))


def _awaiting_in_view() -> State:
    return _down_and_back(reach(S.AWAITING_SUPERVISOR, engage=False))


def _after_rejecting_c1() -> State:
    state = reach(S.REJECTED, engage=False)  # c1 tracked to the standoff from north 0, rejected there
    state, _ = run(state, [TimerTick(1.4)])
    return _down_and_back(state)


def _c1_awaiting_out_of_view() -> State:
    state, _ = _seen_and_left(reach(S.SEARCHING, engage=False), 1.0, "c1")  # at FAR from north 10 m
    return _down_and_back(state)


def _idle() -> State:
    state, _ = run(initial_state(CFG), [auto(0.0)])
    return state


def _aborted() -> State:
    state, _ = run(_searching(), [cmd(NOW_S - 0.5, AbortMission())])
    return state


CASES: list[tuple[str, Callable[[], State], tuple[Detection, ...], Telemetry | None, str | None]] = [
    ("searching: a verified person awaits the supervisor", _searching, (candidate(FAR, "k1"),), None, "awaiting"),
    ("searching: an 'uncertain' is no candidate", _searching, (candidate(FAR, "k1", Verdict.UNCERTAIN),), None, None),
    ("searching: a 'no' is no candidate", _searching, (candidate(FAR, "k1", Verdict.NO),), None, None),
    ("the best of several: the 'yes'", _searching,
     (candidate(ELSEWHERE, "k0", Verdict.UNCERTAIN, score=0.99), candidate(FAR, "k1")), None, "awaiting"),
    ("one in view awaits: after it", _awaiting_in_view, (candidate(ELSEWHERE, "k1"),), None, "queued"),
    ("the one tracked, where it stands", _awaiting_in_view, (candidate(AT_STANDOFF, "k1"),), None, None),
    ("rejected there", _after_rejecting_c1, (candidate(AT_STANDOFF, "k1"),), None, None),
    ("rejected there, someone elsewhere", _after_rejecting_c1, (candidate(ELSEWHERE, "k1"),), None, "awaiting"),
    ("awaiting already, seen there again", _c1_awaiting_out_of_view, (candidate(FAR, "k1"),),
     auto(SEEN_S, north_m=10.0), None),
    ("one awaits out of view, someone elsewhere: shown first", _c1_awaiting_out_of_view,
     (candidate(ELSEWHERE, "k1"),), None, "awaiting"),
    ("no mission running", _idle, (candidate(FAR, "k1"),), None, None),
    ("the mission aborted", _aborted, (candidate(FAR, "k1"),), None, None),
]  # fmt: skip


@pytest.mark.parametrize(
    ("make", "dets", "pose", "status"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_outage_stored_answers(
    make: Callable[[], State], dets: tuple[Detection, ...], pose: Telemetry | None, status: str | None
) -> None:
    before = make()
    state, actions = step(before, stored(before, *dets, pose=pose), CFG)
    assert not [a for a in actions if isinstance(a, TrackerInit)]  # never a track's start
    assert state.mode is before.mode and state.target == before.target
    reports = [a for a in actions if isinstance(a, ReportCandidate)]
    if status is None:
        assert reports == [] and state.pending == before.pending
        return
    (report,) = reports
    at = pose if pose is not None else auto(SEEN_S, north_m=0.0)
    chosen = next(d for d in dets if d.verdict is Verdict.YES)
    assert (report.candidate_id, report.status, report.keyframe_id) == (chosen.candidate_id, status, 90)
    # Placed from where the camera was when the keyframe was captured, not from the vehicle now (200 m on).
    assert report.position == locate_box(CAM, at, chosen.box) and report.position_s == SEEN_S
    assert (
        report.stored and state.pending[-1].stored and state.pending[-1].candidate_id == chosen.candidate_id
    )
    assert not state.backend_down  # it answered


def test_outage_a_stored_answer_to_a_query_still_open_starts_no_track() -> None:
    """A short outage: the stored keyframe's query is still among those in flight; its answer is still a
    look into the past, never a track's start."""
    state = reach(S.SEARCHING, engage=False)
    open_query = state.queries[-1][0]
    state, actions = step(state, stored(state, candidate(FAR, "k1"), query_id=open_query), CFG)
    assert state.mode is S.SEARCHING and not [a for a in actions if isinstance(a, TrackerInit)]
    assert [(a.candidate_id, a.status) for a in actions if isinstance(a, ReportCandidate)] == [
        ("k1", "awaiting")
    ]


def test_outage_a_stored_answer_without_its_pose_places_no_one() -> None:
    state = _searching()
    answer = BackendAnswer(NOW_S, 1, 90, (candidate(FAR, "k1"),), stored=True)
    assert step(state, answer, CFG)[1] == ()


def test_outage_the_supervisor_decides_on_a_stored_candidate_as_on_any_other() -> None:
    """Confirmed, a candidate from a stored keyframe is a find where that keyframe placed it, as old as the
    keyframe; one queued behind another is put to the supervisor when that one is decided, again said to
    come from the store."""
    state = _c1_awaiting_out_of_view()
    state, actions = step(state, stored(state, candidate(ELSEWHERE, "k1")), CFG)
    (shown,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert [p.candidate_id for p in state.pending] == ["c1", "k1"] and awaiting_decision(
        state
    ) is state.pending[-1]
    # Another stored keyframe, a third person: queued behind k1.
    other = candidate(box_at(30.0, u=CAM.cx + 200.0), "k2")
    state, actions = step(state, stored(state, other, pose=auto(SEEN_S + 1.0, north_m=60.0)), CFG)
    assert [(a.candidate_id, a.status) for a in actions if isinstance(a, ReportCandidate)] == [
        ("k2", "awaiting")
    ]
    state, actions = step(state, cmd(NOW_S + 1.0, RejectCandidate("k2")), CFG)
    again = [a for a in actions if isinstance(a, ReportCandidate)]
    assert [(a.candidate_id, a.status, a.stored) for a in again] == [("k1", "awaiting", True)]
    state, actions = step(state, cmd(NOW_S + 2.0, ConfirmCandidate(by="supervisor page")), CFG)
    (find,) = [a for a in actions if isinstance(a, ReportCandidate) and a.status == "confirmed"]
    assert find.candidate_id == "k1" and find.position == shown.position and find.position_s == SEEN_S
    assert state.found.entries[-1].candidate_id == "k1"
    assert [p.candidate_id for p in state.pending] == ["c1"] and awaiting_after(state) == ()
    # Seen again live where it was found: not proposed a second time.
    state, actions = step(state, stored(state, candidate(ELSEWHERE, "k7")), CFG)
    assert actions == ()


def test_outage_stored_answers_on_the_spot_search_start_no_track_either() -> None:
    state, _ = run(initial_state(CFG), [Telemetry(0.0, 47.0, 8.0, 20.0, mode="GUIDED", offboard_active=True)])
    state, _ = run(state, [cmd(0.1, StartMission(PROMPT, allow_engage=True))])
    assert state.mode is S.SEARCHING and not state.along_mission
    pose = Telemetry(SEEN_S, 47.0, 8.0, 20.0, mode="GUIDED", offboard_active=True)
    state, actions = step(state, stored(state, candidate(FAR, "k1"), pose=pose), CFG)
    assert state.mode is S.SEARCHING and state.target is None
    assert [(a.candidate_id, a.status) for a in actions if isinstance(a, ReportCandidate)] == [
        ("k1", "awaiting")
    ]
