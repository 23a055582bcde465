"""The autopilot's own mission (the flight plan it flies in AUTO / Mission mode) as MAVLink mission items.

Value types only: the wire exchange is `cloudtrack/mission_protocol.py`. Fields are MISSION_ITEM_INT's, so
an item survives an upload and a download unchanged: `x`/`y` are latitude/longitude in degrees * 1e7 for a
position item (param5/param6 as integers for others), `z` the altitude in metres in the item's frame.
Sequence numbers are not stored: an item's place in the list is its number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# MAV_CMD values this project plans or reads (MAVLink common.xml).
NAV_WAYPOINT = 16
NAV_LOITER_UNLIM = 17
NAV_LOITER_TURNS = 18
NAV_LOITER_TIME = 19
NAV_RETURN_TO_LAUNCH = 20
NAV_LAND = 21
NAV_TAKEOFF = 22
NAV_LOITER_TO_ALT = 31
NAV_SPLINE_WAYPOINT = 82
DO_CHANGE_SPEED = 178
# MAV_FRAME values used in mission items.
FRAME_GLOBAL = 0
FRAME_MISSION = 2  # not a position: DO_* commands
FRAME_GLOBAL_RELATIVE_ALT = 3  # altitude above home: what QGroundControl plans with
FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
FRAME_GLOBAL_TERRAIN_ALT = 10
FRAME_GLOBAL_TERRAIN_ALT_INT = 11
GLOBAL_FRAMES = frozenset(
    (
        FRAME_GLOBAL,
        FRAME_GLOBAL_RELATIVE_ALT,
        FRAME_GLOBAL_INT,
        FRAME_GLOBAL_RELATIVE_ALT_INT,
        FRAME_GLOBAL_TERRAIN_ALT,
        FRAME_GLOBAL_TERRAIN_ALT_INT,
    )
)
# A global frame and its _INT twin (the same place, integer coordinates): PX4 answers a MISSION_ITEM_INT
# download with the _INT frame whichever was uploaded.
INT_FRAMES = {
    FRAME_GLOBAL: FRAME_GLOBAL_INT,
    FRAME_GLOBAL_RELATIVE_ALT: FRAME_GLOBAL_RELATIVE_ALT_INT,
    FRAME_GLOBAL_TERRAIN_ALT: FRAME_GLOBAL_TERRAIN_ALT_INT,
}
# Navigation commands that fly to the item's latitude/longitude (a take-off's position is optional).
POSITION_COMMANDS = frozenset(
    (NAV_WAYPOINT, NAV_LOITER_UNLIM, NAV_LOITER_TURNS, NAV_LOITER_TIME, NAV_LAND, NAV_LOITER_TO_ALT,
     NAV_SPLINE_WAYPOINT)
)  # fmt: skip
SPEED_TYPE_GROUND = 1  # DO_CHANGE_SPEED param1 (0 airspeed, 1 ground speed)
COMMAND_NAMES = {
    NAV_WAYPOINT: "NAV_WAYPOINT",
    NAV_LOITER_UNLIM: "NAV_LOITER_UNLIM",
    NAV_LOITER_TURNS: "NAV_LOITER_TURNS",
    NAV_LOITER_TIME: "NAV_LOITER_TIME",
    NAV_RETURN_TO_LAUNCH: "NAV_RETURN_TO_LAUNCH",
    NAV_LAND: "NAV_LAND",
    NAV_TAKEOFF: "NAV_TAKEOFF",
    NAV_LOITER_TO_ALT: "NAV_LOITER_TO_ALT",
    NAV_SPLINE_WAYPOINT: "NAV_SPLINE_WAYPOINT",
    DO_CHANGE_SPEED: "DO_CHANGE_SPEED",
}


def degrees_e7(value: float) -> int:
    """Degrees as MISSION_ITEM_INT's integer (1e-7 degree, about 1 cm)."""
    return round(value * 1e7)


@dataclass(frozen=True)
class MissionItem:
    """One mission item, as MISSION_ITEM_INT carries it (without seq, target, current, mission_type)."""

    command: int
    frame: int = FRAME_GLOBAL_RELATIVE_ALT
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: bool = True

    @classmethod
    def waypoint(cls, lat_deg: float, lon_deg: float, altitude_m: float, hold_s: float = 0.0) -> MissionItem:
        """NAV_WAYPOINT at `altitude_m` above home; param4 (yaw) NaN leaves the heading to the autopilot
        (ArduCopter WP_YAW_BEHAVIOR, PX4 MPC_YAW_MODE: both face the next waypoint by default)."""
        return cls(
            NAV_WAYPOINT, FRAME_GLOBAL_RELATIVE_ALT, hold_s, 0.0, 0.0, math.nan,
            degrees_e7(lat_deg), degrees_e7(lon_deg), altitude_m,
        )  # fmt: skip

    @classmethod
    def takeoff(cls, altitude_m: float) -> MissionItem:
        """NAV_TAKEOFF to `altitude_m` above home, where the vehicle stands (no position: 0, 0)."""
        return cls(NAV_TAKEOFF, FRAME_GLOBAL_RELATIVE_ALT, 0.0, 0.0, 0.0, math.nan, 0, 0, altitude_m)

    @classmethod
    def change_speed(cls, speed_m_s: float) -> MissionItem:
        """DO_CHANGE_SPEED: ground speed from here on (throttle unchanged: param3 -1)."""
        return cls(DO_CHANGE_SPEED, FRAME_MISSION, SPEED_TYPE_GROUND, speed_m_s, -1.0, 0.0, 0, 0, 0.0)

    @property
    def lat_deg(self) -> float:
        return self.x / 1e7

    @property
    def lon_deg(self) -> float:
        return self.y / 1e7

    @property
    def has_position(self) -> bool:
        """A navigation item that flies to a latitude/longitude (a take-off at 0, 0 has none)."""
        return (
            self.frame in GLOBAL_FRAMES
            and self.command in (POSITION_COMMANDS | {NAV_TAKEOFF})
            and (self.x != 0 or self.y != 0)
        )

    @property
    def name(self) -> str:
        return COMMAND_NAMES.get(self.command, f"MAV_CMD {self.command}")

    def same_as(self, other: MissionItem, tolerance: float = 1e-3) -> bool:
        """Equal as the autopilot stores it: params and altitude compared as float32 (NaN equals NaN)."""

        def close(a: float, b: float) -> bool:
            return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-6, abs_tol=tolerance)

        return (self.command, self.frame, self.x, self.y, self.autocontinue) == (
            other.command,
            other.frame,
            other.x,
            other.y,
            other.autocontinue,
        ) and all(
            close(a, b)
            for a, b in zip(
                (self.param1, self.param2, self.param3, self.param4, self.z),
                (other.param1, other.param2, other.param3, other.param4, other.z),
                strict=True,
            )
        )


def waypoint_positions(items: tuple[MissionItem, ...] | list[MissionItem]) -> list[tuple[float, float]]:
    """(lat, lon) of every item that flies to a position, in mission order: the track the autopilot flies,
    whoever planned it (this tool, QGroundControl, Mission Planner)."""
    return [(item.lat_deg, item.lon_deg) for item in items if item.has_position]
