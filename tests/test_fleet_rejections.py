"""A rejection by the supervisor holds for every vehicle of the fleet mission, by place (issue 43 item 2): the
back-end's appearance match fails for a look-alike seen from another lane, so each companion keeps the other
vehicles' rejections (`GET /v1/missions/{m}/fleet`) and proposes nobody standing where one was made. The pure
part (`behaviors.mission`, `FleetRejections`), then a companion on the real back-end over HTTP."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import requests

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from behaviors.actions import GcsMessage, TrackerInit
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, FleetRejection, FleetRejections, GcsCommand, RejectionShared
from behaviors.geolocation import GeoEstimate, latlon_to_offset, locate_box, offset_to_latlon
from behaviors.geometry import Box
from behaviors.mission import MissionState, State, initial_state, step
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.rejection_memory import RejectedTarget, RejectionMemory
from behaviors.telemetry import Telemetry
from cloudtrack.api_client import BackendClient, crop_to_base64
from companion.cloud.backend_session import BackendSession
from companion.mission_runner import MissionRunner
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve
from tests.mavlink_harness import wait_for

CFG = MissionConfig()
CAM = CFG.camera
RADIUS = CFG.rejection_radius_m
HEIGHT = 20.0
PROMPT = "a man in a green shirt"
MISSION = StartMission(PROMPT, "person", mission_id="9")
POSE = Telemetry(0.0, lat_deg=47.0, lon_deg=8.0, height_agl=HEIGHT, mode="AUTO")


def box_at(distance_m: float) -> Box:
    """A box whose foot point lies `distance_m` north of POSE on flat ground (the default camera)."""
    depression = math.atan2(HEIGHT, distance_m)
    v = CAM.cy + CAM.fy * math.tan(depression + CAM.mount_pitch)
    return Box.from_center(CAM.cx, v - 20.0, 16.0, 40.0)


def place(north_m: float, east_m: float = 0.0, sigma_m: float = 0.0) -> GeoEstimate:
    lat, lon = offset_to_latlon(POSE.lat_deg, POSE.lon_deg, north_m, east_m)
    return GeoEstimate(lat, lon, north_m, east_m, math.hypot(north_m, east_m), 0.0, sigma_m)


def rejected_at(north_m: float, vehicle: str = "drone-1", rejection_id: int = 4) -> FleetRejection:
    at = place(north_m)
    return FleetRejection(vehicle, rejection_id, at.lat_deg, at.lon_deg)


def searching() -> State:
    state, _ = step(initial_state(CFG), POSE, CFG)
    state, _ = step(state, GcsCommand(0.1, MISSION), CFG)
    assert state.mode is MissionState.SEARCHING
    return state


def answer(state: State, *boxes: Box) -> BackendAnswer:
    """The back-end's answer to the search's query: "yes" on each box, the first scored highest."""
    candidates = tuple(
        Detection(
            box, 0.9 - 0.1 * i, verdict=Verdict.YES, justification="green shirt", candidate_id=f"c{i + 1}"
        )
        for i, box in enumerate(boxes)
    )
    return BackendAnswer(1.0, state.queries[-1][0], 30, candidates, pose=POSE)


def proposed(state: State, event: BackendAnswer) -> list[str]:
    _, actions = step(state, event, CFG)
    return [a.candidate_id for a in actions if isinstance(a, TrackerInit)]


# --- matching: another vehicle's rejection by place, with the radius throughout --------------------------


@pytest.mark.parametrize(
    ("north_m", "sigma_m", "matched"),
    [
        (0.0, 0.0, True),
        (
            RADIUS - 0.1,
            0.0,
            True,
        ),  # the radius: the other vehicle's estimate carries no uncertainty of its own
        (RADIUS + 1.0, 0.0, False),
        (RADIUS + 1.0, 1.0, True),  # widened by two sigma of the candidate's estimate
        (3 * RADIUS - 0.5, 1000.0, True),  # however uncertain, at most three radii
        (3 * RADIUS + 0.5, 1000.0, False),
        (2 * RADIUS, 1.0, False),  # a second person two radii off is proposed
    ],
)
def test_another_vehicles_rejection_matches_by_place(north_m: float, sigma_m: float, matched: bool) -> None:
    memory = RejectionMemory(radius_m=RADIUS).remember(RejectedTarget(position=place(0.0), via="drone-1"))
    assert (memory.matches("", place(north_m, sigma_m=sigma_m), query_id=50) is not None) is matched


def test_another_vehicles_rejection_matches_neither_by_its_id_nor_once_the_back_end_holds_one() -> None:
    """Its candidate id is the other vehicle's (this vehicle's candidate of the same id is someone else), and
    the back-end's holding a rejection of this vehicle's (`RejectionShared`) never narrows it."""
    state, _ = step(searching(), FleetRejections(0.5, "9", (rejected_at(15.0),)), CFG)
    (entry,) = state.fleet_rejections.entries
    assert (entry.candidate_id, entry.via, entry.shared_from_query) == ("", "drone-1", 0)
    assert state.fleet_rejections.matches("c1", query_id=99) is None
    shared, _ = step(state, RejectionShared(0.6, ""), CFG)
    assert shared.fleet_rejections == state.fleet_rejections


# --- the event: taken once for this mission, said to the GCS --------------------------------------------


@pytest.mark.parametrize(
    ("mission_id", "rejections", "kept", "said"),
    [
        ("9", (rejected_at(15.0),), 1, "FLEET: rejected via drone-1, not proposed here"),
        ("9", (rejected_at(15.0), rejected_at(40.0, "drone-3", 7)), 2,
         "FLEET: 2 rejected via drone-1, drone-3"),
        ("9", (rejected_at(15.0), rejected_at(15.0, rejection_id=5)), 1,
         "FLEET: rejected via drone-1, not proposed here"),  # the same place twice: one entry
        ("9", (FleetRejection("drone-1", 4, math.nan, 8.0),), 0, None),
        ("8", (rejected_at(15.0),), 0, None),  # another mission's
        ("9", (), 0, None),
    ],
)  # fmt: skip
def test_the_fleets_rejections_enter_the_memory(
    mission_id: str, rejections: tuple[FleetRejection, ...], kept: int, said: str | None
) -> None:
    state, actions = step(searching(), FleetRejections(0.5, mission_id, rejections), CFG)
    assert len(state.fleet_rejections.entries) == kept
    assert [a.text for a in actions if isinstance(a, GcsMessage)] == ([said] if said else [])
    again, actions = step(state, FleetRejections(0.6, mission_id, rejections), CFG)
    assert again.fleet_rejections == state.fleet_rejections and actions == ()  # known: taken once


def test_the_fleets_rejections_are_kept_apart_and_forgotten_with_the_prompt() -> None:
    state = searching()
    own = RejectedTarget("c7", place(60.0), time_s=0.2)
    state = replace(state, rejections=state.rejections.remember(own))
    many = tuple(rejected_at(100.0 + i, "drone-2", i) for i in range(2 * state.rejections.capacity))
    state, _ = step(state, FleetRejections(0.5, "9", many), CFG)
    assert state.rejections.entries == (own,)  # a fleet's many never push this vehicle's own out
    assert len(state.fleet_rejections.entries) == state.fleet_rejections.capacity
    assert state.fleet_rejections.radius_m == RADIUS
    same, _ = step(state, GcsCommand(1.0, MISSION), CFG)
    assert same.fleet_rejections == state.fleet_rejections
    other, _ = step(state, GcsCommand(1.0, StartMission("a child in a red jacket", mission_id="9")), CFG)
    assert other.fleet_rejections.entries == ()
    idle = initial_state(CFG)
    new, actions = step(idle, FleetRejections(0.5, "9", many), CFG)
    assert new.fleet_rejections.entries == () and actions == ()  # no mission: not this one's


def test_a_candidate_where_another_vehicle_rejected_one_is_not_proposed_one_two_radii_off_is() -> None:
    state = searching()
    rejected_place = locate_box(CAM, POSE, box_at(15.0))
    assert rejected_place is not None
    there, beyond = box_at(16.0), box_at(15.0 + 2 * RADIUS)  # the other vehicle's estimate 1 m off this one's
    assert proposed(state, answer(state, there, beyond)) == ["c1"]  # nothing rejected yet: the higher score
    fleet = FleetRejection("drone-1", 4, rejected_place.lat_deg, rejected_place.lon_deg)
    state, _ = step(state, FleetRejections(0.5, "9", (fleet,)), CFG)
    assert proposed(state, answer(state, there)) == []
    assert proposed(state, answer(state, there, beyond)) == ["c2"]


# --- a companion on the real back-end -----------------------------------------------------------------


@pytest.fixture
def backend(models_dir: Path, tmp_path: Path) -> Iterator[str]:
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        verifier=VerifierConfig(kind="none"),
        sessions=SessionConfig(sqlite_path=str(tmp_path / "sessions.sqlite3")),
    )
    with serve(create_app(config)) as url:
        yield url


class Vehicle:
    def __init__(self) -> None:
        self.said: list[str] = []

    def commands(self) -> list[Any]:
        return []

    def send_status(self, text: str, severity: int = 6) -> None:
        self.said.append(text)

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


def test_a_look_alike_rejected_via_one_vehicle_is_never_proposed_by_another(backend: str) -> None:
    """The supervisor rejects drone-1's candidate on the page (the back-end keeps the place drone-1 reported
    for it); drone-2's companion, searching the same mission, reads it from its /fleet answer and passes over
    its own candidate of the look-alike, seen from elsewhere (its estimate 1 m off drone-1's), while it still
    proposes a person two radii away."""
    rejected_place = locate_box(CAM, POSE, box_at(15.0))
    assert rejected_place is not None
    crop = crop_to_base64(np.full((64, 32, 3), (40, 160, 40), np.uint8))
    awaiting = {"candidate_id": "k3-1", "box": [0, 0, 32, 64], "crop_jpeg_b64": crop,
                "position": [rejected_place.lat_deg, rejected_place.lon_deg]}  # fmt: skip
    drone1 = BackendClient(backend, VEHICLE_TOKENS["drone-1"], vehicle_id="drone-1", mission_id="9")
    drone1.report_status("AWAIT_SUPERVISOR", mission_id="9", awaiting=awaiting)
    rejected = requests.post(
        f"{backend}/v1/vehicles/drone-1/decisions",
        json={"candidate_id": "k3-1", "action": "reject", "operator": "ops"},
        headers={"Authorization": f"Bearer {SUPERVISOR_TOKEN}"},
        timeout=10,
    )
    assert rejected.status_code in (200, 201), rejected.text

    client = BackendClient(backend, VEHICLE_TOKENS["drone-2"], vehicle_id="drone-2", mission_id="9")
    session = BackendSession(client, period_s=0.05).start()
    vehicle = Vehicle()
    none: Any = None
    runner = MissionRunner(CFG, none, none, vehicle, none, session=session)
    runner.state = searching()
    try:
        session.update({"state": "SEARCH", "mission_id": "9"})
        events = wait_for(lambda: runner._ground_events(time.monotonic()), 20.0)
    finally:
        session.close()
    (event,) = events
    assert isinstance(event, FleetRejections) and event.mission_id == "9"
    (fleet,) = event.rejections
    assert fleet.vehicle_id == "drone-1"
    north, east = latlon_to_offset(
        rejected_place.lat_deg, rejected_place.lon_deg, fleet.lat_deg, fleet.lon_deg
    )
    assert math.hypot(north, east) < 0.01  # the candidate's place as drone-1 reported it
    runner._handle(event)
    assert "FLEET: rejected via drone-1, not proposed here" in vehicle.said
    assert runner._ground_events(time.monotonic()) == []  # taken once

    state = runner.state
    there, beyond = box_at(16.0), box_at(15.0 + 2 * RADIUS)
    beyond_place = locate_box(CAM, POSE, beyond)
    assert beyond_place is not None
    apart = latlon_to_offset(
        rejected_place.lat_deg, rejected_place.lon_deg, beyond_place.lat_deg, beyond_place.lon_deg
    )
    assert math.hypot(*apart) >= 2 * RADIUS
    assert proposed(state, answer(state, there)) == []
    assert proposed(state, answer(state, there, beyond)) == ["c2"]
