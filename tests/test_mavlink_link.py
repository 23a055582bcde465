"""The companion's MAVLink link: connection strings, modes, telemetry, garbage, signing."""

from __future__ import annotations

import math
import os
import random
import socket
import subprocess
import sys
import time
from typing import Any

import pytest

from behaviors.mission_commands import ConfirmCandidate
from behaviors.setpoint import Setpoint
from cloudtrack.autopilot_modes import (
    AutopilotKind,
    detect_autopilot,
    mode_for_action,
    mode_name,
    set_mode_params,
)
from cloudtrack.mavlink_connection import parse_connection
from cloudtrack.mavlink_signing import parse_signing_key
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.telemetry_decoder import stream_intervals_us
from companion.mavlink.vehicle_link import VehicleLink
from tests.mavlink_harness import MainLoop, autopilot, gcs, receive_until, vehicle_link, wait_for

KEY_HEX = "a1" * 32
CMD_CONFIRM = 31012


def test_connection_strings() -> None:
    assert parse_connection("serial:/dev/ttyAMA0:921600").device == "/dev/ttyAMA0"
    assert parse_connection("serial:/dev/ttyAMA0:921600").baud == 921600
    assert parse_connection("udpin:0.0.0.0:14540").device == "udpin:0.0.0.0:14540"
    assert parse_connection("udpout:127.0.0.1:14550").kind == "udpout"
    assert parse_connection("tcp:127.0.0.1:5760").kind == "tcp"
    # pymavlink's / MAVProxy's serial form: the device, then ",BAUD"
    assert parse_connection("/dev/ttyAMA0,921600") == parse_connection("serial:/dev/ttyAMA0:921600")
    assert parse_connection("/dev/ttyUSB0").baud == 115200
    for bad in (
        "",
        "udp:1.2.3.4",
        "udpin:0.0.0.0:99999",
        "serial:/dev/ttyUSB0",
        "tcp::5760",
        "bogus:x:1",
        "/dev/ttyUSB0,fast",
    ):
        with pytest.raises(ValueError, match="MAVLink connection"):
            parse_connection(bad)


def test_bad_connection_string_is_refused_with_the_configuration() -> None:
    with pytest.raises(ValueError, match="expected one of"):
        MavlinkConfig(connection="udp:nowhere")


def test_default_connection_listens_on_loopback_only() -> None:
    assert MavlinkConfig().connection.startswith("udpin:127.0.0.1:")


def test_importing_the_link_sets_no_environment_variable_or_dialect() -> None:
    code = (
        "import os, pkgutil, importlib; from pymavlink import mavutil; d = mavutil.mavlink\n"
        "before = dict(os.environ); import companion.mavlink.vehicle_link, gcs.cli, sitl.autopilot\n"
        "assert dict(os.environ) == before, set(os.environ) ^ set(before)\n"
        # every module of ours: no MAVLink variable and the same global dialect (cv2's own loader sets
        # LD_LIBRARY_PATH when it is imported; that one is OpenCV's, not ours)
        "for pkg in ('companion', 'sitl', 'cloudtrack'):\n"
        "    for m in pkgutil.iter_modules(importlib.import_module(pkg).__path__):\n"
        "        importlib.import_module(pkg + '.' + m.name)\n"
        "assert not [k for k in os.environ if k.startswith('MAVLINK') and k not in before], os.environ\n"
        "assert mavutil.mavlink is d, mavutil.mavlink\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MAVLINK20"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)


def test_mode_tables_match_the_autopilots_encodings() -> None:
    assert detect_autopilot(3) is AutopilotKind.ARDUPILOT and detect_autopilot(12) is AutopilotKind.PX4
    assert detect_autopilot(8) is None
    assert (
        mode_name(AutopilotKind.ARDUPILOT, 4) == "GUIDED"
        and mode_name(AutopilotKind.ARDUPILOT, 17) == "BRAKE"
    )
    assert mode_name(AutopilotKind.PX4, (6 << 16)) == "OFFBOARD"
    assert mode_name(AutopilotKind.PX4, (4 << 16) | (3 << 24)) == "HOLD"
    assert mode_name(AutopilotKind.PX4, (4 << 16) | (5 << 24)) == "RTL"
    p = set_mode_params(AutopilotKind.PX4, "HOLD")
    assert (p.base_mode, p.custom_mode, p.custom_sub_mode) == (1, 4, 3)
    assert set_mode_params(AutopilotKind.ARDUPILOT, "LOITER").custom_mode == 5
    assert mode_for_action(AutopilotKind.PX4, "loiter") == "HOLD"
    with pytest.raises(ValueError):
        mode_for_action(AutopilotKind.ARDUPILOT, "arm")
    # pymavlink's tables: every Copter mode (FOLLOW, ZIGZAG...), and Plane/Rover numbers by vehicle type
    assert (
        mode_name(AutopilotKind.ARDUPILOT, 23) == "FOLLOW"
        and mode_name(AutopilotKind.ARDUPILOT, 24) == "ZIGZAG"
    )
    assert mode_name(AutopilotKind.ARDUPILOT, 15, vehicle_type=1) == "GUIDED"  # MAV_TYPE_FIXED_WING
    assert mode_name(AutopilotKind.ARDUPILOT, 4, vehicle_type=10) == "HOLD"  # MAV_TYPE_GROUND_ROVER
    assert set_mode_params(AutopilotKind.ARDUPILOT, "GUIDED", vehicle_type=10).custom_mode == 15
    with pytest.raises(ValueError, match="no mode 'BRAKE'"):
        set_mode_params(AutopilotKind.ARDUPILOT, "BRAKE", vehicle_type=1)
    assert mode_name(AutopilotKind.ARDUPILOT, 250) == "MODE(250)"


def test_stream_requests_cover_every_decoded_message() -> None:
    ids = {msg_id for msg_id, _ in stream_intervals_us(10.0)}
    # HEARTBEAT, SYS_STATUS, ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT, MISSION_CURRENT
    assert ids == {0, 1, 30, 32, 33, 42}
    assert dict(stream_intervals_us(10.0))[30] == 100_000
    assert dict(stream_intervals_us(10.0))[42] == 500_000  # the item changes at waypoints only
    # PX4 refuses a HEARTBEAT rate (FAILED, stays at 1 Hz): its mode comes from CURRENT_MODE (436) too.
    px4 = dict(stream_intervals_us(10.0, AutopilotKind.PX4))
    assert px4[436] == 100_000 and 436 not in dict(stream_intervals_us(10.0, AutopilotKind.ARDUPILOT))


def _frames(system: int = 4) -> tuple[Any, Any]:
    """(an ardupilotmega parser, as the link decodes, and a development-dialect encoder that knows CURRENT_MODE)."""
    from pymavlink.dialects.v20 import ardupilotmega, development

    return ardupilotmega.MAVLink(None), development.MAVLink(None, srcSystem=system, srcComponent=1)


PX4_HOLD, PX4_OFFBOARD, PX4_POSCTL = 4 << 16 | 3 << 24, 6 << 16, 3 << 16


@pytest.mark.parametrize(
    ("custom", "intended", "crc_ok", "system", "expected"),
    [
        (PX4_POSCTL, PX4_POSCTL, True, 4, ("POSCTL", False)),  # the pilot's switch, seen at once
        (PX4_HOLD, PX4_OFFBOARD, True, 4, ("HOLD", True)),  # offboard lost: a failsafe chose HOLD
        (PX4_HOLD, 0, True, 4, ("HOLD", False)),  # intended mode not reported
        (PX4_OFFBOARD, PX4_OFFBOARD, True, 4, ("OFFBOARD", False)),  # no change: still a sign of life
        (PX4_POSCTL, PX4_POSCTL, False, 4, None),  # bad CRC: not a mode report
        (PX4_POSCTL, PX4_POSCTL, True, 9, None),  # another system's
    ],
)
def test_px4_current_mode_updates_the_mode_between_heartbeats(
    custom: int, intended: int, crc_ok: bool, system: int, expected: tuple[str, bool] | None
) -> None:
    from companion.mavlink.telemetry_decoder import TelemetryDecoder

    parser, encoder = _frames()
    decoder = TelemetryDecoder(4)
    heartbeat = encoder.heartbeat_encode(2, 12, 129, PX4_OFFBOARD, 4).pack(encoder)
    assert decoder.feed(parser.decode(bytearray(heartbeat)), 1.0) is not None
    sender = _frames(system)[1]
    frame = bytearray(sender.current_mode_encode(0, custom, intended).pack(sender))
    if not crc_ok:
        frame[-1] ^= 0xFF
    report = decoder.feed(parser.decode(frame), 1.1)  # the link's dialect leaves it UNKNOWN_436
    assert (None if report is None else (report.mode, report.failsafe)) == expected
    assert decoder.heartbeat is not None and decoder.heartbeat.armed


def test_heartbeat_system_status_critical_is_a_failsafe() -> None:
    from companion.mavlink.telemetry_decoder import TelemetryDecoder

    parser, encoder = _frames()
    decoder = TelemetryDecoder(4)
    for status, failsafe in ((4, False), (5, True)):  # MAV_STATE_ACTIVE, MAV_STATE_CRITICAL
        frame = encoder.heartbeat_encode(2, 12, 129, PX4_HOLD, status).pack(encoder)
        hb = decoder.feed(parser.decode(bytearray(frame)), 1.0)
        assert hb is not None and hb.failsafe is failsafe


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_telemetry_is_decoded_from_the_autopilot(personality: str) -> None:
    with autopilot(personality, start_yaw_deg=30.0) as sim, vehicle_link(sim) as link, MainLoop(link):
        assert link.autopilot_kind is AutopilotKind(personality)

        def decoded() -> bool:
            # ATTITUDE and GLOBAL_POSITION_INT arrive as separate messages: wait for both, not the first.
            t = link.telemetry()
            return abs(t.yaw - math.radians(30)) < 1e-3 and abs(t.height_agl - 20.0) < 0.01

        assert wait_for(decoded, 3.0)
        t = link.telemetry()
        assert t.armed
        assert t.lat_deg == pytest.approx(47.397742, abs=1e-6) and t.lon_deg == pytest.approx(
            8.545594, abs=1e-6
        )
        assert t.mode == ("GUIDED" if personality == "ardupilot" else "POSCTL")
        assert t.offboard_active is (personality == "ardupilot")


@pytest.mark.slow
def test_garbage_on_the_link_crashes_nothing() -> None:
    rng = random.Random(1234)
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: len(sim.setpoints) >= 5)
        port = link.endpoint.local_port()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for i in range(1000):
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 280)))
            prefix = (b"", b"\xfd", b"\xfe", b"\xfd\x10\x00\x00")[i % 4]  # plausible MAVLink 2/1 headers too
            sock.sendto(prefix + junk, ("127.0.0.1", port))
            sock.sendto(prefix + junk, ("127.0.0.1", sim.link_port("companion")))
        sock.close()
        before = len(sim.setpoints)
        time.sleep(1.0)
        assert len(sim.setpoints) - before >= 8  # still streaming
        stamp = link.telemetry().time_s
        assert wait_for(lambda: link.telemetry().time_s > stamp, 2.0)  # still decoding telemetry
        # Not the autopilot: dropped before parsing. Fewer than the 1000 sent may arrive: the kernel drops what
        # overflows the socket's buffer while the reader is busy, and that is no datagram the link parsed either.
        assert link.endpoint.conn.refused_datagrams >= 1
        assert sim._links["companion"].bad_data > 0  # the autopilot parsed the junk and went on too
        assert all(t.is_alive() for t in link._threads)


@pytest.mark.slow
def test_signing_refuses_forged_and_unsigned_commands() -> None:
    key = parse_signing_key(KEY_HEX)
    with (
        autopilot("ardupilot", signing_key=key) as sim,
        vehicle_link(sim, signing_key=KEY_HEX, gcs_system_ids=[253, 254, 255]) as link,
        MainLoop(link),
    ):
        # forged: signed with the wrong key
        with gcs(sim, signing_key=bytes(32 * [7])) as forger:
            forger.send(lambda m: m.command_long_send(1, 191, CMD_CONFIRM, 0, 0, 0, 0, 0, 0, 0, 0))
            assert (
                receive_until(
                    forger, lambda m: m.get_type() == "COMMAND_ACK" and m.command == CMD_CONFIRM, 1.5
                )
                is None
            )
        # unsigned
        with gcs(sim, system=254) as plain:
            plain.send(lambda m: m.command_long_send(1, 191, CMD_CONFIRM, 0, 0, 0, 0, 0, 0, 0, 0))
            assert (
                receive_until(
                    plain, lambda m: m.get_type() == "COMMAND_ACK" and m.command == CMD_CONFIRM, 1.5
                )
                is None
            )
        assert link.commands() == []
        assert link.signing.refused.count("COMMAND_LONG") >= 2
        assert any(e.reason == "signing" and e.action == "refused" for e in link.safety_events())
        # the right key is accepted, and the reply is signed
        with gcs(sim, signing_key=key, system=253) as ground:
            ground.send(lambda m: m.command_long_send(1, 191, CMD_CONFIRM, 0, 2, 0, 0, 0, 0, 0, 0))
            ack = receive_until(
                ground, lambda m: m.get_type() == "COMMAND_ACK" and m.command == CMD_CONFIRM, 3.0
            )
            assert ack is not None and ack.result == 0 and ack._signed
        assert link.commands() == [ConfirmCandidate("2", by="gcs")]


def test_bad_signing_key_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="64 hexadecimal"):
        parse_signing_key("not-a-key")
    with pytest.raises(ValueError, match="64 hexadecimal"):
        VehicleLink(MavlinkConfig(signing_key="abcd"), SafetyConfig())


@pytest.mark.parametrize("form", ["{tty},57600", "serial:{tty}:57600"])
def test_serial_link_over_a_pseudo_terminal(form: str) -> None:
    """serial:DEVICE:BAUD through pyserial: the companion detects the autopilot and asks for its streams."""
    import contextlib
    import os
    import tty

    from cloudtrack.mavlink_connection import mavlink

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)

    class PtyWriter:
        def write(self, data: bytes) -> None:
            os.write(master, data)

    autopilot_side = mavlink.MAVLink(PtyWriter(), srcSystem=1, srcComponent=1)
    autopilot_side.robust_parsing = True
    link = VehicleLink(MavlinkConfig(connection=form.format(tty=os.ttyname(slave))), SafetyConfig())
    received: list = []
    try:
        link.start()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not any(m.get_type() == "COMMAND_LONG" for m in received):
            autopilot_side.heartbeat_send(2, 12, 129, 3 << 16, 4)  # PX4, POSCTL
            link.kick()
            time.sleep(0.1)
            with contextlib.suppress(BlockingIOError):  # nothing written yet
                received += autopilot_side.parse_buffer(os.read(master, 4096)) or []
        assert link.autopilot_kind is AutopilotKind.PX4
        kinds = {m.get_type() for m in received}
        assert {"HEARTBEAT", "COMMAND_LONG"} <= kinds  # ours (type 18) and SET_MESSAGE_INTERVAL requests
        assert any(
            m.get_type() == "HEARTBEAT" and m.type == 18 and m.get_srcComponent() == 191 for m in received
        )
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_tcp_link_to_the_autopilot() -> None:
    from sitl.autopilot import AutopilotOptions, SimulatedAutopilot

    sim = SimulatedAutopilot(AutopilotOptions(personality="px4"), {"companion": "tcpin:127.0.0.1:0"})
    sim.start()
    link = VehicleLink(
        MavlinkConfig(connection=f"tcp:127.0.0.1:{sim.link_port('companion')}"), SafetyConfig()
    )
    try:
        link.start()
        with MainLoop(link):
            assert wait_for(lambda: link.telemetry() is not None, 5.0)
            assert link.autopilot_kind is AutopilotKind.PX4
            link.request_offboard()
            link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
            assert wait_for(lambda: sim.mode == "OFFBOARD" and sim.snapshot().vn > 0.5, 6.0)
    finally:
        link.close()
        sim.close()
