"""The mission state machine, table-driven: every state and transition, abort/takeover from every state,
rejection memory, back-end loss and the offboard rules. Every state is reached by real `step` calls."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import pytest

from behaviors.actions import (
    Action,
    BackendQuery,
    FlightMode,
    GcsMessage,
    Hold,
    JudgeCandidates,
    QueryPurpose,
    ReleaseControl,
    RememberRejection,
    ReportCandidate,
    RequestMode,
    SendSetpoint,
    TrackerInit,
    TrackerStop,
)
from behaviors.detection import Detection, Verdict
from behaviors.events import (
    AutopilotLinkLost,
    BackendAnswer,
    BackendUnreachable,
    CompanionHold,
    Event,
    GcsCommand,
    PilotTakeover,
    RejectionShared,
    TimerTick,
)
from behaviors.geometry import Box
from behaviors.mission import (
    HOLD_SHOWS_WITHIN_S,
    MissionState,
    State,
    awaiting_decision,
    initial_state,
    redetect_roi,
    step,
)
from behaviors.mission_commands import (
    AbortMission,
    ConfirmCandidate,
    RejectCandidate,
    StartMission,
    StopTracking,
    TrackRectangle,
)
from behaviors.mission_config import ConfirmAction, LostAction, MissionConfig
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult

# The tables decide a tenth of a second after a candidate appears, as the page does (which names it); the
# GCS's guard against a press meant for the candidate before is tested with its default in
# tests/test_decision_guard.py.
CFG = MissionConfig(gcs_decision_guard_s=0.0)
CAM = CFG.camera
HEIGHT = 20.0
PROMPT = "an injured man in a gray shirt"
S = MissionState


def box_at(distance_m: float, u: float = CAM.cx, h_px: float = 40.0) -> Box:
    """A box whose foot point lies `distance_m` ahead on flat ground, seen from HEIGHT with the default camera."""
    depression = math.atan2(HEIGHT, distance_m)
    v = CAM.cy + CAM.fy * math.tan(depression + CAM.mount_pitch)
    return Box.from_center(u, v - h_px / 2.0, 16.0, h_px)


FAR = box_at(25.0)
AT_STANDOFF = box_at(CFG.standoff_m)


def telemetry(t: float, offboard: bool = True) -> Telemetry:
    return Telemetry(t, lat_deg=47.0, lon_deg=8.0, height_agl=HEIGHT, offboard_active=offboard, mode="GUIDED")


def candidate(
    box: Box, cid: str = "c1", verdict: Verdict = Verdict.YES, score: float = 0.9, sig: tuple[float, ...] = ()
) -> Detection:
    return Detection(
        box, score, verdict=verdict, justification="gray shirt, lying", candidate_id=cid, signature=sig
    )


def tracked(t: float, box: Box | None, ok: bool = True, reason: str = "") -> TrackResult:
    return TrackResult(int(t * 30), t, box, 0.9 if ok else 0.2, ok, reason)


def cmd(t: float, command: object) -> GcsCommand:
    return GcsCommand(t, command)  # type: ignore[arg-type]


def kinds(actions: Sequence[Action]) -> list[str]:
    return [type(a).__name__ for a in actions]


def run(
    state: State, events: Sequence[Event], config: MissionConfig = CFG
) -> tuple[State, tuple[Action, ...]]:
    actions: tuple[Action, ...] = ()
    for event in events:
        state, actions = step(state, event, config)
    return state, actions


def last_query(actions: Sequence[Action]) -> BackendQuery:
    return [a for a in actions if isinstance(a, BackendQuery)][-1]


def reach(mode: MissionState, config: MissionConfig = CFG, allow_engage: bool = False) -> State:
    """Drive a fresh machine into `mode` through real events (time advances from 0)."""
    state, _ = run(initial_state(config), [telemetry(0.0)], config)
    if mode is S.IDLE:
        return state
    if mode is S.ABORTED:
        state, _ = run(state, [cmd(0.1, StartMission(PROMPT)), cmd(0.2, AbortMission())], config)
        return state
    state, actions = step(state, cmd(0.1, StartMission(PROMPT, allow_engage=allow_engage)), config)
    if mode is S.SEARCHING:
        return state
    qid = last_query(actions).query_id
    state, _ = step(state, BackendAnswer(1.0, qid, 30, (candidate(FAR),)), config)
    if mode is S.ACQUIRING:
        return state
    state, _ = step(state, tracked(1.1, FAR), config)
    if mode is S.FOLLOWING:
        return state
    if mode is S.LOST:
        state, _ = step(state, tracked(1.2, None, ok=False, reason="score"), config)
        return state
    state, _ = step(state, tracked(1.2, AT_STANDOFF), config)
    if mode is S.AWAITING_SUPERVISOR:
        return state
    if mode is S.CONFIRMED:
        state, _ = step(state, cmd(1.3, ConfirmCandidate()), config)
        return state
    state, _ = step(state, cmd(1.3, RejectCandidate()), config)
    assert mode is S.REJECTED
    return state


@pytest.mark.parametrize("mode", list(MissionState))
def test_every_state_is_reachable(mode: MissionState) -> None:
    assert reach(mode).mode is mode


# (name, start, event, expected mode, expected action kinds in order)
TRANSITIONS: list[tuple[str, MissionState, Event, MissionState, list[str]]] = [
    (
        "idle start",
        S.IDLE,
        cmd(1, StartMission(PROMPT)),
        S.SEARCHING,
        ["GcsMessage", "SendSetpoint", "BackendQuery"],
    ),
    ("idle empty prompt", S.IDLE, cmd(1, StartMission("  ")), S.IDLE, ["GcsMessage"]),
    # a GCS track rectangle is followed like a candidate: only the supervisor's confirm allows descent
    (
        "idle operator rectangle",
        S.IDLE,
        cmd(1, TrackRectangle(FAR)),
        S.FOLLOWING,
        ["TrackerInit", "GcsMessage"],
    ),
    ("idle bad rectangle", S.IDLE, cmd(1, TrackRectangle(Box(0, 0, 0, 5))), S.IDLE, ["GcsMessage"]),
    ("idle tick", S.IDLE, TimerTick(5), S.IDLE, []),
    ("idle tracker result", S.IDLE, tracked(1, FAR), S.IDLE, []),
    ("idle confirm", S.IDLE, cmd(1, ConfirmCandidate()), S.IDLE, ["GcsMessage"]),
    ("idle stop", S.IDLE, cmd(1, StopTracking()), S.IDLE, []),
    ("searching tick early", S.SEARCHING, TimerTick(0.5), S.SEARCHING, ["SendSetpoint"]),
    ("searching tick due", S.SEARCHING, TimerTick(1.2), S.SEARCHING, ["SendSetpoint", "BackendQuery"]),
    (
        "searching answer yes",
        S.SEARCHING,
        BackendAnswer(1, 1, 30, (candidate(FAR),)),
        S.ACQUIRING,
        ["SendSetpoint", "TrackerInit", "GcsMessage"],
    ),
    (
        "searching answer no",
        S.SEARCHING,
        BackendAnswer(1, 1, 30, (candidate(FAR, verdict=Verdict.NO),)),
        S.SEARCHING,
        [],
    ),
    (
        "searching answer uncertain",
        S.SEARCHING,
        BackendAnswer(1, 1, 30, (candidate(FAR, verdict=Verdict.UNCERTAIN),)),
        S.SEARCHING,
        [],
    ),
    ("searching answer empty", S.SEARCHING, BackendAnswer(1, 1, 30, ()), S.SEARCHING, []),
    ("searching unknown query", S.SEARCHING, BackendAnswer(1, 99, 30, (candidate(FAR),)), S.SEARCHING, []),
    ("searching stop", S.SEARCHING, cmd(1, StopTracking()), S.IDLE, ["ReleaseControl", "GcsMessage"]),
    (
        "searching reject unknown id",
        S.SEARCHING,
        cmd(1, RejectCandidate("c7")),
        S.SEARCHING,
        ["RememberRejection"],
    ),
    ("searching reject nothing", S.SEARCHING, cmd(1, RejectCandidate()), S.SEARCHING, ["GcsMessage"]),
    ("acquiring locked", S.ACQUIRING, tracked(1.1, FAR), S.FOLLOWING, ["GcsMessage", "SendSetpoint"]),
    ("acquiring not yet", S.ACQUIRING, tracked(1.5, None, ok=False), S.ACQUIRING, []),
    (
        "acquiring timeout",
        S.ACQUIRING,
        TimerTick(4.5),
        S.SEARCHING,
        # the verified candidate awaits the supervisor out of view (below: acquire_timeout)
        ["TrackerStop", "GcsMessage", "SendSetpoint", "BackendQuery", "ReportCandidate"],
    ),
    (
        "acquiring stop",
        S.ACQUIRING,
        cmd(1.1, StopTracking()),
        S.IDLE,
        ["ReleaseControl", "TrackerStop", "GcsMessage"],
    ),
    ("following far", S.FOLLOWING, tracked(1.2, FAR), S.FOLLOWING, ["SendSetpoint"]),
    (
        "following arrived",
        S.FOLLOWING,
        tracked(1.2, AT_STANDOFF),
        S.AWAITING_SUPERVISOR,
        ["SendSetpoint", "ReportCandidate", "GcsMessage"],
    ),
    (
        "following tracker lost",
        S.FOLLOWING,
        tracked(1.2, None, ok=False, reason="score"),
        S.LOST,
        ["SendSetpoint", "GcsMessage", "BackendQuery"],
    ),
    (
        "following stale frames",
        S.FOLLOWING,
        TimerTick(1.7),
        S.LOST,
        ["SendSetpoint", "GcsMessage", "BackendQuery"],
    ),
    ("following fresh tick", S.FOLLOWING, TimerTick(1.3), S.FOLLOWING, []),
    (
        "following confirm",
        S.FOLLOWING,
        cmd(1.2, ConfirmCandidate()),
        S.CONFIRMED,
        ["ReportCandidate", "GcsMessage"],
    ),
    (
        "following reject",
        S.FOLLOWING,
        cmd(1.2, RejectCandidate("c1")),
        S.REJECTED,
        ["SendSetpoint", "TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "awaiting tracking",
        S.AWAITING_SUPERVISOR,
        tracked(1.25, AT_STANDOFF),
        S.AWAITING_SUPERVISOR,
        ["SendSetpoint"],
    ),
    (
        "awaiting confirm",
        S.AWAITING_SUPERVISOR,
        cmd(1.3, ConfirmCandidate("c1")),
        S.CONFIRMED,
        ["ReportCandidate", "GcsMessage"],
    ),
    (
        "awaiting confirm wrong id",
        S.AWAITING_SUPERVISOR,
        cmd(1.3, ConfirmCandidate("c9")),
        S.AWAITING_SUPERVISOR,
        ["GcsMessage"],
    ),
    (
        "awaiting reject",
        S.AWAITING_SUPERVISOR,
        cmd(1.3, RejectCandidate()),
        S.REJECTED,
        ["SendSetpoint", "TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "awaiting tracker lost",
        S.AWAITING_SUPERVISOR,
        tracked(1.3, None, ok=False),
        S.LOST,
        ["SendSetpoint", "GcsMessage", "BackendQuery"],
    ),
    ("confirmed tracking", S.CONFIRMED, tracked(1.35, AT_STANDOFF), S.CONFIRMED, ["SendSetpoint"]),
    ("confirmed again", S.CONFIRMED, cmd(1.35, ConfirmCandidate()), S.CONFIRMED, []),
    (
        "confirmed tracker lost",
        S.CONFIRMED,
        tracked(1.35, None, ok=False),
        S.LOST,
        ["SendSetpoint", "GcsMessage", "BackendQuery"],
    ),
    (
        "confirmed supervisor changes mind",
        S.CONFIRMED,
        cmd(1.35, RejectCandidate()),
        S.REJECTED,
        ["SendSetpoint", "TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "rejected tick",
        S.REJECTED,
        TimerTick(1.4),
        S.SEARCHING,
        ["GcsMessage", "SendSetpoint", "BackendQuery"],
    ),
    ("rejected tracker result", S.REJECTED, tracked(1.4, FAR), S.REJECTED, []),
    ("lost untrusted", S.LOST, tracked(1.3, None, ok=False), S.LOST, []),
    ("lost recovered", S.LOST, tracked(1.3, FAR), S.FOLLOWING, ["GcsMessage", "SendSetpoint"]),
    ("lost hold", S.LOST, TimerTick(2.25), S.LOST, ["Hold", "BackendQuery"]),
    ("lost confirm", S.LOST, cmd(1.3, ConfirmCandidate()), S.LOST, ["ReportCandidate", "GcsMessage"]),
    (
        "lost reject",
        S.LOST,
        cmd(1.3, RejectCandidate()),
        S.REJECTED,
        ["SendSetpoint", "TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "aborted restart",
        S.ABORTED,
        cmd(1, StartMission(PROMPT)),
        S.SEARCHING,
        ["GcsMessage", "SendSetpoint", "BackendQuery"],
    ),
    ("aborted tick", S.ABORTED, TimerTick(9), S.ABORTED, []),
    ("aborted tracker result", S.ABORTED, tracked(1, FAR), S.ABORTED, []),
    ("aborted confirm", S.ABORTED, cmd(1, ConfirmCandidate()), S.ABORTED, ["GcsMessage"]),
    ("aborted stop", S.ABORTED, cmd(1, StopTracking()), S.ABORTED, []),
]


@pytest.mark.parametrize(
    ("name", "start", "event", "expected", "expected_kinds"), TRANSITIONS, ids=[t[0] for t in TRANSITIONS]
)
def test_transition_table(
    name: str, start: MissionState, event: Event, expected: MissionState, expected_kinds: list[str]
) -> None:
    state, actions = step(reach(start), event, CFG)
    assert state.mode is expected, name
    assert kinds(actions) == expected_kinds, name


def test_gcs_track_rectangle_confirms_only_when_configured() -> None:
    box = TrackRectangle(FAR)
    assert step(initial_state(CFG), cmd(1, box), CFG)[0].mode is S.FOLLOWING
    trusting = replace(CFG, operator_box_confirms=True)
    assert step(initial_state(trusting), cmd(1, box), trusting)[0].mode is S.CONFIRMED
    assert MissionConfig.from_sections(
        behavior={}, control={}, camera={}, backend={}, safety={"gcs_track_confirms": True}
    ).operator_box_confirms


def test_table_covers_every_state_as_a_source() -> None:
    assert {t[1] for t in TRANSITIONS} == set(MissionState)


STOPS: list[tuple[str, Callable[[float], Event], type[Action]]] = [
    # every abort lets go (stop, hold mode, silence): a Hold would keep streaming zeros in GUIDED
    ("gcs abort", lambda t: cmd(t, AbortMission("operator")), ReleaseControl),
    ("autopilot link lost", lambda t: AutopilotLinkLost(t), ReleaseControl),
    ("pilot takeover", lambda t: PilotTakeover(t, "LOITER"), ReleaseControl),
    ("offboard lost in telemetry", lambda t: telemetry(t, offboard=False), ReleaseControl),
]


@pytest.mark.parametrize("mode", list(MissionState))
@pytest.mark.parametrize(("cause", "make", "stop"), STOPS, ids=[s[0] for s in STOPS])
def test_abort_and_takeover_from_every_state(
    mode: MissionState, cause: str, make: Callable[[float], Event], stop: type[Action]
) -> None:
    start = reach(mode)
    state, actions = step(start, make(5.0), CFG)
    if cause == "offboard lost in telemetry" and mode in (S.IDLE, S.ABORTED):
        # Not commanding: a mode change is the pilot's business and nothing to abort.
        assert state.mode is mode and actions == ()
        return
    assert state.mode is S.ABORTED
    if mode is S.ABORTED:
        assert actions == ()
        return
    commanding = mode not in (S.IDLE,)
    expected = (
        ([stop.__name__] if commanding else [])
        + (
            ["TrackerStop"]
            if mode in (S.ACQUIRING, S.FOLLOWING, S.AWAITING_SUPERVISOR, S.CONFIRMED, S.LOST)
            else []
        )
        + ["GcsMessage"]
    )
    assert kinds(actions) == expected
    assert isinstance(actions[-1], GcsMessage) and actions[-1].severity == "critical"
    # Nothing moves the vehicle afterwards, whatever arrives.
    for event in (tracked(5.1, AT_STANDOFF), TimerTick(50.0), cmd(5.2, ConfirmCandidate())):
        state, actions = step(state, event, CFG)
        assert state.mode is S.ABORTED
        assert not any(isinstance(a, (SendSetpoint, RequestMode, TrackerInit, BackendQuery)) for a in actions)


def test_takeover_never_answered_with_a_hold_or_mode_request() -> None:
    for mode in (S.FOLLOWING, S.CONFIRMED, S.LOST):
        _, actions = step(reach(mode, allow_engage=True), PilotTakeover(3.0, "POSHOLD"), CFG)
        assert not any(isinstance(a, (Hold, RequestMode, SendSetpoint)) for a in actions)


def test_offboard_requested_only_when_mission_allows_engage() -> None:
    base, _ = run(initial_state(CFG), [telemetry(0.0, offboard=False)])
    _, actions = step(base, cmd(0.1, StartMission(PROMPT, allow_engage=False)), CFG)
    assert not any(isinstance(a, RequestMode) for a in actions)
    _, actions = step(base, cmd(0.1, StartMission(PROMPT, allow_engage=True)), CFG)
    assert actions[0] == RequestMode(FlightMode.OFFBOARD, "mission start")
    # Already in the mode: nothing to ask for.
    engaged, _ = run(initial_state(CFG), [telemetry(0.0, offboard=True)])
    _, actions = step(engaged, cmd(0.1, StartMission(PROMPT, allow_engage=True)), CFG)
    assert not any(isinstance(a, RequestMode) for a in actions)


def test_searching_queries_at_the_configured_rate_and_scans() -> None:
    # The search's own rate ([backend] search_interval_s), not the re-detection's and track checks'.
    config = replace(CFG, search_interval_s=2.0, query_interval_s=7.0, search_yaw_rate=math.radians(10.0))
    state = reach(S.SEARCHING, config)
    queries: list[float] = []
    for i in range(1, 27):
        t = 0.25 * i  # exact binary fractions: no rounding at the interval boundary
        state, actions = step(state, TimerTick(t), config)
        assert isinstance(actions[0], SendSetpoint)
        assert math.isclose(actions[0].setpoint.yaw_rate, math.radians(10.0))
        queries += [t for a in actions if isinstance(a, BackendQuery)]
    assert queries == [2.25, 4.25, 6.25]  # one more went out with the start, at 0.1 s
    assert last_query(step(state, TimerTick(99.0), config)[1]).purpose is QueryPurpose.SEARCH


def test_acquire_timeout_a_verified_candidate_the_tracker_cannot_hold_awaits_the_supervisor() -> None:
    """The tracker did not lock on a verified candidate (a few pixels, at survey height): the search goes
    on, and the candidate awaits the supervisor out of view, placed and cropped from its keyframe; seen again
    there it is not tracked a second time. An early (not yet verified) start is only dropped."""
    state, actions = step(reach(S.ACQUIRING), TimerTick(4.5), CFG)
    assert state.mode is S.SEARCHING and [p.candidate_id for p in state.pending] == ["c1"]
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert report.status == "awaiting" and report.keyframe_id == 30 and report.position is not None
    assert awaiting_decision(state) is state.pending[0]
    qid = last_query(actions).query_id
    again, started = step(state, BackendAnswer(5.0, qid, 40, (candidate(FAR, cid="c9"),)), CFG)
    assert again.mode is S.SEARCHING and not [a for a in started if isinstance(a, TrackerInit)]
    early, _ = step(reach(S.SEARCHING), BackendAnswer(1.0, 1, 30, (candidate(FAR),), final=False), CFG)
    assert early.mode is S.ACQUIRING and early.target is not None and early.target.early is not None
    dropped, actions = step(early, TimerTick(4.5), CFG)
    assert dropped.mode is S.SEARCHING and dropped.pending == ()
    assert not [a for a in actions if isinstance(a, ReportCandidate)]


def test_acquiring_prefers_yes_then_uncertain_by_policy() -> None:
    state = reach(S.SEARCHING)
    answer = BackendAnswer(
        1.0,
        1,
        30,
        (
            candidate(box_at(30, u=200), "u", Verdict.UNCERTAIN, 0.99),
            candidate(box_at(30, u=500), "y", Verdict.YES, 0.5),
            candidate(box_at(30, u=400), "y2", Verdict.YES, 0.7),
        ),
    )
    new, actions = step(state, answer, CFG)
    init = [a for a in actions if isinstance(a, TrackerInit)][0]
    assert init.candidate_id == "y2" and init.keyframe_id == 30 and not init.reinit
    only_uncertain = BackendAnswer(1.0, 1, 30, (candidate(FAR, "u", Verdict.UNCERTAIN),))
    assert step(state, only_uncertain, CFG)[0].mode is S.SEARCHING
    lenient = replace(CFG, accept_uncertain=True)
    assert step(state, only_uncertain, lenient)[0].mode is S.ACQUIRING
    # A description the verifier can check nothing of ("a dog"): its "uncertain" is all there will be.
    unjudged = replace(only_uncertain.candidates[0], judged=False)
    new, actions = step(state, replace(only_uncertain, candidates=(unjudged,)), CFG)
    assert new.mode is S.ACQUIRING and [a.candidate_id for a in actions if isinstance(a, TrackerInit)] == [
        "u"
    ]


def test_following_setpoints_approach_and_turn_towards_the_target() -> None:
    state = reach(S.FOLLOWING)
    right_far = box_at(25.0, u=CAM.cx + 120)
    for i in range(10):
        state, actions = step(state, tracked(1.2 + 0.05 * i, right_far), CFG)
    sp = [a for a in actions if isinstance(a, SendSetpoint)][-1].setpoint
    assert sp.forward > 0 and sp.yaw_rate > 0 and sp.down <= 0
    assert sp.horizontal_speed <= CFG.limits.max_speed and abs(sp.yaw_rate) <= CFG.limits.max_yaw_rate


def test_awaiting_reports_once_then_reverifies_periodically() -> None:
    state = reach(S.FOLLOWING)
    state, actions = step(state, tracked(1.2, AT_STANDOFF), CFG)
    reports = [a for a in actions if isinstance(a, ReportCandidate)]
    assert len(reports) == 1 and reports[0].status == "awaiting" and reports[0].candidate_id == "c1"
    assert reports[0].justification == "gray shirt, lying"
    assert reports[0].position is not None and math.isclose(
        reports[0].position.ground_range_m, CFG.standoff_m, rel_tol=0.01
    )
    reverify: list[BackendQuery] = []
    t = 1.2
    while t < 1.2 + 2.5 * CFG.reverify_interval_s:
        t += 0.1
        state, actions = step(state, tracked(t, AT_STANDOFF), CFG)
        assert not any(isinstance(a, ReportCandidate) for a in actions)
        state, actions = step(state, TimerTick(t), CFG)
        reverify += [a for a in actions if isinstance(a, BackendQuery)]
    assert len(reverify) == 2 and all(
        q.purpose is QueryPurpose.REVERIFY and q.roi is not None for q in reverify
    )
    answer = BackendAnswer(t, reverify[-1].query_id, 40, (candidate(AT_STANDOFF, "c1-b", Verdict.YES),))
    state, actions = step(state, answer, CFG)
    assert kinds(actions) == ["ReportCandidate"]
    assert (
        isinstance(actions[0], ReportCandidate)
        and actions[0].status == "reverified"
        and actions[0].candidate_id == "c1"
    )
    missing = BackendAnswer(t, reverify[0].query_id, 41, (candidate(box_at(30, u=50), "other"),))
    _, actions = step(state, missing, CFG)
    assert kinds(actions) == ["GcsMessage"]


def test_the_words_the_back_end_could_not_judge_go_with_the_candidate_to_the_supervisor() -> None:
    """What the back-end could not judge for the chosen candidate (a kind of car, a place it cannot locate)
    is reported with it: the supervisor checks that by eye. A re-verification reports what its own answer
    could not judge; a confirmation keeps it."""
    state, _ = run(initial_state(CFG), [telemetry(0.0)])
    state, actions = step(state, cmd(0.1, StartMission(PROMPT)), CFG)
    unsure = ("injured", "next to the bicycle (the bicycle: not located)")
    seen = replace(candidate(FAR), unjudged=unsure)
    state, _ = run(state, [BackendAnswer(1.0, last_query(actions).query_id, 30, (seen,)), tracked(1.1, FAR)])
    state, actions = step(state, tracked(1.2, AT_STANDOFF), CFG)
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert report.status == "awaiting" and report.unjudged == unsure
    t, reverify = 1.2, None
    while reverify is None:
        t += 0.1
        state, _ = step(state, tracked(t, AT_STANDOFF), CFG)
        state, actions = step(state, TimerTick(t), CFG)
        reverify = next((a for a in actions if isinstance(a, BackendQuery)), None)
    again = replace(candidate(AT_STANDOFF, "c1-b"), unjudged=("injured",))
    state, actions = step(state, BackendAnswer(t, reverify.query_id, 40, (again,)), CFG)
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert report.status == "reverified" and report.unjudged == ("injured",)
    state, actions = step(state, cmd(t + 0.1, ConfirmCandidate()), CFG)
    assert [a.unjudged for a in actions if isinstance(a, ReportCandidate)] == [("injured",)]


def test_a_candidate_chosen_among_look_alikes_says_how_many() -> None:
    """Three people fit what the back-end judged, told apart by the detector's score alone: the report says
    the choice had two others alike (the supervisor should know it was no judgement); one that the
    description's placement singles out has none."""
    state, _ = run(initial_state(CFG), [telemetry(0.0)])
    state, actions = step(state, cmd(0.1, StartMission(PROMPT)), CFG)
    qid = last_query(actions).query_id
    three = (candidate(FAR, "c1", score=0.9), candidate(box_at(25, u=100), "c2", score=0.8),
             candidate(box_at(25, u=540), "c3", score=0.7))  # fmt: skip
    searching = state
    state, _ = run(state, [BackendAnswer(1.0, qid, 30, three), tracked(1.1, FAR)])
    _, actions = step(state, tracked(1.2, AT_STANDOFF), CFG)
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert (report.candidate_id, report.alike) == ("c1", 2)
    placed = (three[0], replace(three[1], placement_ok=True), three[2])
    state, _ = run(searching, [BackendAnswer(1.0, qid, 30, placed), tracked(1.1, placed[1].box)])
    assert state.target is not None and (state.target.candidate_id, state.target.alike) == ("c2", 0)


@pytest.mark.parametrize("on_confirm", list(ConfirmAction))
def test_confirmed_behaviours(on_confirm: ConfirmAction) -> None:
    config = replace(CFG, on_confirm=on_confirm)
    state = reach(S.AWAITING_SUPERVISOR, config)
    state, actions = step(state, cmd(1.3, ConfirmCandidate()), config)
    assert state.mode is S.CONFIRMED
    report = [a for a in actions if isinstance(a, ReportCandidate)][0]
    assert report.status == "confirmed" and report.position is not None
    assert (ReleaseControl("confirmed: hold") in actions) == (on_confirm is ConfirmAction.HOLD)
    assert not any(isinstance(a, Hold) for a in actions)
    for i in range(20):
        state, actions = step(state, tracked(1.35 + 0.05 * i, AT_STANDOFF), config)
    setpoints = [a.setpoint for a in actions if isinstance(a, SendSetpoint)]
    if on_confirm is ConfirmAction.HOLD:
        assert setpoints == []
    elif on_confirm is ConfirmAction.ORBIT:
        assert setpoints[-1].right > 0.5  # circling sideways while yaw keeps the target centred
    else:
        assert abs(setpoints[-1].right) < 1e-9 and abs(setpoints[-1].forward) < 0.2


def test_lost_redetects_near_last_position_and_reinitialises_by_c_box() -> None:
    state = reach(S.FOLLOWING)
    state, actions = step(state, tracked(1.2, None, ok=False, reason="left_frame"), CFG)
    query = last_query(actions)
    assert query.purpose is QueryPurpose.REDETECT and query.roi is not None
    assert query.roi.x <= FAR.x and query.roi.x2 >= FAR.x2 and query.roi.w < CAM.width
    near = Box(FAR.x + 6, FAR.y + 3, FAR.w, FAR.h)
    far_away = Box(5, 5, 60, 120)
    answer = BackendAnswer(
        1.5,
        query.query_id,
        45,
        (
            candidate(far_away, "z"),
            candidate(near, "n", Verdict.UNCERTAIN),
            candidate(FAR, "no", Verdict.NO),
        ),
    )
    state, actions = step(state, answer, CFG)
    assert actions == (TrackerInit(near, 45, "c1", reinit=True),)
    assert state.mode is S.LOST
    state, actions = step(state, tracked(1.6, near), CFG)
    assert state.mode is S.FOLLOWING


def test_lost_ignores_candidates_beyond_the_gate() -> None:
    state = reach(S.LOST)
    query = state.queries[-1][0]
    _, actions = step(state, BackendAnswer(1.5, query, 45, (candidate(Box(560, 400, 70, 70), "z"),)), CFG)
    assert actions == ()


def test_lost_redetects_at_the_search_rate() -> None:
    # Nothing is followed while lost: re-detection asks as often as the search, not as the track checks.
    config = replace(CFG, search_interval_s=2.0, query_interval_s=7.0)
    state = reach(S.LOST, config)  # entered at t=1.2 with a re-detection query
    queries: list[float] = []
    for i in range(1, 27):
        t = 1.25 + 0.25 * i
        state, actions = step(state, TimerTick(t), config)
        queries += [t for a in actions if isinstance(a, BackendQuery)]
    assert queries == [3.25, 5.25, 7.25]
    assert state.mode is S.LOST
    assert last_query(step(state, TimerTick(99.0), config)[1]).purpose is QueryPurpose.REDETECT


@pytest.mark.parametrize("lost_action", list(LostAction))
def test_lost_holds_then_requests_the_configured_action(lost_action: LostAction) -> None:
    config = replace(CFG, lost_action=lost_action, lost_hold_after_s=1.0, lost_action_after_s=5.0)
    state = reach(S.LOST, config)  # entered at t=1.2
    seen: list[tuple[float, Action]] = []
    t = 1.2
    while t < 9.0:
        t = round(t + 0.1, 3)
        state, actions = step(state, TimerTick(t), config)
        seen += [(t, a) for a in actions]
    holds = [t for t, a in seen if isinstance(a, Hold)]
    assert len(holds) == 1 and 2.2 <= holds[0] < 2.35
    requests = [(t, a) for t, a in seen if isinstance(a, RequestMode)]
    queries_after = [t for t, a in seen if isinstance(a, BackendQuery) and t > 6.3]
    if lost_action is LostAction.HOLD:
        assert requests == [] and queries_after  # keeps holding and looking
        assert state.mode is S.LOST
        assert step(state, tracked(9.1, FAR), config)[0].mode is S.FOLLOWING
    else:
        assert len(requests) == 1 and 6.2 <= requests[0][0] < 6.35
        assert requests[0][1] == RequestMode(FlightMode(lost_action.value), "target lost")
        assert queries_after == []
        # The autopilot leaving offboard because we asked is not a takeover; the mission waits for the GCS.
        state, actions = run(state, [telemetry(9.1, offboard=False), tracked(9.2, FAR)], config)
        assert state.mode is S.LOST and actions == ()


def test_resuming_after_a_hold_asks_for_offboard_again_when_allowed() -> None:
    config = replace(CFG, lost_hold_after_s=0.5)
    state = reach(S.LOST, config, allow_engage=True)
    state, actions = run(state, [TimerTick(2.0), telemetry(2.1, offboard=False)], config)
    assert state.mode is S.LOST and state.holding
    state, actions = step(state, tracked(2.2, FAR), config)
    assert state.mode is S.FOLLOWING
    assert kinds(actions) == ["GcsMessage", "RequestMode", "SendSetpoint"]


@pytest.mark.parametrize("reason", ["stale_frames", "main_loop_stalled"])
def test_a_watchdogs_own_hold_is_not_a_pilot_takeover_and_following_resumes(reason: str) -> None:
    """PX4: the companion's stale-frame (or stalled-loop) stop asks for HOLD itself; telemetry then shows
    the offboard mode gone, which is ours, not the pilot's; with frames back it asks for OFFBOARD again."""
    state = reach(S.FOLLOWING, allow_engage=True)
    state, actions = step(state, CompanionHold(1.2, reason), CFG)
    assert actions == () and state.holding and state.mode is S.FOLLOWING
    state, actions = step(state, telemetry(1.3, offboard=False), CFG)
    assert state.mode is S.FOLLOWING and actions == ()
    state, actions = step(state, tracked(1.4, FAR), CFG)
    assert state.mode is S.FOLLOWING and "RequestMode" in kinds(actions) and not state.holding
    # Without the watchdog's word the same telemetry is the pilot taking over.
    state = reach(S.FOLLOWING, allow_engage=True)
    state, actions = step(state, telemetry(1.3, offboard=False), CFG)
    assert state.mode is S.ABORTED and "ReleaseControl" in kinds(actions)
    # Not commanding (no mission): nothing to note.
    idle = reach(S.IDLE)
    assert step(idle, CompanionHold(0.5, reason), CFG) == (replace(idle, now_s=0.5), ())


def test_our_hold_that_shows_only_after_the_resume_is_still_ours() -> None:
    """PX4 on a loaded machine: the watchdog's HOLD shows in telemetry after frames came back and the mission
    asked for OFFBOARD again; it is still ours. Past the window, offboard ending is the pilot's again."""
    state = reach(S.FOLLOWING, allow_engage=True)
    state, _ = step(state, CompanionHold(1.2, "stale_frames"), CFG)
    state, actions = step(state, tracked(1.3, FAR), CFG)  # frames back: following resumes
    assert "SendSetpoint" in kinds(actions) and not state.holding
    state, actions = step(state, telemetry(1.5, offboard=False), CFG)
    assert state.mode is S.FOLLOWING and actions == ()
    state, _ = step(state, telemetry(1.2 + HOLD_SHOWS_WITHIN_S + 0.5, offboard=True), CFG)
    state, actions = step(state, telemetry(1.2 + HOLD_SHOWS_WITHIN_S + 0.6, offboard=False), CFG)
    assert state.mode is S.ABORTED and "ReleaseControl" in kinds(actions)


def test_backend_unreachable_stops_motion_until_it_answers() -> None:
    state = reach(S.FOLLOWING)
    state, actions = step(state, BackendUnreachable(1.2, "timeout"), CFG)
    assert kinds(actions) == ["Hold", "GcsMessage"] and state.mode is S.FOLLOWING
    assert step(state, BackendUnreachable(1.25), CFG)[1] == ()
    state, actions = step(state, tracked(1.3, FAR), CFG)
    assert actions == ()  # still tracking, not moving
    state, actions = step(state, tracked(1.35, None, ok=False), CFG)  # lost while the back-end is down
    qid = last_query(actions).query_id
    state, _ = step(state, BackendAnswer(1.4, qid, 50, ()), CFG)
    assert not state.backend_down
    state, actions = step(state, tracked(1.45, FAR), CFG)
    assert state.mode is S.FOLLOWING and "SendSetpoint" in kinds(actions)


def test_descent_only_after_confirmation() -> None:
    high = replace(CFG, limits=replace(CFG.limits, max_altitude=15.0))
    for mode, allowed in ((S.AWAITING_SUPERVISOR, False), (S.CONFIRMED, True)):
        state = reach(mode, high)
        for i in range(5):
            state, actions = step(state, tracked(1.4 + 0.05 * i, AT_STANDOFF), high)
        sp = [a for a in actions if isinstance(a, SendSetpoint)][-1].setpoint
        assert (sp.down > 0) == allowed


# --- rejection memory ---------------------------------------------------------------------------------


def rejected_then_searching(config: MissionConfig = CFG) -> State:
    state = reach(S.REJECTED, config)
    assert len(state.rejections.entries) == 1
    state, _ = step(state, TimerTick(1.4), config)
    assert state.mode is S.SEARCHING
    return state


def test_rejected_target_is_not_proposed_again_by_position() -> None:
    state = rejected_then_searching()
    qid = state.queries[-1][0]
    same_place = BackendAnswer(2.0, qid, 60, (candidate(AT_STANDOFF, "new-id"),))
    assert step(state, same_place, CFG)[0].mode is S.SEARCHING
    elsewhere = BackendAnswer(
        2.0, qid, 60, (candidate(AT_STANDOFF, "new-id"), candidate(box_at(30.0, u=100), "p2", score=0.1))
    )
    new, actions = step(state, elsewhere, CFG)
    assert new.mode is S.ACQUIRING
    assert [a for a in actions if isinstance(a, TrackerInit)][0].candidate_id == "p2"


def test_rejected_target_is_recognised_by_signature_and_id() -> None:
    sig = (0.1, 0.7, 0.2, 0.0)
    state = reach(S.SEARCHING)
    state, _ = step(state, BackendAnswer(1.0, 1, 30, (candidate(FAR, "c1", sig=sig),)), CFG)
    state, _ = run(state, [tracked(1.1, FAR), cmd(1.2, RejectCandidate()), TimerTick(1.3)])
    assert state.mode is S.SEARCHING and state.rejections.entries[0].signature == sig
    qid = state.queries[-1][0]
    # Same person walked elsewhere: position differs, appearance matches.
    moved = candidate(box_at(40.0, u=600), "x", sig=(0.11, 0.69, 0.2, 0.01))
    assert step(state, BackendAnswer(2.0, qid, 60, (moved,)), CFG)[0].mode is S.SEARCHING
    other = candidate(box_at(40.0, u=600), "y", sig=(0.7, 0.1, 0.0, 0.2))
    assert step(state, BackendAnswer(2.0, qid, 60, (other,)), CFG)[0].mode is S.ACQUIRING
    # The back-end's id alone is enough too.
    same_id = candidate(box_at(40.0, u=600), "c1")
    assert step(state, BackendAnswer(2.0, qid, 60, (same_id,)), CFG)[0].mode is S.SEARCHING


def test_a_rejection_holds_where_the_keyframe_placed_it_when_the_track_placed_it_elsewhere() -> None:
    """A tracker started late (a keyframe seconds older than the live view) held the background from its first
    frame: the track's fix lies 20 m beyond the candidate the keyframe showed and the supervisor rejected (a
    fleet run: the look-alike's rejection remembered 17 m off, the look-alike proposed again from another
    lane). The rejection holds at both places."""
    state = reach(S.SEARCHING)
    state, _ = step(state, BackendAnswer(1.0, 1, 30, (candidate(box_at(12.0), "c1"),)), CFG)
    assert state.mode is S.ACQUIRING and state.target is not None and state.target.proposed_at is not None
    state, _ = run(
        state, [tracked(1.1, box_at(32.0)), tracked(1.2, box_at(32.0)), cmd(1.3, RejectCandidate())]
    )
    entry = state.rejections.entries[-1]
    assert entry.position is not None and entry.position.ground_range_m == pytest.approx(32.0, abs=0.5)
    assert entry.also_at is not None and entry.also_at.ground_range_m == pytest.approx(12.0, abs=0.5)
    state, _ = step(state, TimerTick(1.4), CFG)
    qid = state.queries[-1][0]
    again = BackendAnswer(2.0, qid, 60, (candidate(box_at(12.0), "new-id"),))  # where the keyframe showed it
    assert step(state, again, CFG)[0].mode is S.SEARCHING
    beyond = BackendAnswer(2.0, qid, 60, (candidate(box_at(32.0), "other"),))  # where the track was
    assert step(state, beyond, CFG)[0].mode is S.SEARCHING
    elsewhere = BackendAnswer(2.0, qid, 60, (candidate(box_at(22.0, u=100), "p2"),))
    assert step(state, elsewhere, CFG)[0].mode is S.ACQUIRING


def test_rejection_emits_remember_action_and_memory_survives_same_prompt_only() -> None:
    state = reach(S.AWAITING_SUPERVISOR)
    state, actions = step(state, cmd(1.3, RejectCandidate()), CFG)
    remember = [a for a in actions if isinstance(a, RememberRejection)][0]
    assert remember.candidate_id == "c1" and remember.position is not None
    same, _ = step(state, cmd(2.0, StartMission(PROMPT)), CFG)
    assert len(same.rejections.entries) == 1
    other, _ = step(state, cmd(2.0, StartMission("a child in a red jacket")), CFG)
    assert other.rejections.entries == ()


def test_non_finite_time_is_ignored_with_a_warning() -> None:
    state = reach(S.FOLLOWING)
    new, actions = step(state, TimerTick(math.nan), CFG)
    assert new == state and kinds(actions) == ["GcsMessage"]


def test_zero_setpoint_on_entering_lost() -> None:
    _, actions = step(reach(S.FOLLOWING), tracked(1.2, None, ok=False), CFG)
    assert actions[0] == SendSetpoint(Setpoint.zero())
    assert isinstance(actions[1], GcsMessage) and actions[1].severity == "warning"
    assert isinstance(actions[-1], BackendQuery)
    assert not any(isinstance(a, (TrackerStop, Hold)) for a in actions)


def test_operator_rectangle_outside_a_mission_never_engages() -> None:
    state = reach(S.ABORTED, allow_engage=True)
    state, actions = step(state, cmd(3.0, TrackRectangle(FAR)), CFG)
    assert state.mode is S.FOLLOWING and state.mission is None
    assert kinds(actions) == ["TrackerInit", "GcsMessage"]
    # Lost without a prompt: nothing to ask the back-end, it stops and holds.
    state, actions = step(state, tracked(3.1, None, ok=False), CFG)
    assert state.mode is S.LOST and kinds(actions) == ["SendSetpoint", "GcsMessage"]


def test_config_from_the_companion_sections() -> None:
    from companion.config import CompanionConfig

    companion = CompanionConfig()
    sections = {
        name: getattr(companion, name).model_dump()
        for name in ("behavior", "control", "safety", "camera", "backend")
    }
    config = MissionConfig.from_sections(**sections)
    assert config == MissionConfig()  # the schema's defaults and these defaults agree
    sections["behavior"] = {
        **sections["behavior"],
        "lost_action": "rtl",
        "accept_uncertain": True,
        "search_yaw_rate_deg_s": 10.0,
    }
    sections["safety"] = {**sections["safety"], "max_yaw_rate_deg_s": 30.0}
    tuned = MissionConfig.from_sections(**sections)
    assert tuned.lost_action is LostAction.RTL and tuned.accept_uncertain
    assert math.isclose(tuned.search_yaw_rate, math.radians(10.0)) and math.isclose(
        tuned.limits.max_yaw_rate, math.radians(30.0)
    )
    with pytest.raises(ValueError, match="standoff_m: expected a finite number"):
        MissionConfig.from_sections(**{**sections, "behavior": {"standoff_m": "far"}})
    with pytest.raises(ValueError, match="'sideways' is not a valid ConfirmAction"):
        MissionConfig.from_sections(**{**sections, "behavior": {"on_confirm": "sideways"}})


def test_rejection_memory_matching_rules() -> None:
    from behaviors.geolocation import GeoEstimate, offset_to_latlon
    from behaviors.rejection_memory import RejectedTarget, RejectionMemory, cosine_similarity

    def at(north: float, east: float, sigma: float = 0.0) -> GeoEstimate:
        lat, lon = offset_to_latlon(47.0, 8.0, north, east)
        return GeoEstimate(lat, lon, north, east, math.hypot(north, east), 0.0, sigma)

    memory = RejectionMemory(radius_m=5.0).remember(RejectedTarget("c1", at(0, 0, 1.0), (1.0, 0.0)))
    assert memory.matches("c1") is not None
    assert memory.matches("c2") is None
    assert memory.matches(position=at(3.0, 3.0)) is not None  # 4.2 m
    assert memory.matches(position=at(6.0, 0.0)) is not None  # within radius + 2 sigma (5 + 2)
    assert memory.matches(position=at(8.0, 0.0)) is None
    # A wildly uncertain estimate widens the match only up to three radii.
    assert memory.matches(position=at(14.0, 0.0, 1000.0)) is not None
    assert memory.matches(position=at(16.0, 0.0, 1000.0)) is None
    assert memory.matches(signature=(0.99, 0.05)) is not None
    assert memory.matches(signature=(0.5, 0.5)) is None
    assert memory.matches(signature=(1.0, 0.0, 0.0)) is None  # different length: not comparable
    # Of one keyframe's candidates, only the nearest takes a rejection by place; id and looks match each.
    assert memory.matches_each([("a", at(4.0, 0.0), ()), ("b", at(1.0, 0.0), ())]) == (
        None,
        memory.entries[0],
    )
    assert memory.matches_each([("c1", at(9.0, 0.0), ()), ("b", at(1.0, 0.0), ())]) == memory.entries * 2
    assert (
        memory.matches_each([("a", at(1.0, 0.0), ()), ("b", at(20.0, 0.0), (1.0, 0.0))]) == memory.entries * 2
    )
    assert memory.matches_each([("a", at(8.0, 0.0), ()), ("b", None, ())]) == (None, None)
    assert cosine_similarity((0.0, 0.0), (1.0, 0.0)) == 0.0 and cosine_similarity((), ()) == 0.0
    assert cosine_similarity((math.nan, 1.0), (1.0, 1.0)) == 0.0
    full = RejectionMemory(capacity=3)
    for i in range(5):
        full = full.remember(RejectedTarget(f"c{i}"))
    assert [e.candidate_id for e in full.entries] == ["c2", "c3", "c4"]
    # Once the back-end holds the rejection (answers to query 7 on), position matches only within two sigma
    # of both estimates: appearance is the back-end's verifier's job. Id and signature still match.
    shared = memory.shared("c1", 7)
    assert shared.matches(position=at(6.0, 0.0), query_id=6) is not None  # an older query: radius
    assert shared.matches(position=at(6.0, 0.0), query_id=7) is None
    assert shared.matches(position=at(1.5, 0.0), query_id=7) is not None  # 2 sigma: 2.0 m
    assert shared.matches("c1", query_id=9) is not None and shared.matches(signature=(1.0, 0.1)) is not None
    assert shared.shared("c1", 12).entries[0].shared_from_query == 7  # taken once, the first time counts
    assert memory.shared("c9", 7) == memory


def test_a_person_beside_a_rejected_look_alike_is_proposed_once_the_back_end_holds_the_rejection() -> None:
    """The companion's position rule stands in for appearance, which it does not judge: 6 m from a rejected
    look-alike, the described person (a "yes" from the back-end, which judges appearance against the
    rejection) was never proposed. Until the back-end holds the rejection the radius keeps the look-alike
    from being proposed again under a new id; from the next query after it took the rejection, only the
    estimates' own uncertainty places a candidate on the rejected one."""
    state = rejected_then_searching()
    rejected = state.rejections.entries[0]
    assert rejected.candidate_id == "c1" and rejected.position is not None
    beside = box_at(CFG.standoff_m + 6.0)
    qid = state.queries[-1][0]
    before = BackendAnswer(2.0, qid, 60, (candidate(beside, "c7"),))
    assert step(state, before, CFG)[0].mode is S.SEARCHING  # within the radius: not proposed
    state, actions = step(state, RejectionShared(2.1, "c1"), CFG)
    assert actions == () and state.rejections.entries[0].shared_from_query == qid + 1
    assert step(state, before, CFG)[0].mode is S.SEARCHING  # answered before the back-end held it
    state, actions = run(state, [TimerTick(2.2)])
    (query,) = [a for a in actions if isinstance(a, BackendQuery)]
    new, actions = step(state, BackendAnswer(2.4, query.query_id, 66, (candidate(beside, "c8"),)), CFG)
    assert new.mode is S.ACQUIRING
    assert [a.candidate_id for a in actions if isinstance(a, TrackerInit)] == ["c8"]
    # The look-alike itself, where it stood: still not proposed.
    same = BackendAnswer(2.4, query.query_id, 66, (candidate(AT_STANDOFF, "c9"),))
    assert step(state, same, CFG)[0].mode is S.SEARCHING


def test_a_person_in_one_keyframe_with_a_rejected_look_alike_is_proposed_at_once() -> None:
    """Two people in one keyframe are two people: the look-alike where it was rejected takes the rejection by
    place, and the described person 6 m off (within the radius) is proposed at once, before the back-end
    holds the rejection (CI, search-no-engage: the look-alike rejected before the described person's first
    "yes", who was then never proposed in the rest of the search). Which of the two is nearer decides, not
    the order they came in."""
    state = rejected_then_searching()
    qid = state.queries[-1][0]
    beside = candidate(box_at(CFG.standoff_m + 6.0), "c7", score=0.5)
    for pair in ((candidate(AT_STANDOFF, "c9"), beside), (beside, candidate(AT_STANDOFF, "c9"))):
        new, actions = step(state, BackendAnswer(2.0, qid, 60, pair), CFG)
        assert new.mode is S.ACQUIRING
        assert [a.candidate_id for a in actions if isinstance(a, TrackerInit)] == ["c7"]
    # Alone, the one 6 m off may still be the look-alike under a new id (the previous test).
    assert step(state, BackendAnswer(2.0, qid, 60, (beside,)), CFG)[0].mode is S.SEARCHING


def test_operator_target_is_re_found_whatever_the_verdict() -> None:
    state = reach(S.SEARCHING)
    state, _ = step(state, cmd(1.0, TrackRectangle(FAR)), CFG)
    assert state.mode is S.FOLLOWING and state.mission is not None  # inside a running mission: prompt kept
    state, actions = run(state, [tracked(1.1, FAR), tracked(1.2, None, ok=False)])
    query = last_query(actions)
    no_match = candidate(FAR, "n", Verdict.NO)
    _, actions = step(state, BackendAnswer(1.5, query.query_id, 50, (no_match,)), CFG)
    assert actions == (TrackerInit(FAR, 50, "operator", reinit=True),)
    # A prompt-verified target is not re-found from a "no".
    lost = reach(S.LOST)
    _, actions = step(
        lost, BackendAnswer(1.5, lost.queries[-1][0], 50, (candidate(FAR, "n", Verdict.NO),)), CFG
    )
    assert actions == ()


# Re-detection region by time lost (FAR is 16 x 40 px; default base scale 3, whole frame after 4 s).
@pytest.mark.parametrize(
    ("lost_for_s", "expected"),
    [
        (0.0, (48.0, 120.0)),  # the configured base scale
        (0.5, None),  # between: strictly bigger than the base, checked below
        (2.0, None),
        (4.0, "whole"),  # the whole frame from redetect_full_frame_s on
        (30.0, "whole"),
    ],
)
def test_redetect_region_grows_with_time_lost(lost_for_s: float, expected: object) -> None:
    roi = redetect_roi(FAR, lost_for_s, CFG)
    if expected == "whole":
        assert roi is None
    elif expected is not None:
        assert roi is not None and (roi.w, roi.h) == expected and (roi.cx, roi.cy) == (FAR.cx, FAR.cy)
    else:
        assert roi is not None and roi.w > 3 * FAR.w and roi.x <= FAR.x and roi.x2 >= FAR.x2
        assert roi.w < CAM.width or roi.h < CAM.height


def test_redetect_region_is_monotonic_and_configurable() -> None:
    widths = [
        r.w * r.h if (r := redetect_roi(FAR, t / 10, CFG)) is not None else CAM.width * CAM.height
        for t in range(50)
    ]
    assert widths == sorted(widths) and widths[0] < widths[-1]
    wide = replace(CFG, redetect_roi_scale=5.0, redetect_full_frame_s=10.0)
    assert redetect_roi(FAR, 0.0, wide) == Box.from_center(FAR.cx, FAR.cy, 80.0, 200.0)
    assert redetect_roi(FAR, 5.0, wide) is not None and redetect_roi(FAR, 10.0, wide) is None


def _lost_for(seconds: float) -> tuple[State, int, float]:
    """LOST (entered at 1.2 s), ticked until a re-detect query that was sent `seconds` after the loss."""
    state, t = reach(S.LOST), 1.2
    while t < 1.2 + seconds:
        t = round(t + 0.1, 3)
        state, _ = step(state, TimerTick(t), CFG)
    return state, state.queries[-1][0], t


# (lost for, where the candidate is, its verdict, re-found?): near the last box "uncertain" may re-find the
# target; away from it only "yes" may, however wide the query's region has grown (3.9 s: almost the whole
# frame, 5 s: the whole frame), so a distractor elsewhere in view cannot take over the track.
@pytest.mark.parametrize(
    ("lost_for_s", "near", "verdict", "refound"),
    [
        (0.0, True, Verdict.UNCERTAIN, True),
        (0.0, True, Verdict.NO, False),
        (0.0, False, Verdict.UNCERTAIN, False),
        (0.0, False, Verdict.YES, True),
        (3.9, False, Verdict.UNCERTAIN, False),
        (3.9, False, Verdict.YES, True),
        (5.0, True, Verdict.UNCERTAIN, True),
        (5.0, False, Verdict.UNCERTAIN, False),
        (5.0, False, Verdict.YES, True),
        (5.0, False, Verdict.NO, False),
    ],
)
def test_away_from_the_last_box_only_a_yes_refinds_the_target(
    lost_for_s: float, near: bool, verdict: Verdict, refound: bool
) -> None:
    state, qid, t = _lost_for(lost_for_s)
    where = Box(FAR.x + 3, FAR.y + 2, FAR.w, FAR.h) if near else Box(FAR.x + 120, FAR.y + 40, FAR.w, FAR.h)
    state, actions = step(state, BackendAnswer(t + 0.3, qid, 99, (candidate(where, "d", verdict),)), CFG)
    assert (actions == (TrackerInit(where, 99, "c1", reinit=True),)) is refound


def test_redetect_settings_come_from_the_behavior_section() -> None:
    config = MissionConfig.from_sections(
        behavior={"redetect_roi_scale": 6.0, "redetect_full_frame_s": 8.0},
        control={},
        safety={},
        camera={},
        backend={},
    )
    assert (config.redetect_roi_scale, config.redetect_full_frame_s) == (6.0, 8.0)
    with pytest.raises(ValueError, match="redetect_roi_scale"):
        MissionConfig.from_sections(
            behavior={"redetect_roi_scale": "big"}, control={}, safety={}, camera={}, backend={}
        )


# --- "verified" re-initialisation policy: the mission hands answers to the front-end --------------------

VERIFIED = replace(CFG, verified_reinit=True)


def test_verified_lost_hands_the_answer_to_the_front_end_with_what_the_mission_refuses() -> None:
    state = reach(S.FOLLOWING, VERIFIED)
    state, actions = step(state, cmd(1.15, RejectCandidate("r")), VERIFIED)  # someone else, remembered
    state, actions = step(state, tracked(1.2, None, ok=False, reason="left_frame"), VERIFIED)
    query = last_query(actions)
    near = Box(FAR.x + 6, FAR.y + 3, FAR.w, FAR.h)
    far_away = Box(5, 5, 60, 120)
    cands = (
        candidate(far_away, "z"),  # a "yes" away from the last box: acceptable
        candidate(near, "n", Verdict.UNCERTAIN),  # near, not "no": acceptable
        candidate(FAR, "no", Verdict.NO),  # refused: verdict no
        candidate(far_away, "u", Verdict.UNCERTAIN),  # refused: away from the last box without a "yes"
        candidate(near, "r"),  # refused: the supervisor rejected it
    )
    state, actions = step(state, BackendAnswer(1.5, query.query_id, 45, cands), VERIFIED)
    assert actions == (JudgeCandidates(45, cands, (2, 3, 4)),)  # no TrackerInit: the front-end decides
    assert state.mode is S.LOST and state.target is not None and state.target.box == FAR  # nothing moved yet
    state, _ = step(state, tracked(1.6, near), VERIFIED)
    assert state.mode is S.FOLLOWING  # a trusted result (whoever caused it) ends LOST as before


def test_verified_following_checks_the_track_and_judges_the_answer() -> None:
    state = reach(S.FOLLOWING, VERIFIED)
    state, actions = run(state, [tracked(2.0, FAR), TimerTick(2.05)], VERIFIED)
    query = last_query(actions)
    # The whole frame: after a switch to a neighbour the target is often outside the track's region.
    assert query.purpose is QueryPurpose.TRACK_CHECK and query.roi is None
    state, actions = step(state, tracked(2.06, FAR), VERIFIED)
    answer = BackendAnswer(2.1, query.query_id, 62, (candidate(FAR, "c1", Verdict.NO),))
    state, actions = step(state, answer, VERIFIED)
    assert actions == (JudgeCandidates(62, answer.candidates, (0,)),) and state.mode is S.FOLLOWING


def test_verified_following_asks_for_evidence_when_a_loss_signal_starts() -> None:
    """A lone loss signal does not untrust the track at once ("verified"): its start sends one track check
    at once, not one per frame; a new alarm after a quiet frame sends another."""
    state = reach(S.FOLLOWING, VERIFIED)
    state, _ = step(state, tracked(2.0, FAR), VERIFIED)
    sent = []
    for t, alarm in [(2.03, "appearance"), (2.06, "appearance"), (2.1, ""), (2.13, "score")]:
        result = TrackResult(int(t * 30), t, FAR, 0.9, True, "", alarm)
        state, actions = step(state, result, VERIFIED)
        sent.append([a.purpose for a in actions if isinstance(a, BackendQuery)])
        assert state.mode is S.FOLLOWING and any(isinstance(a, SendSetpoint) for a in actions)
    assert sent == [[QueryPurpose.TRACK_CHECK], [], [], [QueryPurpose.TRACK_CHECK]]
    # The paper's policy asks for nothing while trusted.
    state = reach(S.FOLLOWING)
    _, actions = step(state, TrackResult(61, 2.03, FAR, 0.9, True, "", "appearance"), CFG)
    assert not [a for a in actions if isinstance(a, BackendQuery)]


def test_verified_an_answer_that_found_nothing_still_goes_to_the_front_end() -> None:
    """Nothing found on the track is evidence too (as `eval` judges it): it ends the hold an older
    confirmation has over the track's own score and appearance alarms. Before, an empty answer was dropped:
    a search flown with a supervisor 20 s late followed the background for 14 s on one confirmation, its
    re-verification finding nothing, and reported the find 10.7 m from the person."""
    state = reach(S.FOLLOWING, VERIFIED)
    state, actions = run(state, [tracked(2.0, FAR), TimerTick(2.05)], VERIFIED)
    query = last_query(actions)
    _, actions = step(state, BackendAnswer(2.1, query.query_id, 62, ()), VERIFIED)
    assert actions == (JudgeCandidates(62, (), ()),)
    # Awaiting the supervisor: the re-verification's empty answer, said on the GCS and judged.
    state = reach(S.AWAITING_SUPERVISOR, VERIFIED)
    assert state.target is not None
    state, actions = run(state, [tracked(11.3, state.target.box), TimerTick(11.35)], VERIFIED)
    query = last_query(actions)
    assert query.purpose is QueryPurpose.REVERIFY
    _, actions = step(state, BackendAnswer(11.4, query.query_id, 340, ()), VERIFIED)
    assert kinds(actions) == ["GcsMessage", "JudgeCandidates"]


def test_a_frame_with_a_loss_signal_never_gives_the_find_its_position() -> None:
    """The find is where the track placed the target on frames no loss signal doubted: a tracker sliding
    onto the background while trusted (an old confirmation outweighing its alarm) gives estimates as sharp
    as the target's, and the kept one was the background's."""
    state = reach(S.AWAITING_SUPERVISOR, VERIFIED)
    assert state.target is not None
    box = state.target.box
    state, _ = step(state, tracked(5.0, box), VERIFIED)
    assert state.target is not None and state.target.fix is not None and state.target.fix_s == 5.0
    good = state.target.fix
    elsewhere = Box(box.x + 60, box.y, box.w, box.h)  # as sharp an estimate, metres away
    state, _ = step(state, TrackResult(151, 5.03, elsewhere, 0.8, True, "", "appearance"), VERIFIED)
    assert state.target is not None and state.target.fix == good and state.target.fix_s == 5.0
    assert state.target.position != good and state.target.box == elsewhere  # still followed and shown
    state, _ = step(state, tracked(5.06, box), VERIFIED)  # an undoubted frame: kept again
    assert state.target is not None and state.target.fix_s == 5.06


def test_after_a_loss_the_find_has_no_position_from_the_track_until_the_back_end_sees_it_there() -> None:
    """The tracker re-acquires on its own after a loss (its signals went quiet): the box may be on the
    background it slid onto, with no alarm at all (a search flown with a supervisor 20 s late reported its
    find 25.5 m from the person that way, sigma 0.63 m). Until an answer shows a candidate on the track, its
    frames are followed and shown but give the find no position."""
    state = reach(S.AWAITING_SUPERVISOR, VERIFIED)
    assert state.target is not None
    box = state.target.box
    state, _ = step(state, tracked(5.0, box), VERIFIED)
    state, _ = step(state, tracked(5.03, box, ok=False, reason="collapsed"), VERIFIED)
    assert state.mode is S.LOST
    elsewhere = Box(box.x + 60, box.y, box.w, box.h)
    state, actions = step(state, tracked(5.1, elsewhere), VERIFIED)
    assert state.mode is S.AWAITING_SUPERVISOR and "ReportCandidate" in kinds(actions)  # re-acquired
    assert state.target is not None and state.target.fix_held and state.target.fix_s == 5.0
    frames = [tracked(5.2 + 0.1 * k, elsewhere) for k in range(61)]  # to 11.2 s
    state, actions = run(state, [*frames, TimerTick(11.25)], VERIFIED)
    assert state.mode is S.AWAITING_SUPERVISOR and state.target is not None and state.target.fix_s == 5.0
    # The re-verification finds nobody there: still held. One with the person on the track releases it.
    query = last_query(actions)
    assert query.purpose is QueryPurpose.REVERIFY
    state, _ = step(state, BackendAnswer(11.3, query.query_id, 339, ()), VERIFIED)
    assert state.target is not None and state.target.fix_held and state.target.fix_s == 5.0
    frames = [tracked(11.3 + 0.1 * k, elsewhere) for k in range(101)]  # to 21.3 s
    state, actions = run(state, [*frames, TimerTick(21.35)], VERIFIED)
    query = last_query(actions)
    assert query.purpose is QueryPurpose.REVERIFY and state.mode is S.AWAITING_SUPERVISOR
    state, _ = step(state, BackendAnswer(21.4, query.query_id, 640, (candidate(elsewhere, "c1"),)), VERIFIED)
    assert state.target is not None and not state.target.fix_held
    state, _ = step(state, tracked(21.45, elsewhere), VERIFIED)
    assert state.target is not None and state.target.fix_s == 21.45


def test_a_confirmed_target_re_acquired_after_a_loss_is_checked_with_each_report() -> None:
    """Once confirmed the track only reports its find (no query); after a re-acquisition that holds the find,
    each report asks the back-end about the track too, so the find follows the person again."""
    state = reach(S.CONFIRMED, VERIFIED)
    assert state.target is not None
    box = state.target.box
    t = state.now_s
    frames = [tracked(t + 0.1 * k, box) for k in range(1, 105)]
    state, actions = run(state, [*frames, TimerTick(t + 10.5)], VERIFIED)
    assert not [a for a in actions if isinstance(a, BackendQuery)]  # nothing held: report only
    state, _ = run(
        state, [tracked(t + 10.6, box, ok=False, reason="collapsed"), tracked(t + 10.7, box)], VERIFIED
    )
    assert state.mode is S.CONFIRMED and state.target is not None and state.target.fix_held
    frames = [tracked(t + 10.8 + 0.1 * k, box) for k in range(100)]
    state, actions = run(state, [*frames, TimerTick(t + 20.9)], VERIFIED)
    assert [a.status for a in actions if isinstance(a, ReportCandidate)] == ["confirmed"]
    query = last_query(actions)
    assert query.purpose is QueryPurpose.REVERIFY
    state, _ = step(state, BackendAnswer(t + 21.0, query.query_id, 900, (candidate(box, "c1"),)), VERIFIED)
    assert state.target is not None and not state.target.fix_held


@pytest.mark.parametrize("mode", [S.FOLLOWING, S.LOST])
def test_paper_policy_sends_no_track_checks_and_judges_nothing(mode: MissionState) -> None:
    state = reach(mode)
    _, actions = run(
        state,
        [tracked(1.9, FAR if mode is S.FOLLOWING else None, ok=mode is S.FOLLOWING), TimerTick(2.05)],
        CFG,
    )
    assert all(q.purpose is not QueryPurpose.TRACK_CHECK for q in actions if isinstance(q, BackendQuery))
    query = state.queries[-1][0] if state.queries else None
    if query is not None:
        _, actions = step(
            state, BackendAnswer(1.5, query, 45, (candidate(FAR, "n", Verdict.UNCERTAIN),)), CFG
        )
        assert not [a for a in actions if isinstance(a, JudgeCandidates)]


@pytest.mark.parametrize("mode", [S.ACQUIRING, S.SEARCHING])
def test_verified_judges_nothing_before_a_track_is_locked(mode: MissionState) -> None:
    state = reach(mode, VERIFIED)
    state, actions = step(state, TimerTick(1.05), VERIFIED)
    for qid, _ in state.queries:
        _, actions = step(
            state, BackendAnswer(1.06, qid, 31, (candidate(FAR, "x", Verdict.UNCERTAIN),)), VERIFIED
        )
        assert not [a for a in actions if isinstance(a, JudgeCandidates)]


def test_verified_lost_that_gave_up_judges_nothing() -> None:
    config = replace(VERIFIED, lost_action=LostAction.LOITER)
    state = reach(S.LOST, config)
    query = state.queries[-1][0]
    state, _ = run(
        state,
        [TimerTick(1.2 + config.lost_hold_after_s), TimerTick(1.3 + config.lost_action_after_s)],
        config,
    )
    assert state.lost_stage == 2
    _, actions = step(state, BackendAnswer(40.0, query, 45, (candidate(FAR),)), config)
    assert actions == ()


def test_acquisition_takes_the_candidate_the_back_end_places_where_the_prompt_says() -> None:
    """Acquisition from a prompt that places the target ("between the man in red and the man in green"):
    of several "yes", the one the back-end judged to stand there (`placement_ok`, backend.scene) is taken,
    even over a higher detector score; one judged not to stand there comes last."""
    start = StartMission("the man in the grey shirt walking between the man in red and the man in green")
    state, actions = step(reach(S.IDLE), cmd(0.1, start), CFG)
    left, middle, right = box_at(30, u=200), box_at(30, u=320), box_at(30, u=440)
    answer = BackendAnswer(
        1.0,
        last_query(actions).query_id,
        30,
        (
            replace(candidate(left, "left", Verdict.YES, 0.9), placement_ok=False),
            replace(candidate(middle, "middle", Verdict.YES, 0.5), placement_ok=True),
            replace(candidate(right, "right", Verdict.NO, 0.8), placement_ok=False),
        ),
    )
    init = [a for a in step(state, answer, CFG)[1] if isinstance(a, TrackerInit)][0]
    assert init.candidate_id == "middle"
    unplaced = tuple(replace(c, placement_ok=None) for c in answer.candidates)
    plain = step(state, replace(answer, candidates=unplaced), CFG)[1]  # nothing placed: the best score
    assert [a for a in plain if isinstance(a, TrackerInit)][0].candidate_id == "left"
