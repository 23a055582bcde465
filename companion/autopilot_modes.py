"""ArduCopter and PX4 flight modes: numbers, names, detection from the autopilot's HEARTBEAT.

ArduCopter puts its mode number in HEARTBEAT.custom_mode and takes it in MAV_CMD_DO_SET_MODE param2.
PX4 packs main mode and sub mode into bytes 2 and 3 of custom_mode (custom_mode = main << 16 | sub << 24)
and takes them in param2 and param3.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128


class AutopilotKind(str, Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZE": 0, "ACRO": 1, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "CIRCLE": 7,
    "LAND": 9, "DRIFT": 11, "SPORT": 13, "FLIP": 14, "AUTOTUNE": 15, "POSHOLD": 16, "BRAKE": 17,
    "THROW": 18, "AVOID_ADSB": 19, "GUIDED_NOGPS": 20, "SMART_RTL": 21,
}  # fmt: skip

# name -> (main_mode, sub_mode) from PX4's px4_custom_mode.h
PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "READY": (4, 1), "TAKEOFF": (4, 2),
    "HOLD": (4, 3), "MISSION": (4, 4), "RTL": (4, 5), "LAND": (4, 6), "FOLLOW_TARGET": (4, 8),
    "PRECLAND": (4, 9), "ACRO": (5, 0), "OFFBOARD": (6, 0), "STABILIZED": (7, 0),
}  # fmt: skip

# The mission's generic actions in each autopilot's words.
_ARDUPILOT_ACTIONS = {"offboard": "GUIDED", "loiter": "LOITER", "brake": "BRAKE", "rtl": "RTL", "land": "LAND"}
_PX4_ACTIONS = {"offboard": "OFFBOARD", "loiter": "HOLD", "brake": "HOLD", "hold": "HOLD", "rtl": "RTL", "land": "LAND"}


@dataclass(frozen=True)
class SetModeParams:
    """MAV_CMD_DO_SET_MODE params 1-3."""

    base_mode: float
    custom_mode: float
    custom_sub_mode: float


def detect_autopilot(heartbeat_autopilot: int) -> AutopilotKind | None:
    """The autopilot family from HEARTBEAT.autopilot, None for anything else (GCS, companion, unknown)."""
    if heartbeat_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return AutopilotKind.ARDUPILOT
    if heartbeat_autopilot == MAV_AUTOPILOT_PX4:
        return AutopilotKind.PX4
    return None


def mode_name(kind: AutopilotKind, custom_mode: int) -> str:
    """The mode's name, or MODE(n) for a number this table does not know."""
    if kind is AutopilotKind.ARDUPILOT:
        return next((n for n, v in ARDUCOPTER_MODES.items() if v == custom_mode), f"MODE({custom_mode})")
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    for name, (m, s) in PX4_MODES.items():
        if m == main and (s == sub or m != 4):
            return name
    return f"MODE({main}.{sub})"


def mode_for_action(kind: AutopilotKind, action: str) -> str:
    """offboard / loiter / brake / hold / rtl / land in this autopilot's mode names."""
    table = _ARDUPILOT_ACTIONS if kind is AutopilotKind.ARDUPILOT else _PX4_ACTIONS
    if action not in table:
        raise ValueError(f"no {kind.value} mode for action {action!r}; known: {', '.join(table)}")
    return table[action]


def offboard_mode(kind: AutopilotKind) -> str:
    return mode_for_action(kind, "offboard")


def set_mode_params(kind: AutopilotKind, name: str) -> SetModeParams:
    if kind is AutopilotKind.ARDUPILOT:
        if name not in ARDUCOPTER_MODES:
            raise ValueError(f"unknown ArduCopter mode {name!r}")
        return SetModeParams(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ARDUCOPTER_MODES[name], 0)
    if name not in PX4_MODES:
        raise ValueError(f"unknown PX4 mode {name!r}")
    main, sub = PX4_MODES[name]
    return SetModeParams(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)


def is_armed(base_mode: int) -> bool:
    return bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
