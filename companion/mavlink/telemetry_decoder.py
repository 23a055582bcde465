"""Decoding the autopilot's telemetry into `behaviors.telemetry.Telemetry`, and asking for its rates.

ArduPilot sends nothing but HEARTBEAT on a link until asked, so the companion requests every stream it
reads with MAV_CMD_SET_MESSAGE_INTERVAL (param1 message id, param2 interval in microseconds).
HEARTBEAT is requested at the telemetry rate too: it carries the mode, and a mode change by the pilot
must be seen within a fraction of a second to stop streaming setpoints. PX4 refuses a HEARTBEAT rate
(COMMAND_ACK FAILED, measured on PX4 1.16: it stays at 1 Hz and is not sent on a mode change), so on PX4
the mode also comes from CURRENT_MODE (436), which it streams at the rate asked for.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import development

from behaviors.telemetry import Telemetry
from cloudtrack.autopilot_modes import (
    AutopilotKind,
    detect_autopilot,
    is_armed,
    mission_mode,
    mode_name,
    offboard_mode,
)
from cloudtrack.mavlink_connection import mavlink

MSG_ID_HEARTBEAT = int(mavlink.MAVLINK_MSG_ID_HEARTBEAT)
MSG_ID_SYS_STATUS = int(mavlink.MAVLINK_MSG_ID_SYS_STATUS)
MSG_ID_ATTITUDE = int(mavlink.MAVLINK_MSG_ID_ATTITUDE)
MSG_ID_LOCAL_POSITION_NED = int(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED)
MSG_ID_GLOBAL_POSITION_INT = int(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
MSG_ID_CURRENT_MODE = int(development.MAVLINK_MSG_ID_CURRENT_MODE)  # not in the ardupilotmega dialect
MSG_ID_MISSION_CURRENT = int(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT)
MISSION_CURRENT_HZ = 2.0  # the item changes at waypoints only; the break-off item is read from it
MAV_TYPE_GCS = int(mavlink.MAV_TYPE_GCS)
MAV_TYPE_ONBOARD_CONTROLLER = int(mavlink.MAV_TYPE_ONBOARD_CONTROLLER)
MAV_STATE_CRITICAL = int(mavlink.MAV_STATE_CRITICAL)


def stream_intervals_us(rate_hz: float, kind: AutopilotKind | None = None) -> list[tuple[int, float]]:
    """(message id, interval in microseconds) for each stream the companion keeps current."""
    fast = 1e6 / rate_hz
    streams = [
        (MSG_ID_ATTITUDE, fast),
        (MSG_ID_GLOBAL_POSITION_INT, fast),
        (MSG_ID_LOCAL_POSITION_NED, fast),
        (MSG_ID_HEARTBEAT, fast),
        (MSG_ID_SYS_STATUS, max(fast, 1e6)),  # battery and sensor health change slowly
        (MSG_ID_MISSION_CURRENT, max(fast, 1e6 / MISSION_CURRENT_HZ)),
    ]
    if kind is AutopilotKind.PX4:
        streams.append((MSG_ID_CURRENT_MODE, fast))  # PX4's HEARTBEAT stays at 1 Hz
    return streams


def _current_mode_parser() -> Any:
    """A parser that knows CURRENT_MODE, for re-decoding the frames the link's dialect left unknown: the
    frame's CRC is checked with CURRENT_MODE's own CRC extra. The link's parser has already judged the
    signature, so this one accepts the frame as it is."""
    parser = development.MAVLink(None)
    parser.signing.allow_unsigned_callback = lambda *_: True
    return parser


@dataclass(frozen=True)
class AutopilotHeartbeat:
    kind: AutopilotKind
    mode: str
    armed: bool
    time_s: float
    vehicle_type: int = 2  # HEARTBEAT.type (MAV_TYPE_QUADROTOR): picks ArduPilot's mode table
    # The autopilot is in a failsafe: HEARTBEAT.system_status CRITICAL, or (PX4's CURRENT_MODE) a mode other
    # than the one the pilot, the GCS or the companion asked for.
    failsafe: bool = False


class TelemetryDecoder:
    """Keeps the latest value of every field; thread-safe (the reader feeds, the main loop reads)."""

    def __init__(self, target_system: int, forced_kind: AutopilotKind | None = None):
        self._target_system = target_system
        self._forced_kind = forced_kind
        self._lock = threading.Lock()
        self._fields: dict[str, Any] = {}
        self._time: float | None = None
        self._height: tuple[float, float] | None = None  # (height above ground, when), GLOBAL_POSITION_INT
        self.heartbeat: AutopilotHeartbeat | None = None
        self._current_mode = _current_mode_parser()
        self.battery_remaining: int | None = None
        self.local_position: tuple[float, float, float] | None = None
        self._mission: tuple[int, int | None] | None = None  # MISSION_CURRENT: (seq, total or None)
        self._home_amsl: float | None = None  # the ground under a hovering vehicle, flat-ground assumption

    def feed(self, msg: Any, now: float) -> AutopilotHeartbeat | None:
        """Take one message; returns the decoded HEARTBEAT when `msg` is the autopilot's heartbeat, or its
        mode changed as CURRENT_MODE reports it (PX4)."""
        mtype = msg.get_type()
        if mtype == f"UNKNOWN_{MSG_ID_CURRENT_MODE}":
            try:  # pymavlink leaves an unknown message without its header: decode the frame to read it
                msg, mtype = self._current_mode.decode(bytearray(msg.get_msgbuf())), "CURRENT_MODE"
            except Exception:  # a bad CRC or a truncated frame: not a mode report
                return None
        if msg.get_srcSystem() != self._target_system:
            return None
        with self._lock:
            if mtype == "HEARTBEAT":
                return self._heartbeat(msg, now)
            if mtype == "CURRENT_MODE":
                return self._mode_report(msg, now) if msg.get_srcComponent() == 1 else None
            if mtype == "ATTITUDE":
                self._update(now, roll=msg.roll, pitch=msg.pitch, yaw=msg.yaw)
            elif mtype == "GLOBAL_POSITION_INT":
                if math.isfinite(msg.relative_alt):
                    self._height = (msg.relative_alt / 1000.0, now)
                    self._home_amsl = (msg.alt - msg.relative_alt) / 1000.0
                self._update(
                    now, lat_deg=msg.lat / 1e7, lon_deg=msg.lon / 1e7, height_agl=msg.relative_alt / 1000.0,
                    vn=msg.vx / 100.0, ve=msg.vy / 100.0, vd=msg.vz / 100.0,
                )  # fmt: skip
            elif mtype == "LOCAL_POSITION_NED":
                self.local_position = (msg.x, msg.y, msg.z)
                self._update(now, vn=msg.vx, ve=msg.vy, vd=msg.vz)
            elif mtype == "SYS_STATUS":
                self.battery_remaining = msg.battery_remaining
            elif mtype == "MISSION_CURRENT":
                # `total` (MAVLink 2 extension): 0 not supported, UINT16_MAX no mission on the vehicle.
                total = int(getattr(msg, "total", 0) or 0)
                self._mission = (int(msg.seq), total if 0 < total < 0xFFFF else None)
        return None

    def ground_amsl(self) -> float | None:
        """The ground's altitude above mean sea level (m): home's, from GLOBAL_POSITION_INT (alt - relative)."""
        with self._lock:
            return self._home_amsl

    def mission_item(self) -> int | None:
        """MISSION_CURRENT's sequence number: the item the mission is on, or resumes at; None before one."""
        with self._lock:
            return self._mission[0] if self._mission is not None else None

    def _heartbeat(self, msg: Any, now: float) -> AutopilotHeartbeat | None:
        if msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER) or msg.get_srcComponent() != 1:
            return None  # only the autopilot's own heartbeat tells us its mode
        kind = self._forced_kind or detect_autopilot(msg.autopilot)
        if kind is None:
            return None
        mode = mode_name(kind, msg.custom_mode, msg.type)
        failsafe = msg.system_status == MAV_STATE_CRITICAL
        self.heartbeat = AutopilotHeartbeat(kind, mode, is_armed(msg.base_mode), now, msg.type, failsafe)
        return self.heartbeat

    def _mode_report(self, msg: Any, now: float) -> AutopilotHeartbeat | None:
        """A CURRENT_MODE between heartbeats, as a heartbeat: the mode it reports (PX4 sends it when the mode
        changes), the rest from the last HEARTBEAT."""
        hb = self.heartbeat
        if hb is None or hb.kind is not AutopilotKind.PX4:
            return None
        mode = mode_name(hb.kind, int(msg.custom_mode), hb.vehicle_type)
        failsafe = msg.intended_custom_mode not in (0, msg.custom_mode)
        self.heartbeat = AutopilotHeartbeat(hb.kind, mode, hb.armed, now, hb.vehicle_type, failsafe)
        return self.heartbeat

    def _update(self, now: float, **values: float) -> None:
        if all(math.isfinite(v) for v in values.values()):
            self._fields.update(values)
            self._time = now

    def height(self) -> tuple[float | None, float | None]:
        """(height above ground, when it arrived) from the last GLOBAL_POSITION_INT; (None, None) before."""
        with self._lock:
            return self._height if self._height is not None else (None, None)

    def snapshot(self) -> Telemetry | None:
        """The latest vehicle state, or None before any attitude or position arrived."""
        with self._lock:
            if self._time is None:
                return None
            hb = self.heartbeat
            mode = hb.mode if hb else ""
            item, items = self._mission if self._mission is not None else (None, None)
            return Telemetry(
                time_s=self._time,
                armed=hb.armed if hb else False,
                mode=mode,
                offboard_active=hb is not None and mode == offboard_mode(hb.kind),
                mission_active=hb is not None and mode == mission_mode(hb.kind),
                mission_item=item,
                mission_items=items,
                **self._fields,
            )
