"""Commands from the ground (GCS over MAVLink, or the supervisor web page through the back-end)."""

from __future__ import annotations

from dataclasses import dataclass

from behaviors.geometry import Box


@dataclass(frozen=True)
class StartMission:
    """Begin searching for `prompt`. `allow_engage` lets the companion request GUIDED/OFFBOARD itself."""

    prompt: str
    superset: str = ""
    allow_engage: bool = False
    mission_id: str = ""
    # What the fleet does on the mission's first confirmed find ("continue", "hold", "return"; "": not set
    # by this start). Set on the back-end once for the mission; behaviors/fleet_order.py acts on it.
    on_find: str = ""


@dataclass(frozen=True)
class AbortMission:
    reason: str = "gcs"


@dataclass(frozen=True)
class ConfirmCandidate:
    candidate_id: str = ""  # empty: the candidate currently awaiting the supervisor
    by: str = ""  # who confirmed: "supervisor page", "gcs" (reported with the find)


@dataclass(frozen=True)
class RejectCandidate:
    candidate_id: str = ""


@dataclass(frozen=True)
class TrackRectangle:
    """Operator drew a box (MAV_CMD_CAMERA_TRACK_RECTANGLE): track it, no semantic check needed."""

    box: Box


@dataclass(frozen=True)
class StopTracking:
    pass


MissionCommand = (
    StartMission | AbortMission | ConfirmCandidate | RejectCandidate | TrackRectangle | StopTracking
)
