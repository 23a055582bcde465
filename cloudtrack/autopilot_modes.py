"""ArduPilot and PX4 flight modes: names and numbers from pymavlink's own tables, detection from HEARTBEAT.

ArduPilot puts its mode number in HEARTBEAT.custom_mode and takes it in MAV_CMD_DO_SET_MODE param2; the
numbers depend on the vehicle (Copter, Plane, Rover, Sub...), so the table is pymavlink's
`mode_mapping_bynumber(HEARTBEAT.type)`. PX4 packs main mode and sub mode into bytes 2 and 3 of
custom_mode (custom_mode = main << 16 | sub << 24) and takes them in param2 and param3: pymavlink's
`interpret_px4_mode` and `px4_map`, with PX4's own names where pymavlink differs (its AUTO_LOITER is PX4's
"Hold" mode, HOLD here). No mode number is written out in this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from pymavlink import mavutil

from cloudtrack.mavlink_connection import mavlink

QUADROTOR = int(mavlink.MAV_TYPE_QUADROTOR)
_PX4_RENAMED = {"LOITER": "HOLD", "FOLLOWME": "FOLLOW_TARGET"}  # pymavlink's name -> PX4's
_PX4_PYMAVLINK_NAME = {ours: theirs for theirs, ours in _PX4_RENAMED.items()}


class AutopilotKind(str, Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


# The mission's generic actions in each autopilot's words.
_ARDUPILOT_ACTIONS = {
    "offboard": "GUIDED",
    "loiter": "LOITER",
    "brake": "BRAKE",
    "rtl": "RTL",
    "land": "LAND",
    "mission": "AUTO",
}
_PX4_ACTIONS = {
    "offboard": "OFFBOARD",
    "loiter": "HOLD",
    "brake": "HOLD",
    "hold": "HOLD",
    "rtl": "RTL",
    "land": "LAND",
    "mission": "MISSION",
}


# Flight modes that take a vehicle home or down, out of its search: ArduPilot's (Copter, Plane's VTOL Q
# modes) and PX4's (RTGS: return to the ground station), and "RETURN" as QGroundControl names PX4's RTL.
# A fleet's back-end counts a vehicle reporting one as dropped out; `cloudtrack-gcs replan` refuses it.
RETURN_MODES = frozenset({"RTL", "SMART_RTL", "AUTO_RTL", "LAND", "QRTL", "QLAND", "RTGS", "RETURN"})


@dataclass(frozen=True)
class SetModeParams:
    """MAV_CMD_DO_SET_MODE params 1-3."""

    base_mode: float
    custom_mode: float
    custom_sub_mode: float


def detect_autopilot(heartbeat_autopilot: int) -> AutopilotKind | None:
    """The autopilot family from HEARTBEAT.autopilot, None for anything else (GCS, companion, unknown)."""
    if heartbeat_autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return AutopilotKind.ARDUPILOT
    if heartbeat_autopilot == mavlink.MAV_AUTOPILOT_PX4:
        return AutopilotKind.PX4
    return None


def ardupilot_modes(vehicle_type: int = QUADROTOR) -> dict[str, int]:
    """Name -> number for this ArduPilot vehicle type (HEARTBEAT.type); Copter's for an unknown type."""
    table = mavutil.mode_mapping_byname(vehicle_type) or mavutil.mode_mapping_byname(QUADROTOR)
    return {str(name): int(number) for name, number in table.items()}


def mode_name(kind: AutopilotKind, custom_mode: int, vehicle_type: int = QUADROTOR) -> str:
    """The mode's name, or MODE(n) for a number the table does not know."""
    if kind is AutopilotKind.ARDUPILOT:
        by_number = mavutil.mode_mapping_bynumber(vehicle_type) or mavutil.mode_mapping_bynumber(QUADROTOR)
        name = by_number.get(custom_mode)
        return str(name) if name is not None else f"MODE({custom_mode})"
    name = str(mavutil.interpret_px4_mode(0, custom_mode))
    if name == "UNKNOWN":
        return f"MODE({(custom_mode >> 16) & 0xFF}.{(custom_mode >> 24) & 0xFF})"
    return _PX4_RENAMED.get(name, name)


def mode_for_action(kind: AutopilotKind, action: str) -> str:
    """offboard / loiter / brake / hold / rtl / land / mission in this autopilot's mode names."""
    table = _ARDUPILOT_ACTIONS if kind is AutopilotKind.ARDUPILOT else _PX4_ACTIONS
    if action not in table:
        raise ValueError(f"no {kind.value} mode for action {action!r}; known: {', '.join(table)}")
    return table[action]


def offboard_mode(kind: AutopilotKind) -> str:
    return mode_for_action(kind, "offboard")


def mission_mode(kind: AutopilotKind) -> str:
    """The mode in which the autopilot flies its own mission: ArduPilot AUTO, PX4 MISSION."""
    return mode_for_action(kind, "mission")


def mode_names(kind: AutopilotKind, vehicle_type: int = QUADROTOR) -> list[str]:
    """Every mode `set_mode_params` knows for this autopilot and vehicle type."""
    if kind is AutopilotKind.ARDUPILOT:
        return list(ardupilot_modes(vehicle_type))
    return [_PX4_RENAMED.get(str(name), str(name)) for name in mavutil.px4_map]


def set_mode_params(kind: AutopilotKind, name: str, vehicle_type: int = QUADROTOR) -> SetModeParams:
    """ValueError for a mode this vehicle does not have (e.g. BRAKE on a Plane)."""
    custom = int(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if kind is AutopilotKind.ARDUPILOT:
        modes = ardupilot_modes(vehicle_type)
        if name not in modes:
            raise ValueError(f"this ArduPilot vehicle (type {vehicle_type}) has no mode {name!r}")
        return SetModeParams(custom, modes[name], 0)
    entry = mavutil.px4_map.get(_PX4_PYMAVLINK_NAME.get(name, name))
    if entry is None:
        raise ValueError(f"unknown PX4 mode {name!r}")
    _, main, sub = entry
    return SetModeParams(custom, main, sub)


def is_armed(base_mode: int) -> bool:
    return bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
