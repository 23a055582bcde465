"""What a vehicle of a fleet mission does on another vehicle's confirmed find (behaviors/fleet_order.py):
the start's on_find set once on the real back-end over HTTP by the companion's own session, the order it
reads back after the other vehicle's find, and what the companion then does (told always; with the start's
leave to command: its mission ends and the autopilot is asked to hold or return)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from behaviors.actions import FlightMode
from behaviors.fleet_order import FleetResponse, respond
from behaviors.mission import MissionState, initial_state
from behaviors.mission_commands import AbortMission, StartMission
from behaviors.mission_config import MissionConfig
from cloudtrack.api_client import BackendClient
from cloudtrack.api_models import FleetOrder
from companion.cloud.backend_session import BackendSession
from companion.mission_runner import MissionRunner
from companion.operator_notices import OperatorNotices
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve
from tests.mavlink_harness import wait_for


@pytest.mark.parametrize(
    ("order", "found", "engage", "expected"),
    [
        ("continue", "drone-2/c4", True, None),  # the finder, or a mission that searches on
        ("hold", None, True, None),  # nothing confirmed yet
        ("hold", "drone-2/c4", True,
         FleetResponse("FLEET HOLD: found by drone-2", AbortMission("fleet hold: found by drone-2"), FlightMode.LOITER)),
        ("return", "drone-2/c4", True,
         FleetResponse("FLEET RETURN: found by drone-2", AbortMission("fleet return: found by drone-2"), FlightMode.RTL)),
        ("return", "drone-2/c4", False, FleetResponse("FLEET RETURN: found by drone-2 (pilot)", None, None)),
        ("land", "drone-2/c4", True, None),  # not an order the fleet gives
        ("hold", "a-vehicle-with-a-very-long-name/c4", False,
         FleetResponse("FLEET HOLD: found by a-vehicle-with-a-v (pilot)", None, None)),
    ],
)  # fmt: skip
def test_the_response_to_an_order(
    order: str, found: str | None, engage: bool, expected: FleetResponse | None
) -> None:
    response = respond(order, found, engage)
    assert response == expected
    assert response is None or len(response.message) <= 50  # one STATUSTEXT


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


def test_the_start_sets_on_find_once_and_the_others_are_told_after_a_find(backend: str) -> None:
    sessions = {}
    for vehicle in ("drone-1", "drone-2"):
        client = BackendClient(backend, VEHICLE_TOKENS[vehicle], vehicle_id=vehicle, mission_id="m-fleet")
        sessions[vehicle] = BackendSession(client, period_s=0.05).start()
    finder, other = sessions["drone-1"], sessions["drone-2"]
    try:
        for session in sessions.values():
            session.update({"state": "SEARCH", "mission_id": "m-fleet"})
        other.set_on_find("m-fleet", "hold")
        order = wait_for(lambda: other.fleet_order(), 20.0)
        assert order.on_find == "hold" and order.order == "continue" and order.found is None
        finder.set_on_find("m-fleet", "return")  # a second start with another setting: the first stands
        assert (
            "on_find return refused" in wait_for(finder.on_find_refused, 20.0)
            and "'hold'" in finder.on_find_refused()
        )
        find = {"candidate_id": "c4", "position": [47.3977, 8.5456], "sigma_m": 3.0, "time": 1000.0,
                "prompt": "a man in a green shirt", "confirmed_by": "gcs"}  # fmt: skip
        finder.update({"state": "CONFIRMED", "mission_id": "m-fleet", "find": find})
        told = wait_for(lambda: (o := other.fleet_order()) is not None and o.order == "hold" and o, 20.0)
        assert told.found == "drone-1/c4"
        own = wait_for(lambda: (o := finder.fleet_order()) is not None and o.found and o, 20.0)
        assert own.order == "continue"  # the finder stays with the person
    finally:
        for session in sessions.values():
            session.close()


class Vehicle:
    def __init__(self) -> None:
        self.said: list[str] = []
        self.modes: list[str] = []
        self.released: list[str] = []

    def send_status(self, text: str, severity: int = 6) -> None:
        self.said.append(text)

    def request_mode(self, mode: str) -> None:
        self.modes.append(mode)

    def release_offboard(self, reason: str) -> None:
        self.released.append(reason)

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


class Session:
    def __init__(self, order: FleetOrder | None, refused: str = "") -> None:
        self.order = order
        self.refused = refused

    def fleet_order(self) -> FleetOrder | None:
        return self.order

    def on_find_refused(self) -> str:
        return self.refused


def test_the_operator_hears_when_the_starts_on_find_did_not_stand() -> None:
    none: Any = None
    notices = OperatorNotices()
    refused = "on_find return refused: mission '7' already has on_find 'hold'; that setting stands"
    session: Any = Session(None, refused)
    runner = MissionRunner(MissionConfig(), none, none, Vehicle(), none, session=session, notices=notices)
    mission = StartMission("a man in a green shirt", "person", mission_id="7", on_find="return")
    runner.state = replace(initial_state(MissionConfig()), mode=MissionState.SEARCHING, mission=mission)
    runner._follow_fleet_order(1.0)
    assert "on_find return refused" in notices.current() and "'hold'" in notices.current()


@pytest.mark.parametrize("engage", [True, False])
def test_the_companion_acts_once_on_a_new_order(engage: bool) -> None:
    none: Any = None
    vehicle = Vehicle()
    session: Any = Session(None)
    runner = MissionRunner(MissionConfig(), none, none, vehicle, none, session=session)
    mission = StartMission(
        "a man in a green shirt", "person", allow_engage=engage, mission_id="7", on_find="hold"
    )
    runner.state = replace(initial_state(MissionConfig()), mode=MissionState.SEARCHING, mission=mission)
    runner._follow_fleet_order(1.0)
    session.order = FleetOrder(mission_id="7", vehicle_id="drone-2", on_find="hold", order="continue")
    runner._follow_fleet_order(2.0)
    assert vehicle.said == [] and runner.state.mode is MissionState.SEARCHING  # nothing found yet
    session.order = FleetOrder(
        mission_id="7", vehicle_id="drone-2", on_find="hold", found="drone-1/c4", order="hold"
    )
    runner._follow_fleet_order(3.0)
    runner._follow_fleet_order(4.0)  # the same order again: acted on once
    said = [line for line in vehicle.said if line.startswith("FLEET")]
    if engage:
        assert said == ["FLEET HOLD: found by drone-1"]
        assert runner.state.mode is not MissionState.SEARCHING  # the mission ended: the pilot and GCS own it
        assert vehicle.modes == ["loiter"]
    else:
        assert said == ["FLEET HOLD: found by drone-1 (pilot)"]
        assert runner.state.mode is MissionState.SEARCHING and vehicle.modes == []  # it commands nothing
