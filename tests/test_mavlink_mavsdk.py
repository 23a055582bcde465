"""The MAVSDK offboard adapter (PX4) under the companion's watchdog: a stalled loop stops offboard."""

from __future__ import annotations

import socket
import time

import pytest

from behaviors.setpoint import Setpoint
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavsdk_offboard import mavsdk_address
from companion.safety_watchdog import LOOP_STALLED
from companion.vehicle_link import VehicleLink
from sitl.autopilot import AutopilotOptions, SimulatedAutopilot
from tests.mavlink_harness import MainLoop, wait_for


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_address_form() -> None:
    assert mavsdk_address("udp://:14541") == "udpin://0.0.0.0:14541"
    assert mavsdk_address("serial:///dev/ttyAMA0:921600") == "serial:///dev/ttyAMA0:921600"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # inside mavsdk's own server start-up
@pytest.mark.slow
def test_mavsdk_offboard_is_stopped_when_the_main_loop_stalls() -> None:
    port = _free_udp_port()
    sim = SimulatedAutopilot(
        AutopilotOptions(personality="px4"),
        {"companion": "udpin:127.0.0.1:0", "mavsdk": f"udpout:127.0.0.1:{port}"},
    )
    sim.start()
    config = MavlinkConfig(
        connection=f"udpout:127.0.0.1:{sim.link_port('companion')}",
        use_mavsdk=True,
        mavsdk_address=f"udpin://127.0.0.1:{port}",
    )
    link = VehicleLink(config, SafetyConfig(loop_stall_s=0.3))
    try:
        link.start()
        with MainLoop(link) as loop:
            assert wait_for(lambda: link.autopilot_kind is not None, 5.0)
            link.request_offboard()
            link.set_velocity(Setpoint(1.5, 0.0, 0.0, 0.0))
            assert wait_for(lambda: sim.mode == "OFFBOARD", 10.0)
            assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0)
            from_mavsdk = [s for s in sim.setpoints if s.link == "mavsdk"]
            assert from_mavsdk and from_mavsdk[-1].frame == 8 and from_mavsdk[-1].vx == 1.5
            loop.paused.set()  # hang: MAVSDK alone would keep re-sending 1.5 m/s at 20 Hz
            assert wait_for(lambda: sim.mode == "HOLD", 3.0)
            held_at = next(t for t, mode, _ in sim.mode_history if mode == "HOLD")
            assert any(e.reason == LOOP_STALLED for e in link.safety_events())
            time.sleep(1.0)
            assert [s for s in sim.setpoints if s.link == "mavsdk" and s.time > held_at + 0.3] == []
            assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)
    finally:
        link.close()
        sim.close()
