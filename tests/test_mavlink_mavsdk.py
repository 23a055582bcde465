"""The MAVSDK offboard adapter (PX4) under the companion's watchdog, its MAVLink carried by the companion."""

from __future__ import annotations

import time

import pytest

from behaviors.setpoint import Setpoint
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.vehicle_link import VehicleLink
from companion.safety_watchdog import LOOP_STALLED
from sitl.autopilot import AutopilotOptions, SimulatedAutopilot
from tests.mavlink_harness import MainLoop, wait_for


def _px4_with_mavsdk() -> tuple[SimulatedAutopilot, VehicleLink]:
    sim = SimulatedAutopilot(AutopilotOptions(personality="px4"), {"companion": "udpin:127.0.0.1:0"})
    sim.start()
    config = MavlinkConfig(connection=f"udpout:127.0.0.1:{sim.link_port('companion')}", use_mavsdk=True)
    return sim, VehicleLink(config, SafetyConfig(loop_stall_s=0.3))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # inside mavsdk's own server start-up
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
            # mavsdk_server is the vehicle's onboard component: its ground-station HEARTBEAT (component 190)
            # never reaches the autopilot; only the companion's own identities do
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


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_mavsdk_stop_reaches_hold_when_the_pilot_selected_offboard() -> None:
    sim, link = _px4_with_mavsdk()
    try:
        link.start()
        with MainLoop(link) as loop:
            assert wait_for(lambda: link.autopilot_kind is not None, 5.0)
            link.enable_offboard()  # no engage permission: MAVSDK streams, the pilot selects OFFBOARD
            link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
            assert wait_for(lambda: sim.set_mode("OFFBOARD", "pilot"), 5.0)
            assert wait_for(lambda: sim.snapshot().vn > 0.7, 5.0)
            loop.paused.set()
            assert wait_for(lambda: sim.mode == "HOLD", 3.0), f"left in {sim.mode} with MAVSDK re-sending"
    finally:
        link.close()
        sim.close()
