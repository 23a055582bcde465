"""Everything the mission state machine reacts to. Each event carries the time it happened (seconds).

The main loop turns its inputs into these values and passes them to `behaviors.mission.step`; the
flight record stores them (see `behaviors.event_codec`) so a flight can be replayed decision by decision.
Tracker results and telemetry are the shared value types themselves; both carry `time_s`.
"""

from __future__ import annotations

from dataclasses import dataclass

from behaviors.detection import Detection
from behaviors.geometry import Box
from behaviors.mission_commands import MissionCommand
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult


@dataclass(frozen=True)
class BackendAnswer:
    """The back-end's answer to a `BackendQuery` (same `query_id`), about keyframe `keyframe_id`.

    Candidate boxes are in the camera's pixels (the client scales them back from the keyframe size).
    `pose` is the vehicle's telemetry when the keyframe was captured: a candidate is located on the ground
    from where the camera was then, not from where a surveying drone has flown since (None: use the latest).
    """

    time_s: float
    query_id: int
    keyframe_id: int
    candidates: tuple[Detection, ...] = ()
    final: bool = True  # false: the back-end's fast stage; the final verdicts on the keyframe follow
    pose: Telemetry | None = None
    # The tracker's trusted box on that keyframe when it was sent (None: nothing tracked, or not known): which
    # candidate is the tracked one, on the same frame.
    track_box: Box | None = None
    # The keyframe waited out a back-end outage in the companion's store (`pose` is its capture-time pose):
    # its query was forgotten when the back-end went down, and the person is long out of view.
    stored: bool = False


@dataclass(frozen=True)
class GcsCommand:
    """A command from the ground (GCS over MAVLink, or the supervisor page through the back-end)."""

    time_s: float
    command: MissionCommand


@dataclass(frozen=True)
class TimerTick:
    """The main loop's periodic tick; every timeout in the state machine is checked on these."""

    time_s: float


@dataclass(frozen=True)
class BackendUnreachable:
    """The back-end watchdog fired: no answer for `[safety] backend_lost_s`."""

    time_s: float
    reason: str = ""


@dataclass(frozen=True)
class RejectionShared:
    """The back-end took the supervisor's rejection of `candidate_id` (stored before it answered): from the
    next query on, its verifier judges every candidate against the rejected one's appearance."""

    time_s: float
    candidate_id: str


@dataclass(frozen=True)
class FleetRejection:
    """A rejection by another vehicle of the same fleet mission: where its rejected candidate stood, as that
    vehicle estimated it (the back-end keeps no uncertainty with it)."""

    vehicle_id: str
    rejection_id: int
    lat_deg: float
    lon_deg: float


@dataclass(frozen=True)
class FleetRejections:
    """The back-end listed these rejections by the other vehicles of fleet mission `mission_id`, new since
    it last listed them: candidates standing there are not proposed (`behaviors.mission`, by place only)."""

    time_s: float
    mission_id: str
    rejections: tuple[FleetRejection, ...]


@dataclass(frozen=True)
class AutopilotLinkLost:
    """No autopilot heartbeat for `[safety] heartbeat_timeout_s`."""

    time_s: float


@dataclass(frozen=True)
class PilotTakeover:
    """The pilot or GCS changed the flight mode away from the one that accepts our setpoints."""

    time_s: float
    mode: str = ""


@dataclass(frozen=True)
class CompanionHold:
    """A companion watchdog (stale frames, a stalled main loop) stopped the vehicle and asked for the hold
    mode itself: the mode change that follows is the companion's own, not a pilot's takeover."""

    time_s: float
    reason: str


Event = (
    TrackResult
    | BackendAnswer
    | Telemetry
    | GcsCommand
    | TimerTick
    | BackendUnreachable
    | RejectionShared
    | FleetRejections
    | AutopilotLinkLost
    | PilotTakeover
    | CompanionHold
)
