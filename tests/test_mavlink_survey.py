"""The companion's link along the autopilot's own mission, against the mock's mission flight over real UDP:
MISSION_CURRENT in telemetry, taking the vehicle from AUTO/Mission for a candidate and handing it back at
the item it broke off at (no takeover: it asked), a pilot's switch to AUTO while the companion flies it (a
takeover), the mission downloaded over the companion's own link for the search area, and coverage.

The same hand-back against the real ArduCopter is flown in tests/test_arducopter_scenarios.py (search).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from behaviors.camera_model import CameraModel
from behaviors.geolocation import offset_to_latlon
from behaviors.mission_items import MissionItem
from behaviors.setpoint import Setpoint
from cloudtrack.mission_protocol import MissionClient, MissionTimeouts
from companion.mavlink.vehicle_link import VehicleLink
from companion.search_coverage import SearchCoverage
from sitl.autopilot import SimulatedAutopilot
from sitl.autopilot_mission import MissionOptions
from tests.mavlink_harness import MainLoop, autopilot, gcs, vehicle_link, wait_for

HOME = (47.397742, 8.545594)
MISSION_MODE = {"ardupilot": "AUTO", "px4": "MISSION"}
OFFBOARD = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}


def waypoint(north: float, east: float) -> MissionItem:
    return MissionItem.waypoint(*offset_to_latlon(*HOME, north, east), 10.0)


# A small lawnmower: 20 m lanes 10 m apart.
LANES = [
    waypoint(0, 0),
    waypoint(20, 0),
    waypoint(20, 10),
    waypoint(0, 10),
    waypoint(0, 20),
    waypoint(20, 20),
]


@contextmanager
def surveying(personality: str) -> Iterator[tuple[SimulatedAutopilot, VehicleLink, int]]:
    """The mock flying LANES in its mission mode at 10 m/s, the companion's link on it; the first item's seq."""
    with (
        autopilot(personality, start_height_m=10.0, mission=MissionOptions(speed_m_s=10.0)) as sim,
        gcs(sim) as ground,
    ):
        client = MissionClient(ground, personality, source=(255, 190), timeouts=MissionTimeouts(0.3, 3))
        client.upload(LANES)
        with vehicle_link(sim) as link:
            assert sim.set_mode(MISSION_MODE[personality], source="pilot")
            yield sim, link, client.first_seq


def flying_item(link: VehicleLink) -> int | None:
    t = link.telemetry()
    return t.mission_item if t is not None and t.mission_active else None


@pytest.mark.parametrize("personality", ["ardupilot", pytest.param("px4", marks=pytest.mark.slow)])
def test_taken_for_a_candidate_and_handed_back_where_it_broke_off(personality: str) -> None:
    with surveying(personality) as (sim, link, first), MainLoop(link):
        # MISSION_CURRENT reaches the companion's telemetry; the first lane's end is flown to.
        assert wait_for(lambda: flying_item(link) == first + 1, 20.0), link.telemetry()
        t = link.telemetry()
        assert t is not None and t.mission_items == len(LANES) and t.mode == MISSION_MODE[personality]
        # The candidate: the behaviour takes the vehicle (GUIDED / OFFBOARD after PX4's pre-stream).
        link.request_offboard()
        link.set_velocity(Setpoint.zero())
        assert wait_for(lambda: sim.mode == OFFBOARD[personality], 5.0), sim.mode
        broke_off = first + 1
        time.sleep(1.0)
        t = link.telemetry()
        assert t is not None and t.offboard_active and not t.mission_active and t.mission_item == broke_off
        before = len(sim.setpoints)
        # The candidate was rejected: back to the mission at the item it broke off at.
        link.resume_mission(broke_off, "rejected")
        assert wait_for(lambda: sim.mode == MISSION_MODE[personality], 5.0), sim.mode
        assert wait_for(lambda: flying_item(link) == broke_off, 5.0)
        # Our own request: no takeover reported; silence after the hand-back.
        events = link.safety_events()
        assert not any(e.by_other_party for e in events), events
        assert any("(requested)" in e.detail for e in events), events
        resumed = time.monotonic()
        time.sleep(0.5)
        late = [s for s in sim.setpoints[before:] if s.link == "companion" and s.time > resumed]
        assert late == []
        # It flies on along the survey: the item after the break-off is reached in time.
        assert wait_for(lambda: flying_item(link) == broke_off + 1, 20.0)


def test_the_item_is_set_back_when_the_autopilot_moved_on() -> None:
    with surveying("ardupilot") as (sim, link, first), MainLoop(link), gcs(sim) as ground:
        assert wait_for(lambda: flying_item(link) == first + 1, 20.0)
        link.request_offboard()
        link.set_velocity(Setpoint.zero())
        assert wait_for(lambda: sim.mode == "GUIDED", 5.0)
        # Someone (a GCS) moved the mission on meanwhile: the hand-back puts it back at the break-off item.
        client = MissionClient(ground, "ardupilot", source=(255, 190), timeouts=MissionTimeouts(0.3, 3))
        assert client.set_current(first + 3).seq == first + 3
        assert wait_for(
            lambda: (link.telemetry() or None) and link.telemetry().mission_item == first + 3, 5.0
        )
        link.resume_mission(first + 1, "rejected")
        assert wait_for(lambda: sim.mode == "AUTO", 5.0)
        assert wait_for(lambda: flying_item(link) == first + 1, 5.0), link.telemetry()


def test_a_pilot_switch_to_auto_while_the_companion_flies_is_a_takeover() -> None:
    with surveying("ardupilot") as (sim, link, first), MainLoop(link):
        assert wait_for(lambda: flying_item(link) == first + 1, 20.0)
        link.request_offboard()
        link.set_velocity(Setpoint(1.0, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.mode == "GUIDED", 5.0)
        link.safety_events()
        assert sim.set_mode("AUTO", source="pilot")
        switched = time.monotonic()
        assert wait_for(lambda: any(e.by_other_party for e in link.safety_events()), 2.0)
        time.sleep(0.5)
        late = [s for s in sim.setpoints if s.link == "companion" and s.time > switched + 0.2]
        assert late == []


def test_the_search_area_comes_from_the_autopilots_mission_and_only_analysed_keyframes_count() -> None:
    camera = CameraModel.from_hfov(640, 480, 70.0, -40.0, stabilised=True)
    with surveying("ardupilot") as (_, link, first), MainLoop(link):
        kind = link.autopilot_kind
        assert kind is not None
        coverage = SearchCoverage(camera, 15.0, link.mission_link, lambda: kind.value, (1, 191))
        coverage.start("person")
        assert wait_for(lambda: coverage.report() is not None, 10.0), coverage.error
        report = coverage.report()
        assert report is not None
        # The lanes' hull (20 x 20 m) widened across the lanes by half their spacing (5 m): 20 x 30 m.
        area = report["area"]
        norths = [offset(lat, lon)[0] for lat, lon in area]
        easts = [offset(lat, lon)[1] for lat, lon in area]
        assert max(norths) - min(norths) == pytest.approx(20.0, abs=0.5)
        assert max(easts) - min(easts) == pytest.approx(30.0, abs=0.5)
        assert report["coverage"] == 0.0 and report["pod"]["mean"] == 0.0
        poses = []
        while flying_item(link) != first + 2 and len(poses) < 300:  # the first lane flown (2 s)
            t = link.telemetry()
            if t is not None:
                coverage.update(t)  # the camera pointed there, but nothing was analysed
                poses.append(t)
            time.sleep(0.1)
        time.sleep(1.1)  # the report is recomputed once a second
        flown = coverage.report()
        assert flown is not None and flown["coverage"] == 0.0 and flown["pod"]["looks"] == 0
        for t in poses[::5]:  # every fifth pose's keyframe was analysed
            coverage.add_look(t, t.time_s)
        time.sleep(1.1)
        later = coverage.report()
        assert later is not None
        print(f"coverage {later['coverage']:.3f}, mean POD {later['pod']['mean']:.3f} after the first lane")
        assert later["coverage"] > 0.2
        assert 1 <= len(later["covered"]) <= 20
        # the looks that saw some of the area
        assert 1 <= later["pod"]["looks"] <= len(poses[::5]) and later["pod"]["mean"] > 0.0


def test_a_mission_replaced_mid_search_gets_its_own_map_within_seconds() -> None:
    """A new survey uploaded while the search runs (here 10 m further north, one lane more) is picked up from
    the autopilot's item count; the looks made so far are laid on it."""
    camera = CameraModel.from_hfov(640, 480, 70.0, -40.0, stabilised=True)
    with surveying("ardupilot") as (sim, link, first), MainLoop(link), gcs(sim) as ground:
        coverage = SearchCoverage(camera, 15.0, link.mission_link, lambda: "ardupilot", (1, 191))
        coverage.start("person")
        assert wait_for(lambda: coverage.report() is not None, 10.0), coverage.error
        old = coverage.report()
        assert old is not None
        t = link.telemetry()
        assert t is not None
        coverage.add_look(t, t.time_s)
        lanes = [
            waypoint(10 + n, e) for n, e in ((0, 0), (20, 0), (20, 10), (0, 10), (0, 20), (20, 20), (20, 30))
        ]
        client = MissionClient(ground, "ardupilot", source=(255, 190), timeouts=MissionTimeouts(0.3, 3))
        client.upload(lanes)
        uploaded = time.monotonic()

        def new_area() -> bool:
            snapshot = link.telemetry()
            if snapshot is not None:
                coverage.update(snapshot)  # what the main loop does with every telemetry sample
            report = coverage.report()
            return report is not None and report["area"] != old["area"]

        assert wait_for(new_area, 5.0), coverage.error
        print(f"new area mapped {time.monotonic() - uploaded:.2f} s after the upload")
        report = coverage.report()
        assert report is not None
        assert min(offset(lat, lon)[0] for lat, lon in report["area"]) == pytest.approx(10.0, abs=0.5)
        assert report["pod"]["looks"] == 1  # the look made before is laid on the new area too


def test_a_mission_far_from_the_vehicle_is_not_mapped_and_the_swap_is_named() -> None:
    """A survey typed longitude first (the GeoJSON habit) and uploaded by another tool lies 5,000 km off: the
    companion maps nothing there and says why (the runner puts it on the GCS: NO SEARCH AREA)."""
    camera = CameraModel.from_hfov(640, 480, 70.0, -40.0, stabilised=True)
    swapped = [MissionItem.waypoint(item.lon_deg, item.lat_deg, 10.0) for item in LANES]
    with autopilot("ardupilot", start_height_m=10.0) as sim, gcs(sim) as ground:
        MissionClient(ground, "ardupilot", source=(255, 190), timeouts=MissionTimeouts(0.3, 3)).upload(
            swapped
        )
        with vehicle_link(sim) as link, MainLoop(link):
            coverage = SearchCoverage(
                camera, 15.0, link.mission_link, lambda: "ardupilot", (1, 191), max_distance_m=3000.0
            )
            assert wait_for(lambda: link.telemetry() is not None, 10.0)
            coverage.update(link.telemetry())  # type: ignore[arg-type]
            coverage.start("person")
            assert wait_for(lambda: coverage.error, 10.0)
            assert coverage.report() is None
            assert "km from the vehicle" in coverage.error
            assert "latitude and longitude may be swapped" in coverage.error


def offset(lat: float, lon: float) -> tuple[float, float]:
    from behaviors.geolocation import latlon_to_offset

    return latlon_to_offset(*HOME, lat, lon)


def test_no_mission_means_no_area_and_a_reason() -> None:
    camera = CameraModel.from_hfov(640, 480, 70.0, -40.0, stabilised=True)
    with autopilot("ardupilot", start_height_m=10.0) as sim, vehicle_link(sim) as link:
        coverage = SearchCoverage(camera, 15.0, link.mission_link, lambda: "ardupilot", (1, 191))
        coverage.start()
        assert wait_for(lambda: coverage.error, 10.0)
        assert coverage.report() is None and "no waypoints" in coverage.error
        assert math.isfinite(sim.snapshot().north)
