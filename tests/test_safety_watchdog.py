"""Watchdogs: each stale input ends motion with an explicit stop then the hold, within a bounded time."""

from __future__ import annotations

import time

import pytest

from behaviors.setpoint import Setpoint
from companion.config import SafetyConfig
from companion.safety_watchdog import (
    BACKEND_UNREACHABLE,
    HEARTBEAT_LOST,
    LOOP_STALLED,
    STALE_FRAMES,
    TARGET_LOST,
    SafetyWatchdog,
    stale_conditions,
    thresholds,
)
from tests.mavlink_harness import MainLoop, autopilot, gcs, vehicle_link, wait_for


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_stale_conditions_only_for_armed_inputs_past_their_limit() -> None:
    limits = thresholds(SafetyConfig(frame_stale_s=0.5, heartbeat_timeout_s=2.0))
    seen = {STALE_FRAMES: 10.0, HEARTBEAT_LOST: 9.0}
    assert stale_conditions(seen, limits, 10.4) == set()
    assert stale_conditions(seen, limits, 10.6) == {STALE_FRAMES}
    assert stale_conditions(seen, limits, 11.1) == {STALE_FRAMES, HEARTBEAT_LOST}
    assert BACKEND_UNREACHABLE not in stale_conditions(seen, limits, 1e6)  # never reported: not armed


def test_watchdog_trips_once_clears_once_and_disarms() -> None:
    clock = FakeClock()
    trips: list[str] = []
    clears: list[str] = []
    dog = SafetyWatchdog(
        SafetyConfig(target_lost_s=1.0), lambda r, t: trips.append(r), lambda r, t: clears.append(r), clock
    )
    dog.seen(TARGET_LOST)
    clock.now += 0.9
    dog.check()
    assert trips == []
    clock.now += 0.2
    dog.check()
    dog.check()
    assert trips == [TARGET_LOST] and dog.active() == {TARGET_LOST}
    dog.seen(TARGET_LOST)
    dog.check()
    assert clears == [TARGET_LOST] and dog.active() == set()
    dog.disarm(TARGET_LOST)
    clock.now += 100
    dog.check()
    assert trips == [TARGET_LOST]


def test_watchdog_survives_a_failing_callback() -> None:
    def boom(reason: str, when: float) -> None:
        raise RuntimeError("bug in a callback")

    dog = SafetyWatchdog(SafetyConfig(loop_stall_s=0.05), boom, boom, check_period_s=0.01)
    dog.seen(LOOP_STALLED)
    dog.start()
    try:
        time.sleep(0.3)
        assert dog._thread is not None and dog._thread.is_alive()
    finally:
        dog.close()


def _flying(sim, link, speed: float = 2.0) -> None:  # type: ignore[no-untyped-def]
    link.request_offboard()
    link.set_velocity(Setpoint(speed, 0.0, 0.0, 0.0))
    assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0), "the vehicle never flew the setpoint"


def _reason_at(link, reason: str, timeout: float):  # type: ignore[no-untyped-def]
    events: list = []

    def seen() -> object:
        events.extend(link.safety_events())
        return next((e for e in events if e.reason == reason and e.action == "stop"), None)

    return wait_for(seen, timeout)


def _companion_heartbeats(ground, seconds: float) -> int:  # type: ignore[no-untyped-def]
    count, deadline = 0, time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = ground.receive(timeout=0.1)
        if msg is not None and msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 191:
            assert msg.type == 18  # MAV_TYPE_ONBOARD_CONTROLLER
            count += 1
    return count


@pytest.mark.slow
def test_stalled_main_loop_stops_the_vehicle_and_its_heartbeat() -> None:
    safety = {"loop_stall_s": 0.3}
    with (
        autopilot("ardupilot") as sim,
        vehicle_link(sim, safety=safety) as link,
        MainLoop(link) as loop,
        gcs(sim) as ground,
    ):
        _flying(sim, link)
        assert _companion_heartbeats(ground, 2.2) >= 1  # 1 Hz while the loop is healthy, routed to the GCS
        loop.paused.set()  # the main loop hangs; the setpoint it left behind is 2 m/s forward
        stalled_at = time.monotonic()
        event = _reason_at(link, LOOP_STALLED, 3.0)
        assert event is not None
        assert event.time_s - stalled_at < 0.3 + 0.5
        # explicit stop: zero-velocity setpoints reach the autopilot, not silence
        assert wait_for(lambda: sim.setpoints[-1].vx == 0.0 and sim.setpoints[-1].time > event.time_s, 2.0)
        zero_at = next(s.time for s in sim.setpoints if s.time >= event.time_s and s.vx == 0.0)
        print(
            f"\nstalled loop (limit 0.3 s): tripped {event.time_s - stalled_at:.3f} s after the loop stopped, "
            f"zero setpoint at the autopilot {zero_at - stalled_at:.3f} s"
        )
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)
        assert _companion_heartbeats(ground, 2.0) == 0  # the HEARTBEAT stops with the loop
        loop.paused.clear()
        assert wait_for(
            lambda: any(e.reason == LOOP_STALLED and e.action == "cleared" for e in link.safety_events()), 3.0
        )


@pytest.mark.slow
def test_stalled_main_loop_on_px4_switches_to_hold() -> None:
    with (
        autopilot("px4") as sim,
        vehicle_link(sim, safety={"loop_stall_s": 0.3}) as link,
        MainLoop(link) as loop,
    ):
        _flying(sim, link)
        loop.paused.set()
        assert wait_for(lambda: sim.mode == "HOLD", 3.0)
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)


@pytest.mark.slow
def test_autopilot_heartbeat_loss_leads_to_hold() -> None:
    safety = {"heartbeat_timeout_s": 0.5}
    with autopilot("px4") as sim, vehicle_link(sim, safety=safety) as link, MainLoop(link):
        _flying(sim, link)
        sim.set_link_down("companion", True, inbound_too=False)  # autopilot silent, still listening
        lost_at = time.monotonic()
        event = _reason_at(link, HEARTBEAT_LOST, 3.0)
        assert event is not None and event.time_s - lost_at < 0.5 + 0.5
        assert wait_for(lambda: sim.mode == "HOLD", 2.0)  # the explicit stop and hold got through
        assert any(s.vx == 0.0 and s.time >= event.time_s for s in sim.setpoints)
        sim.set_link_down("companion", False)
        assert wait_for(
            lambda: any(e.reason == HEARTBEAT_LOST and e.action == "cleared" for e in link.safety_events()),
            3.0,
        )


@pytest.mark.slow
def test_stale_frames_stop_motion_and_recover_when_frames_return() -> None:
    with (
        autopilot("ardupilot") as sim,
        vehicle_link(sim, safety={"frame_stale_s": 0.3}) as link,
        MainLoop(link, frames=True) as loop,
    ):
        _flying(sim, link)
        loop.frames = False  # camera stalls, the loop itself keeps running
        assert _reason_at(link, STALE_FRAMES, 3.0) is not None
        assert wait_for(lambda: sim.setpoints[-1].vx == 0.0, 2.0)
        assert sim.mode == "GUIDED"  # default ArduPilot hold: zero velocity in GUIDED
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)
        loop.frames = True
        assert wait_for(lambda: sim.setpoints[-1].vx == 2.0, 3.0)  # recovery: the main loop's setpoint again


def test_lost_target_and_unreachable_backend_each_stop_and_report() -> None:
    safety = {"target_lost_s": 0.3, "backend_lost_s": 0.6}
    with autopilot("ardupilot") as sim, vehicle_link(sim, safety=safety) as link, MainLoop(link):
        _flying(sim, link)
        link.report_target()
        assert _reason_at(link, TARGET_LOST, 3.0) is not None
        assert wait_for(lambda: sim.setpoints[-1].vx == 0.0, 2.0)
        link.clear_target()
        link.report_backend_ok()
        assert _reason_at(link, BACKEND_UNREACHABLE, 3.0) is not None
        # The trip is recorded before its zero is sent: wait for the zero to cross the socket, as above.
        assert wait_for(lambda: sim.setpoints[-1].vx == 0.0, 2.0)
        time.sleep(0.3)
        assert sim.setpoints[-1].vx == 0.0  # and it stays stopped
