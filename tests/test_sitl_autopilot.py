"""The SITL autopilot: personalities, modes, setpoint semantics, ArduCopter and PX4 rules, routing, kinematics."""

from __future__ import annotations

import argparse
import math
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from cloudtrack.mavlink_connection import MavlinkEndpoint
from sitl import autopilot_command
from sitl.vehicle_dynamics import VehicleLimits, VehicleState, VelocityCommand, Wind, step
from tests.mavlink_harness import autopilot, gcs, receive_until, set_mode_from_gcs, wait_for

BODY_OFFSET_NED, LOCAL_NED, BODY_NED = 9, 1, 8
VELOCITY_YAW_RATE_MASK = 0b0000_0101_1100_0111
VELOCITY_ONLY_MASK = 0b0000_1101_1100_0111  # both yaw fields ignored


@contextmanager
def companion(sim) -> Iterator[MavlinkEndpoint]:  # type: ignore[no-untyped-def]
    endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('companion')}", 1, 191)
    try:
        endpoint.send(lambda m: m.heartbeat_send(18, 8, 0, 0, 0))
        assert receive_until(endpoint, lambda m: m.get_type() == "HEARTBEAT", 3.0) is not None
        yield endpoint
    finally:
        endpoint.close()


def velocity(endpoint: MavlinkEndpoint, vx: float, vy: float = 0.0, yaw_rate: float = 0.0,
             frame: int = BODY_OFFSET_NED, mask: int = VELOCITY_YAW_RATE_MASK) -> None:  # fmt: skip
    endpoint.send(
        lambda m: m.set_position_target_local_ned_send(
            0, 1, 1, frame, mask, 0, 0, 0, vx, vy, 0, 0, 0, 0, 0, yaw_rate
        )
    )


def command(endpoint: MavlinkEndpoint, cmd: int, *params: float):  # type: ignore[no-untyped-def]
    p = list(params) + [0.0] * (7 - len(params))
    endpoint.send(lambda m: m.command_long_send(1, 1, cmd, 0, *p))
    return receive_until(endpoint, lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd, 3.0)


@pytest.mark.parametrize(
    ("personality", "autopilot_id", "custom_mode"),
    [("ardupilot", 3, 4), ("px4", 12, 3 << 16)],  # GUIDED = 4; PX4 POSCTL main mode 3 in byte 2
)
def test_heartbeat_identifies_autopilot_type_and_mode(
    personality: str, autopilot_id: int, custom_mode: int
) -> None:
    with autopilot(personality) as sim, companion(sim) as link:
        hb = receive_until(link, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1)
        assert (hb.autopilot, hb.type, hb.custom_mode) == (autopilot_id, 2, custom_mode)
        assert hb.base_mode & 128  # armed and hovering from the start
        assert sim.snapshot().height == pytest.approx(20.0)


@pytest.mark.slow
def test_ardupilot_is_silent_until_set_message_interval() -> None:
    with autopilot("ardupilot") as sim, companion(sim) as link:
        seen: set[str] = set()
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            msg = link.receive(0.1)
            if msg is not None:
                seen.add(msg.get_type())
        assert seen == {"HEARTBEAT"}
        ack = command(link, 511, 30, 50_000)  # ATTITUDE every 50 ms
        assert ack.result == 0
        count, deadline = 0, time.monotonic() + 1.0
        while time.monotonic() < deadline:
            msg = link.receive(0.1)
            count += msg is not None and msg.get_type() == "ATTITUDE"
        assert 10 <= count <= 30


def test_px4_streams_by_default() -> None:
    with autopilot("px4") as sim, companion(sim) as link:
        assert receive_until(link, lambda m: m.get_type() == "LOCAL_POSITION_NED", 2.0) is not None


def test_set_mode_is_acknowledged_and_arming_is_refused() -> None:
    with autopilot("ardupilot") as sim, gcs(sim) as ground:
        assert set_mode_from_gcs(ground, 17).result == 0 and sim.mode == "BRAKE"
        assert set_mode_from_gcs(ground, 99).result == 4  # no such mode: FAILED, as ArduCopter 4.7 answers
        ack = command(ground, 400, 1)  # MAV_CMD_COMPONENT_ARM_DISARM: the simulator never arms for anyone
        assert ack.result == 2


@pytest.mark.slow
def test_guided_flies_last_velocity_until_guid_timeout_then_brakes() -> None:
    with autopilot("ardupilot", guid_timeout_s=1.5) as sim, companion(sim) as link:
        velocity(link, 2.0)  # one setpoint, then silence
        sent = time.monotonic()
        time.sleep(1.2)
        assert sim.snapshot().vn == pytest.approx(2.0, abs=0.05)  # still flying the stale command
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.01, 3.0)
        braked_after = time.monotonic() - sent
        assert braked_after > 1.5
        assert sim.snapshot().north > 2.0 * 1.5 - 0.8  # it kept going for the whole GUID_TIMEOUT


def test_ardupilot_ignores_setpoints_outside_guided() -> None:
    with autopilot("ardupilot") as sim, companion(sim) as link:
        assert sim.set_mode("LOITER")
        for _ in range(10):
            velocity(link, 3.0)
            time.sleep(0.05)
        time.sleep(0.3)
        assert abs(sim.snapshot().vn) < 1e-6 and len(sim.setpoints) == 10


@pytest.mark.slow
def test_setpoint_frame_and_type_mask_are_honoured() -> None:
    with autopilot("ardupilot", start_yaw_deg=90.0) as sim, companion(sim) as link:
        velocity(link, 2.0, frame=BODY_OFFSET_NED)  # forward while facing east
        assert wait_for(lambda: sim.snapshot().ve > 1.9, 3.0)
        assert abs(sim.snapshot().vn) < 0.05
        velocity(link, 2.0, frame=LOCAL_NED)  # north in the local frame, whatever the heading
        assert wait_for(lambda: sim.snapshot().vn > 1.9 and abs(sim.snapshot().ve) < 0.05, 3.0)
        velocity(link, 0.0, 2.0, frame=LOCAL_NED, mask=VELOCITY_ONLY_MASK)  # both yaw fields ignored:
        assert wait_for(
            lambda: abs(sim.snapshot().yaw - math.radians(90)) < 0.05, 3.0
        )  # autopilot turns to travel
        velocity(link, 0.0, 0.0, yaw_rate=0.5, mask=VELOCITY_YAW_RATE_MASK | 0b111000)  # velocity ignored
        assert wait_for(lambda: sim.snapshot().yaw_rate > 0.45, 3.0)


def _px4_mode_outcome(link: MavlinkEndpoint, *params: float):  # type: ignore[no-untyped-def]
    """DO_SET_MODE on PX4 1.16 is answered twice (conformance suite): ACCEPTED at once, then the outcome."""
    first = command(link, 176, *params)
    assert first.result == 0
    return receive_until(link, lambda m: m.get_type() == "COMMAND_ACK" and m.command == 176, 3.0)


@pytest.mark.slow
def test_px4_offboard_needs_a_stream_and_falls_back_to_hold() -> None:
    with autopilot("px4", offboard_loss_s=0.5) as sim, companion(sim) as link:
        ack = _px4_mode_outcome(link, 1, 6, 0)  # OFFBOARD with no setpoints yet
        assert ack.result == 1 and sim.mode == "POSCTL"  # TEMPORARILY_REJECTED
        stop = threading.Event()

        def stream() -> None:
            while not stop.wait(0.05):
                velocity(link, 1.0, frame=BODY_NED)

        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()
        time.sleep(1.0)
        assert _px4_mode_outcome(link, 1, 6, 0).result == 0 and sim.mode == "OFFBOARD"
        assert wait_for(lambda: sim.snapshot().vn > 0.9, 3.0)
        stop.set()
        streamer.join()
        stopped = time.monotonic()
        assert wait_for(lambda: sim.mode == "HOLD", 3.0)
        assert time.monotonic() - stopped >= 0.4
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.01, 3.0)


@pytest.mark.slow
def test_routing_between_gcs_and_companion_links() -> None:
    with autopilot("ardupilot") as sim, companion(sim) as comp, gcs(sim) as ground:
        # addressed to the companion: routed to the companion link only
        ground.send(lambda m: m.command_long_send(1, 191, 31014, 0, 0, 0, 0, 0, 0, 0, 0))
        msg = receive_until(comp, lambda m: m.get_type() == "COMMAND_LONG", 3.0)
        assert msg is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == (255, 190)
        # the reply addressed to the GCS goes back to it; broadcasts reach it too
        comp.send(lambda m: m.command_ack_send(31014, 0, 0, 0, 255, 190))
        comp.send(lambda m: m.statustext_send(6, b"hello from the companion"))
        assert (
            receive_until(ground, lambda m: m.get_type() == "COMMAND_ACK" and m.command == 31014, 3.0)
            is not None
        )
        assert (
            receive_until(ground, lambda m: m.get_type() == "STATUSTEXT" and "companion" in m.text, 3.0)
            is not None
        )
        # a command for the autopilot itself is not forwarded to the companion
        set_mode_from_gcs(ground, 5)
        assert receive_until(comp, lambda m: m.get_type() == "COMMAND_LONG", 1.0) is None


@pytest.mark.slow
def test_rtl_flies_home_then_lands_and_disarms() -> None:
    with (
        autopilot("ardupilot", start_height_m=1.5, land_speed_m_s=1.5, rtl_speed_m_s=3.0) as sim,
        companion(sim) as link,
    ):
        velocity(link, 3.0)
        assert wait_for(lambda: sim.snapshot().north > 2.5, 3.0)
        assert command(link, 20).result == 0  # MAV_CMD_NAV_RETURN_TO_LAUNCH
        assert wait_for(lambda: sim.mode == "LAND", 6.0)
        assert math.hypot(sim.snapshot().north, sim.snapshot().east) < 1.0
        assert wait_for(lambda: not sim.armed, 4.0)
        assert sim.snapshot().height == 0.0 and "Landed: disarmed" in sim.statustexts
        hb = receive_until(link, lambda m: m.get_type() == "HEARTBEAT" and not m.base_mode & 128, 3.0)
        assert hb is not None and hb.custom_mode == 9  # disarmed in LAND


def test_autopilot_survives_garbage_on_its_links() -> None:
    import random
    import socket

    rng = random.Random(7)
    with autopilot("ardupilot") as sim, companion(sim) as link:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for i in range(500):
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300)))
            sock.sendto((b"\xfd" if i % 2 else b"") + junk, ("127.0.0.1", sim.link_port("companion")))
        sock.close()
        # Still answering on the same link. A command can be swallowed by a half-parsed garbage frame, so it
        # is retried as the MAVLink command protocol says a GCS should.
        acks = [set_mode_from_gcs(link, 5) for _ in range(3)]
        assert any(ack is not None and ack.result == 0 for ack in acks)
        assert sim.mode == "LOITER" and sim._links["companion"].bad_data > 0


def test_kinematics_limits_acceleration_yaw_and_ground() -> None:
    limits = VehicleLimits(max_accel=2.0, max_yaw_rate=1.0, max_yaw_accel=2.0)
    state = VehicleState()
    state = step(state, VelocityCommand(20.0, 0.0, 0.0, 5.0), 0.5, limits)
    assert state.vn == pytest.approx(1.0) and state.yaw_rate == pytest.approx(1.0)
    for _ in range(100):
        state = step(state, VelocityCommand(20.0, 0.0, 0.0, 5.0), 0.1, limits)
    assert state.vn == pytest.approx(limits.max_speed) and state.yaw_rate == pytest.approx(1.0)
    landed = step(VehicleState(down=-0.1, vd=2.0), VelocityCommand(0, 0, 2.0, 0), 1.0, limits)
    assert landed.down == 0.0 and landed.vd == 0.0
    drifted = step(VehicleState(), VelocityCommand(), 1.0, limits, Wind(east=5.0, rejection=0.8))
    assert drifted.east == pytest.approx(1.0)


def test_autopilot_subcommand_parses_and_runs(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="cloudtrack-sim")
    autopilot_command.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(
        [
            "autopilot",
            "--autopilot",
            "px4",
            "--gcs",
            "udpin:127.0.0.1:0",
            "--companion",
            "udpin:127.0.0.1:0",
            "--wind",
            "0",
            "3",
            "--duration",
            "0.3",
        ]
    )
    assert args.func(args) == 0
    assert "px4 autopilot simulator" in capsys.readouterr().out
    bad = parser.parse_args(["autopilot", "--gcs", "bogus:1"])
    assert bad.func(bad) == 2


def test_autopilot_help_docs_and_flight_agree_on_the_hover_height() -> None:
    """`cloudtrack-sim autopilot --help`, docs/sitl.md and the mock's own GLOBAL_POSITION_INT name one height."""
    parser = argparse.ArgumentParser(prog="cloudtrack-sim")
    autopilot_command.add_parser(parser.add_subparsers(dest="command"))
    help_text = " ".join(parser._subparsers._group_actions[0].choices["autopilot"].format_help().split())  # type: ignore[union-attr]
    (helped,) = {float(v) for v in re.findall(r"hovering at (\d+(?:\.\d+)?) m", help_text)}
    docs = (Path(__file__).resolve().parents[1] / "docs" / "sitl.md").read_text()
    (line,) = [ln for ln in docs.splitlines() if ln.startswith("cloudtrack-sim autopilot")]
    (documented,) = {float(v) for v in re.findall(r"hovering at (\d+(?:\.\d+)?) m", line)}
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    ground = MavlinkEndpoint.open(f"udpin:127.0.0.1:{port}", 255, 190)
    command = ["autopilot", "--gcs", f"udpout:127.0.0.1:{port}", "--companion", "udpin:127.0.0.1:0"]
    sim = subprocess.Popen([sys.executable, "-m", "sitl.cli", *command, "--duration", "5"])
    try:
        assert receive_until(ground, lambda m: m.get_type() == "HEARTBEAT", 20.0) is not None
        # Like ArduPilot, the mock sends position only when asked (SET_MESSAGE_INTERVAL, 5 Hz).
        ground.send(lambda m: m.command_long_send(1, 1, 511, 0, 33, 200_000, 0, 0, 0, 0, 0))
        position = receive_until(ground, lambda m: m.get_type() == "GLOBAL_POSITION_INT", 5.0)
    finally:
        sim.terminate()
        sim.wait(timeout=10)
        ground.close()
    assert position is not None
    assert helped == documented == pytest.approx(position.relative_alt / 1000.0, abs=0.5)
