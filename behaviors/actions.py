"""Everything the mission state machine asks the main loop to do. The loop executes them in order.

No action forces the autopilot: mode changes are requests the autopilot may refuse, and setpoints are
streamed by the link only while the autopilot is in the mode that accepts them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from behaviors.detection import Detection, Verdict
from behaviors.geolocation import GeoEstimate
from behaviors.geometry import Box
from behaviors.setpoint import Setpoint


class FlightMode(str, Enum):
    """Modes the behaviour may request; the MAVLink layer maps them to ArduPilot/PX4 custom modes."""

    OFFBOARD = "offboard"  # ArduPilot GUIDED, PX4 OFFBOARD
    LOITER = "loiter"
    RTL = "rtl"
    LAND = "land"
    MISSION = "mission"  # the autopilot's own mission: ArduPilot AUTO, PX4 MISSION (see ResumeMission)


class QueryPurpose(str, Enum):
    SEARCH = "search"  # find candidates anywhere in the frame
    REVERIFY = "reverify"  # check the tracked target again while the supervisor decides
    REDETECT = "redetect"  # find the lost target near its last position
    TRACK_CHECK = "track_check"  # "verified" policy: evidence about the followed track (a silent switch?)


@dataclass(frozen=True)
class SendSetpoint:
    """Stream this body-frame velocity (already limited by `apply_limits`) until the next one."""

    setpoint: Setpoint


@dataclass(frozen=True)
class Hold:
    """Stop while the mission still owns the vehicle (lost target, back-end unreachable): an explicit zero
    setpoint, then hold position the autopilot's way (`[mavlink] ardupilot_hold`); setpoints may resume."""

    reason: str


@dataclass(frozen=True)
class ReleaseControl:
    """Let go (every abort, an operator stop, on_confirm = hold): an explicit zero, the autopilot's hold mode
    requested unless the pilot already chose a mode, then no more setpoints; the pilot or GCS owns the
    vehicle."""

    reason: str


@dataclass(frozen=True)
class RequestMode:
    mode: FlightMode
    reason: str = ""


@dataclass(frozen=True)
class ResumeMission:
    """Hand the vehicle back to the autopilot's own mission (ArduPilot AUTO, PX4 MISSION) after a candidate
    the companion had taken it for: at mission item `item`, the one it broke off at (the link sets the
    current item only when the autopilot has moved on from it; None: wherever the autopilot stands).
    Streaming ends; the request is repeated briefly, never against a mode the pilot chose meanwhile."""

    item: int | None
    reason: str = ""


@dataclass(frozen=True)
class GcsMessage:
    """A short status line for the GCS (STATUSTEXT is 50 characters; keep `text` short)."""

    text: str
    severity: str = "info"  # "info", "warning" or "critical"


@dataclass(frozen=True)
class BackendQuery:
    """Send the next keyframe to the back-end; the answer comes back as a `BackendAnswer` with `query_id`."""

    query_id: int
    purpose: QueryPurpose
    prompt: str
    superset: str = ""
    roi: Box | None = None  # camera pixels; None for the whole frame
    early_answer: bool = False  # ask the fast stage first (answered with `final` False), then in full


@dataclass(frozen=True)
class TrackerInit:
    """(Re-)initialise the tracker on `box` in keyframe `keyframe_id` (-1: the newest frame)."""

    box: Box
    keyframe_id: int
    candidate_id: str = ""
    reinit: bool = False
    # The target's class: the candidate's detector label, or the mission's superset for an operator's box
    # ("" unknown). The loss signals model a person's shape only for people.
    label: str = ""


@dataclass(frozen=True)
class JudgeCandidates:
    """Give a back-end answer for the current track to the front-end's "verified" re-initialisation policy,
    which decides whether the evidence moves the track. Candidates at indices in `refused` are ones the
    mission does not accept as the described target (verdict "no", rejected by the supervisor or the
    rejection memory, a non-"yes" away from the last box): they may be the track's evidence, never its
    new target."""

    keyframe_id: int
    candidates: tuple[Detection, ...]
    refused: tuple[int, ...] = ()  # indices into `candidates`, ascending


@dataclass(frozen=True)
class TrackerStop:
    reason: str = ""


@dataclass(frozen=True)
class ReportCandidate:
    """Tell the supervisor about the target: sent on arrival, on each re-verification and on confirmation."""

    candidate_id: str
    justification: str
    verdict: Verdict
    position: GeoEstimate | None
    box: Box
    # "awaiting" (the one the supervisor is shown: candidate 0), "queued" (awaits after it: seen beside the
    # tracked one), "reverified" or "confirmed"
    status: str
    confirmed_by: str = ""  # with "confirmed": who confirmed ("supervisor page", "gcs")
    position_s: float = math.nan  # when `position` was observed (event time): how old it is
    # The keyframe `box` is in, for a candidate the tracker does not hold (its crop comes from there); -1: the
    # tracked one, in the newest frame.
    keyframe_id: int = -1
    # What the back-end could not judge of the description for it: the supervisor checks that by eye.
    unjudged: tuple[str, ...] = ()
    # Others of its answer the search could have taken as well (told apart by the detector's score alone).
    alike: int = 0
    # Seen in a keyframe kept through a back-end outage: `position_s` says how long ago.
    stored: bool = False


@dataclass(frozen=True)
class RememberRejection:
    """The supervisor rejected this target; the loop may log or persist it (the state already keeps it)."""

    candidate_id: str
    position: GeoEstimate | None
    signature: tuple[float, ...] = ()


Action = (
    SendSetpoint
    | Hold
    | ReleaseControl
    | RequestMode
    | ResumeMission
    | GcsMessage
    | BackendQuery
    | TrackerInit
    | JudgeCandidates
    | TrackerStop
    | ReportCandidate
    | RememberRejection
)
