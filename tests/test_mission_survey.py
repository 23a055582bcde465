"""The search along the autopilot's own mission (ArduPilot AUTO, PX4 MISSION), table-driven: the companion
commands nothing while it only looks, takes the vehicle for a candidate only when the start allowed it and
the mission is flying, hands it back at the item it broke off at, and never proposes a rejected person or
a find again. Every state is reached by real `step` calls (docs/behavior.md, "Search along the mission")."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import pytest

from behaviors.actions import (
    Action,
    BackendQuery,
    FlightMode,
    GcsMessage,
    Hold,
    QueryPurpose,
    ReleaseControl,
    ReportCandidate,
    RequestMode,
    ResumeMission,
    SendSetpoint,
    TrackerInit,
    TrackerStop,
)
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, BackendUnreachable, Event, PilotTakeover, TimerTick
from behaviors.geolocation import offset_to_latlon
from behaviors.geometry import Box
from behaviors.mission import (
    MAX_PENDING,
    MissionState,
    State,
    awaiting_after,
    awaiting_decision,
    commanding,
    initial_state,
    step,
)
from behaviors.mission_commands import (
    AbortMission,
    ConfirmCandidate,
    RejectCandidate,
    StartMission,
    TrackRectangle,
)
from behaviors.mission_config import ConfirmAction, MissionConfig, SearchMode
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from tests.test_mission import (
    AT_STANDOFF,
    CAM,
    CFG,
    FAR,
    HEIGHT,
    PROMPT,
    box_at,
    candidate,
    cmd,
    kinds,
    tracked,
)
from tests.test_mission import reach as spot_reach

S = MissionState
BREAK_OFF = 7  # the survey item the autopilot is on when the candidate appears
# What moves the vehicle or its mode: never emitted while the search only looks.
COMMANDS = (SendSetpoint, Hold, RequestMode, ResumeMission, ReleaseControl)


def auto(t: float, item: int = BREAK_OFF, north_m: float = 0.0) -> Telemetry:
    """The autopilot flying its mission (ArduPilot AUTO) on `item`, `north_m` along its lane."""
    lat, lon = offset_to_latlon(47.0, 8.0, north_m, 0.0)
    return Telemetry(
        t, lat, lon, HEIGHT, mode="AUTO", mission_active=True, mission_item=item, mission_items=24
    )


def guided(t: float, item: int = BREAK_OFF) -> Telemetry:
    return Telemetry(t, 47.0, 8.0, HEIGHT, mode="GUIDED", offboard_active=True, mission_item=item)


# Another person after a rejection: not where the rejected one was proposed (from the same pose: FAR), where
# the rejection holds too (`Target.proposed_at`).
ELSEWHERE = box_at(25.0, u=80.0)


def _seen_and_left(state: State, t: float, cid: str) -> tuple[State, list[Action]]:
    """Looking only: the back-end's candidate `cid` at `t` (the survey 10 m further on for each second: a
    person of their own), put to the supervisor, then out of view and given up without a decision."""
    answer = BackendAnswer(t, state.queries[-1][0], int(t * 30), (candidate(FAR, cid),))
    give_up = TimerTick(t + 0.2 + CFG.lost_looking_s + 0.1)
    events = [
        auto(t - 0.05, north_m=10.0 * t),
        answer,
        tracked(t + 0.1, FAR),
        tracked(t + 0.2, None, ok=False),
    ]
    state, actions = run(state, [*events, give_up])
    assert state.mode is S.SEARCHING and state.pending[-1].candidate_id == cid
    return state, actions


def test_candidates_left_before_a_decision_all_await_it_the_newest_shown_first() -> None:
    """A supervisor slower than the survey: three candidates are left undecided. None is lost: the newest is
    the one shown (the page, candidate 0); once it is decided the one before is put to the supervisor again
    (GCS line and page), and the page decides any of them by id at any time."""
    state = reach(S.SEARCHING, engage=False)
    for k, cid in enumerate(("c1", "c2", "c3")):
        state, actions = _seen_and_left(state, 1.0 + 3.0 * k, cid)
    assert [p.candidate_id for p in state.pending] == ["c1", "c2", "c3"]
    shown = awaiting_decision(state)
    assert shown is not None and shown.candidate_id == "c3"
    assert [p.candidate_id for p in awaiting_after(state)] == ["c1", "c2"]  # the page: "2 more awaiting"
    # The page rejects c1, naming it, while c3 is shown: c3 stays shown.
    state, actions = step(state, cmd(20.0, RejectCandidate("c1")), CFG)
    assert (
        kinds(actions) == ["RememberRejection", "GcsMessage"]
        and state.rejections.entries[-1].candidate_id == "c1"
    )
    # The GCS confirms the one shown (candidate 0): a find; c2 awaits again and is said to.
    state, actions = step(state, cmd(21.0, ConfirmCandidate(by="gcs")), CFG)
    reports = [(a.status, a.candidate_id) for a in actions if isinstance(a, ReportCandidate)]
    assert reports == [("confirmed", "c3"), ("awaiting", "c2")]
    assert [p.candidate_id for p in state.pending] == ["c2"] and state.found.entries[-1].candidate_id == "c3"
    state, actions = step(state, cmd(22.0, RejectCandidate()), CFG)
    assert state.pending == () and awaiting_decision(state) is None
    assert not [a for a in actions if isinstance(a, ReportCandidate)]


def test_at_most_max_pending_await_out_of_view_and_the_oldest_is_said_to_be_dropped() -> None:
    state = reach(S.SEARCHING, engage=False)
    said: list[str] = []
    for k in range(MAX_PENDING + 1):
        state, actions = _seen_and_left(state, 1.0 + 3.0 * k, f"c{k}")
        said += [a.text for a in actions if isinstance(a, GcsMessage) and "no longer" in a.text]
    assert [p.candidate_id for p in state.pending] == [f"c{k}" for k in range(1, MAX_PENDING + 1)]
    assert said == ["no longer awaiting c0: too many"]
    assert state.dropped_undecided == ("c0",)  # the page says so too
    # A candidate tracked and awaiting in view is shown before all those left out of view.
    answer = BackendAnswer(40.0, state.queries[-1][0], 1200, (candidate(FAR, "c9"),))
    state, _ = run(state, [auto(39.9, north_m=400.0), answer, tracked(40.1, FAR)])
    assert awaiting_decision(state) is state.target and state.target is not None
    assert [p.candidate_id for p in awaiting_after(state)] == [f"c{k}" for k in range(1, MAX_PENDING + 1)]
    # A new mission starts with none waiting and none dropped.
    state, _ = run(state, [cmd(50.0, StartMission("a man in red", allow_engage=False))])
    assert state.pending == () and state.dropped_undecided == () and awaiting_after(state) == ()


def loiter(t: float) -> Telemetry:
    return Telemetry(t, 47.0, 8.0, HEIGHT, mode="LOITER", mission_item=BREAK_OFF)


def run(state: State, events: Sequence[Event], config: MissionConfig = CFG) -> tuple[State, list[Action]]:
    """Every action of every event, in order."""
    out: list[Action] = []
    for event in events:
        state, actions = step(state, event, config)
        out.extend(actions)
    return state, out


def reach(mode: MissionState, engage: bool = True, config: MissionConfig = CFG) -> State:
    """A search started while the autopilot flies its mission, driven into `mode` (taken over when engaged)."""
    state, _ = run(initial_state(config), [auto(0.0)], config)
    state, actions = run(state, [cmd(0.1, StartMission(PROMPT, allow_engage=engage))], config)
    assert state.along_mission
    if mode is S.SEARCHING:
        return state
    query = [a for a in actions if isinstance(a, BackendQuery)][-1]
    state, _ = run(state, [BackendAnswer(1.0, query.query_id, 30, (candidate(FAR),))], config)
    if engage:  # the autopilot took our GUIDED request
        state, _ = run(state, [guided(1.05)], config)
    if mode is S.ACQUIRING:
        return state
    state, _ = run(state, [tracked(1.1, FAR)], config)
    if mode is S.FOLLOWING:
        return state
    if mode is S.LOST:
        state, _ = run(state, [tracked(1.2, None, ok=False, reason="score")], config)
        return state
    state, _ = run(state, [tracked(1.2, AT_STANDOFF)], config)
    if mode is S.AWAITING_SUPERVISOR:
        return state
    if mode is S.CONFIRMED:
        state, _ = run(state, [cmd(1.3, ConfirmCandidate(by="supervisor page"))], config)
        return state
    state, _ = run(state, [cmd(1.3, RejectCandidate())], config)
    assert mode is S.REJECTED
    return state


@pytest.mark.parametrize("mode", [m for m in MissionState if m not in (S.IDLE, S.ABORTED)])
@pytest.mark.parametrize("engage", [True, False])
def test_every_state_is_reachable_along_the_mission(mode: MissionState, engage: bool) -> None:
    state = reach(mode, engage)
    if mode is S.FOLLOWING and not engage:  # looking only: the supervisor is asked on the first lock
        assert state.mode is S.AWAITING_SUPERVISOR
        return
    assert state.mode is mode and state.along_mission
    assert commanding(state) is (engage and mode is not S.SEARCHING)


# (name, engaged, start, event, expected mode, expected action kinds in order)
SURVEY: list[tuple[str, bool, MissionState, Event, MissionState, list[str]]] = [
    ("searching tick: no setpoint", True, S.SEARCHING, TimerTick(0.7), S.SEARCHING, ["BackendQuery"]),
    (
        "candidate: leave the mission",
        True,
        S.SEARCHING,
        BackendAnswer(1.0, 1, 30, (candidate(FAR),)),
        S.ACQUIRING,
        ["RequestMode", "GcsMessage", "SendSetpoint", "TrackerInit", "GcsMessage"],
    ),
    (
        "candidate without engage: track only",
        False,
        S.SEARCHING,
        BackendAnswer(1.0, 1, 30, (candidate(FAR),)),
        S.ACQUIRING,
        ["TrackerInit", "GcsMessage"],
    ),
    ("locked: follow", True, S.ACQUIRING, tracked(1.1, FAR), S.FOLLOWING, ["GcsMessage", "SendSetpoint"]),
    (
        "locked without engage: ask the supervisor at once",
        False,
        S.ACQUIRING,
        tracked(1.1, FAR),
        S.AWAITING_SUPERVISOR,
        ["GcsMessage", "ReportCandidate", "GcsMessage"],
    ),
    (
        "acquire timeout: back to the mission",
        True,
        S.ACQUIRING,
        TimerTick(4.5),
        S.SEARCHING,
        # the verified candidate awaits the supervisor out of view
        ["TrackerStop", "ResumeMission", "GcsMessage", "GcsMessage", "BackendQuery", "ReportCandidate"],
    ),
    (
        "acquire timeout without engage",
        False,
        S.ACQUIRING,
        TimerTick(4.5),
        S.SEARCHING,
        ["TrackerStop", "GcsMessage", "BackendQuery", "ReportCandidate"],
    ),
    (
        "reject",
        True,
        S.AWAITING_SUPERVISOR,
        cmd(1.3, RejectCandidate()),
        S.REJECTED,
        ["SendSetpoint", "TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "reject without engage",
        False,
        S.AWAITING_SUPERVISOR,
        cmd(1.3, RejectCandidate()),
        S.REJECTED,
        ["TrackerStop", "RememberRejection", "GcsMessage"],
    ),
    (
        "rejected tick: back to the mission",
        True,
        S.REJECTED,
        TimerTick(1.4),
        S.SEARCHING,
        ["ResumeMission", "GcsMessage", "GcsMessage", "BackendQuery"],
    ),
    (
        "rejected tick without engage",
        False,
        S.REJECTED,
        TimerTick(1.4),
        S.SEARCHING,
        ["GcsMessage", "BackendQuery"],
    ),
    (
        "tracker lost: stop",
        True,
        S.FOLLOWING,
        tracked(1.2, None, ok=False),
        S.LOST,
        ["SendSetpoint", "GcsMessage", "BackendQuery"],
    ),
    (
        "tracker lost without engage",
        False,
        S.AWAITING_SUPERVISOR,
        tracked(1.3, None, ok=False),
        S.LOST,
        ["GcsMessage", "BackendQuery"],
    ),
    ("lost hold", True, S.LOST, TimerTick(2.25), S.LOST, ["Hold", "BackendQuery"]),
    ("lost without engage: no hold", False, S.LOST, TimerTick(2.25), S.LOST, ["BackendQuery"]),
    (
        "lost too long: back to the mission",
        True,
        S.LOST,
        TimerTick(1.2 + CFG.lost_resume_after_s),
        S.SEARCHING,
        ["TrackerStop", "ResumeMission", "GcsMessage", "GcsMessage", "BackendQuery"],
    ),
    (
        "lost too long without engage",
        False,
        S.LOST,
        TimerTick(1.2 + CFG.lost_resume_after_s),
        S.SEARCHING,
        ["TrackerStop", "GcsMessage", "BackendQuery"],
    ),
    (
        "confirm",
        True,
        S.AWAITING_SUPERVISOR,
        cmd(1.3, ConfirmCandidate(by="gcs")),
        S.CONFIRMED,
        ["ReportCandidate", "GcsMessage"],
    ),
    (
        "back-end lost while engaged: hold",
        True,
        S.FOLLOWING,
        BackendUnreachable(1.2),
        S.FOLLOWING,
        ["Hold", "GcsMessage"],
    ),
    (
        "back-end lost while looking only",
        False,
        S.AWAITING_SUPERVISOR,
        BackendUnreachable(1.3),
        S.AWAITING_SUPERVISOR,
        ["GcsMessage"],
    ),
    (
        "abort while engaged: let go",
        True,
        S.FOLLOWING,
        cmd(1.2, AbortMission()),
        S.ABORTED,
        ["ReleaseControl", "TrackerStop", "GcsMessage"],
    ),
    (
        "abort while looking only: nothing to let go",
        False,
        S.SEARCHING,
        cmd(1.2, AbortMission()),
        S.ABORTED,
        ["GcsMessage"],
    ),
    (
        "pilot switches away from GUIDED while engaged: takeover",
        True,
        S.FOLLOWING,
        loiter(1.2),
        S.ABORTED,
        ["ReleaseControl", "TrackerStop", "GcsMessage"],
    ),
    (
        "pilot switches the engaged vehicle to AUTO: takeover",
        True,
        S.AWAITING_SUPERVISOR,
        auto(1.3),
        S.ABORTED,
        ["ReleaseControl", "TrackerStop", "GcsMessage"],
    ),
    (
        "pilot switches AUTO to LOITER while looking only: the search goes on",
        False,
        S.SEARCHING,
        loiter(1.2),
        S.SEARCHING,
        [],
    ),
    (
        "operator box: leave the mission",
        True,
        S.SEARCHING,
        cmd(1.2, TrackRectangle(FAR)),
        S.FOLLOWING,
        ["RequestMode", "GcsMessage", "TrackerInit", "GcsMessage"],
    ),
]


@pytest.mark.parametrize(
    ("name", "engage", "start", "event", "expected", "expected_kinds"), SURVEY, ids=[t[0] for t in SURVEY]
)
def test_survey_transition_table(
    name: str,
    engage: bool,
    start: MissionState,
    event: Event,
    expected: MissionState,
    expected_kinds: list[str],
) -> None:
    state, actions = step(reach(start, engage), event, CFG)
    assert state.mode is expected, name
    assert kinds(actions) == expected_kinds, name


def test_the_start_in_auto_commands_nothing_even_with_engage_allowed() -> None:
    state, actions = run(initial_state(CFG), [auto(0.0), cmd(0.1, StartMission(PROMPT, allow_engage=True))])
    assert state.mode is S.SEARCHING and state.along_mission and not commanding(state)
    assert kinds(actions) == ["GcsMessage", "BackendQuery"]
    for i in range(1, 60):
        state, actions = run(state, [auto(0.1 * i, item=BREAK_OFF + i // 20), TimerTick(0.1 * i)])
        assert not any(isinstance(a, COMMANDS) for a in actions)


def test_the_candidate_takes_the_vehicle_and_remembers_the_item() -> None:
    state, actions = step(reach(S.SEARCHING), BackendAnswer(1.0, 1, 30, (candidate(FAR),)), CFG)
    assert actions[0] == RequestMode(FlightMode.OFFBOARD, "candidate")
    assert (
        isinstance(actions[1], GcsMessage)
        and actions[1].text == f"LEFT MISSION at item {BREAK_OFF}: candidate"
    )
    assert actions[2] == SendSetpoint(actions[2].setpoint) and actions[2].setpoint.horizontal_speed == 0.0
    assert state.engaged and state.break_off_item == BREAK_OFF and commanding(state)


def test_reject_hands_the_vehicle_back_at_the_break_off_item_and_sees_it_resume() -> None:
    state = reach(S.REJECTED)
    state, actions = step(state, TimerTick(1.4), CFG)
    assert actions[0] == ResumeMission(BREAK_OFF, "searching again")
    assert GcsMessage(f"RESUMING MISSION at item {BREAK_OFF}") in actions
    assert state.mode_requested is FlightMode.MISSION and not state.engaged and not commanding(state)
    # GUIDED -> AUTO is our own request: no takeover; the resume is told with both items.
    state, actions = step(state, auto(1.5), CFG)
    assert state.mode is S.SEARCHING and state.mode_requested is None
    assert actions == (GcsMessage(f"MISSION RESUMED at item {BREAK_OFF} (left at {BREAK_OFF})"),)
    _, actions = step(state, TimerTick(2.5), CFG)
    assert kinds(actions) == ["BackendQuery"]


def test_a_candidate_found_while_the_mission_is_handed_back_takes_the_vehicle_once_it_flies_it() -> None:
    """The search's next answer can come before the autopilot shows the mission again (the real PX4: a
    candidate 0.1 s after the rejection, MISSION shown 0.3 s later). The vehicle is not the mission's yet,
    so it is not taken then; once the mission shows, it is, at the item the mission is on: before, the
    candidate was only looked at while the survey flew on, lost from view, and confirmed while lost."""
    state, _ = step(reach(S.REJECTED), TimerTick(1.4), CFG)
    assert state.mode_requested is FlightMode.MISSION
    query = state.queries[-1][0]
    state, actions = step(state, BackendAnswer(1.45, query, 40, (candidate(ELSEWHERE, "c2"),)), CFG)
    assert state.mode is S.ACQUIRING and not state.engaged
    assert not any(isinstance(a, COMMANDS) for a in actions)
    state, actions = step(state, auto(1.5, item=BREAK_OFF + 1), CFG)
    assert actions == (
        GcsMessage(f"MISSION RESUMED at item {BREAK_OFF + 1} (left at {BREAK_OFF})"),
        RequestMode(FlightMode.OFFBOARD, "candidate"),
        GcsMessage(f"LEFT MISSION at item {BREAK_OFF + 1}: candidate"),
        SendSetpoint(Setpoint.zero()),
    )
    assert state.engaged and state.break_off_item == BREAK_OFF + 1 and commanding(state)
    assert state.mode is S.ACQUIRING and state.target is not None and state.target.candidate_id == "c2"


def test_the_pilot_choosing_a_mode_meanwhile_is_left_alone() -> None:
    state, _ = step(reach(S.REJECTED), TimerTick(1.4), CFG)
    state, actions = step(state, loiter(1.5), CFG)  # the pilot, before the autopilot took AUTO
    assert state.mode is S.SEARCHING and actions == ()
    # A candidate now is only reported: the vehicle is the pilot's, not the mission's.
    state, actions = step(
        state, BackendAnswer(1.6, state.queries[-1][0], 40, (candidate(ELSEWHERE, "c2"),)), CFG
    )
    assert state.mode is S.ACQUIRING and not any(isinstance(a, COMMANDS) for a in actions)


def test_no_engage_no_command_ever() -> None:
    """Without allow_engage a whole search along the mission (a candidate rejected, one lost, one confirmed,
    searching on) never emits a setpoint, hold, mode request or hand-back."""
    config = replace(CFG, on_confirm=ConfirmAction.SURVEY)
    state, out = run(initial_state(config), [auto(0.0), cmd(0.1, StartMission(PROMPT))], config)
    t = 0.1
    for round_, end in enumerate(("reject", "lost", "confirm")):
        t += 0.5
        box = box_at(20.0, u=100.0 + 230.0 * round_)  # three people about 11 m apart
        query = [q for q, _ in state.queries][-1]
        events: list[Event] = [
            auto(t, BREAK_OFF + round_),
            BackendAnswer(t, query, 30 + round_, (candidate(box, f"c{round_}"),)),
            tracked(t + 0.1, box),
            TimerTick(t + 0.2),
        ]
        if end == "reject":
            events.append(cmd(t + 0.3, RejectCandidate()))
        elif end == "lost":
            events += [tracked(t + 0.3, None, ok=False), TimerTick(t + 0.4 + config.lost_resume_after_s)]
            t += config.lost_resume_after_s
        else:
            events.append(cmd(t + 0.3, ConfirmCandidate(by="gcs")))
        events += [TimerTick(t + 0.5 + k * 0.1) for k in range(10)]
        state, actions = run(state, events, config)
        out += actions
        t += 1.5
    reports = [(a.status, a.candidate_id) for a in out if isinstance(a, ReportCandidate)]
    # c1, lost before a decision, still awaits one: once c2 is decided it is put to the supervisor again.
    assert reports == [
        ("awaiting", "c0"),
        ("awaiting", "c1"),
        ("awaiting", "c2"),
        ("confirmed", "c2"),
        ("awaiting", "c1"),
    ]
    assert [p.candidate_id for p in state.pending] == ["c1"]
    assert not [a for a in out if isinstance(a, COMMANDS)]
    assert state.mode is S.SEARCHING and len(state.found.entries) == 1 and len(state.rejections.entries) == 1


def test_the_rejected_person_is_never_proposed_again_from_another_lane() -> None:
    """The decoy lies 20 m ahead of the drone on item 7; rejected; the survey flies on. From the next lane
    (80 m further north, looking back south) the same spot is seen in another part of the image under
    another candidate id: matched by place, from where the camera was when the keyframe was taken."""
    state = reach(S.REJECTED)
    state, _ = run(state, [TimerTick(1.4), auto(1.5)])
    decoy = state.rejections.entries[-1].position
    assert decoy is not None
    # 40 m further along, flying back: seen 20 m ahead again, i.e. 60 m north of the first view's pose.
    back = replace(auto(30.0, item=BREAK_OFF + 2, north_m=decoy.north_m + 20.0), yaw=math.pi)
    far_on = auto(31.0, item=BREAK_OFF + 3, north_m=-100.0)  # where the drone is when the answer arrives
    query = state.queries[-1][0]
    seen_again = BackendAnswer(31.0, query, 900, (candidate(box_at(20.0, u=330), "c77"),), pose=back)
    state, _ = run(state, [back, far_on])
    after, actions = step(state, seen_again, CFG)
    assert after.mode is S.SEARCHING and actions == ()
    # Located from the latest telemetry instead, it would have passed for someone else.
    assert step(state, replace(seen_again, pose=None), CFG)[0].mode is S.ACQUIRING


@pytest.mark.parametrize("engage", [True, False])
def test_confirm_with_on_confirm_survey_reports_the_find_and_searches_on(engage: bool) -> None:
    config = replace(CFG, on_confirm=ConfirmAction.SURVEY)
    state = reach(S.AWAITING_SUPERVISOR, engage, config)
    state, actions = step(state, cmd(1.3, ConfirmCandidate(by="supervisor page")), config)
    report = [a for a in actions if isinstance(a, ReportCandidate)]
    assert state.mode is S.CONFIRMED and len(report) == 1
    assert report[0].status == "confirmed" and report[0].confirmed_by == "supervisor page"
    assert report[0].position is not None
    state, actions = step(state, TimerTick(1.4), config)
    expected = (
        ["TrackerStop"] + (["ResumeMission", "GcsMessage"] if engage else []) + ["GcsMessage", "BackendQuery"]
    )
    assert state.mode is S.SEARCHING and kinds(actions) == expected
    # The find is not proposed again, under whatever id, while the search flies on.
    answer = BackendAnswer(1.6, state.queries[-1][0], 50, (candidate(AT_STANDOFF, "c9"),), pose=guided(1.2))
    assert step(state, answer, config)[0].mode is S.SEARCHING


def test_a_confirmed_target_followed_after_keeps_the_lost_rules() -> None:
    state = reach(S.CONFIRMED)  # on_confirm = follow: the companion flies after the find
    state, _ = step(state, tracked(1.4, None, ok=False), CFG)
    state, actions = run(state, [TimerTick(1.4 + 0.1 * i) for i in range(1, 150)])
    assert state.mode is S.LOST and Hold("target lost") in actions
    assert not any(isinstance(a, ResumeMission) for a in actions)


@pytest.mark.parametrize("along", [True, False])
def test_on_confirm_hold_lets_go_and_the_hold_mode_is_no_takeover(along: bool) -> None:
    config = replace(CFG, on_confirm=ConfirmAction.HOLD)
    if along:
        state = reach(S.AWAITING_SUPERVISOR, True, config)
    else:
        state = spot_reach(S.AWAITING_SUPERVISOR, config, allow_engage=True)
    state, actions = step(state, cmd(1.3, ConfirmCandidate()), config)
    assert ReleaseControl("confirmed: hold") in actions and not commanding(state)
    state, actions = step(state, loiter(1.4), config)  # the hold mode the release asked for
    assert state.mode is S.CONFIRMED and actions == ()
    state, actions = step(state, tracked(1.5, AT_STANDOFF), config)
    assert state.mode is S.CONFIRMED and not any(isinstance(a, COMMANDS) for a in actions)


def test_a_restart_while_engaged_hands_the_vehicle_back() -> None:
    state = reach(S.FOLLOWING)
    state, actions = step(state, cmd(1.2, StartMission(PROMPT, allow_engage=True)), CFG)
    assert state.mode is S.SEARCHING and state.along_mission
    assert kinds(actions)[:2] == ["TrackerStop", "ResumeMission"]


@pytest.mark.parametrize(
    ("search", "telemetry", "along"),
    [
        (SearchMode.AUTO, auto(0.0), True),
        (SearchMode.AUTO, guided(0.0), False),
        (SearchMode.AUTO, loiter(0.0), False),
        (SearchMode.MISSION, loiter(0.0), True),
        (SearchMode.SPOT, auto(0.0), False),
    ],
)
def test_search_option_decides_where_the_search_looks(
    search: SearchMode, telemetry: Telemetry, along: bool
) -> None:
    config = replace(CFG, search=search)
    state, actions = run(
        initial_state(config), [telemetry, cmd(0.1, StartMission(PROMPT, allow_engage=True))], config
    )
    assert state.along_mission is along
    # On the spot: offboard requested at the start (unless already in it) and the search setpoint streams.
    assert any(isinstance(a, SendSetpoint) for a in actions) is (not along)
    assert any(isinstance(a, RequestMode) for a in actions) is (not along and not telemetry.offboard_active)


def test_search_options_come_from_the_behavior_section() -> None:
    config = MissionConfig.from_sections(
        behavior={"search": "mission", "lost_resume_after_s": 4.0, "on_confirm": "survey"},
        control={},
        safety={},
        camera={},
        backend={},
    )
    assert config.search is SearchMode.MISSION and config.lost_resume_after_s == 4.0
    assert config.on_confirm is ConfirmAction.SURVEY
    assert MissionConfig().search is SearchMode.AUTO


def test_takeover_event_while_looking_only_aborts_without_letting_go() -> None:
    state, actions = step(reach(S.AWAITING_SUPERVISOR, engage=False), PilotTakeover(2.0, "LOITER"), CFG)
    assert state.mode is S.ABORTED and kinds(actions) == ["TrackerStop", "GcsMessage"]


def test_hand_back_to_mission_is_not_sent_without_a_break_off() -> None:
    state = reach(S.ACQUIRING, engage=False)
    _, actions = step(state, TimerTick(4.5), CFG)
    assert not any(isinstance(a, (ResumeMission, TrackerInit)) for a in actions)
    assert TrackerStop("acquire timeout") in actions


def test_the_memories_keep_the_best_estimate_not_the_last() -> None:
    """A surveying drone flies away from a find: the track's last estimates come from the view's far edge
    and drift. The found memory (and the rejection memory) keep the estimate with the smallest error."""
    config = replace(CFG, on_confirm=ConfirmAction.SURVEY)
    state = reach(S.AWAITING_SUPERVISOR, engage=False, config=config)  # locked at the standoff, 12 m
    assert state.target is not None and state.target.position is not None
    near, near_s = state.target.position, state.target.position_s
    state, _ = run(state, [tracked(1.25, box_at(45.0, u=620.0))], config)  # the far edge, 45 m off
    assert state.target is not None and state.target.position is not None
    assert state.target.position.sigma_m > near.sigma_m and state.target.fix == near
    assert state.target.position_s == 1.25 and state.target.fix_s == near_s < 1.25
    state, actions = run(state, [cmd(1.3, ConfirmCandidate(by="gcs")), TimerTick(1.4)], config)
    assert state.mode is S.SEARCHING and state.found.entries[-1].position == near
    # The find says when that estimate was seen, not when it was confirmed or last tracked.
    report = next(a for a in actions if isinstance(a, ReportCandidate) and a.status == "confirmed")
    assert report.position == near and report.position_s == near_s
    # Seen again where it was confirmed, under another id: not proposed again.
    answer = BackendAnswer(1.6, state.queries[-1][0], 60, (candidate(AT_STANDOFF, "c9"),), pose=auto(1.2))
    assert step(state, answer, config)[0].mode is S.SEARCHING


def test_a_followed_person_who_walked_on_is_reported_where_they_are() -> None:
    """The drone follows the person 10 m on before the supervisor confirms, keeping its standoff: the
    estimates stay as good as the first, so the find is the latest, not the first (before, the smallest
    sigma won: a supervisor deciding after 10 s got the follow scenario's find 15 m from the person)."""
    state = reach(S.AWAITING_SUPERVISOR)
    assert state.target is not None and state.target.position is not None
    first = state.target.position
    lat, lon = offset_to_latlon(47.0, 8.0, 10.0, 0.0)
    moved = Telemetry(1.25, lat, lon, HEIGHT, mode="GUIDED", offboard_active=True, mission_item=BREAK_OFF)
    state, _ = run(state, [moved, tracked(1.28, box_at(CFG.standoff_m + 2.0))])  # a little behind
    assert state.target is not None and state.target.position is not None
    latest = state.target.position
    assert first.sigma_m < latest.sigma_m < 1.5 * first.sigma_m and latest.lat_deg > first.lat_deg
    state, actions = run(state, [cmd(1.3, ConfirmCandidate(by="gcs"))])
    report = next(a for a in actions if isinstance(a, ReportCandidate))
    assert report.status == "confirmed" and report.position == latest and report.position_s == 1.28


@pytest.mark.parametrize("decision", ["confirm", "reject"])
def test_a_reported_candidate_out_of_view_still_awaits_the_supervisor(decision: str) -> None:
    """Looking only, the survey flies past a candidate before the supervisor decides: it is given up after
    `lost_looking_s` (the search goes on) but keeps awaiting the decision, which still counts."""
    state = reach(S.AWAITING_SUPERVISOR, engage=False)
    state, _ = run(state, [tracked(1.3, None, ok=False)])
    assert state.mode is S.LOST
    state, _ = run(state, [TimerTick(1.3 + CFG.lost_looking_s - 0.1)])
    assert state.mode is S.LOST  # not yet
    state, actions = run(state, [TimerTick(1.3 + CFG.lost_looking_s + 0.1)])
    assert state.mode is S.SEARCHING and [p.candidate_id for p in state.pending] == ["c1"]
    assert not any(isinstance(a, COMMANDS) for a in actions)
    if decision == "confirm":
        state, actions = step(state, cmd(5.0, ConfirmCandidate("c1", by="supervisor page")), CFG)
        report = [a for a in actions if isinstance(a, ReportCandidate)]
        assert report and report[0].status == "confirmed" and report[0].confirmed_by == "supervisor page"
        assert report[0].position is not None and state.found.entries[-1].candidate_id == "c1"
        assert report[0].position_s < 1.3  # from before it went out of view, and says so
    else:
        state, actions = step(state, cmd(5.0, RejectCandidate()), CFG)
        assert kinds(actions) == ["RememberRejection", "GcsMessage"] and state.rejections.entries
    assert state.mode is S.SEARCHING and state.pending == ()
    # Decided once: a second decision finds nothing awaiting.
    _, actions = step(state, cmd(5.1, ConfirmCandidate("c1")), CFG)
    assert kinds(actions) == ["GcsMessage"]


BESIDE = box_at(40.0, u=CAM.cx + 220.0)  # another person in the same keyframe, about 9 m from the tracked one


def _search_beside(state: State, t: float, *dets: Detection) -> tuple[State, list[Action]]:
    """The tracker still on its candidate, the tick at `t` sends the search's query (whole frame, final
    verdicts only); the back-end answers `dets` on that keyframe."""
    state, actions = run(state, [tracked(t - 0.05, AT_STANDOFF), TimerTick(t)])
    (query,) = [a for a in actions if isinstance(a, BackendQuery)]
    assert query.purpose is QueryPurpose.SEARCH and query.roi is None and not query.early_answer
    return run(state, [BackendAnswer(t + 0.2, query.query_id, int(t * 30), dets)])


def test_looking_only_the_search_goes_on_beside_the_candidate_awaiting_the_supervisor() -> None:
    """Looking only, the survey flies on while the supervisor decides on the tracked candidate: the search
    goes on in the same keyframes, and another verified person in view is queued for the supervisor after
    it (placed and cropped from its keyframe; the GCS hears "queued": its candidate 0 is still the tracked
    one). The tracker stays on the one being decided; ids are per keyframe, so the same people are known
    again by place."""
    state = reach(S.AWAITING_SUPERVISOR, engage=False)
    state, actions = _search_beside(state, 1.7, candidate(AT_STANDOFF, "k1"), candidate(BESIDE, "c2"))
    assert kinds(actions) == ["ReportCandidate"]  # no JudgeCandidates, no TrackerInit: the track stays
    (report,) = actions
    assert isinstance(report, ReportCandidate)
    assert (report.candidate_id, report.status, report.keyframe_id) == ("c2", "queued", 51)
    assert report.box == BESIDE and report.position is not None
    assert state.mode is S.AWAITING_SUPERVISOR and state.target is not None
    assert state.target.candidate_id == "c1" and awaiting_decision(state) is state.target
    assert [p.candidate_id for p in awaiting_after(state)] == ["c2"]
    # The next keyframes show both again under new ids, and a "no" and a third person under an "uncertain"
    # the verifier judged: nobody new is proposed.
    state, actions = _search_beside(
        state,
        2.3,
        candidate(AT_STANDOFF, "k3"),
        candidate(BESIDE, "k4"),
        candidate(box_at(40.0, u=CAM.cx - 220.0), "k5", verdict=Verdict.NO),
        candidate(box_at(60.0, u=CAM.cx - 200.0), "k6", verdict=Verdict.UNCERTAIN),
    )
    assert actions == [] and len(state.pending) == 1
    # The supervisor rejects the one tracked: the one beside is put to the supervisor; confirmed, it is a
    # find where its keyframe placed it.
    state, actions = run(state, [cmd(3.0, RejectCandidate())])
    shown = awaiting_decision(state)
    assert shown is not None and shown.candidate_id == "c2"
    assert [(a.status, a.candidate_id) for a in actions if isinstance(a, ReportCandidate)] == [
        ("awaiting", "c2")
    ]
    state, actions = run(state, [TimerTick(3.1), cmd(3.2, ConfirmCandidate(by="supervisor page"))])
    (find,) = [a for a in actions if isinstance(a, ReportCandidate) and a.status == "confirmed"]
    assert find.candidate_id == "c2" and find.position == report.position
    assert state.pending == () and state.found.entries[-1].candidate_id == "c2"


def test_looking_only_the_search_goes_on_while_a_confirmed_find_is_held_in_view() -> None:
    """Issue 43: looking only, the survey flies on after the supervisor confirmed the find while the tracker
    still holds it in view; the search goes on in the same keyframes (whole-frame SEARCH queries: they count
    as searched, so a fleet going on after the find has no hole there), and another verified person in view
    is the one awaiting the supervisor now (the find is decided)."""
    state = reach(S.CONFIRMED, engage=False)
    assert state.mode is S.CONFIRMED and state.along_mission and not state.engaged
    state, actions = _search_beside(state, 1.7, candidate(AT_STANDOFF, "k1"), candidate(BESIDE, "c2"))
    (report,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert (report.candidate_id, report.status) == ("c2", "awaiting")
    assert state.mode is S.CONFIRMED and awaiting_decision(state) is not None
    assert awaiting_decision(state).candidate_id == "c2"  # type: ignore[union-attr]
    engaged = reach(S.CONFIRMED, engage=True)
    _, actions = run(engaged, [guided(1.7), TimerTick(1.7)])
    assert not [a for a in actions if isinstance(a, BackendQuery) and a.purpose is QueryPurpose.SEARCH]
    # The find itself, where it stands but off the tracker's box on that keyframe (the tracker drifted), is no
    # new candidate: a second find of the same person.
    state = reach(S.CONFIRMED, engage=False)
    assert state.target is not None and state.target.position is not None
    state, actions = run(state, [tracked(1.65, AT_STANDOFF), TimerTick(1.7)])
    (query,) = [a for a in actions if isinstance(a, BackendQuery)]
    drifted = BackendAnswer(1.9, query.query_id, 51, (candidate(AT_STANDOFF, "k7"),), track_box=BESIDE)
    _, actions = run(state, [drifted])
    assert not [a for a in actions if isinstance(a, ReportCandidate)], actions


def test_the_search_beside_the_tracked_candidate_only_looking_and_only_awaiting() -> None:
    """Engaged, the camera is pointed at the candidate: no search beside it (the track checks stay). Looking
    only, a person the supervisor rejected is not proposed beside; nor is anyone while the candidate is lost
    (its re-detection runs), nor from the fast stage's early verdicts."""
    engaged = reach(S.AWAITING_SUPERVISOR, engage=True)
    _, actions = run(engaged, [guided(1.7), TimerTick(1.7)])
    assert not [a for a in actions if isinstance(a, BackendQuery) and a.purpose is QueryPurpose.SEARCH]
    state = reach(S.AWAITING_SUPERVISOR, engage=False)
    state, _ = run(state, [cmd(1.5, RejectCandidate("c9"))])  # the page rejects someone by id
    state, actions = _search_beside(state, 1.7, candidate(BESIDE, "c9"))
    assert actions == [] and state.pending == ()
    early_state, actions = run(state, [tracked(2.25, AT_STANDOFF), TimerTick(2.3)])
    (query,) = [a for a in actions if isinstance(a, BackendQuery)]
    early = BackendAnswer(2.4, query.query_id, 69, (candidate(BESIDE, "c3"),), final=False)
    early_state, actions = run(early_state, [early])
    assert actions == [] and early_state.pending == ()
    lost, actions = run(state, [tracked(2.0, None, ok=False, reason="score"), TimerTick(2.6)])
    assert lost.mode is S.LOST
    assert {a.purpose for a in actions if isinstance(a, BackendQuery)} == {QueryPurpose.REDETECT}


def test_the_tracked_candidate_is_known_by_its_box_on_the_keyframe_so_a_neighbour_is_queued() -> None:
    """The tracker's box on the keyframe (`BackendAnswer.track_box`) says which candidate is the tracked one;
    a person standing 3 m from it is queued. Without that box the tracked one is known by where it stands:
    of the keyframe's candidates the nearest to that place (two people in one keyframe are two people), so
    the neighbour is queued too. Alone in a keyframe, the neighbour within the radius is taken for it."""
    near = box_at(CFG.standoff_m + 3.0)
    state = reach(S.AWAITING_SUPERVISOR, engage=False)
    for pair in ((candidate(AT_STANDOFF, "k1"), candidate(near, "k2")), (candidate(near, "k2"),)):
        beside, actions = _search_beside(state, 1.7, *pair)
        queued = [(a.candidate_id, a.status) for a in actions if isinstance(a, ReportCandidate)]
        assert queued == ([("k2", "queued")] if len(pair) == 2 else []), pair
    state, actions = run(state, [tracked(1.65, AT_STANDOFF), TimerTick(1.7)])
    (query,) = [a for a in actions if isinstance(a, BackendQuery)]
    dets = (candidate(AT_STANDOFF, "k1"), candidate(near, "k2"))
    state, actions = run(state, [BackendAnswer(1.9, query.query_id, 51, dets, track_box=AT_STANDOFF)])
    assert [(a.candidate_id, a.status) for a in actions if isinstance(a, ReportCandidate)] == [
        ("k2", "queued")
    ]


def test_a_candidate_awaiting_a_decision_out_of_view_is_not_proposed_twice_when_seen_again() -> None:
    """The back-end's ids are per keyframe: one already awaiting the supervisor (left undecided, or queued
    beside another) and seen again where it was is not tracked and put to the supervisor a second time."""
    state = reach(S.SEARCHING, engage=False)
    state, _ = _seen_and_left(state, 1.0, "c1")
    again = BackendAnswer(
        4.0, state.queries[-1][0], 120, (candidate(FAR, "c5"),), pose=auto(3.9, north_m=10.0)
    )
    same, actions = run(state, [again])
    assert same.mode is S.SEARCHING and not [a for a in actions if isinstance(a, TrackerInit)]
    # Seen where the vehicle now is (its telemetry with the keyframe's pose): still in view, tracked.
    elsewhere = replace(again, pose=auto(3.9, north_m=40.0))
    other, actions = run(state, [auto(3.95, north_m=40.0), elsewhere])
    assert other.mode is S.ACQUIRING
    assert [a.candidate_id for a in actions if isinstance(a, TrackerInit)] == ["c5"]


# At the image's bottom edge (its foot 10 px above it), the person nearest the vehicle: the first to leave the view.
AT_BOTTOM = Box.from_center(CAM.cx, CAM.height - 30.0, 16.0, 40.0)


@pytest.mark.parametrize("engage", [False, True])
@pytest.mark.parametrize(
    ("flown_m", "box", "tracked_now"),
    [
        (0.0, AT_BOTTOM, True),  # the vehicle has not moved since the keyframe: in view
        (5.0, AT_BOTTOM, False),  # flown on 5 m: the person is behind the image's bottom edge
        (5.0, FAR, True),  # seen 25 m ahead: 20 m ahead now, in view
        (40.0, FAR, False),  # flown past them
    ],
)
def test_a_candidate_that_left_the_view_before_its_answer_awaits_the_supervisor_without_a_track(
    engage: bool, flown_m: float, box: Box, tracked_now: bool
) -> None:
    """The survey flies on while a keyframe is verified. A tracker started on a keyframe whose person has left
    the view since catches up onto the background (a seeded search: the described person proposed from the
    image's bottom edge, the tracker on grass when the supervisor looked, rejected as "none"). Such a candidate
    is not tracked and the vehicle is not taken: it awaits the supervisor out of view, placed from its keyframe,
    decided on the keyframe's crop; a confirmation is a find there."""
    state = reach(S.SEARCHING, engage=engage)
    query = state.queries[-1][0]
    answer = BackendAnswer(1.1, query, 33, (candidate(box, "e1"),), pose=auto(0.9))
    early = replace(answer, final=False)
    state, _ = run(state, [auto(0.9), auto(1.05, north_m=flown_m)])
    if tracked_now:
        new, actions = run(state, [answer])
        assert new.mode is S.ACQUIRING and [
            a.candidate_id for a in actions if isinstance(a, TrackerInit)
        ] == ["e1"]
        return
    # The fast stage's answer starts nothing; the final one puts it to the supervisor.
    same, actions = run(state, [early])
    assert same.mode is S.SEARCHING and actions == [] and same.pending == ()
    state, actions = run(state, [answer])
    assert state.mode is S.SEARCHING and not commanding(state)
    assert not [a for a in actions if isinstance(a, (TrackerInit, *COMMANDS))]
    reports = [(a.candidate_id, a.status, a.keyframe_id) for a in actions if isinstance(a, ReportCandidate)]
    assert reports == [("e1", "awaiting", 33)]
    assert [a.text for a in actions if isinstance(a, GcsMessage)] == ["e1 out of view: decide on keyframe"]
    shown = awaiting_decision(state)
    assert shown is not None and shown.candidate_id == "e1" and shown.position is not None
    placed = shown.position
    state, actions = run(state, [cmd(2.0, ConfirmCandidate(by="gcs"))])
    (found,) = [a for a in actions if isinstance(a, ReportCandidate)]
    assert found.status == "confirmed" and found.position == placed
    assert state.pending == () and state.found.entries[-1].candidate_id == "e1"
