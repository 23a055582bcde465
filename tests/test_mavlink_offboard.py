"""Offboard velocity streaming against the SITL autopilot over loopback UDP: fields, rate, mode policy."""

from __future__ import annotations

import time
from typing import Any

import pytest

from behaviors.events import AutopilotLinkLost, CompanionHold, PilotTakeover
from behaviors.setpoint import Setpoint
from cloudtrack.vehicle_config import SafetyConfig
from companion.config import MavlinkConfig
from companion.mavlink.offboard import (
    MAV_FRAME_BODY_NED,
    MAV_FRAME_BODY_OFFSET_NED,
    TYPE_MASK_VELOCITY_YAW_RATE,
)
from companion.mavlink.telemetry_decoder import AutopilotHeartbeat, AutopilotKind
from companion.mavlink.vehicle_link import VehicleLink
from companion.mission_runner import behavior_event
from companion.safety_watchdog import HEARTBEAT_LOST, LOOP_STALLED, STALE_FRAMES, SafetyEvent
from tests.mavlink_harness import (
    MainLoop,
    autopilot,
    gcs,
    receive_until,
    set_mode_from_gcs,
    vehicle_link,
    wait_for,
)

YAW_RATE_IGNORE = 2048


def test_ardupilot_setpoint_fields_are_body_offset_velocity_with_yaw_rate() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(1.5, -0.5, 0.0, 0.0))
        assert wait_for(lambda: len(sim.setpoints) >= 5)
        sp = sim.setpoints[-1]
        assert (sp.src_system, sp.src_component) == (1, 191)
        assert sp.frame == MAV_FRAME_BODY_OFFSET_NED == 9
        assert sp.type_mask == TYPE_MASK_VELOCITY_YAW_RATE == 0b0000_0101_1100_0111
        assert not sp.type_mask & YAW_RATE_IGNORE  # yaw_rate is always used, 0 when not turning
        assert (sp.vx, sp.vy, sp.vz, sp.yaw_rate) == (1.5, -0.5, 0.0, 0.0)
        assert sp.mode == "GUIDED"
        # and the vehicle flies it: forward at the start heading (north)
        assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0)


@pytest.mark.slow
def test_setpoint_rate_within_20_percent_of_configured() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim, setpoint_rate_hz=15.0) as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.1))
        assert wait_for(lambda: len(sim.setpoints) >= 3)
        start = time.monotonic()
        time.sleep(3.0)
        end = time.monotonic()
        received = [s for s in sim.setpoints if start <= s.time < end]
        rate = len(received) / (end - start)
        gaps = sorted(b.time - a.time for a, b in zip(received, received[1:], strict=False))
        print(
            f"\nsetpoint rate {rate:.2f} Hz (configured 15), gap median {gaps[len(gaps) // 2] * 1000:.1f} ms, max {gaps[-1] * 1000:.1f} ms"
        )
        assert 12.0 <= rate <= 18.0, f"setpoint rate {rate:.1f} Hz, configured 15 Hz"
        assert all(abs(s.yaw_rate - 0.1) < 1e-6 for s in received)


def test_limits_are_applied_before_sending() -> None:
    with (
        autopilot("ardupilot") as sim,
        vehicle_link(sim, safety={"max_speed_m_s": 2.0}) as link,
        MainLoop(link),
    ):
        link.request_offboard()
        link.set_velocity(Setpoint(6.0, 8.0, 2.0, 3.0))  # 10 m/s, descending, spinning fast
        assert wait_for(lambda: len(sim.setpoints) >= 3)
        sp = sim.setpoints[-1]
        assert abs((sp.vx**2 + sp.vy**2) ** 0.5 - 2.0) < 1e-4 and abs(sp.vx / sp.vy - 0.75) < 1e-4
        assert sp.vz == 0.0  # no descent towards an unconfirmed target
        assert sp.yaw_rate <= 0.786


@pytest.mark.parametrize(
    ("personality", "ours", "theirs", "mode_numbers", "back"),
    [("ardupilot", "GUIDED", "LOITER", (5, 0), (4, 0)), ("px4", "OFFBOARD", "POSCTL", (3, 0), (6, 0))],
)
@pytest.mark.slow
def test_mode_change_by_gcs_stops_setpoints_within_200_ms(
    personality: str, ours: str, theirs: str, mode_numbers: tuple[int, int], back: tuple[int, int]
) -> None:
    with autopilot(personality) as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.mode == ours and len(sim.setpoints) >= 10, 5.0)
        time.sleep(0.3)
        ack = set_mode_from_gcs(ground, *mode_numbers)  # chosen by someone else
        assert ack is not None and ack.result == 0
        # PX4 answers ACCEPTED before it changes mode (then the outcome): wait for the change itself.
        assert wait_for(lambda: any(mode == theirs for _, mode, _ in sim.mode_history), 2.0)
        changed_at = next(t for t, mode, _ in sim.mode_history if mode == theirs)
        time.sleep(1.0)
        late = [s for s in sim.setpoints if s.time > changed_at + 0.2]
        assert late == [], f"{len(late)} setpoints more than 200 ms after the mode change"
        last = max((s.time for s in sim.setpoints if s.time > changed_at), default=changed_at)
        print(
            f"\n{personality}: last setpoint {(last - changed_at) * 1000:.0f} ms after the mode change to {theirs}"
        )
        events = link.safety_events()
        assert any(e.reason == "mode_change" and f"{ours} -> {theirs}" in e.detail for e in events), events
        # a takeover is a flag, not a wording: the main loop turns exactly that into PilotTakeover(theirs)
        takeovers = [e for e in events if e.by_other_party]
        assert [e.mode for e in takeovers] == [theirs]
        assert [behavior_event(e) for e in takeovers] == [PilotTakeover(takeovers[0].time_s, theirs)]
        # the GCS is told why, in words
        text = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and "OFFBOARD ENDED" in m.text, 3.0
        )
        assert text is not None
        # and the companion does not take the vehicle back on its own
        set_mode_from_gcs(ground, *back)
        time.sleep(0.5)
        assert [s for s in sim.setpoints if s.time > changed_at + 0.2] == []


def test_companion_waits_for_the_pilot_when_engagement_not_allowed() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link):
        assert sim.set_mode("LOITER")
        assert wait_for(lambda: link.telemetry() is not None and link.telemetry().mode == "LOITER")
        link.enable_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        time.sleep(1.0)
        assert (
            sim.mode == "LOITER" and sim.setpoints == []
        )  # never selects GUIDED itself, never streams outside it
        assert sim.set_mode("GUIDED", "pilot")
        assert wait_for(lambda: len(sim.setpoints) >= 3, 3.0)
        assert all(s.mode == "GUIDED" for s in sim.setpoints)


def test_px4_streams_a_second_before_requesting_offboard() -> None:
    with autopilot("px4") as sim, vehicle_link(sim) as link, MainLoop(link):
        assert link.telemetry().mode == "POSCTL"
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.5, 0.0, -0.2))
        assert wait_for(lambda: sim.mode == "OFFBOARD", 5.0)
        entered = next(t for t, mode, _ in sim.mode_history if mode == "OFFBOARD")
        first = sim.setpoints[0].time
        assert entered - first >= 0.95, f"OFFBOARD after only {entered - first:.2f} s of setpoints"
        sp = sim.setpoints[-1]
        assert sp.frame == MAV_FRAME_BODY_NED == 8 and sp.type_mask == TYPE_MASK_VELOCITY_YAW_RATE
        assert (sp.vx, sp.vy) == (1.0, 0.5) and abs(sp.yaw_rate + 0.2) < 1e-6  # float32 on the wire


@pytest.mark.slow
def test_hold_sends_explicit_zero_then_configured_brake() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim, ardupilot_hold="brake") as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(2.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0)
        link.hold("supervisor review")
        assert wait_for(lambda: sim.mode == "BRAKE", 3.0)
        stop_time = next(t for t, mode, _ in sim.mode_history if mode == "BRAKE")
        zero = [s for s in sim.setpoints if s.vx == 0.0 and s.vy == 0.0 and s.time <= stop_time + 0.05]
        assert zero, "no explicit zero-velocity setpoint before the hold"
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)
        events = link.safety_events()
        assert any(
            e.reason == "mode_change" and "(requested)" in e.detail for e in events
        )  # ours, not a takeover
        assert not any(e.by_other_party for e in events)
        # resuming: the main loop commands again and, engagement allowed, GUIDED is requested again
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.mode == "GUIDED", 3.0)


@pytest.mark.slow
def test_lost_action_mode_is_requested_and_streaming_ends() -> None:
    with autopilot("px4") as sim, vehicle_link(sim) as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.mode == "OFFBOARD" and sim.snapshot().north > 3.0, 8.0)
        link.request_mode("rtl")
        assert wait_for(lambda: sim.mode == "RTL", 3.0)
        changed_at = next(t for t, mode, _ in sim.mode_history if mode == "RTL")
        time.sleep(0.5)
        assert [s for s in sim.setpoints if s.time > changed_at + 0.2] == []
        events = link.safety_events()
        assert any("OFFBOARD -> RTL (requested)" in e.detail for e in events)  # ours, not a takeover
        assert not any(e.by_other_party for e in events)
        assert not any(isinstance(behavior_event(e), PilotTakeover) for e in events)


def test_release_stops_streaming_after_an_explicit_zero() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link):
        link.request_offboard()
        link.set_velocity(Setpoint(2.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.snapshot().vn > 1.5, 5.0)
        before = time.monotonic()
        link.release_offboard("mission aborted")
        released = time.monotonic()
        time.sleep(0.5)
        after = [s for s in sim.setpoints if s.time >= before]
        assert after and after[-1].vx == 0.0  # the explicit stop is the last thing the autopilot heard
        assert not [s for s in sim.setpoints if s.time > released + 0.2]
        assert wait_for(lambda: abs(sim.snapshot().vn) < 0.05, 3.0)  # stopped now, not after GUID_TIMEOUT
        assert (
            sim.mode == "LOITER"
        )  # let go: the hold mode (LOITER for ardupilot_hold = guided_zero), then silence


@pytest.mark.parametrize(
    ("event", "expected"),
    [
        (SafetyEvent(1.0, STALE_FRAMES, "stop"), CompanionHold(1.0, STALE_FRAMES)),
        (SafetyEvent(1.0, LOOP_STALLED, "stop"), CompanionHold(1.0, LOOP_STALLED)),
        (SafetyEvent(1.0, STALE_FRAMES, "cleared"), None),
        (SafetyEvent(1.0, HEARTBEAT_LOST, "stop"), AutopilotLinkLost(1.0)),
        (SafetyEvent(1.0, "mode_change", "offboard_ended", "OFFBOARD -> HOLD (requested)"), None),
        (
            SafetyEvent(1.0, "mode_change", "offboard_ended", "x", by_other_party=True, mode="POSCTL"),
            PilotTakeover(1.0, "POSCTL"),
        ),
    ],
)
def test_the_behaviour_hears_a_watchdogs_own_hold_apart_from_a_takeover(event: Any, expected: Any) -> None:
    assert behavior_event(event) == expected


@pytest.mark.parametrize(
    ("shown", "failsafe", "ours"), [("HOLD", False, True), ("POSCTL", False, False), ("HOLD", True, False)]
)
def test_a_hold_we_asked_for_stays_ours_after_we_asked_for_offboard_again(
    shown: str, failsafe: bool, ours: bool
) -> None:
    """PX4 on a loaded machine: a watchdog's stop asks for HOLD, frames come back and OFFBOARD is asked for
    again, and only then does PX4's HOLD show: it is ours. A mode we never asked for is someone else's, and
    so is PX4's failsafe HOLD (offboard lost while the companion was frozen), though we asked for HOLD too."""
    link = VehicleLink(MavlinkConfig(connection="udpin:127.0.0.1:0"), SafetyConfig())
    try:
        now = time.monotonic()
        link._streams_requested_at = now  # nobody to ask for streams here
        with link._lock:
            link._enabled = True
            assert (
                link._on_heartbeat(AutopilotHeartbeat(AutopilotKind.PX4, "OFFBOARD", True, now), now) is None
            )
            link._note_mode_request("HOLD")
            link._note_mode_request("OFFBOARD")
            event = link._on_heartbeat(
                AutopilotHeartbeat(AutopilotKind.PX4, shown, True, now, failsafe=failsafe), now + 0.3
            )
        assert event is not None and event.by_other_party is not ours, event
    finally:
        link.close()
