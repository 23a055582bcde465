"""The follow-and-await-supervisor mission: a pure state machine `step(state, event, config)`.

Every decision the companion makes about the mission is here; the main loop only turns inputs into
`behaviors.events` and executes the returned `behaviors.actions` in order. No clock, socket or thread:
times arrive on the events. States and transitions are drawn and explained in docs/behavior.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import Enum

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
    ResumeMission,
    SendSetpoint,
    TrackerInit,
    TrackerStop,
)
from behaviors.candidate_selection import (
    alike,
    c_box,
    select_by_c_box,
    select_first_acquisition,
    settle_early_choice,
)
from behaviors.control_law import ControlState, FollowGoal, estimate_distance, follow_step
from behaviors.decision_guard import DecisionGuard, observe, too_new
from behaviors.detection import Detection, Verdict
from behaviors.events import (
    AutopilotLinkLost,
    BackendAnswer,
    BackendUnreachable,
    CompanionHold,
    Event,
    FleetRejections,
    GcsCommand,
    PilotTakeover,
    RejectionShared,
)
from behaviors.geolocation import GeoEstimate, locate_box
from behaviors.geometry import Box, iou
from behaviors.live_view import in_view_now
from behaviors.mission_commands import (
    AbortMission,
    ConfirmCandidate,
    RejectCandidate,
    StartMission,
    StopTracking,
    TrackRectangle,
)
from behaviors.mission_config import ConfirmAction, LostAction, MissionConfig, SearchMode
from behaviors.query_region import around, redetect_region
from behaviors.rejection_memory import RejectedTarget, RejectionMemory
from behaviors.safety_limits import apply_limits
from behaviors.setpoint import Setpoint
from behaviors.target_fix import KeptFix, kept_fix
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult


class MissionState(str, Enum):
    IDLE = "IDLE"
    SEARCHING = "SEARCHING"
    ACQUIRING = "ACQUIRING"
    FOLLOWING = "FOLLOWING"
    AWAITING_SUPERVISOR = "AWAITING_SUPERVISOR"
    CONFIRMED = "CONFIRMED"
    REJECTED = "REJECTED"
    LOST = "LOST"
    ABORTED = "ABORTED"


# States in which the companion is commanding the vehicle (a hold is owed when they end).
ACTIVE = frozenset(
    {
        MissionState.SEARCHING,
        MissionState.ACQUIRING,
        MissionState.FOLLOWING,
        MissionState.AWAITING_SUPERVISOR,
        MissionState.CONFIRMED,
        MissionState.REJECTED,
        MissionState.LOST,
    }
)
# States with a target the tracker follows.
TRACKING = frozenset(
    {
        MissionState.ACQUIRING,
        MissionState.FOLLOWING,
        MissionState.AWAITING_SUPERVISOR,
        MissionState.CONFIRMED,
        MissionState.LOST,
    }
)
# A candidate in view and not yet decided: what the vehicle may be taken from its mission for.
IN_VIEW = frozenset({MissionState.ACQUIRING, MissionState.FOLLOWING, MissionState.AWAITING_SUPERVISOR})
# States whose back-end answers the "verified" policy judges (see `_judging`).
_JUDGED = frozenset(
    {MissionState.FOLLOWING, MissionState.AWAITING_SUPERVISOR, MissionState.CONFIRMED, MissionState.LOST}
)
MAX_PENDING = 4  # candidates awaiting a decision out of view; past it the oldest no longer awaits (said)
_MAX_QUERIES_IN_FLIGHT = 8  # answers to older queries are dropped as stale
_REVERIFY_MIN_IOU = 0.2
# A hold mode we asked for shows in the autopilot's heartbeat within this (as the link's own window).
HOLD_SHOWS_WITHIN_S = 5.0


@dataclass(frozen=True)
class EarlyStart:
    """A track started on the back-end's fast stage: search query `query_id`'s final verdicts are still to
    come, and `box` (in the keyframe) is what the fast stage chose."""

    query_id: int
    box: Box
    since_s: float  # when the early answer came


@dataclass(frozen=True)
class Target:
    """The person being tracked: what the back-end said about them and where they were last seen."""

    candidate_id: str
    justification: str
    verdict: Verdict
    box: Box
    keyframe_id: int
    last_seen_s: float
    position: GeoEstimate | None = None
    signature: tuple[float, ...] = ()
    operator_selected: bool = False
    early: EarlyStart | None = None  # started before the final verdicts (never reported to the supervisor)
    confirmed_by: str = ""  # who confirmed it ("supervisor page", "gcs"), once confirmed
    # Where a find and the memories (rejected, found) place the person: the freshest estimate nearly as good
    # as the track's best (`behaviors.target_fix`). The latest can be the worst (the view's far edge as a
    # survey flies away); the best alone is of a place a walking person has left.
    kept: KeptFix = KeptFix()
    position_s: float = math.nan  # when `position` was observed (event time; the keyframe's pose, a frame)
    # Re-acquired by the tracker alone after a loss, no answer since showing a candidate on the track: its
    # frames may be of the background it slid onto, so they give the find no position (`kept` stays).
    fix_held: bool = False
    # The description's words the back-end could not judge for this candidate ("minivan", "next to the pier
    # (the pier: not located)"): what the supervisor must check by eye before confirming.
    unjudged: tuple[str, ...] = ()
    # How many other candidates of the answer that proposed it the search could have taken as well (the same
    # verdict and placement: told apart by the detector's score alone): the choice among them was a guess.
    alike: int = 0
    # Seen in a keyframe the companion kept through a back-end outage, analysed once it answered again.
    stored: bool = False
    # Where the keyframe that proposed it placed it (its box from the keyframe's pose): the candidate the
    # back-end and the supervisor judge. The track's estimates may be of another place: a tracker started
    # on a keyframe seconds older than the live view (a loaded machine) can hold the background from its
    # first frame (a fleet run: 17 m beyond the look-alike, sigma 1.3 m, its first estimate kept as the fix).
    # A rejection or a find is remembered at both places.
    proposed_at: GeoEstimate | None = None

    @property
    def fix(self) -> GeoEstimate | None:
        return self.kept.estimate or self.position

    @property
    def fix_s(self) -> float:
        """When `fix` was observed (event time): a find's age on the rescuers' map."""
        return self.kept.time_s if self.kept.estimate is not None else self.position_s


@dataclass(frozen=True)
class State:
    mode: MissionState = MissionState.IDLE
    since_s: float = 0.0  # when `mode` was entered
    now_s: float = 0.0  # the newest event time seen
    mission: StartMission | None = None
    telemetry: Telemetry | None = None
    target: Target | None = None
    resume: MissionState = MissionState.FOLLOWING  # where LOST returns once the target is found again
    next_query_id: int = 1
    queries: tuple[tuple[int, QueryPurpose], ...] = ()  # in flight, oldest first
    last_query_s: float | None = None
    last_report_s: float | None = None
    lost_stage: int = 0  # 0: stopped and re-detecting, 1: holding, 2: lost action requested
    backend_down: bool = False
    mode_requested: FlightMode | None = None  # the last mode we asked for
    holding: bool = False  # a Hold was sent; the next setpoint first asks for the offboard mode again
    held_at_s: float | None = None  # when the last hold of ours began (its mode may show after a resume)
    control: ControlState = ControlState()
    rejections: RejectionMemory = RejectionMemory()
    reason: str = ""  # why the current mode was entered
    alarm: bool = False  # a loss signal fires on the trusted track (a track check went out when it began)
    # The final verdicts refused a track the fast stage started: searches wait for final verdicts until a
    # track is verified or the mission restarts (the fast stage would pick the same person again).
    early_refused: bool = False
    # The search runs along the autopilot's own mission (ArduPilot AUTO, PX4 MISSION): the companion
    # commands nothing while it only looks. `engaged`: it took the vehicle from the mission for the
    # current candidate (allowed by the start) when the mission was on item `break_off_item`, and hands
    # it back there when the candidate ends (docs/behavior.md, "Search along the mission").
    along_mission: bool = False
    engaged: bool = False
    break_off_item: int | None = None
    let_go: bool = False  # the companion let go on a confirmation (on_confirm = hold): it commands nothing
    found: RejectionMemory = RejectionMemory()  # confirmed finds the search went on from: not proposed again
    # The fleet mission's other vehicles' rejections (`FleetRejections`), by place: apart from `rejections`,
    # so a fleet's many never push this vehicle's own out.
    fleet_rejections: RejectionMemory = RejectionMemory()
    # Candidates put to the supervisor that the search gave up (out of view, the survey flew on) before a
    # decision, newest last: each keeps awaiting one while the search goes on (confirm: a find; reject:
    # remembered). The newest is the one shown (`awaiting_decision`); once it is decided, the one before.
    pending: tuple[Target, ...] = ()
    # Ids of candidates dropped from `pending` undecided (a fifth came), newest last, the last MAX_PENDING:
    # the supervisor page says so, as the GCS heard it.
    dropped_undecided: tuple[str, ...] = ()
    # Which candidate a decision naming none (the GCS's candidate 0) would apply to, and since when.
    undirected: DecisionGuard = DecisionGuard()


Result = tuple[State, tuple[Action, ...]]


def initial_state(config: MissionConfig) -> State:
    memory = RejectionMemory(
        radius_m=config.rejection_radius_m, signature_threshold=config.signature_threshold
    )
    return State(rejections=memory, found=memory, fleet_rejections=memory)


def commanding(state: State) -> bool:
    """Whether the companion flies the vehicle now (setpoints, holds; a stop is owed when it ends): an active
    state, not after letting go on a confirmation, and along the autopilot's mission only once engaged."""
    if state.mode not in ACTIVE or state.let_go:
        return False
    return not state.along_mission or state.engaged


def awaiting_decision(state: State) -> Target | None:
    """The candidate the supervisor has still to decide on: while AWAITING_SUPERVISOR, and while LOST on the
    way back to it (a short loss of the track must not take the candidate off the supervisor's page); else
    the newest the search gave up before a decision (`State.pending`: a survey flew on past it)."""
    waiting = state.mode is MissionState.AWAITING_SUPERVISOR or (
        state.mode is MissionState.LOST and state.resume is MissionState.AWAITING_SUPERVISOR
    )
    if waiting:
        return state.target
    return state.pending[-1] if state.pending else None


def awaiting_after(state: State) -> tuple[Target, ...]:
    """The other candidates awaiting a decision, oldest first: each is put to the supervisor again once the
    one shown (`awaiting_decision`) is decided, the newest first."""
    shown = awaiting_decision(state)
    return tuple(p for p in state.pending if p is not shown)


def _awaiting_id(state: State) -> str:
    awaiting = awaiting_decision(state)
    return awaiting.candidate_id if awaiting is not None else ""


def _pending(state: State, candidate_id: str) -> Target | None:
    """The candidate of that id among those awaiting a decision out of view."""
    return next((p for p in state.pending if candidate_id and p.candidate_id == candidate_id), None)


def _left_awaiting(state: State, target: Target) -> Result:
    """`target` was given up before the supervisor decided: it awaits the decision with the others."""
    others = tuple(p for p in state.pending if p.candidate_id != target.candidate_id)
    kept = (*others, target)[-MAX_PENDING:]
    dropped = others[: len(others) + 1 - len(kept)]
    said = tuple(GcsMessage(f"no longer awaiting {p.candidate_id}: too many", "warning") for p in dropped)
    gone = (*state.dropped_undecided, *(p.candidate_id for p in dropped))[-MAX_PENDING:]
    return replace(state, pending=kept, dropped_undecided=gone), said


def undirected_candidate(state: State) -> Target | None:
    """What a decision naming no candidate (the GCS's candidate 0) is for: the one awaiting the supervisor,
    else the one tracked."""
    awaiting = awaiting_decision(state)
    if awaiting is None and state.mode in TRACKING:
        return state.target
    return awaiting


def step(state: State, event: Event, config: MissionConfig) -> Result:
    """The next state and the actions to execute, in order, for one event."""
    new, actions = _step(state, event, config)
    shown = awaiting_decision(new)
    if (
        shown is not None
        and shown is not new.target
        and shown.candidate_id != _awaiting_id(state)
        and not _reported_awaiting(actions, shown)
    ):
        # The one shown was decided and one left before it awaits again: say so (GCS and page).
        actions = (*actions, _report(shown, "awaiting"))
    undirected = undirected_candidate(new)
    guard = observe(new.undirected, undirected.candidate_id if undirected else "", new.now_s)
    return (new if guard is new.undirected else replace(new, undirected=guard)), actions


def _reported_awaiting(actions: Sequence[Action], target: Target) -> bool:
    return any(
        isinstance(a, ReportCandidate) and a.status == "awaiting" and a.candidate_id == target.candidate_id
        for a in actions
    )


def _step(state: State, event: Event, config: MissionConfig) -> Result:
    if not math.isfinite(event.time_s):
        return state, (GcsMessage("ignored event with a non-finite time", "warning"),)
    state = replace(state, now_s=max(state.now_s, event.time_s))
    if isinstance(event, AutopilotLinkLost):
        return _abort(state, "autopilot link lost")
    if isinstance(event, PilotTakeover):
        return _abort(state, f"pilot takeover {event.mode}".strip())
    if isinstance(event, CompanionHold):
        # The watchdog has stopped the vehicle and told the GCS why; the hold mode it asked for is ours, and
        # the next setpoint asks for the offboard mode again where the mission allows it (as after any Hold).
        return (_hold(state), ()) if commanding(state) else (state, ())
    if isinstance(event, GcsCommand):
        return _command(state, event, config)
    if isinstance(event, Telemetry):
        return _telemetry(state, event)
    if isinstance(event, TrackResult):
        return _track(state, event, config)
    if isinstance(event, BackendAnswer):
        return _answer(state, event, config)
    if isinstance(event, BackendUnreachable):
        return _backend_down(state, event)
    if isinstance(event, RejectionShared):
        # Answers to the queries from the next one on were judged with it (`behaviors.rejection_memory`).
        return replace(state, rejections=state.rejections.shared(event.candidate_id, state.next_query_id)), ()
    if isinstance(event, FleetRejections):
        return _fleet_rejected(state, event)
    return _tick(state, config)  # TimerTick, the last kind of event


# --- transitions -------------------------------------------------------------------------------------


def _enter(state: State, mode: MissionState, reason: str, severity: str = "info") -> Result:
    new = replace(state, mode=mode, since_s=state.now_s, reason=reason)
    return new, (GcsMessage(f"{mode.value}: {reason}"[:50], severity),)


def _abort(state: State, reason: str) -> Result:
    if state.mode is MissionState.ABORTED:
        return state, ()
    stop: list[Action] = []
    if commanding(state):
        # Every abort lets go: stop, the autopilot's hold mode (none after a pilot's own mode change),
        # then silence.
        stop.append(ReleaseControl(reason))
    if state.mode in TRACKING:
        stop.append(TrackerStop(reason))
    new, msg = _enter(
        replace(state, control=ControlState(), queries=(), engaged=False),
        MissionState.ABORTED,
        reason,
        "critical",
    )
    return new, (*stop, *msg)


def _start_search(state: State, reason: str, config: MissionConfig) -> Result:
    """SEARCHING (again): along the mission the vehicle goes back to it, if the companion had taken it, at
    the item it broke off at; on the spot the search setpoint starts."""
    hand_back: tuple[Action, ...] = ()
    if state.engaged:
        state = replace(state, engaged=False, holding=False, mode_requested=FlightMode.MISSION)
        item = state.break_off_item
        hand_back = (ResumeMission(item, reason), GcsMessage(f"RESUMING MISSION at item {_item(item)}"))
    new, msg = _enter(
        replace(state, target=None, control=ControlState(), lost_stage=0, last_query_s=None, let_go=False),
        MissionState.SEARCHING,
        reason,
    )
    new, query = _search_query(new, config)
    scan: tuple[Action, ...] = ()
    if not new.along_mission:
        new, scan = _scan(new, config)
    return new, (*hand_back, *msg, *scan, *query)


def _fleet_rejected(state: State, event: FleetRejections) -> Result:
    """Rejections by the other vehicles of this fleet mission: candidates standing there (within the rejection
    radius, widened by the candidate's uncertainty) are not proposed, as where this vehicle's own rejections
    stand. By place alone: their candidate ids are the other vehicle's, and nobody here saw their looks."""
    mission = state.mission
    if mission is None or not mission.mission_id or event.mission_id != mission.mission_id:
        return state, ()  # another mission's, or one this vehicle no longer searches
    memory = state.fleet_rejections
    via: list[str] = []
    for rejected in event.rejections:
        known = any(
            e.via == rejected.vehicle_id
            and e.position is not None
            and (e.position.lat_deg, e.position.lon_deg) == (rejected.lat_deg, rejected.lon_deg)
            for e in memory.entries
        )
        if known or not (math.isfinite(rejected.lat_deg) and math.isfinite(rejected.lon_deg)):
            continue
        # The other vehicle's estimate, without its uncertainty (the back-end keeps none): the radius covers it.
        place = GeoEstimate(rejected.lat_deg, rejected.lon_deg, 0.0, 0.0, 0.0, 0.0, 0.0)
        memory = memory.remember(RejectedTarget(position=place, time_s=state.now_s, via=rejected.vehicle_id))
        via.append(rejected.vehicle_id)
    if not via:
        return state, ()
    # "FLEET": not a line starting "rejected ", which the GCS takes as the answer to its own reject.
    count = f"{len(via)} " if len(via) > 1 else ""
    said = f"FLEET: {count}rejected via {', '.join(dict.fromkeys(via))}"
    said = f"{said}, not proposed here" if len(said) <= 31 else said[:50]
    return replace(state, fleet_rejections=memory), (GcsMessage(said),)


def _remembered(target: Target, now_s: float) -> RejectedTarget:
    """A rejection or a find of `target` to remember: where the track placed it and, when that is another
    place, where the keyframe that proposed it did (`Target.proposed_at`)."""
    fix = target.fix
    also = target.proposed_at if target.proposed_at is not fix else None
    return RejectedTarget(target.candidate_id, fix, target.signature, now_s, also_at=also)


def _remember_found(state: State, target: Target) -> State:
    """A confirmed find the search goes on from: never proposed again in this mission."""
    entry = _remembered(target, state.now_s)
    return replace(state, found=state.found.remember(entry))


def _start_lost(state: State, reason: str, config: MissionConfig) -> Result:
    assert state.target is not None
    resume = state.mode if state.mode is not MissionState.LOST else state.resume
    new, msg = _enter(
        replace(state, resume=resume, control=ControlState(), lost_stage=0, last_query_s=None),
        MissionState.LOST,
        reason,
        "warning",
    )
    new, query = _redetect(new, state.target.box, config)
    stop: tuple[Action, ...] = (SendSetpoint(Setpoint.zero()),) if commanding(state) else ()
    return new, (*stop, *msg, *query)


def _confirm(state: State, by: str, config: MissionConfig) -> Result:
    assert state.target is not None
    target = replace(state.target, confirmed_by=by)
    state = replace(state, target=target)
    report = _report(target, "confirmed")
    if state.mode is MissionState.LOST:
        new = replace(state, resume=MissionState.CONFIRMED, last_report_s=state.now_s)
        return new, (report, GcsMessage("CONFIRMED while lost: re-detecting"))
    new, msg = _enter(
        replace(state, last_report_s=state.now_s), MissionState.CONFIRMED, "supervisor confirmed"
    )
    hold: tuple[Action, ...] = ()
    if config.on_confirm is ConfirmAction.HOLD:
        if commanding(state):  # the autopilot holds there; the GCS owns the vehicle
            hold = (ReleaseControl("confirmed: hold"),)
        new = replace(new, let_go=True, engaged=False)
    return new, (*hold, report, *msg)


def _reject(state: State, candidate_id: str) -> Result:
    target = state.target if state.mode in TRACKING else None
    if target is None or (candidate_id and candidate_id != target.candidate_id):
        pending = _pending(state, candidate_id)
        if pending is not None:
            entry = _remembered(pending, state.now_s)
            rest = tuple(p for p in state.pending if p is not pending)
            return replace(state, rejections=state.rejections.remember(entry), pending=rest), (
                RememberRejection(pending.candidate_id, pending.fix, pending.signature),
                GcsMessage(f"rejected {pending.candidate_id}"[:50]),
            )
        if not candidate_id:
            return state, (GcsMessage("reject: no candidate awaiting", "warning"),)
        # Not the one we track: remember the id so the back-end's candidate is never picked.
        entry = RejectedTarget(candidate_id=candidate_id, time_s=state.now_s)
        return replace(state, rejections=state.rejections.remember(entry)), (
            RememberRejection(candidate_id, None),
        )
    entry = _remembered(target, state.now_s)
    new, msg = _enter(
        replace(state, rejections=state.rejections.remember(entry), target=None, control=ControlState()),
        MissionState.REJECTED,
        "supervisor rejected",
    )
    stop: tuple[Action, ...] = (SendSetpoint(Setpoint.zero()),) if commanding(state) else ()
    actions: tuple[Action, ...] = (
        *stop,
        TrackerStop("rejected"),
        RememberRejection(target.candidate_id, target.fix, target.signature),
        *msg,
    )
    return new, actions


# --- events ------------------------------------------------------------------------------------------


def _command(state: State, event: GcsCommand, config: MissionConfig) -> Result:
    cmd = event.command
    if isinstance(cmd, AbortMission):
        return _abort(state, f"GCS abort {cmd.reason}".strip())
    if isinstance(cmd, StartMission):
        if not cmd.prompt.strip():
            return state, (GcsMessage("start refused: empty prompt", "warning"),)
        keep = state.mission is not None and state.mission.prompt == cmd.prompt
        rejections = state.rejections if keep else _forgotten(state.rejections)
        found = state.found if keep else _forgotten(state.found)
        fleet = state.fleet_rejections if keep else _forgotten(state.fleet_rejections)
        stop: tuple[Action, ...] = (TrackerStop("new mission"),) if state.mode in TRACKING else ()
        new = replace(
            state,
            mission=cmd,
            rejections=rejections,
            found=found,
            fleet_rejections=fleet,
            backend_down=False,
            mode_requested=None,
            holding=False,
            early_refused=False,
            along_mission=_along_mission(state, config),
            pending=(),
            dropped_undecided=(),
        )
        engage: tuple[Action, ...] = ()
        if not new.along_mission:  # on the spot: fly from the start (when allowed)
            new, engage = _engage(new, "mission start")
        new, actions = _start_search(new, "mission started", config)
        return new, (*stop, *engage, *actions)
    if isinstance(cmd, TrackRectangle):
        if not cmd.box.is_valid():
            return state, (GcsMessage("track refused: invalid rectangle", "warning"),)
        target = Target(
            "operator",
            "selected by the operator",
            Verdict.YES,
            cmd.box,
            -1,
            state.now_s,
            operator_selected=True,
        )
        # Outside a running mission an old mission's prompt and engage permission no longer apply.
        mission = state.mission if state.mode in ACTIVE else None
        new = replace(
            state,
            mission=mission,
            target=target,
            control=ControlState(),
            lost_stage=0,
            holding=False,
            let_go=False,
            along_mission=state.along_mission and mission is not None,
        )
        if new.along_mission:  # taken from the autopilot's mission (when allowed), handed back after
            new, engage = _take_control(new, "operator target")
        else:
            new, engage = _engage(replace(new, mode_requested=None), "operator target")
        if config.operator_box_confirms:
            new, msg = _enter(new, MissionState.CONFIRMED, "operator selected target")
        else:  # followed like any candidate; only the supervisor's confirm allows descent
            new, msg = _enter(new, MissionState.FOLLOWING, "operator selected target")
        kind = mission.superset if mission is not None else ""  # what the mission searches for
        return new, (*engage, TrackerInit(cmd.box, -1, "operator", label=kind), *msg)
    if isinstance(cmd, StopTracking):
        if state.mode not in ACTIVE:
            return state, ()
        stop = (TrackerStop("operator stop"),) if state.mode in TRACKING else ()
        new, msg = _enter(
            replace(state, target=None, control=ControlState(), queries=()),
            MissionState.IDLE,
            "operator stop",
        )
        return new, (ReleaseControl("operator stop"), *stop, *msg)
    if isinstance(cmd, ConfirmCandidate | RejectCandidate) and not cmd.candidate_id:
        undirected = undirected_candidate(state)
        if undirected is not None:
            if too_new(state.undirected, state.now_s, config.gcs_decision_guard_s):
                verb = "CONFIRM" if isinstance(cmd, ConfirmCandidate) else "REJECT"
                text = f"{verb} REFUSED: {undirected.candidate_id} is new, press again"
                return state, (GcsMessage(text, "warning"),)
            cmd = replace(cmd, candidate_id=undirected.candidate_id)
    if isinstance(cmd, ConfirmCandidate):
        current = state.target
        if (
            current is None
            or state.mode not in TRACKING
            or (cmd.candidate_id and cmd.candidate_id != current.candidate_id)
        ):
            pending = _pending(state, cmd.candidate_id)
            if pending is not None:
                # Out of view by now: the find is where the track placed it (`Target.fix`); the search goes on.
                decided = replace(pending, confirmed_by=cmd.by)
                rest = tuple(p for p in state.pending if p is not pending)
                new = _remember_found(replace(state, pending=rest), decided)
                return new, (
                    _report(decided, "confirmed"),
                    GcsMessage(f"confirmed {decided.candidate_id}"[:50]),
                )
            return state, (GcsMessage("confirm: no such candidate", "warning"),)
        if state.mode is MissionState.CONFIRMED:
            return state, ()
        return _confirm(state, cmd.by, config)
    if isinstance(cmd, RejectCandidate):
        return _reject(state, cmd.candidate_id)
    return state, ()


def _forgotten(memory: RejectionMemory) -> RejectionMemory:
    return RejectionMemory((), memory.radius_m, memory.signature_threshold, memory.capacity)


def _along_mission(state: State, config: MissionConfig) -> bool:
    """Does a search starting now run along the autopilot's mission? (`[behavior] search`.) A restart while
    the companion holds a vehicle it took from the mission stays along it (and hands it back)."""
    if config.search is SearchMode.SPOT:
        return False
    if config.search is SearchMode.MISSION:
        return True
    flying_mission = state.telemetry is not None and state.telemetry.mission_active
    return flying_mission or (state.along_mission and state.engaged)


def _take_control(state: State, reason: str) -> Result:
    """Along the mission: take the vehicle from it for a candidate, only when the start allowed it and the
    autopilot is flying its mission at that moment (never from a mode the pilot chose). Remembers the item
    to hand it back at."""
    if not state.along_mission or state.engaged or state.mission is None or not state.mission.allow_engage:
        return state, ()
    telemetry = state.telemetry
    if telemetry is None or not telemetry.mission_active:
        return state, ()
    item = telemetry.mission_item
    new = replace(state, engaged=True, break_off_item=item, mode_requested=FlightMode.OFFBOARD, holding=False)
    return new, (
        RequestMode(FlightMode.OFFBOARD, reason),
        GcsMessage(f"LEFT MISSION at item {_item(item)}: {reason}"[:50]),
    )


def _item(item: int | None) -> str:
    return "?" if item is None else str(item)


def _engage(state: State, reason: str) -> Result:
    """Ask for the offboard mode only when the mission allows it and the autopilot is not already in it."""
    if state.mission is None or not state.mission.allow_engage:
        return state, ()
    if state.telemetry is not None and state.telemetry.offboard_active:
        return state, ()
    return replace(state, mode_requested=FlightMode.OFFBOARD), (RequestMode(FlightMode.OFFBOARD, reason),)


def _telemetry(state: State, telemetry: Telemetry) -> Result:
    previous = state.telemetry
    new = replace(state, telemetry=telemetry)
    # Leaving offboard is expected after our own hold (PX4 HOLD, ArduPilot BRAKE/LOITER) or mode request
    # (the mission handed back included); then only the link's PilotTakeover event, which knows what it
    # asked for, reports a takeover.
    # A hold of ours shows within a few seconds, possibly after setpoints resumed and asked for the offboard
    # mode again (PX4's HOLD after a watchdog's stop); the link knows that HOLD too.
    recent_hold = state.held_at_s is not None and state.now_s - state.held_at_s <= HOLD_SHOWS_WITHIN_S
    our_request = state.holding or recent_hold or state.mode_requested not in (None, FlightMode.OFFBOARD)
    if (
        commanding(state)
        and previous is not None
        and previous.offboard_active
        and not telemetry.offboard_active
        and not our_request
    ):
        return _abort(new, f"pilot takeover {telemetry.mode}".strip())
    if state.mode_requested is FlightMode.MISSION and telemetry.mission_active:
        new = replace(new, mode_requested=None)
        if previous is None or not previous.mission_active:
            item, left = _item(telemetry.mission_item), _item(state.break_off_item)
            resumed = GcsMessage(f"MISSION RESUMED at item {item} (left at {left})")
            if new.mode in IN_VIEW and new.target is not None:
                # A candidate the search found while the mission was being handed back: the vehicle is the
                # mission's again only now, so it is taken for the candidate now (stopped, as `_acquire`
                # stops it, until the follow law's next setpoint).
                new, take = _take_control(new, "candidate")
                stop: tuple[Action, ...] = (SendSetpoint(Setpoint.zero()),) if take else ()
                return new, (resumed, *take, *stop)
            return new, (resumed,)
    return new, ()


def _track(state: State, result: TrackResult, config: MissionConfig) -> Result:
    target = state.target
    if state.mode not in TRACKING or target is None or _given_up(state, config):
        return state, ()
    if not result.trusted or result.box is None:
        if state.mode is MissionState.ACQUIRING:
            return _acquire_timeout(state, config)
        if state.mode is MissionState.LOST:
            return state, ()
        return _start_lost(state, f"tracker lost ({result.lost_reason or 'failed'})", config)

    position = locate_box(config.camera, state.telemetry, result.box) if state.telemetry else None
    # The find's position comes only from frames the evidence stands behind: not one on which a loss signal
    # fires, nor any after a re-acquisition the back-end has not yet seen on the track (a tracker sliding
    # onto the background gives estimates as sharp as the target's).
    held = target.fix_held or state.mode is MissionState.LOST
    doubted = bool(result.alarm) or held
    target = replace(
        target,
        box=result.box,
        last_seen_s=result.time_s,
        position=position or target.position,
        position_s=result.time_s if position is not None else target.position_s,
        kept=target.kept if doubted or position is None else kept_fix(target.kept, position, result.time_s),
        fix_held=held,
    )
    state = replace(state, target=target)
    actions: list[Action] = []
    if state.mode is MissionState.ACQUIRING:
        state, msg = _enter(state, MissionState.FOLLOWING, f"tracking {target.candidate_id}")
        actions.extend(msg)
    elif state.mode is MissionState.LOST:
        state, msg = _enter(replace(state, lost_stage=0), state.resume, "target re-acquired")
        actions.extend(msg)
        if state.mode is MissionState.AWAITING_SUPERVISOR:
            actions.append(_report(target, "awaiting"))  # the candidate again, for whoever missed it

    if config.verified_reinit and state.mode is MissionState.FOLLOWING:
        starting = bool(result.alarm) and not state.alarm
        state = replace(state, alarm=bool(result.alarm))
        if starting:
            # Evidence before a loss: a signal began to fire on the trusted track, ask now rather than at
            # the next periodic check (the answer can confirm the track, re-frame it or show a rival).
            state, query = _track_check(state)
            actions.extend(query)
    state, setpoint = _follow(state, result.box, result.time_s, config)
    actions.extend(setpoint)

    if state.mode is MissionState.FOLLOWING and target.early is None and _arrived(state, result.box, config):
        state, msg = _enter(
            replace(state, last_report_s=state.now_s), MissionState.AWAITING_SUPERVISOR, "awaiting supervisor"
        )
        actions.extend((_report(target, "awaiting"), *msg))
    return state, tuple(actions)


def _answer(state: State, answer: BackendAnswer, config: MissionConfig) -> Result:
    purpose = dict(state.queries).get(answer.query_id)
    if answer.final:  # an early answer leaves its query open for the final one
        state = replace(state, queries=tuple(q for q in state.queries if q[0] != answer.query_id))
    state = replace(state, backend_down=False)
    if answer.stored:
        return _from_store(state, answer, config)
    if purpose is None:
        return state, ()
    target = state.target
    early = target.early if target is not None and state.mode in TRACKING else None
    if answer.final and early is not None and early.query_id == answer.query_id:
        assert target is not None
        return _settle_early_start(state, target, early, answer, config)
    if purpose is QueryPurpose.SEARCH and state.mode is MissionState.SEARCHING:
        chosen = _choose(state, answer.candidates, config, answer)
        if chosen is None:
            return state, ()
        if _left_view(state, chosen[0], chosen[1], config):
            return _out_of_view(state, answer, chosen) if answer.final else (state, ())
        return _acquire(state, *chosen, answer)
    if target is None or not answer.final:  # a fast stage's verdicts only ever start a search's track
        return state, ()
    seen = _on_track(answer, target.box) if target.fix_held else None
    if (
        seen is not None
        and seen.verdict is not Verdict.NO
        and state.mode in IN_VIEW | {MissionState.CONFIRMED}
    ):
        target = replace(target, fix_held=False)  # the back-end sees it where the tracker is: positions again
        state = replace(state, target=target)
    if purpose is QueryPurpose.SEARCH and _searching_on(state):
        return _propose_other(state, target, answer, config)
    state, actions = _answer_for_target(state, target, purpose, answer, config)
    if config.verified_reinit and _judging(state, config):
        # Every answer for the track goes to the front-end's policy, with what the mission refuses marked;
        # one with no candidate too (as `eval` judges): nothing found on the track is evidence, and it ends
        # the hold an older confirmation has over the track's own loss signals.
        excluded = _excluded(state, config, answer)
        refused = tuple(i for i, d in enumerate(answer.candidates) if _refused(target, d, config, excluded))
        actions = (*actions, JudgeCandidates(answer.keyframe_id, answer.candidates, refused))
    return state, actions


def _acquire(
    state: State, det: Detection, position: GeoEstimate | None, others: int, answer: BackendAnswer
) -> Result:
    """Start tracking `det` from the answer's keyframe; on an early answer, provisionally."""
    early = None if answer.final else EarlyStart(answer.query_id, det.box, state.now_s)
    picked = replace(_seen_in(answer, det, position, others), early=early)
    # Along the mission the vehicle is taken from it now (when allowed): at survey speed the candidate
    # would be out of view before the tracker has locked on.
    state, take = _take_control(replace(state, target=picked, control=ControlState()), "candidate")
    new, msg = _enter(
        state,
        MissionState.ACQUIRING,
        f"candidate {det.candidate_id}" + (" (early)" if early is not None else ""),
    )
    # Stop (any search scan, or the survey's motion) while the tracker locks on; the link repeats it.
    stop: tuple[Action, ...] = (SendSetpoint(Setpoint.zero()),) if commanding(new) else ()
    init = TrackerInit(det.box, answer.keyframe_id, det.candidate_id, label=det.label)
    return new, (*take, *stop, init, *msg)


def _left_view(state: State, det: Detection, position: GeoEstimate | None, config: MissionConfig) -> bool:
    """Whether the candidate has left the camera's view since its keyframe (`behaviors.live_view`): a tracker
    started on it would catch up onto the background. Unknown (no place, no pose) is in view, as before."""
    now = state.telemetry
    return position is not None and now is not None and not in_view_now(config.camera, det.box, position, now)


def _out_of_view(
    state: State, answer: BackendAnswer, chosen: tuple[Detection, GeoEstimate | None, int]
) -> Result:
    """A search's candidate that left the view before its answer came: no track (it would start on the
    background); it awaits the supervisor out of view, placed from its keyframe, as one from the store, and
    the search goes on. The supervisor decides on its keyframe's crop."""
    seen = _seen_in(answer, *chosen)
    state, actions = _aside(state, seen, answer)
    return state, (*actions, GcsMessage(f"{seen.candidate_id} out of view: decide on keyframe"[:50]))


def _aside(state: State, seen: Target, answer: BackendAnswer) -> Result:
    """`seen`, a candidate of `answer`'s keyframe the tracker does not hold, awaits the supervisor out of view
    (`State.pending`), reported with that keyframe (its crop comes from there). "queued", not "awaiting", while
    another is shown (the tracked one awaiting: a decision naming no candidate is still for it)."""
    state, said = _left_awaiting(state, seen)
    status = "awaiting" if awaiting_decision(state) is seen else "queued"
    return state, (replace(_report(seen, status), keyframe_id=answer.keyframe_id), *said)


def _seen_in(answer: BackendAnswer, det: Detection, position: GeoEstimate | None, others: int = 0) -> Target:
    """The candidate `det` of `answer`, standing at `position` when its keyframe was captured, chosen from
    `others` alike."""
    return Target(
        det.candidate_id,
        det.justification,
        det.verdict,
        det.start_box,
        answer.keyframe_id,
        answer.time_s,
        position,
        det.signature,
        position_s=answer.pose.time_s if answer.pose is not None else answer.time_s,
        unjudged=det.unjudged,
        alike=others,
        proposed_at=position,
    )


def _settle_early_start(
    state: State, target: Target, early: EarlyStart, answer: BackendAnswer, config: MissionConfig
) -> Result:
    """The final verdicts on the keyframe an early track started from: while they accept the early choice
    the track stays (with the final verdict and candidate id; another candidate they also accept is no
    reason to switch); when they refuse it the track moves to their own choice, or ends and the search
    goes on when they accept no one."""

    def acceptable(candidates: Sequence[Detection]) -> Detection | None:
        chosen = _choose(state, candidates, config, answer)
        return chosen[0] if chosen is not None else None

    det, kept = settle_early_choice(answer.candidates, early.box, acceptable)
    if det is None:
        new, actions = _start_search(
            replace(state, early_refused=True), f"not verified: {target.candidate_id}", config
        )
        return new, (TrackerStop("early candidate not verified"), *actions)
    others = alike(answer.candidates, det, config.accept_uncertain, _eligible(state, config, answer))
    if not kept:
        return _acquire(state, det, _position(state, det, config, answer.pose), others, answer)
    verified = replace(
        target,
        candidate_id=det.candidate_id,
        justification=det.justification,
        verdict=det.verdict,
        signature=det.signature or target.signature,
        early=None,
        unjudged=det.unjudged,
        alike=others,
    )
    return replace(state, target=verified, early_refused=False), (
        GcsMessage(f"verified {det.candidate_id}"[:50]),
    )


def _on_track(answer: BackendAnswer, box: Box) -> Detection | None:
    """The answer's candidate on the tracked box: the best overlap, at least `_REVERIFY_MIN_IOU`."""
    match = max(answer.candidates, key=lambda d: iou(d.box, box), default=None)
    return match if match is not None and iou(match.box, box) >= _REVERIFY_MIN_IOU else None


def _searching_on(state: State) -> bool:
    """Looking only (along the mission, not engaged), a candidate awaiting the supervisor in view, or a find
    the tracker still holds after the confirmation: the survey flies on whatever the tracker holds, so the
    search goes on in the same keyframes (and counts as searched: coverage, POD). Others in view are put to
    the supervisor too (`_propose_other`); before, one tracked at a time hid anyone seen beside it, and the
    survey had flown past them by the time the track ended (after a find, the lanes flown while the find was
    held in view were left unsearched: a fleet that goes on after a find had holes there)."""
    return (
        state.mode in (MissionState.AWAITING_SUPERVISOR, MissionState.CONFIRMED)
        and state.along_mission
        and not state.engaged
    )


def _propose_other(state: State, target: Target, answer: BackendAnswer, config: MissionConfig) -> Result:
    """A search answer while `_searching_on`: the best verified candidate that is not the tracked one (its box
    on that keyframe, else where it stands), nor one already queued (by place: ids are per keyframe),
    rejected or found, is queued for the supervisor after the tracked one (`State.pending`, placed from its
    keyframe). The tracker stays on its candidate, and the front-end's policy is not given these answers:
    the supervisor is deciding on that candidate."""
    where = [(target.candidate_id, target.position), (target.candidate_id, target.fix)]
    if answer.track_box is not None:
        # A confirmed find is known by where it stands too: a tracker drifting off it must not make the person
        # a new candidate (a second find of them).
        tracked, placed = (
            _on_track(answer, answer.track_box),
            where if state.mode is MissionState.CONFIRMED else [],
        )
    else:
        tracked, placed = None, where
    chosen = _choose(state, answer.candidates, config, answer, placed, tracked)
    if chosen is None or chosen[1] is None:  # nowhere to place it: nothing to tell it apart by
        return state, ()
    # Beside a confirmed find the new one is the one awaiting (as one from the store).
    return _aside(state, _seen_in(answer, *chosen), answer)


def _from_store(state: State, answer: BackendAnswer, config: MissionConfig) -> Result:
    """An answer to a keyframe the companion kept through a back-end outage: never a track's start (the
    person is long out of view). The best verified candidate that is not rejected, found, already awaiting a
    decision or the one tracked is placed from the keyframe's pose and awaits the supervisor out of view
    (`State.pending`), said with how long ago it was seen; the supervisor decides on it as on any other."""
    if state.mode not in ACTIVE or answer.pose is None or not answer.final:
        return state, ()
    target = state.target if state.mode in TRACKING else None
    placed = (
        [] if target is None else [(target.candidate_id, target.position), (target.candidate_id, target.fix)]
    )
    chosen = _choose(state, answer.candidates, config, answer, placed)
    if chosen is None or chosen[1] is None:  # nowhere to place it: nothing to send anyone to
        return state, ()
    return _aside(
        state, replace(_seen_in(answer, *chosen), last_seen_s=answer.pose.time_s, stored=True), answer
    )


def _answer_for_target(
    state: State, target: Target, purpose: QueryPurpose, answer: BackendAnswer, config: MissionConfig
) -> Result:
    if purpose is QueryPurpose.REVERIFY and state.mode in (
        MissionState.AWAITING_SUPERVISOR,
        MissionState.CONFIRMED,
    ):
        match = _on_track(answer, target.box)
        if match is None:
            return state, (GcsMessage("re-verify: target not in keyframe", "warning"),)
        target = replace(
            target,
            verdict=match.verdict,
            justification=match.justification or target.justification,
            unjudged=match.unjudged if match.justification else target.unjudged,
        )
        status = "reverified" if state.mode is MissionState.AWAITING_SUPERVISOR else "confirmed"
        return replace(state, target=target, last_report_s=state.now_s), (_report(target, status),)
    if (
        purpose is QueryPurpose.REDETECT
        and state.mode is MissionState.LOST
        and not _given_up(state, config)
        and not config.verified_reinit  # the paper's policy: the mission picks the box itself
    ):
        excluded = _excluded(state, config, answer)
        usable = [d for d in answer.candidates if not _refused(target, d, config, excluded)]
        best = select_by_c_box(target.box, usable)
        gate = config.reinit_gate * (config.camera.width + config.camera.height)
        if best is None or c_box(target.box, best.box) > gate:
            return state, ()
        target = replace(target, box=best.box, keyframe_id=answer.keyframe_id)
        return replace(state, target=target), (
            TrackerInit(best.box, answer.keyframe_id, target.candidate_id, reinit=True),
        )
    return state, ()


def _judging(state: State, config: MissionConfig) -> bool:
    """States in which an answer may move the track: a track the mission follows or re-detects (not while
    the first lock is still being acquired, nor once LOST has given up)."""
    return state.mode in _JUDGED and not _given_up(state, config)


def _refused(
    target: Target, det: Detection, config: MissionConfig, excluded: Callable[[Detection], bool]
) -> bool:
    """A candidate the mission would never re-initialise on. Away from the last box only a "yes" may re-find
    the target, however wide the query's region: anything less could be a distractor anywhere in view.
    Near it, the operator's own target (never checked against the prompt) may be re-found on any verdict,
    others on anything but "no". The rejection memory (supervisor's rejections) is never re-found."""
    near = _centre_inside(det.box, _roi(target.box, config))
    return not _redetect_verdict_ok(det.verdict, near, target.operator_selected) or excluded(det)


def _backend_down(state: State, event: BackendUnreachable) -> Result:
    if state.backend_down:
        return state, ()
    new = replace(state, backend_down=True, queries=())
    msg = GcsMessage(f"back-end unreachable {event.reason}".strip()[:50], "warning")
    if commanding(state):
        # Watchdog rule: motion ends with a stop then hold; setpoints resume once the back-end answers.
        return _hold(new), (Hold("back-end unreachable"), msg)
    return new, (msg,)


def _tick(state: State, config: MissionConfig) -> Result:
    now = state.now_s
    mode = state.mode
    if mode is MissionState.REJECTED:
        return _start_search(state, "searching again", config)
    if mode is MissionState.CONFIRMED and config.on_confirm is ConfirmAction.SURVEY and state.target:
        # The find is reported; the search goes on (along the mission: the vehicle goes back to it).
        found = _remember_found(state, state.target)
        new, back = _start_search(found, "find reported: searching on", config)
        return new, (TrackerStop("confirmed: searching on"), *back)
    if mode is MissionState.SEARCHING:
        actions: tuple[Action, ...] = ()
        if _query_due(state, config.search_interval_s):
            state, actions = _search_query(state, config)
        scan: tuple[Action, ...] = ()
        if not state.along_mission:
            state, scan = _scan(state, config)
        return state, (*scan, *actions)
    early = state.target.early if state.target is not None and mode in TRACKING else None
    if early is not None and now - early.since_s > config.final_answer_timeout_s:
        new, actions = _start_search(
            replace(state, early_refused=True), "early candidate not verified", config
        )
        return new, (TrackerStop("no final verdicts on the early candidate"), *actions)
    if mode is MissionState.ACQUIRING:
        if now - state.since_s > config.acquire_timeout_s:
            return _acquire_timeout(state, config)
        return state, ()
    target = state.target
    if target is None:
        return state, ()
    if mode in (MissionState.FOLLOWING, MissionState.AWAITING_SUPERVISOR, MissionState.CONFIRMED):
        if now - target.last_seen_s > config.frame_stale_s:
            return _start_lost(state, "no tracker result", config)
        if mode is MissionState.AWAITING_SUPERVISOR and _report_due(state, config):
            state, query = _query(
                replace(state, last_report_s=now), QueryPurpose.REVERIFY, _roi(target.box, config)
            )
            return state, query
        if _searching_on(state) and _query_due(state, config.search_interval_s):
            return _query(state, QueryPurpose.SEARCH, None)  # final verdicts only: no early answer
        if mode is MissionState.CONFIRMED and _report_due(state, config):
            state, report = replace(state, last_report_s=now), (_report(target, "confirmed"),)
            if target.fix_held:  # re-acquired since: only an answer on the track moves the find again
                state, query = _query(state, QueryPurpose.REVERIFY, _roi(target.box, config))
                return state, (*report, *query)
            return state, report
        if (
            mode is MissionState.FOLLOWING
            and config.verified_reinit
            and _query_due(state, config.query_interval_s)
        ):
            # Evidence for the front-end's policy while trusted too: a tracker that slid onto a neighbour
            # follows them smoothly, and only a keyframe answer can show it.
            return _track_check(state)
        return state, ()
    if mode is MissionState.LOST:
        return _lost_tick(state, target, config)
    return state, ()


def _lost_tick(state: State, target: Target, config: MissionConfig) -> Result:
    if _given_up(state, config):
        return state, ()
    elapsed = state.now_s - state.since_s
    give_up_s = config.lost_resume_after_s if commanding(state) else config.lost_looking_s
    if _lost_ends_in_search(state) and elapsed >= give_up_s:
        if state.resume is MissionState.CONFIRMED:
            state = _remember_found(state, target)  # reported already; never proposed again
        said: tuple[Action, ...] = ()
        if state.resume is MissionState.AWAITING_SUPERVISOR:
            state, said = _left_awaiting(state, target)  # still awaits the supervisor's decision
        new, back = _start_search(state, "target not found again", config)
        return new, (TrackerStop("lost: back to the search"), *said, *back)
    actions: list[Action] = []
    # Looking only (along the mission, not engaged): nothing to hold or request.
    if commanding(state) and state.lost_stage == 0 and elapsed >= config.lost_hold_after_s:
        state = replace(_hold(state), lost_stage=1)
        actions.append(Hold("target lost"))
    if commanding(state) and state.lost_stage == 1 and elapsed >= config.lost_action_after_s:
        state = replace(state, lost_stage=2)
        if config.lost_action is LostAction.HOLD:
            actions.append(GcsMessage("LOST: still holding, re-detecting", "warning"))
        else:
            mode = FlightMode(config.lost_action.value)
            state = replace(state, mode_requested=mode, queries=())
            actions.extend(
                (
                    RequestMode(mode, "target lost"),
                    TrackerStop("target lost"),
                    GcsMessage(f"LOST: requesting {mode.value}", "warning"),
                )
            )
            return state, tuple(actions)
    # Nothing is followed while lost: re-detect at the search's rate, not the track check's.
    if _query_due(state, config.search_interval_s):
        state, query = _redetect(state, target.box, config)
        actions.extend(query)
    return state, tuple(actions)


def _lost_ends_in_search(state: State) -> bool:
    """Along the mission a target lost for `lost_resume_after_s` is given up and the search flies on; only a
    confirmed target the companion flies after keeps the lost rules (hold, `lost_action`)."""
    return state.along_mission and not (state.resume is MissionState.CONFIRMED and commanding(state))


def _given_up(state: State, config: MissionConfig) -> bool:
    """LOST's action was a mode request (loiter, RTL, land): the mission ends until the GCS restarts it."""
    return (
        state.mode is MissionState.LOST
        and state.lost_stage >= 2
        and config.lost_action is not LostAction.HOLD
    )


# --- helpers -----------------------------------------------------------------------------------------


def _acquire_timeout(state: State, config: MissionConfig) -> Result:
    """The tracker did not lock on the candidate: the search goes on. A candidate the back-end verified (its
    final verdict) and placed still awaits the supervisor, out of view, cropped from its keyframe (`State
    .pending`): the back-end found the person; a tracker that cannot hold a few pixels must not lose them."""
    if state.now_s - state.since_s <= config.acquire_timeout_s:
        return state, ()
    target = state.target
    new, actions = _start_search(state, "tracker did not lock", config)
    actions = (TrackerStop("acquire timeout"), *actions)
    if target is None or target.early is not None or target.operator_selected or target.position is None:
        return new, actions
    new, said = _left_awaiting(new, target)
    status = "awaiting" if awaiting_decision(new) is target else "queued"  # else after the one shown
    return new, (*actions, replace(_report(target, status), keyframe_id=target.keyframe_id), *said)


def _query(state: State, purpose: QueryPurpose, roi: Box | None, early_answer: bool = False) -> Result:
    mission = state.mission
    if mission is None:
        return state, ()
    qid = state.next_query_id
    queries = (*state.queries, (qid, purpose))[-_MAX_QUERIES_IN_FLIGHT:]
    new = replace(state, next_query_id=qid + 1, queries=queries, last_query_s=state.now_s)
    return new, (BackendQuery(qid, purpose, mission.prompt, mission.superset, roi, early_answer),)


def _search_query(state: State, config: MissionConfig) -> Result:
    return _query(state, QueryPurpose.SEARCH, None, config.early_answer and not state.early_refused)


def _query_due(state: State, interval_s: float) -> bool:
    return state.last_query_s is None or state.now_s - state.last_query_s >= interval_s


def _report_due(state: State, config: MissionConfig) -> bool:
    return state.last_report_s is None or state.now_s - state.last_report_s >= config.reverify_interval_s


def _scan(state: State, config: MissionConfig) -> Result:
    """SEARCHING's setpoint: a slow yaw scan, or standing still; none while the back-end is down."""
    if state.backend_down:
        return state, ()
    height = state.telemetry.height_agl if state.telemetry is not None else None
    state, engage = _resume_from_hold(state)
    return state, (
        *engage,
        SendSetpoint(apply_limits(Setpoint(yaw_rate=config.search_yaw_rate), config.limits, height)),
    )


def _hold(state: State) -> State:
    """The vehicle is being held on our request: the offboard mode leaving next is ours."""
    return replace(state, holding=True, held_at_s=state.now_s)


def _resume_from_hold(state: State) -> Result:
    """Setpoints after a Hold: ask for the offboard mode again when allowed (the hold may have left it)."""
    if not state.holding:
        return state, ()
    return _engage(replace(state, holding=False), "resume after hold")


def _track_check(state: State) -> Result:
    """A check of the followed track looks at the whole frame, not the region around the track: after a
    silent switch to a neighbour the target is often just outside that region (people walking side by side
    stand 1.5-2 box widths apart), and only an answer that shows it can undo the switch. Measured with
    `eval` (docs/benchmarks.md, issue 12 round 6): checks in the 3x region cost uav123_group1_1 0.654 ->
    0.413 with nano."""
    return _query(state, QueryPurpose.TRACK_CHECK, None)


def _redetect(state: State, box: Box, config: MissionConfig) -> Result:
    """A re-detect query around the last box, the region growing with the time lost (None: whole frame)."""
    return _query(state, QueryPurpose.REDETECT, redetect_roi(box, state.now_s - state.since_s, config))


def redetect_roi(box: Box, lost_for_s: float, config: MissionConfig) -> Box | None:
    """The re-detection region after `lost_for_s` seconds lost (`behaviors.query_region`); None once it is
    the whole frame."""
    cam = config.camera
    return redetect_region(
        box, lost_for_s, config.redetect_roi_scale, config.redetect_full_frame_s, cam.width, cam.height
    )


def _redetect_verdict_ok(verdict: Verdict, near_last_box: bool, operator_selected: bool) -> bool:
    if not near_last_box:
        return verdict is Verdict.YES
    return operator_selected or verdict is not Verdict.NO


def _centre_inside(box: Box, region: Box | None) -> bool:
    return region is not None and region.x <= box.cx <= region.x2 and region.y <= box.cy <= region.y2


def _roi(box: Box, config: MissionConfig) -> Box | None:
    """Where to look for the target: its box grown by `redetect_roi_scale`, inside the image."""
    return around(box, config.redetect_roi_scale, config.camera.width, config.camera.height)


def _follow(state: State, box: Box, time_s: float, config: MissionConfig) -> tuple[State, tuple[Action, ...]]:
    if state.backend_down or not commanding(state):
        return state, ()
    telemetry = state.telemetry or Telemetry(time_s, height_agl=math.nan)  # unknown height: zero output
    confirmed = state.mode is MissionState.CONFIRMED
    lateral = config.orbit_speed_m_s if confirmed and config.on_confirm is ConfirmAction.ORBIT else 0.0
    goal = FollowGoal(config.standoff_m, lateral, descent_allowed=confirmed)
    setpoint, control = follow_step(
        box, config.camera, telemetry, goal, config.gains, config.limits, state.control, time_s
    )
    state, engage = _resume_from_hold(replace(state, control=control))
    return state, (*engage, SendSetpoint(setpoint))


def _arrived(state: State, box: Box, config: MissionConfig) -> bool:
    if state.now_s - state.since_s >= config.approach_timeout_s or not commanding(state):
        return True  # looking only (along the mission, not engaged): the supervisor is asked at once
    if state.telemetry is None:
        return False
    distance = estimate_distance(config.camera, state.telemetry, box, config.gains.target_height_m)
    return distance is not None and abs(distance.ground_m - config.standoff_m) <= config.arrive_tolerance_m


def _excluded(state: State, config: MissionConfig, answer: BackendAnswer) -> Callable[[Detection], bool]:
    """Which of the answer's candidates were rejected by the supervisor (via this vehicle by id, place or
    looks; via another of the fleet mission by place) or are a find the search already went on from. Judged
    together: of one keyframe's candidates only the nearest takes a rejection by place
    (`RejectionMemory.matches_each`), so a rejected person does not hide the one beside them."""
    seen = [
        (d.candidate_id, _position(state, d, config, answer.pose), d.signature) for d in answer.candidates
    ]
    matched = [
        memory.matches_each(seen, answer.query_id)
        for memory in (state.rejections, state.found, state.fleet_rejections)
    ]
    excluded = [d for i, d in enumerate(answer.candidates) if any(m[i] is not None for m in matched)]
    return lambda det: any(det is d for d in excluded)


def _places(places: Sequence[tuple[str, GeoEstimate | None]], config: MissionConfig) -> RejectionMemory:
    """Where candidates already put to the supervisor stand, matched as a rejection is before the back-end
    holds it (by id, or within the radius): the back-end's ids are per keyframe."""
    entries = tuple(RejectedTarget(cid, at) for cid, at in places if at is not None)
    return RejectionMemory(entries, radius_m=config.rejection_radius_m, capacity=len(entries) or 1)


def _choose(
    state: State,
    candidates: Sequence[Detection],
    config: MissionConfig,
    answer: BackendAnswer,
    placed: Sequence[tuple[str, GeoEstimate | None]] = (),
    tracked: Detection | None = None,
) -> tuple[Detection, GeoEstimate | None, int] | None:
    """A verified candidate not rejected or found before (`select_first_acquisition`), nor already awaiting
    a decision out of the tracker's hold (`State.pending`: seen again, it is not put to the supervisor
    twice) or where `placed` stand, nor `tracked`; where it stands; and how many others it was chosen from
    by the detector's score alone (`candidate_selection.alike`)."""
    eligible = _eligible(state, config, answer, placed, tracked)
    best = select_first_acquisition(candidates, config.accept_uncertain, eligible)
    if best is None:
        return None
    others = alike(candidates, best, config.accept_uncertain, eligible)
    return best, _position(state, best, config, answer.pose), others


def _eligible(
    state: State,
    config: MissionConfig,
    answer: BackendAnswer,
    placed: Sequence[tuple[str, GeoEstimate | None]] = (),
    tracked: Detection | None = None,
) -> Callable[[Detection], bool]:
    """Which of the answer's candidates `_choose` may take (see there)."""
    excluded = _excluded(state, config, answer)
    queued = _places([*((p.candidate_id, p.fix) for p in state.pending), *placed], config)
    # As a rejection: of the keyframe's others (the tracked one is someone else), the nearest is the one queued.
    others = [d for d in answer.candidates if d is not tracked]
    seen = [(d.candidate_id, _position(state, d, config, answer.pose), ()) for d in others]
    taken = [d for d, match in zip(others, queued.matches_each(seen), strict=True) if match is not None]

    def eligible(d: Detection) -> bool:
        return d is not tracked and d.box.is_valid() and not excluded(d) and not any(d is t for t in taken)

    return eligible


def _position(
    state: State, det: Detection, config: MissionConfig, pose: Telemetry | None
) -> GeoEstimate | None:
    """Where `det` stands on the ground, seen from `pose` (the vehicle when its keyframe was captured; else
    the latest telemetry: a surveying drone moves metres while a keyframe is verified)."""
    telemetry = pose or state.telemetry
    return locate_box(config.camera, telemetry, det.box) if telemetry else None


def _report(target: Target, status: str) -> ReportCandidate:
    # A confirmation reports the fix the track kept (a passing survey's last estimate can be poor, its best stale).
    return ReportCandidate(
        target.candidate_id,
        target.justification,
        target.verdict,
        target.fix if status == "confirmed" else target.position,
        target.box,
        status,
        target.confirmed_by if status == "confirmed" else "",
        target.fix_s if status == "confirmed" else target.position_s,
        unjudged=target.unjudged,
        alike=target.alike,
        stored=target.stored,
    )
