"""A MAVLink autopilot simulator with an ArduCopter and a PX4 personality, on real UDP/TCP sockets.

It behaves the way the companion has to cope with on a real vehicle:
- HEARTBEAT with the personality's autopilot id, MAV_TYPE_QUADROTOR and its own custom_mode encoding
  (ArduCopter mode numbers; PX4 main/sub mode packed in bytes 2 and 3 of custom_mode);
- COMMAND_LONG MAV_CMD_DO_SET_MODE (and the legacy SET_MODE message) answered with COMMAND_ACK;
- SET_POSITION_TARGET_LOCAL_NED honouring coordinate_frame and type_mask. ArduCopter flies it only in
  GUIDED and keeps flying the last velocity until GUID_TIMEOUT (3 s) runs out, then brakes (a position
  target, e.g. a GCS's "fly to", is flown until reached: GUID_TIMEOUT does not apply to it). PX4 refuses
  OFFBOARD until a setpoint stream is coming in and falls back to HOLD when it stops (COM_OF_LOSS_T);
- ArduCopter's silence: only HEARTBEAT until a link asks for streams with MAV_CMD_SET_MESSAGE_INTERVAL;
  PX4 streams a default set. Intervals are per link, as on the real autopilots;
- routing between links (GCS and companion) by the MAVLink routing rules: a message addressed to a
  component goes only to the link where that component was seen, broadcasts go everywhere; the raw bytes
  are forwarded so signatures survive;
- it starts armed and hovering and never arms for anyone (arm and take-off requests are denied);
- a mission through the real mission protocol, flown in AUTO (ArduCopter) / Mission (PX4), resumed where it
  broke off after GUIDED/OFFBOARD, with MISSION_CURRENT and MISSION_ITEM_REACHED (sitl/autopilot_mission.py).

Mode numbers are written out here independently of `cloudtrack.autopilot_modes` on purpose: a wrong table
on the companion side must show up as a failing test, not cancel out.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import development

from cloudtrack.mavlink_connection import mavlink, receive_message, use_mavlink2
from sitl.autopilot_mission import AutopilotMission, MissionOptions
from sitl.vehicle_dynamics import (
    VehicleLimits,
    VehicleState,
    VelocityCommand,
    Wind,
    body_to_ned,
    step,
    wrap_pi,
)

log = logging.getLogger(__name__)

ARDUCOPTER_MODES = {
    "STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6,
    "LAND": 9, "POSHOLD": 16, "BRAKE": 17,
}  # fmt: skip
# PX4 (main_mode, sub_mode); custom_mode = main << 16 | sub << 24.
PX4_MODES = {
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "TAKEOFF": (4, 2), "HOLD": (4, 3),
    "MISSION": (4, 4), "RTL": (4, 5), "LAND": (4, 6), "OFFBOARD": (6, 0),
}  # fmt: skip
PERSONALITIES = ("ardupilot", "px4")
MSG_ID_CURRENT_MODE = development.MAVLINK_MSG_ID_CURRENT_MODE  # PX4 1.16; not in the ardupilotmega dialect
PX4_STANDARD_MODES = {"POSCTL": 1}  # CURRENT_MODE.standard_mode (MAV_STANDARD_MODE), as PX4 1.16 reports
PX4_CURRENT_MODE_PERIOD_S = 0.6
# ArduCopter's flight-mode switch (FLTMODE_CH 5) with the shipped SITL copter.parm's FLTMODE1..6, and the
# PWM each slot ends at (RC_Channel: <=1230, <=1360, <=1490, <=1620, <=1749, above). CIRCLE and STABILIZE are
# not flown here; they stay unmapped.
FLTMODE_SLOTS = (
    ("CIRCLE", 1230),
    ("LAND", 1360),
    ("RTL", 1490),
    ("AUTO", 1620),
    ("LOITER", 1749),
    ("STABILIZE", 2200),
)
RC_MODE_SWITCH_PWM = {"LAND": 1295, "RTL": 1425, "LOITER": 1685}
RC_START_PWM = 1800  # the SITL's own RC input on channel 5 (slot 6): no switch change until someone moves it

POSITION_IGNORE = 0b111
VELOCITY_IGNORE = 0b111000
YAW_IGNORE = 1024
YAW_RATE_IGNORE = 2048
PX4_VELOCITY_FRAMES = {mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_NED}  # what PX4 1.16 flies
BODY_FRAMES = {
    mavlink.MAV_FRAME_BODY_NED,
    mavlink.MAV_FRAME_BODY_OFFSET_NED,
    mavlink.MAV_FRAME_BODY_FRD,
}
PX4_DEFAULT_INTERVALS = {  # seconds; what PX4's onboard MAVLink instance streams without being asked
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.05,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.1,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.1,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    MSG_ID_CURRENT_MODE: 2.0,
}
ARDUPILOT_DEFAULT_INTERVALS = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
EARTH_RADIUS = 6_378_137.0


@dataclass(frozen=True)
class AutopilotOptions:
    personality: str = "ardupilot"
    system_id: int = 1
    guid_timeout_s: float = 3.0  # ArduCopter GUID_TIMEOUT
    offboard_loss_s: float = 1.0  # PX4 COM_OF_LOSS_T
    home_lat: float = 47.397742
    home_lon: float = 8.545594
    home_alt_m: float = 488.0
    start_height_m: float = 20.0
    start_yaw_deg: float = 0.0
    physics_hz: float = 50.0
    rtl_speed_m_s: float = 5.0
    land_speed_m_s: float = 1.0
    limits: VehicleLimits = VehicleLimits()
    wind: Wind = Wind()
    signing_key: bytes | None = None  # sign everything sent (unsigned input is still accepted)
    mission: MissionOptions = MissionOptions()


@dataclass(frozen=True)
class ReceivedSetpoint:
    """One SET_POSITION_TARGET_LOCAL_NED as it arrived, for tests and metrics."""

    time: float
    link: str
    src_system: int
    src_component: int
    frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw_rate: float
    mode: str
    time_boot_ms: int = 0  # the sender's stamp: the companion puts the time the setpoint was computed here


@dataclass
class _Link:
    name: str
    url: str
    conn: mavutil.mavfile
    intervals: dict[int, float]
    next_due: dict[int, float] = field(default_factory=dict)
    seen: set[tuple[int, int]] = field(default_factory=set)
    down: bool = False
    deaf: bool = False
    bad_data: int = 0


class SimulatedAutopilot:
    """The simulator. `links` maps a name ("gcs", "companion") to a pymavlink connection string."""

    def __init__(
        self, options: AutopilotOptions, links: dict[str, str], clock: Callable[[], float] = time.monotonic
    ):
        if options.personality not in PERSONALITIES:
            raise ValueError(
                f"unknown autopilot personality {options.personality!r}; use one of {PERSONALITIES}"
            )
        if not links:
            raise ValueError("the autopilot needs at least one link")
        self.options = options
        self._clock = clock
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.state = VehicleState(down=-options.start_height_m, yaw=math.radians(options.start_yaw_deg))
        self.armed = True
        self.mode = "GUIDED" if self.is_ardupilot else "POSCTL"
        # PX4: the mode the pilot, the GCS or the companion asked for; a failsafe holds in another one until
        # its cause clears (setpoints coming back after an offboard loss), then returns to this one.
        self._intended_mode = self.mode
        self._px4_failsafe = False
        self.mode_history: list[tuple[float, str, str]] = []
        self.setpoints: list[ReceivedSetpoint] = []
        self.statustexts: list[str] = []
        # (time, link, command) of every COMMAND_LONG (SET_MODE as DO_SET_MODE) addressed to the autopilot
        self.commands: list[tuple[float, str, int]] = []
        self._velocity_target = VelocityCommand()
        self._yaw_target: float | None = None
        self._auto_yaw = False
        self._position_target: tuple[float, float, float] | None = None
        self._last_setpoint_time = -math.inf
        self._mode_switch_slot = self._slot(RC_START_PWM)
        self.mission = AutopilotMission(
            options.personality, options.mission, (options.home_lat, options.home_lon, options.home_alt_m)
        )
        self._boot = clock()
        defaults = PX4_DEFAULT_INTERVALS if not self.is_ardupilot else ARDUPILOT_DEFAULT_INTERVALS
        self._links: dict[str, _Link] = {}
        for name, url in links.items():
            conn = use_mavlink2(
                mavutil.mavlink_connection(url, source_system=options.system_id, source_component=1)
            )
            if options.signing_key is not None:
                conn.setup_signing(
                    options.signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: True
                )
            self._links[name] = _Link(name, url, conn, dict(defaults))

    # ----------------------------------------------------------------------------------------------- API
    @property
    def is_ardupilot(self) -> bool:
        return self.options.personality == "ardupilot"

    def start(self) -> None:
        for link in self._links.values():
            t = threading.Thread(
                target=self._receive_loop, args=(link,), name=f"autopilot-rx-{link.name}", daemon=True
            )
            self._threads.append(t)
        self._threads.append(
            threading.Thread(target=self._physics_loop, name="autopilot-physics", daemon=True)
        )
        for t in self._threads:
            t.start()

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        for link in self._links.values():
            link.conn.close()

    def __enter__(self) -> SimulatedAutopilot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def link_port(self, name: str) -> int:
        """The local port a link is bound to (for udpin/tcpin links opened on port 0)."""
        conn = self._links[name].conn
        sock = getattr(conn, "port", None) or getattr(conn, "listen", None)
        if sock is None:
            raise ValueError(f"link {name!r} ({self._links[name].url}) has no local socket")
        return int(sock.getsockname()[1])

    def set_link_down(self, name: str, down: bool, inbound_too: bool = True) -> None:
        """Simulate a cut link: nothing is sent on it and (with `inbound_too`) whatever arrives is dropped.

        `inbound_too=False` is a one-way failure: the autopilot goes silent but still obeys what it hears.
        """
        with self._lock:
            self._links[name].down = down
            self._links[name].deaf = down and inbound_too

    def snapshot(self) -> VehicleState:
        with self._lock:
            return self.state

    def set_mode(self, name: str, source: str = "sim") -> bool:
        """Change mode as a pilot's RC switch would (no MAVLink involved); False if refused."""
        with self._lock:
            return self._try_set_mode(name, source)

    # ------------------------------------------------------------------------------------------ modes
    def _custom_mode(self) -> int:
        if self.is_ardupilot:
            return ARDUCOPTER_MODES[self.mode]
        main, sub = PX4_MODES[self.mode]
        return (main << 16) | (sub << 24)

    def _mode_from_numbers(self, custom_main: float, custom_sub: float) -> str | None:
        if self.is_ardupilot:
            return next((n for n, v in ARDUCOPTER_MODES.items() if v == int(custom_main)), None)
        return next((n for n, v in PX4_MODES.items() if v == (int(custom_main), int(custom_sub))), None)

    def _try_set_mode(self, name: str, source: str) -> bool:
        now = self._clock()
        if name == "OFFBOARD" and not self._px4_stream_alive(now):
            self._status(f"Offboard refused: no setpoint stream (requested by {source})")
            return False
        if name == "TAKEOFF":
            return False  # no take-off in this simulator
        mission_mode = "AUTO" if self.is_ardupilot else "MISSION"
        if name == mission_mode and name != self.mode and not self.mission.start_or_resume():
            self._status(
                "Mode change to AUTO failed: init failed" if self.is_ardupilot else "No valid mission"
            )
            return False
        self._px4_failsafe = source == "failsafe"
        if not self._px4_failsafe:
            self._intended_mode = name
        if name != self.mode:
            if self.mode == mission_mode:
                self.mission.stop()
            self.mode = name
            self.mode_history.append((now, name, source))
            self._position_target = None
            if name in ("GUIDED", "OFFBOARD"):
                self._velocity_target = VelocityCommand()
            if self.is_ardupilot:  # ArduCopter announces a new mode at once on every link (conformance suite)
                for link in self._links.values():
                    if not link.down:
                        self._send_message(link, mavlink.MAVLINK_MSG_ID_HEARTBEAT, now)
            else:  # PX4 sends CURRENT_MODE on a change to the links that stream it (its HEARTBEAT waits)
                for link in self._links.values():
                    if not link.down and MSG_ID_CURRENT_MODE in link.intervals:
                        self._send_message(link, MSG_ID_CURRENT_MODE, now)
            log.info("mode %s (by %s)", name, source)  # after the announcement: a slow log never delays it
        return True

    def _px4_stream_alive(self, now: float) -> bool:
        recent = [s for s in self.setpoints[-40:] if now - s.time <= 1.0]
        return len(recent) >= 2 and now - recent[-1].time <= self.options.offboard_loss_s

    # -------------------------------------------------------------------------------------- receiving
    def _receive_loop(self, link: _Link) -> None:
        while not self._stop.is_set():
            try:
                msg = receive_message(link.conn, 0.05)
            except Exception as exc:  # a hostile peer must never stop the autopilot
                log.warning("link %s: receive error %s", link.name, exc)
                time.sleep(0.01)
                continue
            if msg is None:
                continue
            with self._lock:
                if link.deaf:
                    continue
                try:
                    self._on_message(link, msg)
                except Exception:
                    log.exception("link %s: could not handle %s", link.name, msg.get_type())

    def _on_message(self, link: _Link, msg: mavutil.mavlink.MAVLink_message) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            link.bad_data += 1
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        link.seen.add(src)
        target_system = getattr(msg, "target_system", None)
        target_component = getattr(msg, "target_component", 0) if target_system is not None else None
        self._route(link, msg, target_system, target_component)
        sysid = self.options.system_id
        local = target_system in (None, 0) or (target_system == sysid and target_component in (0, 1))
        if not local:
            return
        if mtype.startswith("MISSION_"):
            self.mission.handle(
                msg, self._sender(link), self._broadcast, link.name, self._clock(), self._status
            )
        elif mtype == "COMMAND_LONG":
            self._on_command(link, msg)
        elif (
            mtype == "COMMAND_INT" and msg.command == mavlink.MAV_CMD_DO_REPOSITION and not self.is_ardupilot
        ):
            self._reposition(link, msg)
        elif mtype == "SET_POSITION_TARGET_LOCAL_NED":
            self._on_setpoint(link, msg)
        elif mtype == "RC_CHANNELS_OVERRIDE" and self.is_ardupilot:
            self._on_rc_override(link, msg)
        elif mtype == "SET_MODE":
            self.commands.append((self._clock(), link.name, int(mavlink.MAV_CMD_DO_SET_MODE)))
            name = (
                self._mode_from_numbers(msg.custom_mode, 0)
                if self.is_ardupilot
                else self._mode_from_numbers((msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF)
            )
            if name is not None:
                self._try_set_mode(name, f"{link.name} {src[0]}/{src[1]}")

    @staticmethod
    def _slot(pwm: int) -> int:
        return next(i for i, (_, top) in enumerate(FLTMODE_SLOTS) if pwm <= top)

    def _on_rc_override(self, link: _Link, msg: mavutil.mavlink.MAVLink_message) -> None:
        """ArduCopter's flight-mode switch: a new switch position selects its FLTMODE (0 and UINT16_MAX
        release the channel, so nothing changes)."""
        pwm = int(msg.chan5_raw)
        if pwm in (0, 65535) or not 800 <= pwm <= 2200:
            return
        slot = self._slot(pwm)
        if slot == self._mode_switch_slot:
            return
        self._mode_switch_slot = slot
        name = FLTMODE_SLOTS[slot][0]
        if name in ARDUCOPTER_MODES:
            self._try_set_mode(name, f"pilot rc {link.name}")

    def _route(
        self, source: _Link, msg: mavutil.mavlink.MAVLink_message, ts: int | None, tc: int | None
    ) -> None:
        buf = msg.get_msgbuf()
        for other in self._links.values():
            if other is source or other.down:
                continue
            broadcast = ts in (None, 0)
            seen_there = any(s == ts and (tc == 0 or c == tc) for s, c in other.seen)
            if broadcast or seen_there:
                other.conn.write(buf)

    def _sender(self, link: _Link) -> Callable[[Callable[[Any], Any]], None]:
        def send(build: Callable[[Any], Any]) -> None:
            if not link.down:
                build(link.conn.mav)

        return send

    def _broadcast(self, build: Callable[[Any], Any]) -> None:
        for link in self._links.values():
            if not link.down:
                build(link.conn.mav)

    def _ack(self, link: _Link, msg: mavutil.mavlink.MAVLink_message, result: int) -> None:
        if link.down:
            return
        link.conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _on_command(self, link: _Link, msg: mavutil.mavlink.MAVLink_message) -> None:
        who = f"{link.name} {msg.get_srcSystem()}/{msg.get_srcComponent()}"
        cmd = msg.command
        self.commands.append((self._clock(), link.name, int(cmd)))
        if len(self.commands) > 20000:
            del self.commands[:10000]
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            if not self.is_ardupilot:  # PX4 1.16 answers twice: ACCEPTED at once, then the outcome
                self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED)
            name = self._mode_from_numbers(msg.param2, msg.param3)
            if (
                name is None
            ):  # ArduCopter 4.7 answers FAILED to a mode number it does not have (conformance suite)
                # PX4 1.16 accepts a main mode it does not have (the second ACK too) and changes nothing.
                self._ack(
                    link, msg, mavlink.MAV_RESULT_FAILED if self.is_ardupilot else mavlink.MAV_RESULT_ACCEPTED
                )
                return
            ok = self._try_set_mode(name, who)
            # ArduCopter 4.7 answers FAILED to a mode whose init fails (AUTO without a mission).
            refused = (
                mavlink.MAV_RESULT_FAILED if self.is_ardupilot else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            )
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED if ok else refused)
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = int(msg.param1), msg.param2
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT and not self.is_ardupilot:
                self._ack(link, msg, mavlink.MAV_RESULT_FAILED)  # PX4's HEARTBEAT stays at 1 Hz
                return
            if interval_us < 0:
                link.intervals.pop(msg_id, None)
            elif interval_us == 0:
                defaults = ARDUPILOT_DEFAULT_INTERVALS if self.is_ardupilot else PX4_DEFAULT_INTERVALS
                if msg_id in defaults:
                    link.intervals[msg_id] = defaults[msg_id]
                else:
                    link.intervals.pop(msg_id, None)
            else:
                link.intervals[msg_id] = interval_us / 1e6
                if msg_id == MSG_ID_CURRENT_MODE:  # PX4 1.16: about 1.7 Hz however fast, and on a change
                    link.intervals[msg_id] = max(link.intervals[msg_id], PX4_CURRENT_MODE_PERIOD_S)
            link.next_due.pop(msg_id, None)
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            sent = self._send_message(link, int(msg.param1), self._clock())
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED if sent else mavlink.MAV_RESULT_UNSUPPORTED)
        elif cmd in (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF):
            self._status(f"Arming/take-off request from {who} refused: the simulator never arms for anyone")
            # ArduCopter answers FAILED to a take-off while flying (this simulator always is, or has landed).
            failed = cmd == mavlink.MAV_CMD_NAV_TAKEOFF and self.is_ardupilot
            self._ack(link, msg, mavlink.MAV_RESULT_FAILED if failed else mavlink.MAV_RESULT_DENIED)
        elif cmd == mavlink.MAV_CMD_NAV_LAND:
            self._try_set_mode("LAND", who)
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._try_set_mode("RTL", who)
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_MISSION_START and self.is_ardupilot:
            # ArduCopter: first/last item unsupported; AUTO (nothing changes in it), then a mission that is
            # not running resumed (GCS_MAVLINK_Copter::handle_MAV_CMD_MISSION_START).
            if msg.param1 or msg.param2:
                self._ack(link, msg, mavlink.MAV_RESULT_DENIED)
                return
            ok = self._try_set_mode("AUTO", who) and self.mission.resume_in_auto()
            self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_FAILED)
        else:
            self._ack(link, msg, mavlink.MAV_RESULT_UNSUPPORTED)

    def _reposition(self, link: _Link, msg: mavutil.mavlink.MAVLink_message) -> None:
        """PX4's MAV_CMD_DO_REPOSITION (a GCS's "go to location"): HOLD, flying to the point."""
        o = self.options
        north = math.radians(msg.x / 1e7 - o.home_lat) * EARTH_RADIUS
        east = math.radians(msg.y / 1e7 - o.home_lon) * EARTH_RADIUS * math.cos(math.radians(o.home_lat))
        relative = msg.frame in (
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        )
        down = -msg.z if relative else o.home_alt_m - msg.z
        self._try_set_mode("HOLD", f"{link.name} {msg.get_srcSystem()}/{msg.get_srcComponent()}")
        self._position_target = (north, east, down if math.isfinite(down) else self.state.down)
        self._ack(link, msg, mavlink.MAV_RESULT_ACCEPTED)

    def _on_setpoint(self, link: _Link, msg: mavutil.mavlink.MAVLink_message) -> None:
        now = self._clock()
        self.setpoints.append(
            ReceivedSetpoint(
                now, link.name, msg.get_srcSystem(), msg.get_srcComponent(), msg.coordinate_frame,
                msg.type_mask, msg.vx, msg.vy, msg.vz, msg.yaw_rate, self.mode, msg.time_boot_ms,
            )
        )  # fmt: skip
        if len(self.setpoints) > 20000:
            del self.setpoints[:10000]
        active = "GUIDED" if self.is_ardupilot else "OFFBOARD"
        if not self.is_ardupilot and msg.coordinate_frame not in PX4_VELOCITY_FRAMES:
            return  # PX4 1.16 flies LOCAL_NED and BODY_NED only; other frames are no offboard signal either
        if not self.is_ardupilot:
            self._last_setpoint_time = now  # PX4 counts the stream in any mode (needed before OFFBOARD)
            if self._px4_failsafe and self._intended_mode == "OFFBOARD" and self._px4_stream_alive(now):
                self._try_set_mode("OFFBOARD", "failsafe cleared")  # PX4 1.16 goes back on its own
        if self.mode != active:
            return  # ArduPilot ignores setpoints outside GUIDED; PX4 only flies them in OFFBOARD
        self._last_setpoint_time = now
        mask = msg.type_mask
        yaw = self.state.yaw
        frame = msg.coordinate_frame
        if not mask & VELOCITY_IGNORE:
            vn, ve = msg.vx, msg.vy
            if frame in BODY_FRAMES:
                vn, ve = body_to_ned(msg.vx, msg.vy, yaw)
            self._velocity_target = VelocityCommand(vn, ve, msg.vz, 0.0)
            self._position_target = None
        elif not mask & POSITION_IGNORE:
            n, e = msg.x, msg.y
            if frame in BODY_FRAMES:
                dn, de = body_to_ned(msg.x, msg.y, yaw)
                n, e = self.state.north + dn, self.state.east + de
            self._position_target = (n, e, msg.z)
        yaw_rate = 0.0
        self._yaw_target = None
        self._auto_yaw = False
        if not mask & YAW_RATE_IGNORE:
            yaw_rate = msg.yaw_rate
        elif not mask & YAW_IGNORE:
            self._yaw_target = msg.yaw
        elif self.is_ardupilot:
            self._auto_yaw = True  # ArduPilot 4.3+: both yaw fields ignored -> its own yaw behaviour
        v = self._velocity_target
        self._velocity_target = VelocityCommand(v.vn, v.ve, v.vd, yaw_rate)

    # ----------------------------------------------------------------------------------- physics loop
    def _physics_loop(self) -> None:
        period = 1.0 / self.options.physics_hz
        last = self._clock()
        while not self._stop.wait(period):
            now = self._clock()
            with self._lock:
                try:
                    self._tick(now, min(now - last, 0.2))
                    self.mission.tick(now, lambda name: self._sender(self._links[name]), self._status)
                    self._send_streams(now)
                except Exception:
                    log.exception("autopilot tick failed")
            last = now

    def _mode_command(self, now: float) -> VelocityCommand:
        s = self.state
        if self.mode in ("GUIDED", "OFFBOARD"):
            timeout = self.options.guid_timeout_s if self.is_ardupilot else self.options.offboard_loss_s
            # ArduCopter's GUID_TIMEOUT stops velocity commands only; a position target is flown until
            # reached.
            position_held = self.is_ardupilot and self._position_target is not None
            if now - self._last_setpoint_time > timeout and not position_held:
                if not self.is_ardupilot:  # COM_OBL_RC_ACT Hold; back to OFFBOARD when setpoints return
                    self._try_set_mode("HOLD", "failsafe")
                    self._status("Failsafe activated")
                return VelocityCommand()  # ArduCopter GUIDED: brake once GUID_TIMEOUT runs out
            cmd = self._velocity_target
            if self._position_target is not None:
                n, e, d = self._position_target
                cmd = VelocityCommand(
                    (n - s.north) * 0.8, (e - s.east) * 0.8, (d - s.down) * 0.8, cmd.yaw_rate
                )
            if self._yaw_target is not None:
                cmd = VelocityCommand(cmd.vn, cmd.ve, cmd.vd, 2.0 * wrap_pi(self._yaw_target - s.yaw))
            elif self._auto_yaw and math.hypot(cmd.vn, cmd.ve) > 0.5:
                cmd = VelocityCommand(
                    cmd.vn, cmd.ve, cmd.vd, 2.0 * wrap_pi(math.atan2(cmd.ve, cmd.vn) - s.yaw)
                )
            return cmd
        if self.mode == "RTL":
            dist = math.hypot(s.north, s.east)
            if dist < 1.0:
                self._try_set_mode("LAND", "rtl")
                return VelocityCommand()
            speed = min(self.options.rtl_speed_m_s, 0.5 * dist)
            return VelocityCommand(-s.north / dist * speed, -s.east / dist * speed, 0.0, 0.0)
        if self.mode == "LAND":
            return VelocityCommand(0.0, 0.0, self.options.land_speed_m_s, 0.0)
        if self.mode == "HOLD" and self._position_target is not None:  # PX4's reposition
            n, e, d = self._position_target
            return VelocityCommand((n - s.north) * 0.8, (e - s.east) * 0.8, (d - s.down) * 0.8, 0.0)
        if self.mode in ("AUTO", "MISSION"):
            cmd = self.mission.command(s, self._broadcast, self._status)
            if math.hypot(cmd.vn, cmd.ve) > 0.5:  # WP_YAW_BEHAVIOR 2 / MPC_YAW_MODE 0: face the way it flies
                cmd = VelocityCommand(
                    cmd.vn, cmd.ve, cmd.vd, 2.0 * wrap_pi(math.atan2(cmd.ve, cmd.vn) - s.yaw)
                )
            return cmd
        return VelocityCommand()  # BRAKE, LOITER, POSHOLD, ALT_HOLD, HOLD, POSCTL...: hold position

    def _tick(self, now: float, dt: float) -> None:
        if not self.armed:
            return
        self.state = step(self.state, self._mode_command(now), dt, self.options.limits, self.options.wind)
        if self.mode == "LAND" and self.state.down >= 0.0:
            self.armed = False
            self._status("Landed: disarmed")

    # ------------------------------------------------------------------------------------- telemetry
    def _status(self, text: str) -> None:
        self.statustexts.append(text)
        for link in self._links.values():
            if not link.down:
                link.conn.mav.statustext_send(mavlink.MAV_SEVERITY_INFO, text.encode()[:50])

    def _send_streams(self, now: float) -> None:
        for link in self._links.values():
            if link.down:
                continue
            for msg_id, interval in list(link.intervals.items()):
                due = link.next_due.get(msg_id, now)
                if now >= due:
                    self._send_message(link, msg_id, now)
                    # Catch up at most one period so a stalled tick does not cause a burst.
                    link.next_due[msg_id] = max(due + interval, now)

    def _send_message(self, link: _Link, msg_id: int, now: float) -> bool:
        mav = link.conn.mav
        s = self.state
        boot_ms = int((now - self._boot) * 1000) & 0xFFFFFFFF
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if self.armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            if self.mode in ("GUIDED", "OFFBOARD"):
                base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
            autopilot = (
                mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if self.is_ardupilot else mavlink.MAV_AUTOPILOT_PX4
            )
            status = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
            if self._px4_failsafe:
                status = mavlink.MAV_STATE_CRITICAL
            mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, autopilot, base, self._custom_mode(), status)
        elif msg_id == MSG_ID_CURRENT_MODE and not self.is_ardupilot:
            main, sub = PX4_MODES[self._intended_mode]
            mav.send(
                development.MAVLink_current_mode_message(
                    PX4_STANDARD_MODES.get(self.mode, 0), self._custom_mode(), main << 16 | sub << 24
                )
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            mav.attitude_send(boot_ms, s.roll, s.pitch, s.yaw, 0.0, 0.0, s.yaw_rate)
        elif msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            mav.local_position_ned_send(boot_ms, s.north, s.east, s.down, s.vn, s.ve, s.vd)
        elif msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            o = self.options
            lat = o.home_lat + math.degrees(s.north / EARTH_RADIUS)
            lon = o.home_lon + math.degrees(s.east / (EARTH_RADIUS * math.cos(math.radians(o.home_lat))))
            mav.global_position_int_send(
                boot_ms, int(lat * 1e7), int(lon * 1e7), int((o.home_alt_m + s.height) * 1000), int(s.height * 1000),
                int(s.vn * 100), int(s.ve * 100), int(s.vd * 100), int(math.degrees(s.yaw) % 360 * 100),
            )  # fmt: skip
        elif msg_id == mavlink.MAVLINK_MSG_ID_MISSION_CURRENT:
            self.mission.send_current(mav)
        elif msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = 0x3FFF
            mav.sys_status_send(sensors, sensors, sensors, 250, 15800, 1200, 85, 0, 0, 0, 0, 0, 0)
        else:
            return False
        return True
