"""The MAVSDK offboard adapter (PX4) under the companion's watchdog, its MAVLink carried by the companion."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink

from behaviors.setpoint import Setpoint
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.vehicle_link import VehicleLink
from companion.safety_watchdog import LOOP_STALLED
from sitl.autopilot import AutopilotOptions, SimulatedAutopilot
from tests.mavlink_harness import MainLoop, wait_for


def _px4_with_mavsdk(use_mavsdk: bool = True) -> tuple[SimulatedAutopilot, VehicleLink]:
    sim = SimulatedAutopilot(AutopilotOptions(personality="px4"), {"companion": "udpin:127.0.0.1:0"})
    sim.start()
    config = MavlinkConfig(connection=f"udpout:127.0.0.1:{sim.link_port('companion')}", use_mavsdk=use_mavsdk)
    return sim, VehicleLink(config, SafetyConfig(loop_stall_s=0.3))


@pytest.mark.slow
def test_mavsdk_offboard_is_stopped_when_the_main_loop_stalls() -> None:
    sim, link = _px4_with_mavsdk()
    try:
        link.start()
        with MainLoop(link) as loop:
            assert wait_for(lambda: link.autopilot_kind is not None, 5.0)
            link.request_offboard()
            link.set_velocity(Setpoint(1.5, 0.0, 0.0, 0.0))
            assert wait_for(lambda: sim.mode == "OFFBOARD", 10.0)
            assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0)
            assert sim.setpoints[-1].frame == 8 and sim.setpoints[-1].vx == 1.5
            # MAVSDK is the vehicle's onboard component and its own HEARTBEATs never reach the autopilot;
            # only the companion's own identities do
            assert {c for s, c in sim._links["companion"].seen if s == 1} <= {191, 100}
            assert (
                link._relay is not None and link._relay.heartbeats_dropped > 0 and link._relay.forwarded > 0
            )
            loop.paused.set()  # hang: MAVSDK alone would keep re-sending 1.5 m/s at 20 Hz
            assert wait_for(lambda: sim.mode == "HOLD", 3.0)
            held_at = next(t for t, mode, _ in sim.mode_history if mode == "HOLD")
            assert any(e.reason == LOOP_STALLED for e in link.safety_events())
            time.sleep(1.0)
            assert [s for s in sim.setpoints if s.time > held_at + 0.3] == []
            assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)
    finally:
        link.close()
        sim.close()


def test_mavsdk_stop_reaches_hold_when_the_pilot_selected_offboard() -> None:
    sim, link = _px4_with_mavsdk()
    try:
        link.start()
        with MainLoop(link) as loop:
            assert wait_for(lambda: link.autopilot_kind is not None, 5.0)
            link.enable_offboard()  # no engage permission: MAVSDK streams, the pilot selects OFFBOARD
            link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
            assert wait_for(lambda: sim.set_mode("OFFBOARD", "pilot"), 5.0)
            # 10 s: under `make check`'s parallel load the first second of MAVSDK's stream can be slow to come
            # (seen once at 5 s); the modes it went through say why if it never flies.
            assert wait_for(lambda: sim.snapshot().vn > 0.7, 10.0), (sim.mode, sim.mode_history[-5:])
            loop.paused.set()
            assert wait_for(lambda: sim.mode == "HOLD", 3.0), f"left in {sim.mode} with MAVSDK re-sending"
    finally:
        link.close()
        sim.close()


def _tcp_listeners() -> set[str]:
    """Inodes of TCP sockets in LISTEN state (on any address), machine-wide."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A":  # TCP_LISTEN
                inodes.add(fields[9])
    return inodes


def _own_sockets() -> set[str]:
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def _children() -> set[str]:
    pids: set[str] = set()
    for task in os.listdir("/proc/self/task"):
        pids |= set(Path(f"/proc/self/task/{task}/children").read_text().split())
    return pids


def test_mavsdk_listens_on_nothing_and_is_the_vehicles_onboard_component() -> None:
    """The issue asked for mavsdk_server's gRPC API on loopback only; MAVSDK 4 in-process has no server at all."""
    sim, link = _px4_with_mavsdk()
    plain_sim, plain_link = _px4_with_mavsdk(use_mavsdk=False)
    heartbeats: list[Any] = []
    try:
        before = _own_sockets()
        plain_link.start()
        opened_without_mavsdk = len(_own_sockets() - before)
        before = _own_sockets()
        children_before = _children()
        link.start()  # returns once MAVSDK has found the autopilot through the companion's link
        assert link._mavsdk is not None and link._relay is not None
        opened_with_mavsdk = _own_sockets() - before
        assert len(opened_with_mavsdk) == opened_without_mavsdk  # the companion's link socket, nothing more
        assert not opened_with_mavsdk & _tcp_listeners()
        assert _children() == children_before  # no mavsdk_server process

        parser = mavlink.MAVLink(None)
        link._mavsdk._mavsdk.subscribe_raw_bytes_to_be_sent(
            lambda data: heartbeats.extend(
                m for m in parser.parse_buffer(data) or [] if m.get_type() == "HEARTBEAT"
            )
        )
        assert wait_for(lambda: len(heartbeats) >= 1 and link._relay.heartbeats_dropped >= 1, 3.0)
        own = heartbeats[0]
        assert (own.get_srcSystem(), own.get_srcComponent()) == (1, 191)
        assert own.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER != mavlink.MAV_TYPE_GCS
        # and the autopilot never hears it: the only heartbeats from system 1 are the companion's
        assert {c for s, c in sim._links["companion"].seen if s == 1} <= {191, 100}
    finally:
        for closing in (link, sim, plain_link, plain_sim):
            closing.close()


def test_relay_holds_mavsdks_setpoints_after_a_takeover() -> None:
    """MAVSDK re-sends its last setpoint until PX4's 1 Hz HEARTBEAT tells it OFFBOARD ended; the companion
    learns it within 100 ms and closes the relay to MAVSDK's setpoints (and only those)."""
    from pymavlink.dialects.v20 import ardupilotmega

    from companion.mavlink.mavsdk_relay import MavsdkRelay

    sent: list[Any] = []

    class Endpoint:
        def send(self, build: Any, component: int | None = None) -> bool:
            build(Recorder())
            return True

    class Recorder:
        def send(self, msg: Any) -> None:
            sent.append(msg.get_type())

    mav = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=191)
    setpoint = mav.set_position_target_local_ned_encode(
        0, 1, 1, 8, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0
    ).pack(mav)
    status = mav.statustext_encode(6, b"hello").pack(mav)
    zero = mav.set_position_target_local_ned_encode(0, 1, 1, 8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav)
    relay = MavsdkRelay(Endpoint())  # type: ignore[arg-type]
    relay.note_setpoint((1.0, 0.0, 0.0, 0.0))
    relay.from_mavsdk(setpoint)
    relay.setpoints_allowed = False  # VehicleLink: the pilot took over
    relay.from_mavsdk(setpoint)
    relay.from_mavsdk(status)
    relay.setpoints_allowed = True  # a mission enabled offboard again
    relay.from_mavsdk(setpoint)
    assert sent == ["SET_POSITION_TARGET_LOCAL_NED", "STATUSTEXT", "SET_POSITION_TARGET_LOCAL_NED"]
    assert relay.setpoints_dropped == 1

    # After a freeze MAVSDK's timer re-sends the pre-freeze setpoint first: older than the bound, dropped; and
    # still dropped once the watchdog's zero has been handed to MAVSDK but not yet taken in (11 ms on PX4).
    now = [100.0]
    sent.clear()
    fresh = MavsdkRelay(Endpoint(), max_setpoint_age_s=0.5, clock=lambda: now[0])  # type: ignore[arg-type]
    fresh.from_mavsdk(setpoint)  # nothing handed yet
    fresh.note_setpoint((1.0, 0.0, 0.0, 0.0))
    now[0] = 100.4
    fresh.from_mavsdk(setpoint)
    now[0] = 103.4  # three seconds frozen
    fresh.from_mavsdk(setpoint)
    fresh.note_setpoint((0.0, 0.0, 0.0, 0.0))  # the watchdog's zero
    fresh.from_mavsdk(setpoint)  # MAVSDK's re-send of the pre-freeze command
    fresh.from_mavsdk(zero)
    assert sent == ["SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_LOCAL_NED"]
    assert fresh.setpoints_dropped == 3
