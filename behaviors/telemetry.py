"""The vehicle state the behaviours read, as decoded from the autopilot's MAVLink telemetry."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Telemetry:
    """A snapshot of the vehicle. Angles in radians, NED frame, heights in metres.

    `height_agl` is the height above the ground the target stands on (relative altitude from
    GLOBAL_POSITION_INT on flat ground). `offboard_active` is true while the autopilot is in the mode
    that accepts our setpoints (ArduPilot GUIDED, PX4 OFFBOARD), `mission_active` while it flies its own
    mission (ArduPilot AUTO, PX4 MISSION); `mission_item` is MISSION_CURRENT's sequence number (the item
    the mission is on or resumes at), `mission_items` its item count, None before the autopilot said.
    """

    time_s: float
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    height_agl: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    armed: bool = False
    mode: str = ""
    offboard_active: bool = False
    mission_active: bool = False
    mission_item: int | None = None
    mission_items: int | None = None
