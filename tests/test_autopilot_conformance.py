"""The mock's ArduCopter personality held to the real ArduCopter: the same MAVLink exchanges, the same answers.

Every exchange runs against both vehicles, each armed and hovering at 10 m in GUIDED with GUID_TIMEOUT 1 s:
`mock` (sitl/autopilot.py) and `arducopter` (the real SITL binary, ../shared/sitl/arducopter, armed and
taken off by the GCS as a pilot would). The client speaks as the companion does (1/191) on the companion's
link; the pilot's side is `ScriptedGcs` on the GCS link. Each test reduces what it saw to an answer and
compares it with `REAL`, what the real ArduCopter 4.7 answers; where the mock differs on purpose the
difference is in `KNOWN_DIFFERENCES` with its reason (listed in docs/sitl.md). `pytest -k arducopter`
selects the real side (slow: one SITL boot for the module, about a minute).

The mission exchanges (`test_mission_*`) upload, download, clear and fly a small mission around where the
vehicle hovers, through `cloudtrack.mission_protocol.MissionClient` on the companion's link. They are
written for any autopilot the fixture provides; `MISSION_ANSWERS` keys them by the autopilot's family (the
PX4 side follows with PX4 SITL). `cloudtrack-gcs survey` on a second ground station's link (the SITL's
SERIAL5) is flown in the search scenario (tests/test_arducopter_scenarios.py::test_arducopter_search).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil

from behaviors.geolocation import offset_to_latlon
from behaviors.mission_items import NAV_WAYPOINT, MissionItem
from cloudtrack.mission_protocol import MissionClient, MissionError, MissionTimeouts, positions_match
from sitl.scenarios import ScriptedGcs

pytestmark = pytest.mark.slow  # real time on both sides: about a minute each
mavlink = mavutil.mavlink
MODES = {"STABILIZE": 0, "ALT_HOLD": 2, "GUIDED": 4, "LOITER": 5, "POSHOLD": 16, "BRAKE": 17}
VELOCITY_ONLY = 0b0000_0101_1100_0111  # position, acceleration and yaw ignored; velocity and yaw rate used
POSITION_ONLY = 0b0000_1101_1111_1000
VELOCITY_AND_YAW = 0b0000_1001_1100_0111  # velocity and yaw angle used, yaw rate ignored

# What the real ArduCopter answers (measured with this suite); the mock must give the same unless listed below.
REAL: dict[str, Any] = {
    "mode_numbers": {name: (0, number) for name, number in MODES.items() if name != "STABILIZE"},
    "unknown_mode_ack": 4,  # MAV_RESULT_FAILED for a custom mode ArduCopter does not have
    "acks": {
        "set_message_interval": 0,
        "request_message": 0,
        "unknown_command": 3,
        "takeoff_while_flying": 4,
    },
    "arm": 0,  # already armed: accepted
    "guid_timeout": {"moving_at_0_7_s": True, "stopped_by_3_s": True},
    "rates_hz": {"ATTITUDE": 20, "GLOBAL_POSITION_INT": 5},
    "disabled_after_minus_one": True,
    "course_deg": {"LOCAL_NED": 0, "BODY_NED": 90, "BODY_OFFSET_NED": 90},
    "ignored_outside_guided": True,
    "fly_to_arrives": True,
    "heartbeat_within_0_2_s_of_a_mode_change": True,
    "yaw_rate": {"clockwise": True, "within_30_percent": True},
}
KNOWN_DIFFERENCES: dict[str, str] = {
    # name -> reason; the mock's answer is not compared for these (docs/sitl.md lists them).
    "arm": "the mock starts armed and hovering and denies every arm request, so a companion that tries to arm "
    "fails a test; the real ArduCopter arms for whoever asks once its pre-arm checks pass",
}


@dataclass
class Vehicle:
    kind: str
    client: Any  # pymavlink connection on the companion's link, as 1/191
    gcs: ScriptedGcs
    closer: Any
    autopilot: str = "ardupilot"

    def recv(self, types: list[str], timeout: float) -> Any:
        return self.client.recv_match(type=types, blocking=True, timeout=timeout)

    def command(self, command: int, *params: float, component: int = 1, timeout: float = 3.0) -> int | None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.client.mav.command_long_send(1, component, command, 0, *p)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            msg = self.recv(["COMMAND_ACK"], 0.2)
            if msg is not None and msg.command == command:
                return int(msg.result)
        return None

    def interval(self, msg_id: int, hz: float) -> int | None:
        return self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz if hz > 0 else -1)

    def mode(self, timeout: float = 2.0) -> int | None:
        end = time.monotonic() + timeout
        latest = None
        while time.monotonic() < end:
            msg = self.recv(["HEARTBEAT"], 0.2)
            if msg is not None and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1:
                latest = int(msg.custom_mode)
                break
        return latest

    def set_mode(self, number: int) -> int | None:
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)

    def setpoint(
        self,
        frame: int,
        mask: int,
        pos: tuple[float, float, float] = (0, 0, 0),
        vel: tuple[float, float, float] = (0, 0, 0),
        yaw: float = 0.0,
    ) -> None:
        self.client.mav.set_position_target_local_ned_send(0, 1, 1, frame, mask, *pos, *vel, 0, 0, 0, yaw, 0)

    def track(self, seconds: float, every: Any = None) -> list[tuple[float, Any]]:
        """LOCAL_POSITION_NED for `seconds`; `every(elapsed)` is called about 10 times a second."""
        out: list[tuple[float, Any]] = []
        start = time.monotonic()
        last = -1.0
        while (elapsed := time.monotonic() - start) < seconds:
            if every is not None and elapsed - last >= 0.1:
                every(elapsed)
                last = elapsed
            msg = self.recv(["LOCAL_POSITION_NED"], 0.05)
            if msg is not None:
                out.append((time.monotonic() - start, msg))
        return out

    def settle(self) -> None:
        """Back to GUIDED, stopped, facing north: where every exchange starts (each test settles first, so
        none settles again at its end)."""
        assert self.set_mode(MODES["GUIDED"]) == 0
        self.track(2.5, lambda _: self.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW))


def _mock() -> Vehicle:
    from sitl.autopilot import AutopilotOptions, SimulatedAutopilot
    from sitl.autopilot_mission import MissionOptions

    # The stalled upload waits out the autopilot's upload timeout: ArduCopter's 8 s, the mock's shortened to 2 s
    # here (the answers do not depend on it).
    sim = SimulatedAutopilot(
        AutopilotOptions(
            start_height_m=10.0, guid_timeout_s=1.0, mission=MissionOptions(upload_timeout_s=2.0)
        ),
        {"gcs": "udpin:127.0.0.1:0", "companion": "udpin:127.0.0.1:0"},
    )
    sim.start()
    client = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{sim.link_port('companion')}", source_system=1, source_component=191
    )
    gcs = ScriptedGcs(f"udpout:127.0.0.1:{sim.link_port('gcs')}").start()
    return Vehicle("mock", client, gcs, lambda: (gcs.stop(), client.close(), sim.close()))


def _arducopter(work: Path) -> Vehicle:
    from sitl.arducopter_sitl import ArduCopterSitl, RealAutopilot, find_binary

    sitl = ArduCopterSitl(find_binary(), work, (47.397742, 8.545594, 488.0, 0.0), speedup=10.0).start()
    gcs = ScriptedGcs(f"tcp:127.0.0.1:{sitl.ports.gcs}").start()
    real = RealAutopilot(sitl, gcs)
    try:
        real.fly_up(10.0, progress=print)
    except Exception:
        gcs.stop()
        real.close()
        raise
    # The project's parameters took: GUID_TIMEOUT 1 s and the 4.5+ stream-rate names on the companion's port.
    params = {
        name: gcs.read_param(name) for name in ("GUID_TIMEOUT", "MAV3_POSITION", "MAV3_EXTRA1", "SIM_SPEEDUP")
    }
    print(f"arducopter parameters: {params}")
    assert params == {"GUID_TIMEOUT": 1.0, "MAV3_POSITION": 10.0, "MAV3_EXTRA1": 10.0, "SIM_SPEEDUP": 1.0}
    client = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{real.bridge.udp_port}", source_system=1, source_component=191
    )
    client.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return Vehicle("arducopter", client, gcs, lambda: (gcs.stop(), client.close(), real.close()))


@pytest.fixture(scope="module", params=["mock", "arducopter"])
def vehicle(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Vehicle]:
    v = _mock() if request.param == "mock" else _arducopter(tmp_path_factory.mktemp("arducopter"))
    v.client.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    assert v.interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10) == 0
    try:
        yield v
    finally:
        v.closer()


def _compare(v: Vehicle, name: str, answer: Any) -> None:
    print(f"{v.kind} {name}: {answer}")
    if v.kind == "mock" and name in KNOWN_DIFFERENCES:
        return
    assert answer == REAL[name], (
        f"{v.kind} answers {answer} to {name}; the real ArduCopter answers {REAL[name]}"
    )


def _drain(v: Vehicle) -> None:
    while v.client.recv_match(blocking=False) is not None:
        pass


def _course(track: list[tuple[float, Any]], t0: float, t1: float) -> tuple[float, float]:
    """Mean course (deg, 0 = north, 90 = east) and speed over [t0, t1] of a LOCAL_POSITION_NED track."""
    pts = [m for t, m in track if t0 <= t <= t1]
    vn = sum(m.vx for m in pts) / len(pts)
    ve = sum(m.vy for m in pts) / len(pts)
    return math.degrees(math.atan2(ve, vn)) % 360, math.hypot(vn, ve)


def test_mode_numbers(vehicle: Vehicle) -> None:
    """DO_SET_MODE with each ArduCopter mode number the companion and the pilot use: ACK, then HEARTBEAT."""
    answer = {}
    for name, number in MODES.items():
        if name == "STABILIZE":
            continue  # a manual-throttle mode on the SITL's idle throttle would drop the vehicle
        ack = vehicle.set_mode(number)
        time.sleep(0.3)
        answer[name] = (ack, vehicle.mode())
    _compare(vehicle, "mode_numbers", answer)
    _compare(vehicle, "unknown_mode_ack", vehicle.set_mode(99))
    vehicle.settle()


def test_command_acks(vehicle: Vehicle) -> None:
    acks = {
        "set_message_interval": vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 4),
        "request_message": vehicle.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_ATTITUDE),
        "unknown_command": vehicle.command(31099),
        "takeoff_while_flying": vehicle.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 20),
    }
    vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1)
    _compare(vehicle, "acks", acks)
    _compare(vehicle, "arm", vehicle.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1))


def test_velocity_after_guid_timeout(vehicle: Vehicle) -> None:
    """One 2 m/s velocity setpoint, then silence: flown until GUID_TIMEOUT (1 s), then the vehicle stops."""
    vehicle.settle()
    vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY, vel=(2.0, 0.0, 0.0))
    track = vehicle.track(4.0)
    speed_07 = _course(track, 0.6, 0.8)[1]
    speed_3 = _course(track, 2.8, 3.2)[1]
    travelled = math.dist((track[0][1].x, track[0][1].y), (track[-1][1].x, track[-1][1].y))
    print(
        f"{vehicle.kind}: {speed_07:.2f} m/s at 0.7 s, {speed_3:.2f} m/s at 3 s, {travelled:.2f} m travelled"
    )
    _compare(vehicle, "guid_timeout", {"moving_at_0_7_s": speed_07 > 0.5, "stopped_by_3_s": speed_3 < 0.3})


def test_message_rates_after_set_message_interval(vehicle: Vehicle) -> None:
    rates = {"ATTITUDE": (mavlink.MAVLINK_MSG_ID_ATTITUDE, 20), "GLOBAL_POSITION_INT": (33, 5)}
    for msg_id, hz in rates.values():
        assert vehicle.interval(msg_id, hz) == 0
    time.sleep(0.5)
    _drain(vehicle)  # what queued while the new rates settled is not part of the 3 s count
    counts = dict.fromkeys(rates, 0)
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        msg = vehicle.recv(list(rates), 0.1)
        if msg is not None:
            counts[msg.get_type()] += 1
    measured = {name: counts[name] / 3.0 for name in rates}
    print(f"{vehicle.kind}: {measured}")
    # Within 20 %: both schedule on their own loop, so a period is quantised to it.
    _compare(
        vehicle,
        "rates_hz",
        {name: hz for name, (_, hz) in rates.items() if abs(measured[name] - hz) <= 0.2 * hz}
        | {
            name: round(measured[name], 1)
            for name, (_, hz) in rates.items()
            if abs(measured[name] - hz) > 0.2 * hz
        },
    )
    for msg_id, _ in rates.values():
        assert vehicle.interval(msg_id, -1) == 0
    time.sleep(0.5)
    _drain(vehicle)
    seen = 0
    end = time.monotonic() + 1.5
    while time.monotonic() < end:
        if vehicle.recv(["GLOBAL_POSITION_INT"], 0.1) is not None:
            seen += 1
    _compare(vehicle, "disabled_after_minus_one", seen == 0)


def test_velocity_frames_the_companion_uses(vehicle: Vehicle) -> None:
    """2 m/s "forward" in each frame with the vehicle facing east: LOCAL_NED flies north, body frames east."""
    vehicle.settle()
    vehicle.track(
        4.0, lambda _: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_AND_YAW, yaw=math.pi / 2)
    )
    courses = {}
    for name, frame in (
        ("LOCAL_NED", mavlink.MAV_FRAME_LOCAL_NED),
        ("BODY_NED", mavlink.MAV_FRAME_BODY_NED),
        ("BODY_OFFSET_NED", mavlink.MAV_FRAME_BODY_OFFSET_NED),
    ):
        track = vehicle.track(2.0, lambda _, f=frame: vehicle.setpoint(f, VELOCITY_ONLY, vel=(2.0, 0.0, 0.0)))
        course, speed = _course(track, 1.2, 2.0)
        print(f"{vehicle.kind} {name}: course {course:.0f} deg at {speed:.2f} m/s")
        courses[name] = round(course / 45) * 45 % 360 if speed > 0.8 else None
        vehicle.track(2.5, lambda _: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY))
    _compare(vehicle, "course_deg", courses)


def test_setpoints_ignored_outside_guided(vehicle: Vehicle) -> None:
    vehicle.settle()
    assert vehicle.set_mode(MODES["LOITER"]) == 0
    track = vehicle.track(
        2.0, lambda _: vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY, vel=(2.0, 0, 0))
    )
    _compare(vehicle, "ignored_outside_guided", _course(track, 1.0, 2.0)[1] < 0.3)


def test_gcs_position_target_in_local_ned(vehicle: Vehicle) -> None:
    """The GCS's "fly to" (the abort scenario's): a LOCAL_NED position target 8 m north is reached."""
    vehicle.settle()
    start = vehicle.track(0.5)[-1][1]
    vehicle.gcs.fly_to(start.x + 8.0, start.y, start.z)
    track = vehicle.track(8.0)
    end = track[-1][1]
    miss = math.dist((end.x, end.y), (start.x + 8.0, start.y))
    print(f"{vehicle.kind}: {miss:.2f} m from the target after 8 s")
    _compare(vehicle, "fly_to_arrives", miss < 1.5)


def test_heartbeat_follows_a_mode_change(vehicle: Vehicle) -> None:
    """With HEARTBEAT at its default 1 Hz, how soon a mode change shows: what a companion's takeover
    detection waits for when it has not asked for faster heartbeats."""
    vehicle.settle()
    delays = []
    for name in ("LOITER", "GUIDED", "BRAKE", "GUIDED"):
        number = MODES[name]
        vehicle.client.mav.command_long_send(
            1,
            1,
            mavlink.MAV_CMD_DO_SET_MODE,
            0,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            number,
            0,
            0,
            0,
            0,
            0,
        )
        sent = time.monotonic()
        while time.monotonic() - sent < 2.0:
            msg = vehicle.recv(["HEARTBEAT"], 0.05)
            if msg is not None and msg.get_srcComponent() == 1 and msg.custom_mode == number:
                delays.append(time.monotonic() - sent)
                break
        else:
            delays.append(math.inf)
        time.sleep(0.5)
    print(f"{vehicle.kind}: HEARTBEAT with the new mode {[round(d, 3) for d in delays]} s after DO_SET_MODE")
    _compare(vehicle, "heartbeat_within_0_2_s_of_a_mode_change", max(delays) < 0.2)


def test_yaw_rate_in_the_companions_frame(vehicle: Vehicle) -> None:
    """The follow law's yaw: 0.3 rad/s in BODY_OFFSET_NED with zero velocity turns the vehicle clockwise."""
    vehicle.settle()
    assert vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 10) == 0
    yaws: list[tuple[float, float]] = []
    start = time.monotonic()
    while (elapsed := time.monotonic() - start) < 3.0:
        vehicle.setpoint(mavlink.MAV_FRAME_BODY_OFFSET_NED, VELOCITY_ONLY)
        vehicle.client.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_BODY_OFFSET_NED, VELOCITY_ONLY, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.3
        )
        end = time.monotonic() + 0.1
        while time.monotonic() < end:
            msg = vehicle.recv(["ATTITUDE"], 0.05)
            if msg is not None:
                yaws.append((elapsed, msg.yaw))
    vehicle.interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1)
    window = [(t, y) for t, y in yaws if 1.5 <= t <= 3.0]
    turned = math.remainder(window[-1][1] - window[0][1], math.tau)
    rate = turned / (window[-1][0] - window[0][0])
    print(f"{vehicle.kind}: yaw rate {rate:.3f} rad/s for 0.3 commanded")
    _compare(vehicle, "yaw_rate", {"clockwise": rate > 0, "within_30_percent": abs(rate - 0.3) <= 0.09})


# ----------------------------------------------------------------------------------------------- missions
# What each autopilot family answers to the mission exchanges (measured with this suite on ArduCopter 4.7);
# the mock's personality of that family must give the same.
MISSION_ANSWERS: dict[str, dict[str, Any]] = {
    "ardupilot": {
        "upload_download_clear": {
            "requests": [
                "MISSION_REQUEST"
            ],  # not MISSION_REQUEST_INT: answered with MISSION_ITEM_INT all the same
            "round_trip": True,
            "home_is_item_0": True,
            "current_after_set": (1, 5, 2),  # seq, total (without home), NOT_STARTED
            "after_clear": (0, False, 1),  # items, home item, NO_MISSION
        },
        "refusals": {
            "too_many": (4, "the previous mission is unchanged"),  # NO_SPACE at MISSION_COUNT
            "limit_text": "Only 650 items are supported",
            "previous_kept": True,
            "bad_frame": (2, "the partly written mission was cleared"),  # UNSUPPORTED_FRAME
            "bad_command": (3, "the partly written mission was cleared"),  # UNSUPPORTED
            "items_after_refusal": 0,
            "auto_without_mission": 4,  # COMMAND_ACK FAILED
        },
        "stalled_upload": {
            "autopilot_cancels": (15, "the partly written mission was cleared", 0),  # OPERATION_CANCELLED
            "cancel_text": "Mission upload timeout",
            "ground_gives_up": ("the partly written mission was cleared", 0),
        },
        "auto_resume": {
            "auto_ack": 0,
            "survey_speed_on_the_first_leg": True,  # DO_CHANGE_SPEED 3 m/s, within 0.5 m/s
            "reached_before_break": [1, 2],  # DO_CHANGE_SPEED is "reached" too
            "current_after_break": (3, 2),  # the item it broke off at, NOT_STARTED
            "first_reached_after_resume": 3,  # that item, not the first one
            "straight_from_break_off": True,  # within 2 m of the line from where AUTO resumed to the item
            "faster_than_the_survey_speed": True,  # DO_CHANGE_SPEED was dropped: WPNAV_SPEED again
            "end": (5, 3),  # COMPLETE, and still in AUTO (custom_mode 3)
        },
    },
}
SURVEY_SPEED = 3.0
STEP_TIMEOUTS = MissionTimeouts(1.0, 5)
LEG_M = 15.0


class _Link:
    """`cloudtrack.mission_protocol.MissionLink` over the test's client, noting what arrives on the way."""

    def __init__(self, v: Vehicle, drop: Any = None) -> None:
        self.v = v
        self.drop = drop  # drop(build) -> True: this message is lost on the way to the autopilot
        self.types: set[str] = set()
        self.texts: list[str] = []
        self.reached: list[int] = []
        self.positions: list[tuple[float, float, float]] = []  # (time, north, east)

    def send(self, build: Any) -> bool:
        if self.drop is None or not self.drop(build):
            build(self.v.client.mav)
        return True

    def receive(self, timeout: float) -> Any:
        msg = self.v.client.recv_match(blocking=True, timeout=timeout)
        if msg is not None:
            self.note(msg)
        return msg

    def note(self, msg: Any) -> None:
        kind = msg.get_type()
        self.types.add(kind)
        if kind == "STATUSTEXT":
            self.texts.append(str(msg.text))
        elif kind == "MISSION_ITEM_REACHED":
            self.reached.append(int(msg.seq))
        elif kind == "LOCAL_POSITION_NED":
            self.positions.append((time.monotonic(), float(msg.x), float(msg.y)))

    def pump(self, seconds: float, until: Any = None) -> bool:
        """Read for up to `seconds`, or until `until()` holds."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.receive(0.05)
            if until is not None and until():
                return True
        return False


def _mission_client(v: Vehicle, link: _Link, timeouts: MissionTimeouts = STEP_TIMEOUTS) -> MissionClient:
    return MissionClient(link, v.autopilot, target=(1, 1), source=(1, 191), timeouts=timeouts)


def _here(v: Vehicle, link: _Link) -> tuple[float, float, float, float]:
    """(lat, lon, north, east) of the vehicle now: GLOBAL_POSITION_INT asked for, LOCAL_POSITION_NED streamed."""
    v.client.mav.command_long_send(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 33, 0, 0, 0, 0, 0, 0)
    found: list[Any] = []
    link.positions.clear()
    end = time.monotonic() + 5.0
    while time.monotonic() < end and not (found and link.positions):
        msg = link.receive(0.1)
        if msg is not None and msg.get_type() == "GLOBAL_POSITION_INT":
            found.append(msg)
    assert found and link.positions, "no GLOBAL_POSITION_INT / LOCAL_POSITION_NED"
    _, north, east = link.positions[-1]
    return found[0].lat / 1e7, found[0].lon / 1e7, north, east


def _square(lat: float, lon: float, alt: float = 10.0) -> list[MissionItem]:
    """Waypoints LEG_M north, then east, then south of (lat, lon): three legs of a square."""
    corners = ((LEG_M, 0.0), (LEG_M, LEG_M), (0.0, LEG_M))
    return [MissionItem.waypoint(*offset_to_latlon(lat, lon, n, e), alt) for n, e in corners]


def _compare_mission(v: Vehicle, name: str, answer: dict[str, Any]) -> None:
    print(f"{v.kind} {name}: {answer}")
    expected = MISSION_ANSWERS[v.autopilot][name]
    assert answer == expected, f"{v.kind} answers {answer} to {name}; the real autopilot answers {expected}"


def _ending(exc: MissionError) -> str:
    return str(exc).rsplit("; ", 1)[-1]


def test_mission_upload_download_clear(vehicle: Vehicle) -> None:
    vehicle.settle()
    link = _Link(vehicle)
    client = _mission_client(vehicle, link)
    lat, lon, _, _ = _here(vehicle, link)
    items = [MissionItem.change_speed(SURVEY_SPEED), *_square(lat, lon), MissionItem.waypoint(lat, lon, 10.0)]
    link.types.clear()
    client.upload(items)
    requests = sorted(link.types & {"MISSION_REQUEST", "MISSION_REQUEST_INT"})
    got = client.download()
    current = client.set_current(client.first_seq)
    answer: dict[str, Any] = {
        "requests": requests,
        "round_trip": positions_match(got.items, items),
        "home_is_item_0": got.home is not None,
        "current_after_set": (current.seq, current.total, current.state),
    }
    client.clear()
    after = client.download()
    answer["after_clear"] = (len(after.items), after.home is not None, client.read_current().state)
    _compare_mission(vehicle, "upload_download_clear", answer)


def test_mission_refusals(vehicle: Vehicle) -> None:
    """More items than the autopilot stores, a frame and a command it cannot store, AUTO without a mission:
    each refusal as the client reports it, and what is left on the vehicle."""
    vehicle.settle()
    link = _Link(vehicle)
    client = _mission_client(vehicle, link)
    lat, lon, _, _ = _here(vehicle, link)
    good = _square(lat, lon)
    client.upload(good)
    answer: dict[str, Any] = {}
    with pytest.raises(MissionError) as too_many:
        client.upload(good[:1] * 650)  # 651 with home
    answer["too_many"] = (too_many.value.result, _ending(too_many.value))
    link.pump(1.0)
    answer["limit_text"] = next((t for t in link.texts if "items are supported" in t), None)
    answer["previous_kept"] = positions_match(client.download().items, good)
    for name, bad in (
        (
            "bad_frame",
            MissionItem(NAV_WAYPOINT, 7, x=good[0].x, y=good[0].y, z=10.0),
        ),  # MAV_FRAME_LOCAL_NED_INT?
        ("bad_command", MissionItem(31010, 2)),
    ):
        with pytest.raises(MissionError) as refused:
            client.upload([good[0], bad, good[1]])
        answer[name] = (refused.value.result, _ending(refused.value))
    answer["items_after_refusal"] = len(client.download().items)
    answer["auto_without_mission"] = vehicle.set_mode(3)
    _compare_mission(vehicle, "refusals", answer)


def test_mission_stalled_upload(vehicle: Vehicle) -> None:
    """The ground's link stops carrying items midway. With the protocol's own timeouts the autopilot gives up
    first (it cancels after 8 s, the mock here after 2 s); with short ones the ground tool gives up while the
    autopilot still waits for items (it then refuses MISSION_CLEAR_ALL, and the client clears with an empty
    upload). Either way what the autopilot had written is gone: nothing half uploaded stays."""
    from cloudtrack.mission_protocol import send_item

    vehicle.settle()

    def cut(build: Any) -> bool:  # items after the second never arrive
        return getattr(build, "func", None) is send_item and build.keywords["seq"] > 2

    link = _Link(vehicle, drop=cut)
    client = _mission_client(vehicle, link, MissionTimeouts(1.5, 8))
    lat, lon, _, _ = _here(vehicle, link)
    old = _square(lat, lon)
    _mission_client(vehicle, _Link(vehicle)).upload(old)
    new = _square(lat, lon, alt=12.0) + _square(lat, lon, alt=12.0)
    answer: dict[str, Any] = {}
    with pytest.raises(MissionError) as cancelled:
        client.upload(new)
    answer["autopilot_cancels"] = (
        cancelled.value.result,
        _ending(cancelled.value),
        len(_mission_client(vehicle, _Link(vehicle)).download().items),
    )
    answer["cancel_text"] = next((t for t in link.texts if "upload timeout" in t), None)
    _mission_client(vehicle, _Link(vehicle)).upload(old)
    short = _mission_client(vehicle, _Link(vehicle, drop=cut), MissionTimeouts(0.3, 1))
    with pytest.raises(MissionError) as gave_up:
        short.upload(new)
    answer["ground_gives_up"] = (
        _ending(gave_up.value),
        len(_mission_client(vehicle, _Link(vehicle)).download().items),
    )
    _compare_mission(vehicle, "stalled_upload", answer)


def test_mission_auto_resume(vehicle: Vehicle) -> None:
    """AUTO flies the mission; GUIDED takes the vehicle away halfway along a leg; AUTO again resumes at the item
    it broke off at, flying straight there from where it is (ArduCopter MIS_RESTART 0)."""
    vehicle.settle()
    link = _Link(vehicle)
    client = _mission_client(vehicle, link)
    lat, lon, north0, east0 = _here(vehicle, link)
    square = _square(lat, lon)
    client.upload([MissionItem.change_speed(SURVEY_SPEED), *square])
    client.set_current(client.first_seq)
    first_wp = client.first_seq + 1
    link.reached.clear()
    t_auto = time.monotonic()
    answer: dict[str, Any] = {"auto_ack": vehicle.set_mode(3)}
    assert link.pump(20.0, lambda: first_wp in link.reached), f"{vehicle.kind} never reached {first_wp}"
    first_leg = _top_speed([p for p in link.positions if p[0] >= t_auto])
    answer["survey_speed_on_the_first_leg"] = abs(first_leg - SURVEY_SPEED) < 0.5
    # Halfway along the next leg (east), the pilot or the companion takes the vehicle: GUIDED, 8 m away.
    assert link.pump(10.0, lambda: link.positions[-1][2] - east0 > LEG_M / 2)
    answer["reached_before_break"] = list(link.reached)
    assert vehicle.set_mode(MODES["GUIDED"]) == 0
    _, n, e = link.positions[-1]
    vehicle.setpoint(mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, pos=(n - 8.0, e - 8.0, -10.0))
    link.pump(7.0)
    current = client.read_current()
    answer["current_after_break"] = (current.seq, current.state)
    link.reached.clear()
    t_resume = time.monotonic()
    assert vehicle.set_mode(3) == 0
    target = (north0 + LEG_M, east0 + LEG_M)
    assert link.pump(20.0, lambda: bool(link.reached)), f"{vehicle.kind} reached nothing after the resume"
    answer["first_reached_after_resume"] = link.reached[0]
    leg = [(t, n, e) for t, n, e in link.positions if t >= t_resume]
    start = (leg[0][1], leg[0][2])
    deviation = max(_off_line((n, e), start, target) for _, n, e in leg)
    top = _top_speed(leg)
    print(f"{vehicle.kind}: first leg at {first_leg:.1f} m/s; resumed from {start} to {target}: "
          f"{deviation:.2f} m off the line, top speed {top:.1f} m/s")  # fmt: skip
    answer["straight_from_break_off"] = deviation < 2.0
    answer["faster_than_the_survey_speed"] = top > SURVEY_SPEED + 0.5
    last = client.first_seq + len(square)
    assert link.pump(20.0, lambda: last in link.reached), f"{vehicle.kind} never reached the last item"
    end = client.read_current()
    answer["end"] = (end.state, vehicle.mode())
    _compare_mission(vehicle, "auto_resume", answer)
    assert vehicle.set_mode(MODES["GUIDED"]) == 0  # ArduCopter refuses a clear in AUTO
    client.clear()


def _top_speed(track: list[tuple[float, float, float]]) -> float:
    """The highest speed over half-second spans of a (time, north, east) track."""
    pairs = zip(track, track[5:], strict=False)
    return max((math.dist(a[1:], b[1:]) / (b[0] - a[0]) for a, b in pairs if b[0] > a[0]), default=0.0)


def _off_line(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    ax, ay = b[0] - a[0], b[1] - a[1]
    t = max(0.0, min(1.0, ((p[0] - a[0]) * ax + (p[1] - a[1]) * ay) / (ax * ax + ay * ay)))
    return math.dist(p, (a[0] + t * ax, a[1] + t * ay))
