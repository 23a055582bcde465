"""The mock's PX4 personality held to the real PX4 1.16 (SIH): the same MAVLink exchanges, the same answers.

Every exchange runs against both vehicles, each armed and hovering at 10 m with COM_OF_LOSS_T 0.5 s and
COM_OBL_RC_ACT Hold: `mock` (sitl/autopilot.py, personality px4) and `px4_sitl` (the real binary,
../shared/sitl/px4, armed and taken off by the GCS as a pilot would, the pilot's joystick centred). The
client speaks as the companion does (system N+1 / 191) on the companion's link; the pilot's side is
`ScriptedGcs` on the GCS link. Each test reduces what it saw to an answer and compares it with `REAL`, what
the real PX4 answers; where the mock differs on purpose the difference is in `KNOWN_DIFFERENCES` with its
reason (docs/sitl.md lists both). `pytest -k px4_sitl` selects the real side (slow: the PX4 it shares with
tests/test_px4_sitl_scenarios.py, one boot and take-off for both).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import development

from sitl.scenarios import ScriptedGcs

pytestmark = [pytest.mark.slow, pytest.mark.shares_px4]
mavlink = development  # the client decodes CURRENT_MODE (development.xml); PX4 speaks the common set
EARTH_RADIUS = 6_378_137.0
# PX4's custom_mode: main mode in byte 2, sub mode in byte 3. Written out here, not taken from the mock.
MODES = {"ALTCTL": (2, 0), "POSCTL": (3, 0), "HOLD": (4, 3), "OFFBOARD": (6, 0)}
VELOCITY_ONLY = 0b0000_0101_1100_0111  # position, acceleration and yaw ignored; velocity and yaw rate used
VELOCITY_AND_YAW = 0b0000_1001_1100_0111  # velocity and yaw angle used, yaw rate ignored
# A fresh-clone CI run once saw HOLD's second DO_SET_MODE ACK later than 1 s (the mode itself had changed).
LATE_ACK_S = 2.0
STOPPED_M_S = 0.15  # settled: the mean velocity over the last half second under this (SIH's hover wanders)
SETTLE_MAX_S = 6.0  # ...waiting at most this long for it
FAILED, UNSUPPORTED, ACCEPTED, TEMPORARILY_REJECTED, DENIED = 4, 3, 0, 1, 2


def custom_mode(name: str) -> int:
    main, sub = MODES[name]
    return main << 16 | sub << 24


# What the real PX4 1.16 answers (measured with this suite); the mock must give the same unless listed below.
REAL: dict[str, Any] = {
    # PX4 answers DO_SET_MODE twice: ACCEPTED at once, then the outcome.
    "mode_encoding": {name: ([ACCEPTED, ACCEPTED], True, True) for name in ("ALTCTL", "POSCTL", "HOLD")},
    "unknown_mode": {"acks": [ACCEPTED, ACCEPTED], "mode": "HOLD"},  # accepted, and nothing changes
    "acks": {
        "set_message_interval": [ACCEPTED],
        "heartbeat_interval": [FAILED],  # the HEARTBEAT rate is fixed at 1 Hz
        "current_mode_interval": [ACCEPTED],
        "request_message": [ACCEPTED],
        "unknown_command": [UNSUPPORTED],
    },
    "arm": [ACCEPTED],  # already armed: accepted
    "offboard_without_stream": {
        "acks": [ACCEPTED, TEMPORARILY_REJECTED],
        "mode": "HOLD",
        "mode_once_the_stream_runs": "HOLD",
    },
    "offboard_after_a_stream": {"acks": [ACCEPTED, ACCEPTED], "mode": "OFFBOARD"},
    "offboard_loss": {
        "left_offboard_for": "HOLD",
        "after_com_of_loss_t": True,  # 0.5 s (+ CURRENT_MODE's report of it)
        "intended_mode": "OFFBOARD",  # the failsafe's mode, not the one asked for
        "system_status_critical": True,
        "told_the_gcs": True,  # STATUSTEXT "Failsafe activated"
        "stopped_by_3_s": True,
        "back_in_offboard_when_setpoints_return": True,
    },
    "rates_hz": {"ATTITUDE": 20, "GLOBAL_POSITION_INT": 5},
    # CURRENT_MODE asked for at 10 Hz comes at 1.7 Hz, and within 0.11 s of a mode change (below).
    "current_mode": {"at_the_requested_10_hz": False, "at_least_1_hz": True},
    "disabled_after_minus_one": True,
    # CURRENT_MODE is sent on the change (0.11 s idle, 0.21 s once under CI's load); HEARTBEAT only on its 1 Hz
    # beat (0.2-1.0 s): whether a beat falls within 0.2 s is chance, so only "by the next beat" is compared.
    "mode_change_seen": {"current_mode_within_0_4_s": True, "heartbeat_within_1_5_s": True},
    # (course, mode while streaming): PX4 flies velocities in LOCAL_NED and BODY_NED only; a stream in the
    # other body frames is no offboard signal, so it falls into its offboard-loss failsafe.
    "course_deg": {
        "LOCAL_NED": (0, "OFFBOARD"),
        "BODY_NED": (90, "OFFBOARD"),
        "BODY_OFFSET_NED": (None, "HOLD"),
    },
    "ignored_outside_offboard": True,
    "reposition_arrives": {"mode": "HOLD", "within_1_5_m": True},
    "yaw_rate": {"clockwise": True, "within_30_percent": True},
}
KNOWN_DIFFERENCES: dict[str, str] = {
    # name -> reason; the mock's answer is not compared for these (docs/sitl.md lists them).
    "arm": "the mock starts armed and hovering and denies every arm request, so a companion that tries to arm "
    "fails a test; the real PX4 arms for whoever asks once its pre-arm checks pass",
}


@dataclass
class Px4Link:
    """The companion's side of the link (system `system`, component 191), every message kept with its time."""

    kind: str
    system: int
    client: Any
    gcs: ScriptedGcs
    closer: Callable[[], Any]
    messages: list[tuple[float, Any]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self) -> Px4Link:
        threading.Thread(target=self._read, name=f"{self.kind}-client", daemon=True).start()
        self.client.mav.heartbeat_send(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4
        )
        return self

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.client.recv_msg()
            except Exception:
                continue
            if msg is None:
                time.sleep(0.005)
                continue
            if msg.get_srcSystem() == self.system and msg.get_srcComponent() == 1:
                with self._lock:
                    self.messages.append((time.monotonic(), msg))

    def close(self) -> None:
        self._stop.set()
        self.closer()

    def since(self, t0: float, *types: str) -> list[tuple[float, Any]]:
        with self._lock:
            return [(t, m) for t, m in self.messages if t >= t0 and m.get_type() in types]

    def latest(self, kind: str) -> Any:
        with self._lock:
            return next((m for _, m in reversed(self.messages) if m.get_type() == kind), None)

    def send_command(self, command: int, *params: float) -> float:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        sent = time.monotonic()
        self.client.mav.command_long_send(self.system, 1, command, 0, *p)
        return sent

    def command(self, command: int, *params: float, wait: float = 1.0, expect: int = 1) -> list[int]:
        """Every COMMAND_ACK result for `command` within `wait` seconds (PX4 may answer more than once);
        under load it waits up to `LATE_ACK_S` longer for the `expect`-th, so a late ACK is not read as none."""
        sent = self.send_command(command, *params)
        time.sleep(wait)
        end = time.monotonic() + LATE_ACK_S
        while True:
            acks = [int(m.result) for _, m in self.since(sent, "COMMAND_ACK") if m.command == command]
            if len(acks) >= expect or time.monotonic() > end:
                return acks
            time.sleep(0.02)

    def interval(self, msg_id: int, hz: float) -> list[int]:
        """Its one COMMAND_ACK comes within milliseconds (DO_SET_MODE's second one takes longer)."""
        return self.command(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz if hz > 0 else -1, wait=0.4
        )

    def set_mode(self, name: str, wait: float = 1.0) -> list[int]:
        main, sub = MODES[name]
        return self.command(
            mavlink.MAV_CMD_DO_SET_MODE,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            main,
            sub,
            wait=wait,
            expect=2,
        )

    def intended_mode(self) -> str | None:
        """The mode the pilot (or the companion) asked for, as the newest CURRENT_MODE reports it: a failsafe's
        mode stands in for it while the failsafe lasts (an offboard loss shows HOLD, intended OFFBOARD)."""
        current = self.latest("CURRENT_MODE")
        if current is None:
            return None
        return next((n for n in MODES if custom_mode(n) == current.intended_custom_mode), "?")

    def mode(self) -> str | None:
        """The mode the newest HEARTBEAT or CURRENT_MODE reported."""
        with self._lock:
            latest = next(
                (m for _, m in reversed(self.messages) if m.get_type() in ("HEARTBEAT", "CURRENT_MODE")), None
            )
        if latest is None:
            return None
        return next(
            (n for n in MODES if custom_mode(n) == latest.custom_mode), f"MODE({latest.custom_mode:#x})"
        )

    def wait_pilots_mode(self, name: str, timeout: float) -> bool:
        """Until CURRENT_MODE reports `name` as both the mode and the intended mode (False after `timeout`)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            current = self.latest("CURRENT_MODE")
            if current is not None and current.custom_mode == current.intended_custom_mode == custom_mode(
                name
            ):
                return True
            time.sleep(0.02)
        return False

    def wait_mode(self, name: str, timeout: float = 3.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.mode() == name:
                return True
            time.sleep(0.02)
        return False

    def setpoint(
        self,
        frame: int,
        mask: int,
        vel: tuple[float, float, float] = (0, 0, 0),
        yaw: float = 0.0,
        yaw_rate: float = 0.0,
    ) -> None:
        self.client.mav.set_position_target_local_ned_send(
            0, self.system, 1, frame, mask, 0, 0, 0, *vel, 0, 0, 0, yaw, yaw_rate
        )

    def stream_autopilot_time(
        self, seconds: float, send: Callable[[], None], most_s: float = 10.0
    ) -> list[tuple[float, Any]]:
        """Call `send` at 20 Hz until `seconds` have passed by the autopilot's own clock (LOCAL_POSITION_NED's
        time_boot_ms): a busy machine that delays its messages lengthens the stream, not shortens what the
        autopilot had of it. The LOCAL_POSITION_NED seen, timed from the first one in autopilot seconds."""
        start = time.monotonic()
        first: int | None = None
        while True:
            send()
            time.sleep(0.05)
            seen = self.since(start, "LOCAL_POSITION_NED")
            if seen:
                first = seen[0][1].time_boot_ms if first is None else first
                if seen[-1][1].time_boot_ms - first >= seconds * 1000:
                    return [((m.time_boot_ms - first) / 1000.0, m) for _, m in seen]
            assert time.monotonic() - start < most_s, f"{len(seen)} LOCAL_POSITION_NED in {most_s} s"

    def stream(self, seconds: float, send: Callable[[], None] | None = None) -> list[tuple[float, Any]]:
        """Call `send` at 20 Hz for `seconds` (nothing when None); the LOCAL_POSITION_NED seen, from 0 s."""
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            if send is not None:
                send()
            time.sleep(0.05)
        return [(t - start, m) for t, m in self.since(start, "LOCAL_POSITION_NED")]

    def hold(self, seconds: float = 0.0) -> None:
        """Zero velocity facing north (a stream), for `seconds`."""
        self.stream(seconds, lambda: self.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW))

    def settle(self) -> None:
        """HOLD, stopped: where every exchange that flies starts (the pilot's mode, set from the GCS); none
        ends with it, the next one settles (CI pays for each second of the real half).

        HOLD as PX4 reports it, the intended mode too: an exchange that ended in OFFBOARD leaves PX4 in its
        offboard-loss failsafe, which also shows HOLD but ends as soon as setpoints come again (intended
        OFFBOARD). The GCS's one DO_SET_MODE is asked again until CURRENT_MODE reports the pilot's HOLD, each
        time within PX4's own bounds (DO_SET_MODE answered within LATE_ACK_S, CURRENT_MODE sent on the change),
        so a request lost or late on a busy machine is not read as one that took."""
        main, sub = MODES["HOLD"]
        for _ in range(3):
            self.gcs.set_mode(main, sub)
            if self.wait_pilots_mode("HOLD", LATE_ACK_S + 1.0):
                break
        assert (self.mode(), self.intended_mode()) == ("HOLD", "HOLD"), (self.mode(), self.intended_mode())
        # PX4's HOLD brakes and comes back to where it was asked; after 2 m/s that can take longer than 1.5 s,
        # and an exchange that measures speed must not read the braking as its answer.
        track = self.stream(1.5)
        end = time.monotonic() + SETTLE_MAX_S
        while time.monotonic() < end and not _stopped(track, 1.0, 1.5):
            track = self.stream(1.5)

    def offboard(self) -> None:
        """OFFBOARD, stopped, facing north (after a 1 s stream, as the companion does)."""
        self.hold(1.0)
        self.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW)  # one more right before the request
        self.send_command(mavlink.MAV_CMD_DO_SET_MODE, 1, *MODES["OFFBOARD"])
        self.hold(1.5)
        assert self.mode() == "OFFBOARD", self.mode()


def _mock() -> Px4Link:
    from sitl.autopilot import AutopilotOptions, SimulatedAutopilot

    sim = SimulatedAutopilot(
        AutopilotOptions(personality="px4", start_height_m=10.0, offboard_loss_s=0.5),
        {"gcs": "udpin:127.0.0.1:0", "companion": "udpin:127.0.0.1:0"},
    )
    sim.start()
    gcs = ScriptedGcs(f"udpout:127.0.0.1:{sim.link_port('gcs')}").start()
    client = _client(f"udpout:127.0.0.1:{sim.link_port('companion')}", 1)

    def close() -> None:
        gcs.stop()
        client.close()
        sim.close()

    return Px4Link("mock", 1, client, gcs, close).start()


def _client(url: str, system: int) -> Any:
    client = mavutil.mavlink_connection(url, source_system=system, source_component=191)
    client.mav = development.MAVLink(client, srcSystem=system, srcComponent=191)
    client.mav.robust_parsing = True
    return client


def _px4_sitl(shared: Any) -> Px4Link:
    """The real PX4 the scenario flights share (tests/conftest.py `shared_px4`), back over home in HOLD."""
    real = shared.get()
    real.reuse(None)  # the bridge answers whoever speaks to it: this client
    real.return_home(10.0, progress=print)
    client = _client(f"udpout:127.0.0.1:{real.bridge.udp_port}", real.system_id)
    return Px4Link("px4_sitl", real.system_id, client, real.gcs, client.close).start()


@pytest.fixture(scope="module", params=["mock", "px4_sitl"])
def vehicle(request: pytest.FixtureRequest) -> Iterator[Px4Link]:
    v = _mock() if request.param == "mock" else _px4_sitl(request.getfixturevalue("shared_px4"))
    try:
        assert v.interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10) == [ACCEPTED]
        assert v.interval(mavlink.MAVLINK_MSG_ID_CURRENT_MODE, 10) == [ACCEPTED]
        v.settle()
        yield v
    finally:
        v.close()


def _compare(v: Px4Link, name: str, answer: Any) -> None:
    print(f"{v.kind} {name}: {answer}")
    if v.kind == "mock" and name in KNOWN_DIFFERENCES:
        return
    assert answer == REAL[name], f"{v.kind} answers {answer} to {name}; the real PX4 answers {REAL[name]}"


def _mode_name(msg: Any) -> str:
    return next((n for n in MODES if custom_mode(n) == msg.custom_mode), f"MODE({msg.custom_mode:#x})")


def _stopped(track: list[tuple[float, Any]], t0: float, t1: float) -> bool:
    """The mean velocity over [t0, t1] under `STOPPED_M_S` (nothing seen: not known to be stopped)."""
    return any(t0 <= t <= t1 for t, _ in track) and _course(track, t0, t1)[1] < STOPPED_M_S


def _course(track: list[tuple[float, Any]], t0: float, t1: float) -> tuple[float, float]:
    """Mean course (deg, 0 = north, 90 = east) and speed over [t0, t1] of a LOCAL_POSITION_NED track."""
    pts = [m for t, m in track if t0 <= t <= t1]
    vn = sum(m.vx for m in pts) / len(pts)
    ve = sum(m.vy for m in pts) / len(pts)
    return math.degrees(math.atan2(ve, vn)) % 360, math.hypot(vn, ve)


def test_mode_encoding(vehicle: Px4Link) -> None:
    """DO_SET_MODE with PX4's main and sub mode for the modes a pilot selects: the ACKs, then HEARTBEAT and
    CURRENT_MODE carry the same custom_mode."""
    answer = {}
    for name in ("ALTCTL", "POSCTL", "HOLD"):
        acks = vehicle.set_mode(name)
        time.sleep(1.2)  # one HEARTBEAT period
        hb, current = vehicle.latest("HEARTBEAT"), vehicle.latest("CURRENT_MODE")
        answer[name] = (acks, hb.custom_mode == custom_mode(name), current.custom_mode == custom_mode(name))
    _compare(vehicle, "mode_encoding", answer)  # in HOLD, the last one
    acks = vehicle.command(
        mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 13, 0, wait=1.5, expect=2
    )
    _compare(vehicle, "unknown_mode", {"acks": acks, "mode": vehicle.mode()})


def test_command_acks(vehicle: Px4Link) -> None:
    acks = {
        "set_message_interval": vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 4),
        "heartbeat_interval": vehicle.interval(mavlink.MAVLINK_MSG_ID_HEARTBEAT, 10),
        "current_mode_interval": vehicle.interval(mavlink.MAVLINK_MSG_ID_CURRENT_MODE, 10),
        "request_message": vehicle.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_ATTITUDE),
        "unknown_command": vehicle.command(31099),
    }
    vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1)
    _compare(vehicle, "acks", acks)
    _compare(vehicle, "arm", vehicle.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1))


def test_offboard_entry_without_and_with_a_setpoint_stream(vehicle: Px4Link) -> None:
    """PX4 refuses OFFBOARD until setpoints are arriving (and does not switch later by itself when they start);
    after a 1 s stream it switches."""
    vehicle.settle()
    acks = vehicle.set_mode("OFFBOARD", wait=1.5)
    refused_mode = vehicle.mode()
    vehicle.hold(1.5)  # the stream starts; no new request
    _compare(
        vehicle,
        "offboard_without_stream",
        {"acks": acks, "mode": refused_mode, "mode_once_the_stream_runs": vehicle.mode()},
    )
    # One more setpoint right before the request: a stall of this thread must not read as the stream's end.
    vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW)
    sent = vehicle.send_command(mavlink.MAV_CMD_DO_SET_MODE, 1, *MODES["OFFBOARD"])
    vehicle.hold(1.5)
    acks = [
        int(m.result)
        for _, m in vehicle.since(sent, "COMMAND_ACK")
        if m.command == mavlink.MAV_CMD_DO_SET_MODE
    ]
    _compare(vehicle, "offboard_after_a_stream", {"acks": acks, "mode": vehicle.mode()})


def test_what_happens_after_com_of_loss_t(vehicle: Px4Link) -> None:
    """Flying 1.5 m/s in OFFBOARD, the setpoints stop: the failsafe (COM_OBL_RC_ACT Hold) after COM_OF_LOSS_T,
    and what it does when setpoints come back."""
    vehicle.settle()
    vehicle.offboard()
    vehicle.stream(2.0, lambda: vehicle.setpoint(mavlink.MAV_FRAME_BODY_NED, VELOCITY_ONLY, (1.5, 0, 0)))
    stopped = time.monotonic()
    track = vehicle.stream(3.0)
    left = next(
        (
            (t, m)
            for t, m in vehicle.since(stopped, "CURRENT_MODE", "HEARTBEAT")
            if m.custom_mode != custom_mode("OFFBOARD")
        ),
        None,
    )
    current = next(
        (m for t, m in vehicle.since(stopped, "CURRENT_MODE") if m.custom_mode != custom_mode("OFFBOARD")),
        None,
    )
    statuses = [m.system_status for _, m in vehicle.since(stopped, "HEARTBEAT")]
    texts = [text for t, text in list(vehicle.gcs.statustexts) if t >= stopped]  # on the GCS link
    print(
        f"{vehicle.kind}: left OFFBOARD {None if left is None else round(left[0] - stopped, 3)} s after the last "
        f"setpoint; heartbeat status {statuses}; texts {texts}"
    )
    speed = _course(track, 2.5, 3.0)[1]
    print(f"{vehicle.kind}: {speed:.2f} m/s 2.5-3 s after the last setpoint")
    vehicle.hold(1.0)  # setpoints again, no mode request
    back = vehicle.mode() == "OFFBOARD"
    answer = {
        "left_offboard_for": None
        if left is None
        else next((n for n in MODES if custom_mode(n) == left[1].custom_mode), "?"),
        # COM_OF_LOSS_T 0.5 s plus CURRENT_MODE's report of it (0.11 s idle, up to 0.4 s under load)
        "after_com_of_loss_t": left is not None and 0.4 <= left[0] - stopped <= 0.9,
        "intended_mode": None
        if current is None
        else next((n for n in MODES if custom_mode(n) == current.intended_custom_mode), "?"),
        "system_status_critical": mavlink.MAV_STATE_CRITICAL in statuses,
        "told_the_gcs": any(text.startswith("Failsafe activated") for text in texts),
        "stopped_by_3_s": speed < 0.5,  # SIH's hover wanders at up to 0.3 m/s
        "back_in_offboard_when_setpoints_return": back,
    }
    _compare(vehicle, "offboard_loss", answer)


def test_message_rates_after_set_message_interval(vehicle: Px4Link) -> None:
    rates = {
        "ATTITUDE": (mavlink.MAVLINK_MSG_ID_ATTITUDE, 20),
        "GLOBAL_POSITION_INT": (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5),
    }
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_CURRENT_MODE, 10) == [ACCEPTED]
    for msg_id, hz in rates.values():
        assert vehicle.interval(msg_id, hz) == [ACCEPTED]
    time.sleep(0.5)
    start = time.monotonic()
    time.sleep(3.0)
    measured = {name: len(vehicle.since(start, name)) / 3.0 for name in (*rates, "CURRENT_MODE")}
    print(f"{vehicle.kind}: {measured}")
    current = measured["CURRENT_MODE"]
    _compare(
        vehicle, "current_mode", {"at_the_requested_10_hz": current >= 8.0, "at_least_1_hz": current >= 1.0}
    )
    # Within 20 %: both schedule on their own loop, so a period is quantised to it.
    _compare(
        vehicle,
        "rates_hz",
        {
            name: hz if abs(measured[name] - hz) <= 0.2 * hz else round(measured[name], 1)
            for name, (_, hz) in rates.items()
        },
    )
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, -1) == [ACCEPTED]
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1) == [ACCEPTED]
    time.sleep(0.5)
    start = time.monotonic()
    time.sleep(1.5)
    _compare(vehicle, "disabled_after_minus_one", not vehicle.since(start, "GLOBAL_POSITION_INT"))
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10) == [ACCEPTED]  # the others use it


def test_how_soon_a_mode_change_shows(vehicle: Px4Link) -> None:
    """After the GCS's mode change: CURRENT_MODE (asked for at 10 Hz) and HEARTBEAT (fixed 1 Hz)."""
    vehicle.settle()
    delays: dict[str, list[float]] = {"CURRENT_MODE": [], "HEARTBEAT": []}
    for name in ("POSCTL", "HOLD"):
        sent = time.monotonic()
        vehicle.gcs.set_mode(*MODES[name])
        time.sleep(1.6)  # past the next 1 Hz HEARTBEAT
        for kind in delays:
            seen = [t for t, m in vehicle.since(sent, kind) if m.custom_mode == custom_mode(name)]
            delays[kind].append(round(seen[0] - sent, 3) if seen else math.inf)
    print(f"{vehicle.kind}: new mode seen after {delays} s")
    _compare(
        vehicle,
        "mode_change_seen",
        {
            "current_mode_within_0_4_s": max(delays["CURRENT_MODE"]) < 0.4,
            "heartbeat_within_1_5_s": max(delays["HEARTBEAT"]) < 1.5,
        },
    )


def test_velocity_frames_of_set_position_target_local_ned_and_yaw_rate(vehicle: Px4Link) -> None:
    """2 m/s "forward" in each frame with the vehicle facing east (the companion uses BODY_NED on PX4); then
    the yaw rate. (BODY_OFFSET_NED's failsafe leaves OFFBOARD: the yaw rate enters it again.)"""
    vehicle.settle()
    vehicle.offboard()
    vehicle.stream(
        3.0, lambda: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW, yaw=math.pi / 2)
    )
    courses = {}
    for name, frame in (
        ("LOCAL_NED", mavlink.MAV_FRAME_LOCAL_NED),
        ("BODY_NED", mavlink.MAV_FRAME_BODY_NED),
        ("BODY_OFFSET_NED", mavlink.MAV_FRAME_BODY_OFFSET_NED),
    ):
        track = vehicle.stream(2.5, partial(vehicle.setpoint, frame, VELOCITY_ONLY, (2.0, 0.0, 0.0)))
        course, speed = _course(track, 1.5, 2.5)
        print(f"{vehicle.kind} {name}: course {course:.0f} deg at {speed:.2f} m/s")
        courses[name] = (round(course / 45) * 45 % 360 if speed > 0.8 else None, vehicle.mode())
        vehicle.stream(
            1.5, lambda: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW, yaw=math.pi / 2)
        )
    _compare(vehicle, "course_deg", courses)
    # The follow law's yaw, in the same flight: 0.3 rad/s in BODY_NED with zero velocity turns it clockwise.
    vehicle.offboard()
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 10) == [ACCEPTED]
    start = time.monotonic()
    vehicle.stream(3.0, lambda: vehicle.setpoint(mavlink.MAV_FRAME_BODY_NED, VELOCITY_ONLY, yaw_rate=0.3))
    vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1)
    window = [(t - start, m.yaw) for t, m in vehicle.since(start, "ATTITUDE") if 1.5 <= t - start <= 3.0]
    turned = math.remainder(window[-1][1] - window[0][1], math.tau)
    rate = turned / (window[-1][0] - window[0][0])
    print(f"{vehicle.kind}: yaw rate {rate:.3f} rad/s for 0.3 commanded")
    _compare(vehicle, "yaw_rate", {"clockwise": rate > 0, "within_30_percent": abs(rate - 0.3) <= 0.09})


def test_setpoints_ignored_outside_offboard(vehicle: Px4Link) -> None:
    """2 m/s north streamed for 2 s of the autopilot's time in the pilot's HOLD (settle: not a failsafe's
    HOLD, which the stream would end): PX4 stays in HOLD at its hold point. Judged by what it reports: every
    mode it reported during the stream, and how far north its position moved (following, it would be 2.5 m
    or more by then: MPC_ACC_HOR 3 m/s^2 to 2 m/s; holding, SIH's wander of up to 0.3 m/s about the hold
    point keeps it well within 1 m)."""
    vehicle.settle()
    started = time.monotonic()
    track = vehicle.stream_autopilot_time(
        2.0, lambda: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY, (2.0, 0, 0))
    )
    modes = {_mode_name(m) for _, m in vehicle.since(started, "HEARTBEAT", "CURRENT_MODE")}
    north = track[-1][1].x - track[0][1].x
    speed = _course(track, 1.0, 2.0)[1]
    print(f"{vehicle.kind}: moved {north:.2f} m north ({speed:.2f} m/s in the last second) in {sorted(modes)} "
          "while 2 m/s north was streamed")  # fmt: skip
    _compare(vehicle, "ignored_outside_offboard", modes == {"HOLD"} and north < 1.0)


def test_gcs_reposition(vehicle: Px4Link) -> None:
    """The GCS's "go to location" (MAV_CMD_DO_REPOSITION, the abort scenario's fly-to) 8 m north of the vehicle."""
    vehicle.settle()
    vehicle.offboard()
    asked = vehicle.send_command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
    time.sleep(0.5)
    here = next((m for _, m in reversed(vehicle.since(asked, "GLOBAL_POSITION_INT"))), None)
    assert here is not None
    lat = here.lat / 1e7 + math.degrees(8.0 / EARTH_RADIUS)
    start = vehicle.latest("LOCAL_POSITION_NED")
    vehicle.gcs.reposition(lat, here.lon / 1e7, here.alt / 1000.0)
    sent = time.monotonic()
    miss = math.inf
    while time.monotonic() - sent < 8.0 and miss >= 1.0:  # arrived: stop waiting
        time.sleep(0.1)
        end = vehicle.latest("LOCAL_POSITION_NED")
        miss = math.dist((end.x, end.y), (start.x + 8.0, start.y))
    print(f"{vehicle.kind}: {miss:.2f} m from the target after 8 s, mode {vehicle.mode()}")
    _compare(vehicle, "reposition_arrives", {"mode": vehicle.mode(), "within_1_5_m": miss < 1.5})
