"""THE companion main loop: frames -> tracking front-end -> `behaviors.mission.step` -> actions.

Each iteration turns its inputs into behaviour events (telemetry, GCS commands, the tracker's result on
the newest frame, back-end answers, watchdog events, a timer tick), runs the pure state machine on each
and executes the actions it returns: setpoints, holds and mode requests go to the vehicle link, queries
to the background back-end worker (never waited for), tracker (re-)initialisations to the front-end,
status lines and candidate reports to the GCS.

Hooks for operations: a `LoopObserver` sees every event and every action (the flight record), and the
systemd `Notifier` gets READY once the autopilot and the camera are up, WATCHDOG only from a healthy
iteration, STOPPING on shutdown. `request_stop()` (SIGTERM) ends the loop: the vehicle is told to
stop (explicit zero, then hold) unless the pilot holds control, the GCS is told, and `run` returns
within a fraction of a second.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

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
from behaviors.detection import Detection
from behaviors.events import (
    AutopilotLinkLost,
    BackendAnswer,
    BackendUnreachable,
    CompanionHold,
    Event,
    FleetRejection,
    FleetRejections,
    GcsCommand,
    PilotTakeover,
    RejectionShared,
    TimerTick,
)
from behaviors.fleet_order import respond
from behaviors.geometry import Box
from behaviors.mission import (
    ACTIVE,
    MissionState,
    State,
    awaiting_after,
    awaiting_decision,
    commanding,
    initial_state,
    step,
)
from behaviors.mission_commands import MissionCommand, StartMission, TrackRectangle
from behaviors.mission_config import MissionConfig
from behaviors.reinit_policy import ReinitAction, ReinitDecision
from behaviors.scene_light import low_light_note, too_dark
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult
from cloudtrack.api_models import ALIKE_MAX, FleetOrder
from cloudtrack.service_notify import Notifier
from companion.cloud.backend_worker import BackendWorker
from companion.cloud.candidate_crop import candidate_crop
from companion.cloud.keyframe_store import KeyframeStore, StoreCounts
from companion.operator_notices import OperatorNotices
from companion.safety_watchdog import (
    BACKEND_UNREACHABLE,
    HEARTBEAT_LOST,
    LOOP_STALLED,
    STALE_FRAMES,
    SafetyEvent,
)
from companion.status_report import StatusReport
from companion.vision.frame_sources import Frame, FrameSource

log = logging.getLogger(__name__)

# A probe id no state-machine query uses: its answer only tells the behaviour the back-end is back.
PROBE_QUERY_ID = 0


class VehicleLink(Protocol):
    """`companion.mavlink.vehicle_link.VehicleLink` as the loop uses it (the autopilot, and the GCS through it)."""

    def telemetry(self) -> Telemetry | None: ...

    def commands(self) -> list[MissionCommand]: ...

    def safety_events(self) -> list[SafetyEvent]: ...

    def set_velocity(self, setpoint: Setpoint, descent_allowed: bool = False) -> None: ...

    def hold(self, reason: str) -> None: ...

    def enable_offboard(self) -> None: ...

    def request_offboard(self) -> None: ...

    def release_offboard(self, reason: str) -> None: ...

    def request_mode(self, action: str) -> None: ...

    def resume_mission(self, item: int | None, reason: str = "") -> None: ...

    def kick(self) -> None: ...

    def report_frame(self, when: float | None = None) -> None: ...

    def report_backend_ok(self, when: float | None = None) -> None: ...

    def report_target(self, when: float | None = None) -> None: ...

    def clear_target(self) -> None: ...

    def send_status(self, text: str, severity: int = 6) -> None: ...

    def send_value(self, name: str, value: float) -> None: ...

    def announce_find(
        self,
        lat: float,
        lon: float,
        sigma_m: float,
        slant_range_m: float,
        prompt: str,
        confirmed_by: str,
        seen_before_s: float | None = None,
    ) -> None: ...

    def send_find_position(self, lat: float, lon: float, sigma_m: float, slant_range_m: float) -> None: ...

    def report_tracking(self, box: Box | None, image_size: tuple[int, int]) -> None: ...


class BackendSessionLike(Protocol):
    """`companion.cloud.backend_session.BackendSession`: status for the supervisor page, its decisions, rejections."""

    def update(self, status: dict[str, Any]) -> None: ...

    def reject(self, candidate_id: str, position: tuple[float, float] | None) -> None: ...

    def commands(self) -> list[MissionCommand]: ...

    def shared_rejections(self) -> list[str]: ...

    def last_success(self) -> float | None: ...

    def set_on_find(self, mission_id: str, on_find: str) -> None: ...

    def fleet_order(self) -> FleetOrder | None: ...

    def on_find_refused(self) -> str: ...


class SearchCoverageLike(Protocol):
    """`companion.search_coverage.SearchCoverage`: the search area, the share of it seen and its POD map,
    from the keyframes the back-end analysed."""

    pod_error: str
    error: str

    def start(self, target_class: str = "") -> None: ...

    def stop(self) -> None: ...

    def update(self, telemetry: Telemetry) -> None: ...

    def add_look(self, pose: Telemetry, capture_time: float, lit: bool = True) -> None: ...

    def report(self) -> dict[str, Any] | None: ...


class TrackingFrontendLike(Protocol):
    """`companion.vision.tracking_frontend.TrackingFrontend` as the loop uses it."""

    def feed(self, frame: Frame) -> TrackResult: ...

    def start(self, keyframe_id: int, box: Any, kind: str = "", detected: bool = False) -> bool: ...

    def apply_candidates(self, keyframe_id: int, detections: Sequence[Detection]) -> Detection | None: ...

    def judge_candidates(
        self, keyframe_id: int, detections: Sequence[Detection], refused: Collection[int] = ()
    ) -> ReinitDecision | None: ...

    def stop(self) -> None: ...


class LoopObserver(Protocol):
    """Sees everything the loop decides, in order (flight record, SITL event log, tests)."""

    def on_event(self, event: Event) -> None: ...

    def on_step(self, event: Event, state: State, actions: tuple[Action, ...]) -> None: ...

    def on_health(self, time_s: float, healthy: bool, reasons: tuple[str, ...]) -> None: ...


# An observer may also define `on_safety(event: SafetyEvent)` to see the link's watchdog and mode events, and
# `on_reinit(init: TrackerInit, time_s: float)` to see a re-initialisation the front-end's policy decided.


@dataclass(frozen=True)
class LoopSettings:
    tick_s: float = 0.1  # TimerTick period: every timeout in the state machine is checked on ticks
    frame_wait_s: float = 0.05  # longest wait for a new frame before the rest of the iteration runs
    frame_stale_s: float = 0.5  # no frame this long: not healthy (no watchdog ping)
    loop_stall_s: float = 0.5


SEVERITY = {"info": 6, "warning": 4, "critical": 2}  # MAV_SEVERITY for the GCS
NOT_CHECKED_CHARS = 150  # of the words nothing judged, on the GCS line (the page shows all of them)
MAX_CROPS = 8  # candidates' crops kept (a candidate awaiting a decision out of view keeps its crop)
KEYFRAMES_KEPT = 8  # as many as the mission keeps queries in flight: an older answer is stale
POSE_HISTORY = 400  # telemetry snapshots kept to locate a keyframe's candidates (40 s at 10 Hz)
FOLLOWING_STATES = frozenset(
    {MissionState.FOLLOWING, MissionState.AWAITING_SUPERVISOR, MissionState.CONFIRMED}
)


@dataclass
class LoopStats:
    iterations: int = 0
    frames: int = 0
    events: int = 0
    actions: int = 0
    setpoints: int = 0
    holds: int = 0
    max_iteration_s: float = 0.0


class MissionRunner:
    """Owns the behaviour state and runs the loop until `request_stop()`."""

    def __init__(
        self,
        mission: MissionConfig,
        frames: FrameSource,
        frontend: TrackingFrontendLike,
        vehicle: VehicleLink,
        backend: BackendWorker,
        session: BackendSessionLike | None = None,
        settings: LoopSettings = LoopSettings(),
        observers: Sequence[LoopObserver] = (),
        notifier: Notifier | None = None,
        clock: Callable[[], float] = time.monotonic,
        video_sinks: Sequence[Callable[[Any, Box | None, str], None]] = (),
        wall_clock: Callable[[], float] = time.time,
        keyframe_max_width: int = 640,  # [backend] max_keyframe_width: the status's boxes are in its pixels
        coverage: SearchCoverageLike | None = None,
        notices: OperatorNotices | None = None,
        keyframe_store: KeyframeStore | None = None,  # the worker's, for the status's counts
    ) -> None:
        # One policy for flight and eval: with the front-end's "verified" policy ([tracker] reinit_policy)
        # the mission hands it every answer for the track instead of choosing a re-init box itself.
        self.mission = replace(mission, verified_reinit=getattr(frontend, "policy", "c_box") == "verified")
        self.frames = frames
        self.frontend = frontend
        self.vehicle = vehicle
        self.backend = backend
        self.session = session
        self.settings = settings
        self.observers = list(observers)
        self.notifier = notifier
        # Why it cannot do its job right now (waiting for the autopilot or the back-end, a refused token or
        # prompt): said once per change in the journal and on the GCS, carried by every status report.
        self.notices = notices or OperatorNotices()
        self.clock = clock
        self.video_sinks = list(video_sinks)  # `(image, tracked box, state)` for every frame (record video)
        self.state = initial_state(mission)
        self.stats = LoopStats()
        self._stop = threading.Event()
        self._latest: Frame | None = None
        self._last_tick = -float("inf")
        self._ready = False
        self._pending_since: float | None = None  # oldest back-end request not answered yet
        self._crops: dict[str, dict[str, Any]] = {}  # candidate id -> its crop fields, encoded once
        # The newest keyframes sent, by frame id: (image, the trusted track's box on it). A candidate the
        # tracker does not hold is cropped from the keyframe the back-end found it in, and an answer says which
        # of its candidates the tracker held on that frame.
        self._keyframes: dict[int, tuple[Any, Box | None]] = {}
        self._poses: deque[Telemetry] = deque(maxlen=POSE_HISTORY)  # newest last
        self._result: TrackResult | None = None  # the tracker's result on the newest frame
        # Progress, finds and the tracked keyframe box for the status report.
        self.report = StatusReport(
            (mission.camera.width, mission.camera.height), keyframe_max_width, wall_clock
        )
        self.coverage = coverage
        # (when the GCS last got the value, tenths of the area seen and at the target POD announced)
        self._coverage_told: tuple[float, int, int] = (-float("inf"), 0, 0)
        self._pod_error_told = ""  # why there is no POD map, as last told
        self._no_area_told = ""  # why there is no search area, as last told
        self.keyframe_store = keyframe_store
        self._keyframe_width = keyframe_max_width  # the crop keeps the verifier's margin in native pixels
        self._analysed = 0  # keyframes of this mission analysed whole (laid on the search map)
        self._dark_keyframes = 0  # of them, too dark for the detection curve (no POD laid)
        self._fleet_seen: tuple[str, str, str | None] | None = None  # the fleet order last acted on
        # Ids of the other vehicles' rejections the last /fleet answer listed (each passed to the behaviour once).
        self._fleet_rejections_seen: set[int] = set()
        self._store_base = StoreCounts()  # the store's counts when this mission started

    # ------------------------------------------------------------------------------------------ control
    def request_stop(self) -> None:
        """Ask the loop to end (signal-handler safe: only sets an event)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def run(self) -> int:
        """Loop until `request_stop()`; then stop the vehicle, tell the GCS and return 0."""
        log.info("main loop started")
        try:
            while not self._stop.is_set():
                self.iterate()
        finally:
            self._shutdown()
        return 0

    # ---------------------------------------------------------------------------------------- iteration
    def iterate(self) -> None:
        """One pass: gather events, step the behaviour on each, execute the actions, report health."""
        started = self.clock()
        self.vehicle.kick()
        frame = self.frames.read(timeout_s=self.settings.frame_wait_s)
        now = self.clock()
        # The watchdogs' events first: a hold mode they asked for must be known as ours before telemetry
        # shows the offboard mode gone (else it reads as a pilot's takeover).
        events: list[Event] = self._safety_events()
        telemetry = self.vehicle.telemetry()
        if telemetry is not None and (
            self.state.telemetry is None or telemetry.time_s > self.state.telemetry.time_s
        ):
            events.append(telemetry)
            self._poses.append(telemetry)
        events.extend(self._ground_events(now))
        self._follow_fleet_order(now)
        if frame is not None:
            self._latest = frame
            self.stats.frames += 1
            self.vehicle.report_frame(frame.capture_time)
            result = self.frontend.feed(frame)
            self._result = result
            events.append(result)
        answer = self.backend.poll()
        if answer is not None:
            self._pending_since = None
            query_id = int(answer.fields.get("query_id", PROBE_QUERY_ID))
            if query_id != PROBE_QUERY_ID and answer.final:
                self.report.on_answer(answer.detections)
            # A stored keyframe carries its own capture-time pose: the history here is only 40 s long.
            pose = answer.pose if answer.stored else self._pose_at(answer.capture_time)
            self._lay_look(answer, pose)
            track_box = None if answer.stored else self._keyframes.get(answer.frame_id, (None, None))[1]
            if answer.stored and answer.image is not None:  # its candidates are cropped from it
                self._keep_keyframe(answer.frame_id, answer.image, None)
            events.append(
                BackendAnswer(
                    now,
                    query_id,
                    answer.frame_id,
                    answer.detections,
                    answer.final,
                    pose,
                    track_box,
                    answer.stored,
                )
            )
        if now - self._last_tick >= self.settings.tick_s:
            self._last_tick = now
            events.append(TimerTick(now))
        for event in events:
            self._handle(event)
        if frame is not None:
            self._video(frame, result)
        self._feed_watchdogs(now)
        self._tell_notices(telemetry is not None)
        self._report_health(started)

    def _lay_look(self, answer: Any, pose: Telemetry | None) -> None:
        """A keyframe the back-end analysed whole (a final answer to a query without a region) is a look at
        the search area from where it was captured; nothing else counts as searched."""
        if (
            pose is not None
            and answer.final
            and answer.fields.get("roi") is None
            and self.state.mode in ACTIVE
        ):
            self._analysed += 1
            lit = answer.mean_luma is None or not too_dark(answer.mean_luma)
            if lit:
                self.notices.set("light", None)
            else:  # the operator knows why the POD map stays where it is
                self._dark_keyframes += 1
                self.notices.set("light", low_light_note(answer.mean_luma, self._dark_keyframes))
            if self.coverage is not None:
                self.coverage.add_look(pose, answer.capture_time, lit)

    def _pose_at(self, when: float) -> Telemetry | None:
        """The newest telemetry received at or before `when` (a keyframe's capture time); None if none is
        that old (the behaviour then uses the latest)."""
        times = [t.time_s for t in self._poses]
        i = bisect.bisect_right(times, when)
        return self._poses[i - 1] if i > 0 else None

    def _handle(self, event: Event) -> None:
        self.stats.events += 1
        for obs in self.observers:
            obs.on_event(event)
        before = self.state
        self.state, actions = step(self.state, event, self.mission)
        if isinstance(event, GcsCommand) and isinstance(event.command, StartMission) and self.state.mission:
            self.report.start(self.state.mission.mission_id or self.state.mission.prompt)
            self._analysed = 0
            self._dark_keyframes = 0
            self.notices.set("light", None)
            self._fleet_seen = None
            mission = self.state.mission
            if self.session is not None and mission.on_find and mission.mission_id:
                self.session.set_on_find(mission.mission_id, mission.on_find)
            if self.keyframe_store is not None:
                self._store_base = self.keyframe_store.counts()
            self.notices.set("start", None)  # a start went through: an earlier refusal no longer holds
            self.notices.search_accepted()
            self._start_coverage()
        elif self.coverage is not None and before.mode in ACTIVE and self.state.mode not in ACTIVE:
            self.coverage.stop()  # aborted or stopped: the figures stay, no more views
        if isinstance(event, Telemetry) and self.coverage is not None and self.state.mode in ACTIVE:
            self.coverage.update(event)
        if _operator_started(event, self.state) and commanding(self.state):
            # A mission or an operator's track box the behaviour accepted may fly the vehicle once the
            # pilot or GCS selects GUIDED/OFFBOARD; asking for that mode itself is the behaviour's
            # RequestMode, emitted only when the running mission allowed engagement. Never arms. A search
            # along the autopilot's mission commands nothing: the link streams nothing (not even PX4's
            # pre-stream) until the behaviour takes the vehicle for a candidate.
            self.vehicle.enable_offboard()
        if self.state.mode is not before.mode:
            log.info("state %s -> %s (%s)", before.mode.value, self.state.mode.value, self.state.reason)
        for obs in self.observers:
            obs.on_step(event, self.state, actions)
        for action in actions:
            self._execute(action)
        if isinstance(event, TrackResult):
            self._report_track(event)

    def _execute(self, action: Action) -> None:
        self.stats.actions += 1
        if isinstance(action, SendSetpoint):
            self.stats.setpoints += 1
            self.vehicle.set_velocity(
                action.setpoint, descent_allowed=self.state.mode is MissionState.CONFIRMED
            )
        elif isinstance(action, Hold):
            self.stats.holds += 1
            self.vehicle.hold(action.reason)
        elif isinstance(action, ReleaseControl):
            self.vehicle.release_offboard(action.reason)
        elif isinstance(action, RequestMode):
            if action.mode is FlightMode.OFFBOARD:
                self.vehicle.request_offboard()
            else:
                self.vehicle.request_mode(action.mode.value)
        elif isinstance(action, ResumeMission):
            self.vehicle.resume_mission(action.item, action.reason)
        elif isinstance(action, GcsMessage):
            self.vehicle.send_status(action.text, SEVERITY.get(action.severity, 6))
        elif isinstance(action, BackendQuery):
            self._submit(action)
        elif isinstance(action, TrackerInit):
            self._tracker_init(action)
        elif isinstance(action, JudgeCandidates):
            self._judge(action)
        elif isinstance(action, TrackerStop):
            self.frontend.stop()
        elif isinstance(action, ReportCandidate):
            self._report_candidate(action)
        elif isinstance(action, RememberRejection):
            self.report.on_rejection()
            position = (
                (action.position.lat_deg, action.position.lon_deg) if action.position is not None else None
            )
            if self.session is not None:
                self.session.reject(action.candidate_id, position)

    def _submit(self, query: BackendQuery) -> None:
        frame = self._latest
        if frame is None:
            log.debug("query %d: no frame yet", query.query_id)
            return
        fields: dict[str, Any] = {"prompt": query.prompt, "query_id": query.query_id}
        if query.superset:
            fields["superset"] = query.superset
        if query.roi is not None:
            fields["roi"] = query.roi
        if query.early_answer:
            fields["early_answer"] = True
        if self.state.mission is not None and self.state.mission.mission_id:
            fields["mission_id"] = self.state.mission.mission_id
        # A search keyframe of the whole view goes with the pose it was captured from: kept through an
        # outage, its answer comes back long after this loop's pose history has moved on.
        search = query.purpose is QueryPurpose.SEARCH and query.roi is None
        pose = (self._pose_at(frame.capture_time) or self.state.telemetry) if search else None
        self.backend.submit(frame.frame_id, frame.image, frame.capture_time, pose=pose, **fields)
        result = self._result
        tracked = result is not None and result.frame_id == frame.frame_id and result.trusted
        track_box = result.box if tracked and result is not None else None
        self.report.on_keyframe(frame.frame_id, track_box)
        self._keep_keyframe(frame.frame_id, frame.image, track_box)
        if self._pending_since is None:
            self._pending_since = self.clock()

    def _keep_keyframe(self, frame_id: int, image: Any, track_box: Box | None) -> None:
        recent = list(self._keyframes.items())[-(KEYFRAMES_KEPT - 1) :]
        self._keyframes = {**dict(recent), frame_id: (image, track_box)}

    def _ground_events(self, now: float) -> list[Event]:
        """Commands from the GCS and the supervisor page, the rejections the back-end has taken, and the fleet
        mission's other vehicles' rejections new to this vehicle."""
        commands = self.vehicle.commands() + (self.session.commands() if self.session is not None else [])
        events: list[Event] = [GcsCommand(now, cmd) for cmd in commands]
        if self.session is not None:
            events.extend(RejectionShared(now, cid) for cid in self.session.shared_rejections())
            events.extend(self._fleet_rejections(now))
        return events

    def _fleet_rejections(self, now: float) -> list[Event]:
        """The other vehicles' rejections of this fleet mission that the back-end's last /fleet answer lists
        and the behaviour has not had yet (each once, by rejection id)."""
        mission = self.state.mission
        order = self.session.fleet_order() if self.session is not None else None
        if (
            mission is None
            or not mission.mission_id
            or order is None
            or order.mission_id != mission.mission_id
        ):
            return []
        new = tuple(
            FleetRejection(r.vehicle_id, r.rejection_id, r.position[0], r.position[1])
            for r in order.rejections
            if r.rejection_id not in self._fleet_rejections_seen
        )
        # Only the listed ids are kept: the list is the newest few, so one that left it is never listed again.
        self._fleet_rejections_seen = {r.rejection_id for r in order.rejections}
        for r in new:
            log.info(
                "rejected via %s (rejection %d) at %.7f, %.7f",
                r.vehicle_id,
                r.rejection_id,
                r.lat_deg,
                r.lon_deg,
            )
        return [FleetRejections(now, mission.mission_id, new)] if new else []

    def _follow_fleet_order(self, now: float) -> None:
        """A new order of the fleet mission for this vehicle (another vehicle's find was confirmed), acted
        on once as behaviors/fleet_order.py says: told to the GCS; with the start's leave to command, the
        mission ends (as the GCS's abort) and the autopilot is asked to hold or return."""
        mission = self.state.mission
        if self.session is None or mission is None or not mission.mission_id:
            return
        refused = self.session.on_find_refused()
        if refused:  # the start's on_find did not stand: the operator hears which one does
            self.notices.set("start", refused)
        order = self.session.fleet_order()
        if order is None or order.mission_id != mission.mission_id:
            return
        seen = (order.mission_id, order.order, order.found)
        if seen == self._fleet_seen:
            return
        self._fleet_seen = seen
        response = respond(order.order, order.found, mission.allow_engage)
        if response is None:
            return
        log.warning("fleet order %s (find %s): %s", order.order, order.found, response.message)
        self._execute(GcsMessage(response.message, "warning"))
        if response.abort is not None:
            self._handle(GcsCommand(now, response.abort))
        if response.mode is not None:
            self._execute(RequestMode(response.mode, response.message))

    def _tracker_init(self, action: TrackerInit) -> None:
        newest = self._latest.frame_id if self._latest is not None else 0
        keyframe = action.keyframe_id if action.keyframe_id >= 0 else newest
        if action.reinit:
            chosen = self.frontend.apply_candidates(
                keyframe, [Detection(action.box, 1.0, candidate_id=action.candidate_id)]
            )
            if chosen is not None:
                return
        detected = bool(action.candidate_id) and action.candidate_id != "operator"
        self.frontend.start(keyframe, action.box, action.label, detected=detected)

    def _judge(self, action: JudgeCandidates) -> None:
        decision = self.frontend.judge_candidates(action.keyframe_id, action.candidates, action.refused)
        if decision is None:
            return
        log.debug("answer on frame %d: %s (%s)", action.keyframe_id, decision.action.value, decision.reason)
        if decision.action is ReinitAction.REINIT and decision.index is not None:
            chosen = action.candidates[decision.index]
            # The re-initialisation the front-end decided, told like the mission's own (flight record, SITL).
            reinit = TrackerInit(chosen.box, action.keyframe_id, chosen.candidate_id, reinit=True)
            for obs in self.observers:
                on_reinit = getattr(obs, "on_reinit", None)
                if on_reinit is not None:
                    on_reinit(reinit, self.state.now_s)

    def _report_candidate(self, report: ReportCandidate) -> None:
        if report.keyframe_id >= 0:  # not the tracked one: cropped from its keyframe while that is kept
            image = self._keyframes.get(report.keyframe_id, (None, None))[0]
            self._candidate_crop(report.candidate_id, report.box, in_view=False, image=image)
        if report.status in ("awaiting", "queued"):  # put to the supervisor
            self.report.on_proposed(report.candidate_id)
        if report.status == "confirmed":
            self._report_find(report)
        else:
            where = ""
            if report.position is not None:
                where = f" at {report.position.lat_deg:.6f},{report.position.lon_deg:.6f}"
            self.vehicle.send_status(
                f"CANDIDATE {report.status.upper()} {report.candidate_id}{where}{self._seen_ago(report)}"
                f"{_alike(report.alike)}{_not_checked(report.unjudged)}",
                SEVERITY["info"],
            )
        if self.session is not None:
            self.session.update(self._status())

    def _seen_ago(self, report: ReportCandidate) -> str:
        """What the GCS line adds for a candidate seen in a keyframe kept through a back-end outage: how long
        ago it was there ("; seen 23 s ago")."""
        age = self.state.now_s - report.position_s
        return f"; seen {max(0.0, age):.0f} s ago" if report.stored and math.isfinite(age) else ""

    def _report_find(self, report: ReportCandidate) -> None:
        """A confirmed candidate is a find: announced to the GCS once (QGC pops it up), its position sent
        again with every later confirmed report, and carried by every status report (`find`)."""
        new = self.report.find_of(report.candidate_id) is None
        in_view = self.state.target is not None and self.state.target.candidate_id == report.candidate_id
        crop = self._candidate_crop(report.candidate_id or "tracked", report.box, in_view).get(
            "crop_jpeg_b64"
        )
        prompt = self.state.mission.prompt if self.state.mission is not None else ""
        find = self.report.record_find(report, prompt, crop, now_s=self.state.now_s)
        if find is None:
            self.vehicle.send_status(
                f"FOUND {report.candidate_id}: position unknown (no telemetry)", SEVERITY["critical"]
            )
            return
        if new:
            seen_before = find.time - find.seen_at if find.seen_at is not None else None
            log.warning(
                "FOUND %s at %.7f,%.7f +-%.1f m (confirmed by %s; position seen %s s before)",
                find.candidate_id, find.lat, find.lon, find.sigma_m, find.confirmed_by,
                "?" if seen_before is None else f"{seen_before:.1f}",
            )  # fmt: skip
            self.vehicle.announce_find(
                find.lat,
                find.lon,
                find.sigma_m,
                find.slant_range_m,
                find.prompt,
                find.confirmed_by,
                seen_before,
            )
        else:
            self.vehicle.send_find_position(find.lat, find.lon, find.sigma_m, find.slant_range_m)

    def _status(self) -> dict[str, Any]:
        state = self.state
        status: dict[str, Any] = {"state": state.mode.value, **self.report.fields(state, self._search())}
        notice = self.notices.current()
        if notice:
            status["reason"] = notice  # what keeps it from its job before why it is in its state
        if state.mission is not None:
            status["prompt"] = state.mission.prompt
            if state.mission.superset:
                status["superset"] = state.mission.superset  # the page warns of words outside it
            if state.mission.mission_id:
                status["mission_id"] = state.mission.mission_id
        if state.telemetry is not None:
            status["position"] = [state.telemetry.lat_deg, state.telemetry.lon_deg]
            status["altitude_m"] = state.telemetry.height_agl
        # The candidate awaiting the supervisor rides every report while it waits, whatever happens to the
        # track (a short loss, a re-acquisition, the survey flying on): the page keeps it and its Confirm button.
        awaiting = self._awaiting()
        if awaiting is not None:
            status["awaiting"] = awaiting
        # The page says how many more wait behind it, and which a slow supervisor never got to decide.
        more = [p.candidate_id for p in awaiting_after(state) if p.candidate_id]
        if more:
            status["awaiting_more"] = more
        if state.dropped_undecided:
            status["dropped_undecided"] = list(state.dropped_undecided)
        status["keyframes"] = self._keyframe_counts()
        return status

    def _keyframe_counts(self) -> dict[str, int]:
        """The status's `keyframes`, since the mission started: analysed whole, and the outage store's."""
        now = self.keyframe_store.counts() if self.keyframe_store is not None else StoreCounts()
        base = self._store_base
        return {
            "analysed": self._analysed,
            "stored": now.stored - base.stored,
            "waiting": now.waiting,
            "sent": now.sent - base.sent,
            "dropped": now.dropped - base.dropped,
        }

    def _awaiting(self) -> dict[str, Any] | None:
        """The candidate awaiting the supervisor's decision: the tracked one (also while it is lost), else
        one the search gave up before a decision (`State.pending`, out of view: its crop from when it was)."""
        state = self.state
        target = awaiting_decision(state)
        if target is None:
            return None
        tracked = target is state.target
        awaiting: dict[str, Any] = {
            "candidate_id": target.candidate_id or "tracked",
            "box": list(target.box.xyxy()),
            "verdict": target.verdict.value,
            "justification": target.justification[:2000],
            "unjudged": [word[:200] for word in target.unjudged[:32]],
            "alike": min(target.alike, ALIKE_MAX),
        }
        position = target.position if tracked else target.fix
        if position is not None:
            awaiting["position"] = [position.lat_deg, position.lon_deg]
            # How old it is: a Confirm on the page makes the find from it before the vehicle's own arrives.
            seen_at = self.report.wall_time(target.position_s if tracked else target.fix_s, state.now_s)
            if seen_at is not None:
                awaiting["seen_at"] = round(seen_at, 3)
        in_view = state.mode is MissionState.AWAITING_SUPERVISOR
        awaiting.update(self._candidate_crop(awaiting["candidate_id"], target.box, in_view))
        return awaiting

    def _start_coverage(self) -> None:
        """A search along the autopilot's mission covers the mission's area; on the spot there is none."""
        if self.coverage is None:
            return
        if self.state.along_mission and self.state.mode in ACTIVE and self.state.mission is not None:
            self.coverage.start(self.state.mission.superset)
            self._coverage_told = (-float("inf"), 0, 0)
            self._pod_error_told = ""
        else:
            self.coverage.stop()

    def _search(self) -> dict[str, Any] | None:
        """The status report's `search`: where the autopilot's mission stands (mode, item, item count) and,
        along it, the search area and the share of it seen."""
        t = self.state.telemetry
        if self.state.mission is None or t is None:
            return None
        search: dict[str, Any] = {"mode": t.mode[:32]}
        if t.mission_item is not None and 0 <= t.mission_item <= 65535:
            search["mission_item"] = t.mission_item
        if t.mission_items is not None:
            search["mission_items"] = t.mission_items
        covered = self.coverage.report() if self.coverage is not None else None
        self._tell_no_area(self.coverage.error if self.coverage is not None and covered is None else "")
        if covered is not None:
            search.update(covered)
            pod = covered.get("pod")
            self._tell_coverage(float(covered["coverage"]), pod)
        return search

    def _tell_no_area(self, why: str) -> None:
        """Once per reason: why the search has no area to map (no waypoints, too far from the vehicle, the
        download failing)."""
        if why and why != self._no_area_told:
            self.vehicle.send_status(f"NO SEARCH AREA: {why[:180]}", SEVERITY["warning"])
        self._no_area_told = why

    def _tell_coverage(self, share: float, pod: dict[str, Any] | None) -> None:
        """The share seen to the GCS: NAMED_VALUE_FLOAT `coverage` (0..1) once a second, and a status line at
        every tenth of the area seen or of the area at or above the target POD; once, why there is no POD
        map."""
        now = self.clock()
        last, tenths, pod_tenths = self._coverage_told
        if now - last < 1.0:
            return
        self.vehicle.send_value("coverage", share)
        reached = int(share * 10.0 + 1e-9)
        pod_share = float(pod["at_target"]) if pod is not None else 0.0
        pod_reached = int(pod_share * 10.0 + 1e-9)
        if reached > tenths or pod_reached > pod_tenths:
            at_pod = f"; {pod_share * 100:.0f}% at POD >= {float(pod['target_pod']):g}" if pod else ""
            self.vehicle.send_status(f"COVERAGE {reached * 10}% of the search area{at_pod}", SEVERITY["info"])
        self._coverage_told = (now, max(tenths, reached), max(pod_tenths, pod_reached))
        error = self.coverage.pod_error if self.coverage is not None else ""
        if error and error != self._pod_error_told:
            self.vehicle.send_status(f"NO POD MAP: {error[:180]}", SEVERITY["warning"])
        self._pod_error_told = error

    def _video(self, frame: Frame, result: TrackResult) -> None:
        box = result.box if result.trusted else None
        for sink in self.video_sinks:
            try:
                sink(frame.image, box, self.state.mode.value)
            except Exception:  # a full disk or a codec error must not stop the flight
                log.exception("video frame not recorded")

    def _candidate_crop(
        self, candidate_id: str, box: Box, in_view: bool = True, image: Any = None
    ) -> dict[str, Any]:
        """The supervisor's crop of this candidate from `image`, else from the newest frame (both native
        resolution; a keyframe kept through an outage is its sent JPEG, decoded), encoded once per
        candidate (and only while it is in view: a candidate out of view keeps the crop it had, or has none)."""
        if candidate_id not in self._crops:
            if image is None and in_view and self._latest is not None:
                image = self._latest.image
            if image is None:
                return {}
            crop = candidate_crop(image, box, keyframe_width=self._keyframe_width)
            if crop is None:
                return {}
            self._crops = {**dict(list(self._crops.items())[-(MAX_CROPS - 1) :]), candidate_id: crop}
        return self._crops[candidate_id]

    def _report_track(self, result: TrackResult) -> None:
        cam = self.mission.camera
        following = self.state.mode in FOLLOWING_STATES
        self.vehicle.report_tracking(
            result.box if result.trusted and following else None, (cam.width, cam.height)
        )
        if following and result.trusted:
            self.vehicle.report_target(result.time_s)
        elif not following:
            self.vehicle.clear_target()

    # ---------------------------------------------------------------------------------------- watchdogs
    def _safety_events(self) -> list[Event]:
        """The link's watchdog and mode-policy events as behaviour events (the link already stopped)."""
        out: list[Event] = []
        for ev in self.vehicle.safety_events():
            for obs in self.observers:
                on_safety = getattr(obs, "on_safety", None)
                if on_safety is not None:
                    on_safety(ev)
            event = behavior_event(ev)
            if event is not None:
                out.append(event)
        return out

    def _feed_watchdogs(self, now: float) -> None:
        """The back-end counts as alive from its last answer or status report. A request still out is given
        the benefit of the doubt (overdue only backend_lost_s after it went out), but only while nothing
        has failed since the last answer: fresh requests failing one after another prove nothing alive."""
        health = self.backend.health()
        if not health.busy:
            self._pending_since = None  # answered or failed: nothing is overdue any more
        times = [
            t for t in (health.last_success_time, self.session.last_success() if self.session else None) if t
        ]
        if self._pending_since is not None and health.consecutive_failures == 0:
            times.append(self._pending_since)
        elif self.session is None and health.consecutive_failures == 0:
            times.append(now)
        if times:
            self.vehicle.report_backend_ok(max(times))
        if self.session is not None:
            self.session.update(self._status())

    def _tell_notices(self, heard: bool) -> None:
        """Each change of what the operator must know, once: in the journal and on the GCS."""
        self.notices.autopilot_heard(heard)
        for topic, text in self.notices.changes():
            if text is not None:
                log.warning("%s", text)
                # With no autopilot there is no GCS link to tell; a refused start the GCS heard already.
                if topic not in ("autopilot", "start"):
                    self.vehicle.send_status(text, SEVERITY["warning"])
            elif topic == "autopilot":
                log.info("autopilot heard on %s", self.notices.autopilot_address)
            elif topic in ("backend", "auth"):
                log.info("the back-end at %s answers", self.notices.backend_url)
                self.vehicle.send_status("back-end answers", SEVERITY["info"])

    def _report_health(self, started: float) -> None:
        end = self.clock()
        duration = end - started
        self.stats.iterations += 1
        self.stats.max_iteration_s = max(self.stats.max_iteration_s, duration)
        reasons: list[str] = []
        if duration > self.settings.loop_stall_s:
            reasons.append("loop_stalled")
        if self.vehicle.telemetry() is None:
            reasons.append("no_telemetry")
        if self._latest is None or end - self._latest.capture_time > self.settings.frame_stale_s:
            reasons.append("no_frames")
        healthy = not reasons
        if not self._ready and healthy:
            self._ready = True
            log.info("autopilot and camera up: ready")
            if self.notifier is not None:
                self.notifier.ready("autopilot and camera up")
        if healthy and self.notifier is not None:
            self.notifier.watchdog()
        for obs in self.observers:
            obs.on_health(end, healthy, tuple(reasons))

    # ----------------------------------------------------------------------------------------- shutdown
    def _shutdown(self) -> None:
        if self.notifier is not None:
            self.notifier.stopping("companion stopping")
        try:
            if self.state.mode in ACTIVE:
                self.vehicle.release_offboard("companion stopping")  # stop, hold mode, then silence
            self.vehicle.send_status("CloudTrack companion stopping", SEVERITY["warning"])
        except Exception:  # the link may already be gone; shutting down must still finish
            log.exception("could not tell the vehicle we are stopping")
        self.backend.close(timeout_s=0.2)
        self.frames.close()
        log.info("main loop stopped (%d iterations, %d frames)", self.stats.iterations, self.stats.frames)


def _operator_started(event: Event, state: State) -> bool:
    """A GCS start or track box that the behaviour accepted (it is now flying a mission)."""
    return (
        isinstance(event, GcsCommand)
        and isinstance(event.command, (StartMission, TrackRectangle))
        and state.mode in ACTIVE
    )


def behavior_event(ev: SafetyEvent) -> Event | None:
    """The behaviour event a link safety event stands for, if any (the link has already stopped the vehicle)."""
    if ev.reason == HEARTBEAT_LOST and ev.action == "stop":
        return AutopilotLinkLost(ev.time_s)
    if ev.reason == BACKEND_UNREACHABLE and ev.action == "stop":
        return BackendUnreachable(ev.time_s, "no answer")
    if ev.reason == BACKEND_UNREACHABLE and ev.action == "cleared":
        # The behaviour resumes once the back-end answers: this is that answer (no query of its own).
        return BackendAnswer(ev.time_s, PROBE_QUERY_ID, -1, ())
    if ev.by_other_party:
        return PilotTakeover(ev.time_s, ev.mode)
    if ev.reason in (STALE_FRAMES, LOOP_STALLED) and ev.action == "stop":
        return CompanionHold(ev.time_s, ev.reason)
    return None


def _alike(others: int) -> str:
    """What the GCS line adds for a candidate chosen from others the search could have taken as well
    (`behaviors.candidate_selection.alike`): the choice among them was the detector's score, no judgement."""
    return f"; {others} others alike" if others > 0 else ""


def _not_checked(unjudged: tuple[str, ...]) -> str:
    """What the GCS line adds for a candidate: the description's words the back-end could not judge, which
    the supervisor must check by eye before confirming ("; not checked: minivan")."""
    if not unjudged:
        return ""
    words = "; ".join(unjudged)
    if len(words) > NOT_CHECKED_CHARS:
        words = words[: NOT_CHECKED_CHARS - 3].rstrip() + "..."
    return f"; not checked: {words}"


def _box(box: Any) -> list[float] | None:
    return None if box is None else [round(box.x, 1), round(box.y, 1), round(box.w, 1), round(box.h, 1)]


def describe_event(event: Event) -> dict[str, Any] | None:
    """A JSON-ready summary of an event for the event log; None for plain telemetry and ticks (too many)."""
    if isinstance(event, TrackResult):
        return {
            "kind": "track",
            "t": event.time_s,
            "frame_id": event.frame_id,
            "box": _box(event.box),
            "trusted": event.trusted,
            "lost_reason": event.lost_reason,
        }
    if isinstance(event, BackendAnswer):
        return {
            "kind": "answer",
            "t": event.time_s,
            "query_id": event.query_id,
            "keyframe_id": event.keyframe_id,
            "final": event.final,
            **({"stored": True} if event.stored else {}),
            "candidates": [
                {
                    "id": c.candidate_id,
                    "box": _box(c.box),
                    "verdict": c.verdict.value,
                    "justification": c.justification[:120],
                }
                for c in event.candidates
            ],
        }
    if isinstance(event, GcsCommand):
        return {
            "kind": "command",
            "t": event.time_s,
            "command": type(event.command).__name__,
            **{k: str(v) for k, v in vars(event.command).items()},
        }
    if isinstance(event, (AutopilotLinkLost, BackendUnreachable)):
        return {"kind": type(event).__name__, "t": event.time_s}
    if not isinstance(event, (Telemetry, TimerTick)):
        return {"kind": type(event).__name__, "t": event.time_s}
    return None


def describe_action(action: Action, t: float) -> dict[str, Any]:
    if isinstance(action, SendSetpoint):
        s = action.setpoint
        return {
            "kind": "setpoint",
            "t": t,
            "forward": round(s.forward, 3),
            "right": round(s.right, 3),
            "down": round(s.down, 3),
            "yaw_rate": round(s.yaw_rate, 4),
        }
    if isinstance(action, TrackerInit):
        return {
            "kind": "reinit" if action.reinit else "tracker_init",
            "t": t,
            "box": _box(action.box),
            "keyframe_id": action.keyframe_id,
            "candidate_id": action.candidate_id,
        }
    if isinstance(action, JudgeCandidates):
        return {
            "kind": "judge",
            "t": t,
            "keyframe_id": action.keyframe_id,
            "candidates": len(action.candidates),
            "refused": list(action.refused),
        }
    if isinstance(action, ReportCandidate):
        return {
            "kind": "candidate_report",
            "t": t,
            "status": action.status,
            "candidate_id": action.candidate_id,
            "verdict": action.verdict.value,
            "box": _box(action.box),
            "justification": action.justification[:120],
            **({"keyframe_id": action.keyframe_id} if action.keyframe_id >= 0 else {}),
            **({"unjudged": list(action.unjudged)} if action.unjudged else {}),
            **({"alike": action.alike} if action.alike else {}),
            **({"stored": True, "seen_s": action.position_s} if action.stored else {}),
        }
    if isinstance(action, BackendQuery):
        return {
            "kind": "query",
            "t": t,
            "query_id": action.query_id,
            "purpose": action.purpose.value,
            "prompt": action.prompt,
            "roi": _box(action.roi),
        }
    if isinstance(action, (Hold, ReleaseControl, TrackerStop)):
        return {
            "kind": {Hold: "hold", ReleaseControl: "release", TrackerStop: "tracker_stop"}[type(action)],
            "t": t,
            "reason": action.reason,
        }
    if isinstance(action, RequestMode):
        return {"kind": "request_mode", "t": t, "mode": action.mode.value, "reason": action.reason}
    if isinstance(action, ResumeMission):
        return {"kind": "resume_mission", "t": t, "item": action.item, "reason": action.reason}
    if isinstance(action, GcsMessage):
        return {"kind": "gcs_message", "t": t, "text": action.text, "severity": action.severity}
    return {"kind": type(action).__name__, "t": t, "candidate_id": getattr(action, "candidate_id", "")}


class EventLogObserver:
    """Writes the loop's decisions as JSON lines (`t` on the monotonic clock) to `write(line)`.

    State changes, every action, tracker results, back-end answers, GCS commands and health changes: the
    SITL scenario runner reads this to score a run, and it doubles as a readable trace of a flight.
    """

    def __init__(self, write: Callable[[str], object]) -> None:
        import json

        self._dumps = json.dumps
        self._write = write
        self._mode: MissionState | None = None
        self._healthy: bool | None = None
        self._lock = threading.Lock()

    def _emit(self, entry: dict[str, Any]) -> None:
        with self._lock:
            self._write(self._dumps(entry, default=str) + "\n")

    def on_event(self, event: Event) -> None:
        entry = describe_event(event)
        if entry is not None:
            self._emit(entry)

    def on_step(self, event: Event, state: State, actions: tuple[Action, ...]) -> None:
        if state.mode is not self._mode:
            self._mode = state.mode
            self._emit(
                {
                    "kind": "state",
                    "t": state.now_s,
                    "state": state.mode.value.lower(),
                    "reason": state.reason,
                    "prompt": state.mission.prompt if state.mission else "",
                }
            )
        for action in actions:
            self._emit(describe_action(action, state.now_s))

    def on_safety(self, event: SafetyEvent) -> None:
        self._emit(
            {
                "kind": "safety",
                "t": event.time_s,
                "reason": event.reason,
                "action": event.action,
                "detail": event.detail,
                "by_other_party": event.by_other_party,
            }
        )

    def on_reinit(self, init: TrackerInit, time_s: float) -> None:
        self._emit(describe_action(init, time_s))

    def on_health(self, time_s: float, healthy: bool, reasons: tuple[str, ...]) -> None:
        if healthy is not self._healthy:
            self._healthy = healthy
            self._emit({"kind": "health", "t": time_s, "healthy": healthy, "reasons": list(reasons)})
