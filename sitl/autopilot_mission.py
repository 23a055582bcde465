"""The simulated autopilot's mission: storage through the real mission protocol, and AUTO / Mission flight.

`AutopilotMission` is the server side of https://mavlink.io/en/services/mission.html as each personality
answers it. The ArduCopter side is held to the real ArduCopter 4.7 by tests/test_autopilot_conformance.py;
what that suite measured is written here.

ArduCopter (AP_Mission, MissionItemProtocol_Waypoints)
- item 0 is home: a download returns the vehicle's home there (count 1 on a fresh vehicle, 0 after a
  clear); what an upload sends as item 0 is ignored;
- MISSION_COUNT above `max_items` (650 in the SITL, home included) is refused with NO_SPACE and "Only 650
  items are supported", and nothing changes; otherwise the stored mission is truncated to the new count
  at once and every item is written as it arrives, so an upload that stops midway leaves a mix of new and
  old items (the hazard `cloudtrack/mission_protocol.py` cleans up after);
- items are asked for with MISSION_REQUEST (not _INT), re-asked every 1 s, and the upload is cancelled
  (OPERATION_CANCELLED, "Mission upload timeout") 8 s after the last item; an item it cannot store ends
  the upload with UNSUPPORTED (command) or UNSUPPORTED_FRAME;
- MISSION_CLEAR_ALL is refused (ERROR) while the mission runs (in AUTO);
- AUTO is refused (COMMAND_ACK FAILED, "Mode change to AUTO failed: init failed") without an item besides
  home. Entering it resumes (MIS_RESTART 0): the interrupted navigation item is started again from where
  the vehicle is, so it flies straight to the waypoint it was heading for (the interrupted leg is not
  re-flown from its start), at WPNAV_SPEED: a DO_CHANGE_SPEED passed before the interruption no longer
  applies. A completed mission starts again from item 1; MIS_RESTART 1 (`restart`) always does;
- MISSION_CURRENT only when asked (MAV_CMD_REQUEST_MESSAGE, SET_MESSAGE_INTERVAL, MISSION_SET_CURRENT):
  seq 0 until the mission first runs, `total` without home, mission_state NO_MISSION / NOT_STARTED (also
  when interrupted) / ACTIVE / COMPLETE, mission_mode 1 in AUTO; MISSION_ITEM_REACHED to every link for
  every item, DO_CHANGE_SPEED included; STATUSTEXT "Mission: 2 WP", "Reached command #2";
- at the end it holds where the last waypoint put it, still in AUTO. MISSION_SET_CURRENT then leaves the
  mission stopped at that item, the vehicle holding in AUTO (`held`), until AUTO is entered again or
  MAV_CMD_MISSION_START resumes it there (from ArduPilot's source, AP_Mission::set_current_cmd and
  GCS_MAVLINK_Copter::handle_MAV_CMD_MISSION_START; not measured by the conformance suite);

PX4 (navigator, MavlinkMissionManager; what the real PX4 1.16 SIH showed is marked measured)
- items start at 0; an upload goes into a spare slot and replaces the mission only when complete, so a
  failed upload leaves the old mission whole, and begins at item 0, or at the item sent with current=1
  (MavlinkMissionManager's _transfer_current_seq, from PX4's source); items are asked for with
  MISSION_REQUEST_INT;
- clearing is allowed at any time; Mission mode needs a mission;
- a download (MISSION_REQUEST_INT) answers a global item in its _INT frame (GLOBAL_RELATIVE_ALT comes back as
  GLOBAL_RELATIVE_ALT_INT; measured on the real PX4 1.16);
- re-entering Mission mode continues at the item it left, at the speed of the last DO_CHANGE_SPEED before
  it (measured: a 2.5 m/s survey flew 2.3-2.4 m/s after HOLD and Mission again, not MPC_XY_CRUISE's 5; PX4 replays them; it goes back one waypoint only when the mission triggers a camera by distance, which
  a video search does not); MISSION_CURRENT is also sent when the item changes, PAUSED once interrupted.

Both fly NAV_WAYPOINT along the straight line from the previous waypoint (or from where AUTO began) at the
waypoint speed (ArduCopter WPNAV_SPEED 10 m/s, PX4 MPC_XY_CRUISE 5 m/s; DO_CHANGE_SPEED overrides), slow
down to reach it (WPNAV_ACCEL 2.5 m/s^2), count it reached within `radius_m` (WPNAV_RADIUS 2 m), face the
direction of travel (WP_YAW_BEHAVIOR 2 / MPC_YAW_MODE 0) and move on. NAV_TAKEOFF in the air climbs to its
altitude; DO_CHANGE_SPEED takes effect at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from behaviors.mission_items import (
    DO_CHANGE_SPEED,
    FRAME_GLOBAL,
    FRAME_MISSION,
    GLOBAL_FRAMES,
    INT_FRAMES,
    NAV_LAND,
    NAV_LOITER_TIME,
    NAV_LOITER_UNLIM,
    NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    MissionItem,
)
from cloudtrack.mission_protocol import item_from_message, send_item
from sitl.vehicle_dynamics import VehicleState, VelocityCommand

Send = Callable[[Callable[[Any], Any]], None]  # send on one link: send(lambda mav: mav.xxx_send(...))
Status = Callable[[str], None]

SUPPORTED_COMMANDS = (NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, NAV_RETURN_TO_LAUNCH, NAV_LOITER_UNLIM,
                      NAV_LOITER_TIME, DO_CHANGE_SPEED)  # fmt: skip
SHORT_NAMES = {NAV_WAYPOINT: "WP", NAV_TAKEOFF: "Takeoff", NAV_LAND: "Land", NAV_RETURN_TO_LAUNCH: "RTL",
               NAV_LOITER_UNLIM: "LoitUnlim", NAV_LOITER_TIME: "LoitTime", DO_CHANGE_SPEED: "ChangeSpeed"}  # fmt: skip
# MAV_MISSION_RESULT
ACCEPTED, ERROR, UNSUPPORTED_FRAME, UNSUPPORTED, NO_SPACE = 0, 1, 2, 3, 4
INVALID_PARAM5_X, INVALID_PARAM6_Y, INVALID_SEQUENCE, DENIED, OPERATION_CANCELLED = 10, 11, 13, 14, 15
# MISSION_STATE (MISSION_CURRENT.mission_state)
NO_MISSION, NOT_STARTED, ACTIVE, PAUSED, COMPLETE = 1, 2, 3, 4, 5
EARTH_RADIUS = 6_378_137.0  # the simulator's spherical earth (sitl/autopilot.py's GLOBAL_POSITION_INT)
DEFAULTS = {  # (max items incl. ArduPilot's home, waypoint speed m/s)
    "ardupilot": (650, 10.0),  # measured on the SITL: "Only 650 items are supported"; WPNAV_SPEED 1000 cm/s
    "px4": (10000, 5.0),  # px4_sitl's CONFIG_NUM_MISSION_ITMES_SUPPORTED; MPC_XY_CRUISE
}


@dataclass(frozen=True)
class MissionOptions:
    max_items: int | None = None  # None: the personality's (see DEFAULTS); set lower to test "too many"
    restart: bool = False  # ArduPilot MIS_RESTART: AUTO always starts from the first item
    speed_m_s: float | None = None  # WPNAV_SPEED / MPC_XY_CRUISE; None: the personality's default
    accel_m_s2: float = 2.5  # WPNAV_ACCEL
    radius_m: float = 2.0  # WPNAV_RADIUS / NAV_ACC_RAD
    upload_timeout_s: float = 8.0  # ArduPilot cancels an upload this long after the last item
    request_resend_s: float = 1.0


@dataclass
class _Upload:
    link: str
    peer: tuple[int, int]
    count: int
    next_seq: int
    last_item_time: float
    last_request_time: float
    staged: list[MissionItem] | None  # PX4 writes into a spare slot
    flagged: int | None = None  # PX4: the item sent with current=1 becomes the current one


class AutopilotMission:
    """The mission storage, protocol server and AUTO/Mission navigator of one simulated autopilot.

    Not thread-safe: the simulator calls it under its own lock.
    """

    def __init__(self, personality: str, options: MissionOptions, home: tuple[float, float, float]):
        self.ardupilot = personality == "ardupilot"
        self.options = options
        self.home = home  # lat, lon, alt AMSL
        max_items, speed = DEFAULTS[personality]
        self.max_items = options.max_items if options.max_items is not None else max_items
        self.default_speed = options.speed_m_s or speed
        self.items: list[MissionItem] = [self._home_item()] if self.ardupilot else []
        self.current = 0  # MISSION_CURRENT.seq: the item flown, or to be flown next
        self.running = False  # in AUTO / Mission mode
        self.complete = False
        self.interrupted = False  # PX4: left Mission mode before the end
        self.held = False  # ArduPilot: set current after the end: stopped there, holding in AUTO
        self.reached: list[int] = []  # every MISSION_ITEM_REACHED sent, in order (tests and metrics)
        self._upload: _Upload | None = None
        self._origin: tuple[float, float, float] | None = None  # where the current leg starts (NED)
        self._started_item = False
        self._speed = self.default_speed
        self._do_from: int | None = None  # ArduPilot: DO items set current before AUTO, run when it starts

    @property
    def first_seq(self) -> int:
        return 1 if self.ardupilot else 0

    @property
    def has_mission(self) -> bool:
        return len(self.items) > self.first_seq

    @property
    def state(self) -> int:
        if not self.has_mission:
            return NO_MISSION
        if self.complete:
            return COMPLETE
        if self.held:
            return NOT_STARTED  # AP_Mission's MISSION_STOPPED
        if self.running:
            return ACTIVE
        return PAUSED if self.interrupted and not self.ardupilot else NOT_STARTED

    def _home_item(self) -> MissionItem:
        lat, lon, alt = self.home
        return MissionItem(NAV_WAYPOINT, FRAME_GLOBAL, x=round(lat * 1e7), y=round(lon * 1e7), z=alt)

    # ---------------------------------------------------------------------------------- protocol
    def handle(self, msg: Any, reply: Send, broadcast: Send, link: str, now: float, status: Status) -> None:
        """Answer a mission-protocol message (MISSION_*) that arrived on `link`."""
        kind = msg.get_type()
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if getattr(msg, "mission_type", 0) != 0:  # fences and rally points are not simulated
            if kind in ("MISSION_COUNT", "MISSION_REQUEST_LIST", "MISSION_CLEAR_ALL"):
                reply(lambda m: m.mission_ack_send(*peer, UNSUPPORTED, msg.mission_type))
            return
        if kind == "MISSION_COUNT":
            self._on_count(int(msg.count), peer, reply, link, now, status)
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            self._on_item(msg, peer, reply, now, status)
        elif kind == "MISSION_REQUEST_LIST":
            count = len(self.items)
            if self._upload is not None:
                reply(lambda m: m.mission_ack_send(*peer, DENIED, 0))
            else:
                reply(lambda m: m.mission_count_send(*peer, count, 0))
        elif kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            self._on_request(msg, peer, reply)
        elif kind == "MISSION_CLEAR_ALL":
            ok = self._upload is None and not (self.ardupilot and self.running and not self.complete)
            if ok:
                self.items = []
                self.current, self.complete, self.interrupted, self.held = 0, False, False, False
            reply(lambda m: m.mission_ack_send(*peer, ACCEPTED if ok else ERROR, 0))
        elif kind == "MISSION_SET_CURRENT":
            seq = int(msg.seq)
            self._set_current(seq)
            reply(lambda m: self.send_current(m, seq))  # the answer names the item asked for
            if not self.ardupilot:
                broadcast(self.send_current)

    def _on_count(self, count: int, peer: tuple[int, int], reply: Send, link: str, now: float,
                  status: Status) -> None:  # fmt: skip
        if self._upload is not None and self._upload.peer != peer:
            reply(lambda m: m.mission_ack_send(*peer, DENIED, 0))
            return
        if count > self.max_items:
            self._upload = None
            reply(lambda m: m.mission_ack_send(*peer, NO_SPACE, 0))
            status(f"Only {self.max_items} items are supported")
            return
        self._upload = _Upload(link, peer, count, 0, now, now, None if self.ardupilot else [])
        if self.ardupilot:
            del self.items[count:]  # AP_Mission::truncate: the stored mission shrinks at once
        if count == 0:
            self._complete_upload(reply, status)
        else:
            self._request(reply, now)

    def _request(self, reply: Send, now: float) -> None:
        up = self._upload
        assert up is not None
        up.last_request_time = now
        seq, peer = up.next_seq, up.peer
        if self.ardupilot:
            reply(lambda m: m.mission_request_send(*peer, seq, 0))
        else:
            reply(lambda m: m.mission_request_int_send(*peer, seq, 0))

    def _on_item(self, msg: Any, peer: tuple[int, int], reply: Send, now: float, status: Status) -> None:
        up = self._upload
        if up is None:
            return  # not receiving: both autopilots ignore a stray item
        if peer != up.peer:
            reply(lambda m: m.mission_ack_send(*peer, DENIED, 0))
            return
        if int(msg.seq) != up.next_seq:
            reply(lambda m: m.mission_ack_send(*peer, INVALID_SEQUENCE, 0))
            return
        item = item_from_message(msg)
        result = ACCEPTED if self.ardupilot and up.next_seq == 0 else self._check(item)
        if result != ACCEPTED:
            self._upload = None  # ArduPilot keeps what it wrote so far; PX4 drops its spare slot
            reply(lambda m: m.mission_ack_send(*peer, result, 0))
            return
        if up.staged is not None:
            up.staged.append(item)
            if getattr(msg, "current", 0) == 1:
                up.flagged = up.next_seq
        elif up.next_seq == 0:
            if not self.items:
                self.items.append(self._home_item())  # ArduPilot keeps its own home as item 0
        elif up.next_seq < len(self.items):
            self.items[up.next_seq] = item
        else:
            self.items.append(item)
        up.next_seq += 1
        up.last_item_time = now
        if up.next_seq >= up.count:
            self._complete_upload(reply, status)
        else:
            self._request(reply, now)

    @staticmethod
    def _check(item: MissionItem) -> int:
        if item.command not in SUPPORTED_COMMANDS:
            return UNSUPPORTED
        if item.command == DO_CHANGE_SPEED:
            return ACCEPTED if item.frame in (FRAME_MISSION, *GLOBAL_FRAMES) else UNSUPPORTED_FRAME
        if item.frame not in GLOBAL_FRAMES:
            return UNSUPPORTED_FRAME
        if abs(item.x) > 900_000_000:
            return INVALID_PARAM5_X
        if abs(item.y) > 1_800_000_000:
            return INVALID_PARAM6_Y
        return ACCEPTED

    def _complete_upload(self, reply: Send, status: Status) -> None:
        up = self._upload
        assert up is not None
        self._upload = None
        if up.staged is not None:  # PX4: the new mission replaces the old one whole, from its start
            self.items = up.staged  # (or from the item sent as current: MavlinkMissionManager's current_seq)
            self.current, self.complete, self.interrupted = up.flagged or 0, False, False
            self._started_item = False
            self._origin = None
        elif self.current >= len(self.items):
            self.current = 0
        reply(lambda m: m.mission_ack_send(*up.peer, ACCEPTED, 0))
        status("Flight plan received" if self.ardupilot else "Mission accepted")

    def _on_request(self, msg: Any, peer: tuple[int, int], reply: Send) -> None:
        seq = int(msg.seq)
        if self._upload is not None:
            reply(lambda m: m.mission_ack_send(*peer, DENIED, 0))
            return
        home = self.ardupilot and seq == 0  # ArduPilot always answers item 0 with its home
        if seq >= len(self.items) and not home:
            count = len(self.items)
            reply(lambda m: m.mission_count_send(*peer, count, 0))
            reply(lambda m: m.mission_ack_send(*peer, ERROR, 0))
            return
        item = self._home_item() if home else self.items[seq]
        current = int(seq == self.current and self.running)
        if msg.get_type() == "MISSION_REQUEST":
            reply(
                lambda m: m.mission_item_send(
                    *peer,
                    seq,
                    item.frame,
                    item.command,
                    current,
                    int(item.autocontinue),
                    item.param1,
                    item.param2,
                    item.param3,
                    item.param4,
                    item.x / 1e7,
                    item.y / 1e7,
                    item.z,
                    0,
                )  # fmt: skip
            )
        else:
            if not self.ardupilot:  # PX4 answers a global item in its _INT frame, whichever was uploaded
                item = replace(item, frame=INT_FRAMES.get(item.frame, item.frame))
            reply(lambda m: send_item(m, peer, seq, item))

    def tick(self, now: float, reply_on: Callable[[str], Send], status: Status) -> None:
        """Re-ask for a missing item; cancel an upload that stalled (ArduPilot's timeout)."""
        up = self._upload
        if up is None:
            return
        if now - up.last_item_time > self.options.upload_timeout_s:
            self._upload = None
            reply_on(up.link)(lambda m: m.mission_ack_send(*up.peer, OPERATION_CANCELLED, 0))
            status("Mission upload timeout")
        elif now - up.last_request_time > self.options.request_resend_s:
            self._request(reply_on(up.link), now)

    def send_current(self, mav: Any, seq: int | None = None) -> None:
        """MISSION_CURRENT (MAVLink 2: with total, mission_state, mission_mode)."""
        total = max(0, len(self.items) - self.first_seq)
        mav.mission_current_send(self.current if seq is None else seq, total, self.state, int(self.running))

    def _set_current(self, seq: int) -> None:
        if not self.first_seq <= seq < len(self.items):
            return
        self._do_from = None
        if self.ardupilot:  # AP_Mission loads the navigation item at or after it and reports that one; the
            # DO items before it still run when AUTO starts (measured: MISSION_ITEM_REACHED for them)
            nav = next(
                (k for k in range(seq, len(self.items)) if self.items[k].command != DO_CHANGE_SPEED), seq
            )
            self._do_from = seq if nav > seq else None
            seq = nav
            self.held = self.held or self.complete  # a finished mission is not restarted by this alone
        self.current, self.complete = seq, False
        self._started_item = False
        if self.running:
            self._origin = None  # fly to the new item from here

    # ----------------------------------------------------------------------------------- navigation
    def start_or_resume(self) -> bool:
        """Entering AUTO/Mission; False (the mode change is refused) without a mission."""
        if not self.has_mission:
            return False
        if self.options.restart or self.complete or not self.first_seq <= self.current < len(self.items):
            self.current = self.first_seq
            self._speed = self.default_speed
        elif self.ardupilot:
            self._speed = self.default_speed  # re-entering AUTO resets WPNAV_SPEED (measured)
            if self._do_from is not None:
                self.current = self._do_from
        else:
            speeds = [
                i.param2 for i in self.items[: self.current] if i.command == DO_CHANGE_SPEED and i.param2 > 0
            ]
            self._speed = speeds[-1] if speeds else self.default_speed  # PX4 replays its speed items
        self.running, self.complete, self._do_from, self.held = True, False, None, False
        self._origin = None  # the interrupted item is flown from where the vehicle is now
        self._started_item = False
        return True

    def resume_in_auto(self) -> bool:
        """ArduCopter's MAV_CMD_MISSION_START in AUTO: a mission that is not running (held, or finished: from
        its first item) runs again; False without a mission."""
        if not self.has_mission:
            return False
        if self.held:
            self.held = False
            self._origin, self._started_item = None, False
        elif self.complete:
            self.start_or_resume()
        return True

    def stop(self) -> None:
        """Leaving AUTO/Mission: the current item is kept for the resume."""
        if self.running and not self.complete:
            self.interrupted = True
        self.running = False

    def _target_ned(self, item: MissionItem, state: VehicleState) -> tuple[float, float, float]:
        lat0, lon0, _ = self.home
        if item.x == 0 and item.y == 0:  # a take-off or landing "here"
            n, e = state.north, state.east
        else:
            n = math.radians(item.lat_deg - lat0) * EARTH_RADIUS
            e = math.radians(item.lon_deg - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
        return n, e, (0.0 if item.command == NAV_LAND else -item.z)

    def command(self, state: VehicleState, broadcast: Send, status: Status) -> VelocityCommand:
        """The velocity AUTO/Mission flies now (zero: hold)."""
        if (
            not self.running
            or self.complete
            or self.held
            or not self.first_seq <= self.current < len(self.items)
        ):
            return VelocityCommand()  # hold (also after the mission was cleared under it, as PX4 allows)
        while not self.complete and self.items[self.current].command == DO_CHANGE_SPEED:
            item = self.items[self.current]
            status(f"Mission: {self.current} {SHORT_NAMES[DO_CHANGE_SPEED]}")
            if item.param2 > 0:
                self._speed = item.param2
            self._reached(broadcast, status, announce=False)
        if self.complete:
            return VelocityCommand()
        item = self.items[self.current]
        if not self._started_item:
            self._started_item = True
            status(f"Mission: {self.current} {SHORT_NAMES.get(item.command, item.name)}")
            if self._origin is None:
                self._origin = (state.north, state.east, state.down)
        target = self._target_ned(item, state)
        if item.command == NAV_TAKEOFF:
            target = (state.north, state.east, target[2])
        elif item.command == NAV_RETURN_TO_LAUNCH:
            target = (0.0, 0.0, state.down)
        elif item.command == NAV_LAND:
            return VelocityCommand(0.0, 0.0, 1.0, 0.0)
        cmd, remaining = self._along_leg(state, target)
        if remaining <= self.options.radius_m and item.command != NAV_LOITER_UNLIM:
            self._origin = target
            self._reached(broadcast, status, announce=True)
        return cmd

    def _along_leg(
        self, state: VehicleState, target: tuple[float, float, float]
    ) -> tuple[VelocityCommand, float]:
        """Track the straight line from the leg's origin to `target`, braking to arrive there; the velocity
        and the distance left."""
        on, oe, od = self._origin or (state.north, state.east, state.down)
        tn, te, td = target
        ln, le, ld = tn - on, te - oe, td - od
        length = math.sqrt(ln * ln + le * le + ld * ld)
        remaining = math.sqrt((tn - state.north) ** 2 + (te - state.east) ** 2 + (td - state.down) ** 2)
        if length < 0.5 or remaining < 0.5:  # at the end of the line: home in on the point itself
            return VelocityCommand(
                (tn - state.north) * 0.8, (te - state.east) * 0.8, (td - state.down) * 0.8
            ), remaining
        un, ue, ud = ln / length, le / length, ld / length
        along = min(
            max((state.north - on) * un + (state.east - oe) * ue + (state.down - od) * ud, 0.0), length
        )
        speed = min(self._speed, math.sqrt(2.0 * self.options.accel_m_s2 * (length - along)))
        # The cross-track error pulls the vehicle back onto the line (a position controller's P term).
        cn, ce, cd = on + un * along - state.north, oe + ue * along - state.east, od + ud * along - state.down
        return VelocityCommand(un * speed + 0.8 * cn, ue * speed + 0.8 * ce, ud * speed + 0.8 * cd), remaining

    def _reached(self, broadcast: Send, status: Status, announce: bool) -> None:
        seq = self.current
        self.reached.append(seq)
        broadcast(lambda m: m.mission_item_reached_send(seq))
        if announce:
            status(f"Reached command #{seq}")
        self._started_item = False
        if seq + 1 >= len(self.items):
            self.complete = True  # hold where the last item left the vehicle, still in AUTO/Mission
        else:
            self.current = seq + 1
        if not self.ardupilot:
            broadcast(self.send_current)
