"""One mission of the fleet on the back-end (issue 43 item 2): the vehicles searching the same mission id
share its rejections (where they were made), its finds (one per person) and its map (merged), in both
stores (SQLite, and Debian's real redis-server as in test_backend_store)."""

from __future__ import annotations

import base64
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from backend.mission_merge import merged_pod
from backend.redis_store import RedisStore
from backend.schemas import (
    AwaitingCandidate,
    DecisionIn,
    Find,
    PodGrid,
    Rejection,
    RejectionIn,
    SearchStatus,
    StoredFind,
    VehicleStatusIn,
)
from backend.sessions import SessionStore, distance_m
from backend.state_store import SqliteStore, StateStore, vector_bytes
from backend_tools.fleet_services import RedisServer
from cloudtrack.api_models import FLEET_REJECTIONS_MAX
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import MAX_CELLS, decode_grid, grid_value
from tests.backend_fixtures import SUPERVISOR, auth, backend_config

RED = [1.0] + [0.0] * 127
BLUE = [0.0] * 127 + [1.0]
RED_BYTES = vector_bytes(RED)
HERE = [47.0, 8.0]
FRAME = LocalFrame(*HERE)


def _at(east_m: float, north_m: float) -> list[float]:
    return list(FRAME.latlon(east_m, north_m))


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer() as server:
        yield server


@pytest.fixture(params=["sqlite", "redis"])
def state(request: pytest.FixtureRequest, tmp_path: Path, redis_server: RedisServer) -> Iterator[StateStore]:
    if request.param == "sqlite":
        store: StateStore = SqliteStore(tmp_path / "sessions.sqlite3")
    else:
        store = RedisStore(redis_server.url)
        store._redis.flushdb()  # type: ignore[attr-defined]
    yield store
    store.close()


def _grid(origin: list[float], rows: int, cols: int, pod: float, cell_m: float = 10.0) -> PodGrid:
    values = bytes([round(pod * 250)] * (rows * cols))
    return PodGrid(
        target="person",
        posture="standing",
        target_pod=0.8,
        origin=origin,
        cell_m=cell_m,
        rows=rows,
        cols=cols,
        values=base64.b64encode(values).decode(),
        mean=pod,
        at_target=0.0,
        looks=3,
    )


def _square(west_m: float, south_m: float, side_m: float) -> list[list[float]]:
    return [
        _at(west_m, south_m),
        _at(west_m + side_m, south_m),
        _at(west_m + side_m, south_m + side_m),
        _at(west_m, south_m + side_m),
    ]


def test_the_vehicles_of_one_mission_id_are_listed_and_expire(state: StateStore) -> None:
    state.touch_mission("d1", "m1", 100.0, 60, 8)
    state.touch_mission("d2", "m1", 110.0, 60, 8)
    state.touch_mission("d3", "m2", 110.0, 60, 8)
    assert state.mission_vehicles("m1", 10) == ["d2", "d1"]  # the most recently seen first
    assert state.mission_vehicles("m1", 1) == ["d2"]  # bounded
    assert state.expire(105.0) == 1
    assert state.mission_vehicles("m1", 10) == ["d2"]


def test_a_rejection_on_one_vehicle_refuses_the_same_place_proposed_by_another(state: StateStore) -> None:
    store = SessionStore(state, radius_m=100)
    store.remember_candidates("d1", "m1", [("c1", RED)])
    awaiting = AwaitingCandidate(candidate_id="c1", box=[0, 0, 60, 120], position=HERE)
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="AWAIT_SUPERVISOR", awaiting=awaiting))
    store.add_decision("d1", DecisionIn(candidate_id="c1", action="reject", note="not him"))
    store.open_mission("d2", "m1")
    near = store.rejection_check("d2", "m1", _at(30, 40))  # 50 m from the rejected place
    reason = near(RED)
    assert reason is not None and "c1" in reason and "via d1" in reason
    assert near(BLUE) is None  # another look is a new candidate
    assert store.rejection_check("d2", "m1", _at(300, 0))(RED) is None  # a look-alike elsewhere
    assert store.rejection_check("d2", "m1", None)(RED) is None  # no place: nothing to match it by
    assert store.rejection_check("d2", "m2", HERE)(RED) is None  # another mission id
    # Today's own-vehicle rule holds: d1's rejection matches d1 anywhere without a position.
    assert store.rejection_check("d1", "m1", None)(RED) is not None


def test_a_rejection_without_a_place_holds_for_its_vehicle_only(state: StateStore) -> None:
    store = SessionStore(state, radius_m=100)
    store.remember_candidates("d1", "m1", [("c1", RED)])
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="SEARCH"))
    store.add_decision("d1", DecisionIn(candidate_id="c1", action="reject"))
    store.open_mission("d2", "m1")
    assert store.rejection_check("d1", "m1", HERE)(RED) is not None
    assert store.rejection_check("d2", "m1", HERE)(RED) is None


def _find(candidate: str, position: list[float], sigma_m: float | None) -> Find:
    return Find(
        candidate_id=candidate,
        position=position,
        sigma_m=sigma_m,
        time=1000.0,
        prompt="a man",
        confirmed_by="ops",
    )


def test_one_person_seen_by_two_vehicles_is_one_find(state: StateStore) -> None:
    told: list[StoredFind] = []
    store = SessionStore(state, on_find=told.append)
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a7", HERE, 3.0)))
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("b2", _at(4, 3), 4.0))
    )
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("b2", _at(4, 3), 4.0))
    )
    assert [(f.vehicle_id, f.candidate_id) for f in store.mission_finds("m1")] == [("d1", "a7")]
    assert store.finds("d2", "m1") == []
    assert [f.same_as for f in store.sightings("d2", "m1")] == ["d1/a7"]
    assert [f.candidate_id for f in told] == ["a7"]  # told once (Cursor-on-Target)
    # Another person, beyond the two finds' uncertainty, is a find of its own.
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("b3", _at(60, 0), 4.0))
    )
    assert [f.candidate_id for f in store.mission_finds("m1")] == ["a7", "b3"]
    # Another mission id is another mission.
    store.set_status("d3", VehicleStatusIn(mission_id="m2", state="CONFIRMED", find=_find("c1", HERE, 3.0)))
    assert [f.candidate_id for f in store.mission_finds("m2")] == ["c1"]


def test_one_vehicle_finding_the_same_person_again_under_another_candidate_is_one_find(
    state: StateStore,
) -> None:
    """A tracker that lost the person and picked them up again gives them a new candidate id: still one
    person, one find; the same candidate reported again is its find refined, and someone 60 m off another."""
    told: list[StoredFind] = []
    store = SessionStore(state, on_find=told.append)
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a7", HERE, 3.0)))
    store.set_status(
        "d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a7", _at(1, 0), 2.0))
    )
    store.set_status(
        "d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a9", _at(2, 1), 3.0))
    )
    assert [f.candidate_id for f in store.mission_finds("m1")] == ["a7"]
    assert [f.same_as for f in store.sightings("d1", "m1")] == ["d1/a7"]
    store.set_status(
        "d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("b1", _at(60, 0), 3.0))
    )
    assert [f.candidate_id for f in store.mission_finds("m1")] == ["a7", "b1"]
    assert [f.candidate_id for f in told] == ["a7", "b1"]  # each person told once (Cursor-on-Target)


def test_a_supervisors_confirm_of_the_same_person_on_another_vehicle_is_no_second_find(
    state: StateStore,
) -> None:
    store = SessionStore(state)
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a7", HERE, 5.0)))
    awaiting = AwaitingCandidate(candidate_id="b2", box=[0, 0, 60, 120], position=_at(8, 0))
    store.set_status("d2", VehicleStatusIn(mission_id="m1", state="AWAIT_SUPERVISOR", awaiting=awaiting))
    _, created = store.add_decision("d2", DecisionIn(candidate_id="b2", action="confirm"))
    assert created  # the decision stands and goes to d2 as any other
    assert [f.candidate_id for f in store.mission_finds("m1")] == ["a7"]
    assert [f.same_as for f in store.sightings("d2", "m1")] == ["d1/a7"]


def test_merged_pod_combines_overlapping_grids_of_different_origins() -> None:
    a = _grid(HERE, 2, 2, 0.5)
    b = _grid(_at(10, 0), 2, 2, 0.5)  # one cell farther east: their middle column overlaps
    merged = merged_pod([a, b])
    assert merged is not None and (merged.rows, merged.cols) == (2, 3) and merged.cell_m == 10.0
    values = decode_grid(merged.model_dump())
    assert np.allclose(values, [[0.5, 0.75, 0.5], [0.5, 0.75, 0.5]], atol=0.004)  # 1 - (1 - p1)(1 - p2)
    report = merged.model_dump()
    assert grid_value(report, *_at(15, 5)) == pytest.approx(0.75, abs=0.004)
    assert grid_value(report, *_at(-5, 5)) is None  # beyond every grid


def test_merged_pod_stays_bounded_when_the_grids_lie_far_apart() -> None:
    a = _grid(HERE, 64, 64, 0.4, cell_m=2.0)
    b = _grid(_at(3000, 2000), 64, 64, 0.6, cell_m=2.0)
    merged = merged_pod([a, b])
    assert merged is not None and merged.rows * merged.cols <= MAX_CELLS
    values = decode_grid(merged.model_dump())
    assert np.nanmax(values) == pytest.approx(0.6, abs=0.004) and np.isnan(values).any()  # between: outside
    assert merged_pod([_grid(HERE, 1, 1, 0.5), _grid(_at(1e6, 0), 1, 1, 0.5)]) is None  # no cell spans it
    broken = _grid(HERE, 2, 2, 0.5).model_copy(update={"values": base64.b64encode(b"\x01").decode()})
    assert merged_pod([broken]) is None  # a grid that does not decode says nothing


def test_the_mission_map_merges_every_vehicles_area_coverage_and_pod(state: StateStore) -> None:
    store = SessionStore(state)
    west, east = _square(0, 0, 20), _square(20, 0, 20)  # two halves of a 40 x 20 m area
    west_seen = SearchStatus(area=west, covered=[west], coverage=1.0, pod=_grid(HERE, 2, 2, 0.5))
    east_seen = SearchStatus(area=east, covered=[], coverage=0.0, pod=_grid(_at(10, 0), 2, 3, 0.2))
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="SEARCH", position=HERE, search=west_seen))
    store.set_status("d2", VehicleStatusIn(mission_id="m1", state="SEARCH", position=HERE, search=east_seen))
    store.set_status("d3", VehicleStatusIn(mission_id="m2", state="SEARCH", position=HERE, search=east_seen))
    merged = store.merged_map("m1")
    assert merged is not None and sorted(merged.vehicles) == ["d1", "d2"]
    assert merged.coverage == pytest.approx(0.5, abs=0.01)
    assert len(merged.area) == 1 and len(merged.covered) == 1
    assert merged.pod is not None
    report = merged.pod.model_dump()
    assert grid_value(report, *_at(5, 5)) == pytest.approx(0.5, abs=0.004)  # d1's alone
    assert grid_value(report, *_at(15, 5)) == pytest.approx(1 - 0.5 * 0.8, abs=0.004)  # both
    assert grid_value(report, *_at(35, 5)) == pytest.approx(0.2, abs=0.004)  # d2's alone
    assert store.merged_map("m9") is None
    assert math.isclose(store.merged_map("m2").coverage or 0.0, 0.0)  # type: ignore[union-attr]


def test_the_mission_map_is_served_to_the_supervisor_only(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir))
    west, east = _square(0, 0, 20), _square(20, 0, 20)
    with TestClient(app) as client:
        for vehicle, area, pod in (("drone-1", west, 0.5), ("drone-2", east, 0.2)):
            search = SearchStatus(area=area, covered=[area], coverage=1.0, pod=_grid(area[0], 2, 2, pod))
            status = VehicleStatusIn(mission_id="7", state="SEARCH", position=HERE, search=search)
            response = client.post(
                f"/v1/vehicles/{vehicle}/status", json=status.model_dump(mode="json"), headers=auth(vehicle)
            )
            assert response.status_code == 200, response.text
        supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
        answer = client.get("/v1/missions/7/map", headers=supervisor)
        assert answer.status_code == 200, answer.text
        merged = answer.json()
        assert sorted(merged["vehicles"]) == ["drone-1", "drone-2"]
        assert merged["coverage"] == pytest.approx(1.0, abs=0.01)
        assert (merged["pod"]["rows"], merged["pod"]["cols"]) == (2, 4)
        # Kept and merged at most once per [fleet] merge_period_s: the answer says how old it is.
        assert merged["as_of"] > 0 and 0 <= merged["age_s"] < 60
        assert client.get("/v1/missions/7/map", headers=auth("drone-1")).status_code == 403
        assert client.get("/v1/missions/8/map", headers=supervisor).status_code == 404


def test_the_fleet_setting_stands_once_and_goes_with_the_last_vehicle(state: StateStore) -> None:
    state.touch_mission("d1", "m1", 100.0, 60, 8)
    state.touch_mission("d2", "m1", 110.0, 60, 8)
    assert state.set_fleet("m1", "on_find", "hold") == "hold"
    assert state.set_fleet("m1", "on_find", "return") == "hold"  # the first stands
    assert state.fleet("m1") == {"on_find": "hold"} and state.fleet("m2") == {}
    state.expire(105.0)  # d1's search of it is gone, d2's lives
    assert state.fleet("m1") == {"on_find": "hold"}
    state.expire(200.0)
    assert state.fleet("m1") == {}


def test_on_a_confirmed_find_the_others_do_what_was_set_at_the_start(state: StateStore) -> None:
    store = SessionStore(state)
    for vehicle in ("d1", "d2", "d3"):
        store.set_status(vehicle, VehicleStatusIn(mission_id="m1", state="SEARCH"))
    assert store.set_on_find("m1", "return") == "return"
    assert store.fleet_order("d2", "m1").order == "continue"  # nothing found yet
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("a7", HERE, 3.0)))
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="CONFIRMED", find=_find("b2", _at(3, 0), 3.0))
    )
    finder, other = store.fleet_order("d1", "m1"), store.fleet_order("d3", "m1")
    assert (finder.order, finder.found) == ("continue", "d1/a7")  # the finder stays with the person
    assert (other.order, other.on_find, other.found) == ("return", "return", "d1/a7")
    assert store.fleet_order("d2", "m1").order == "return"  # it saw the same person second: one find
    unknown = store.fleet_order("d9", "m2")
    assert (unknown.on_find, unknown.found, unknown.order) == ("continue", None, "continue")
    # Without a setting the fleet goes on.
    store.set_status("d4", VehicleStatusIn(mission_id="m3", state="CONFIRMED", find=_find("c1", HERE, 3.0)))
    assert store.fleet_order("d5", "m3").order == "continue"


def test_on_find_is_set_once_and_each_vehicle_is_told_over_the_api(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir))
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    with TestClient(app) as client:
        put = client.put("/v1/missions/9/on_find", json={"on_find": "hold"}, headers=auth("drone-1"))
        assert put.status_code == 200, put.text
        assert (
            client.put("/v1/missions/9/on_find", json={"on_find": "hold"}, headers=supervisor).status_code
            == 200
        )
        refused = client.put("/v1/missions/9/on_find", json={"on_find": "return"}, headers=supervisor)
        assert refused.status_code == 409 and "'hold'" in refused.json()["detail"]
        assert (
            client.put("/v1/missions/9/on_find", json={"on_find": "dance"}, headers=supervisor).status_code
            == 422
        )
        for vehicle in ("drone-1", "drone-2"):
            status = VehicleStatusIn(mission_id="9", state="SEARCH")
            client.post(
                f"/v1/vehicles/{vehicle}/status", json=status.model_dump(mode="json"), headers=auth(vehicle)
            )
        assert client.get("/v1/missions/9/fleet", headers=auth("drone-2")).json()["order"] == "continue"
        found = VehicleStatusIn(mission_id="9", state="CONFIRMED", find=_find("c1", HERE, 3.0))
        client.post(
            "/v1/vehicles/drone-1/status", json=found.model_dump(mode="json"), headers=auth("drone-1")
        )
        told = client.get("/v1/missions/9/fleet", headers=auth("drone-2")).json()
        assert (told["order"], told["found"], told["vehicle_id"]) == ("hold", "drone-1/c1", "drone-2")
        assert client.get("/v1/missions/9/fleet", headers=auth("drone-1")).json()["order"] == "continue"
        assert (
            client.get("/v1/missions/9/fleet?vehicle_id=drone-1", headers=auth("drone-2")).status_code == 403
        )
        by_supervisor = client.get("/v1/missions/9/fleet?vehicle_id=drone-2", headers=supervisor)
        assert by_supervisor.json()["order"] == "hold"
        assert client.get("/v1/missions/9/fleet", headers=supervisor).status_code == 422


def test_the_other_vehicles_rejections_are_read_newest_first_and_bounded(state: StateStore) -> None:
    for vehicle in ("d1", "d2"):
        state.touch_mission(vehicle, "m1", 100.0, 60, 8)
        for i in range(5):
            record = Rejection(
                rejection_id=0,
                mission_id="m1",
                vehicle_id=vehicle,
                candidate_id=f"{vehicle}-c{i}",
                position=HERE,
                reason="",
                created_at=1.0,
            )
            state.add_rejection(vehicle, "m1", record, bytes(RED_BYTES), 10)
    both = state.mission_rejections("m1", ["d1", "d2"], 4)
    assert len(both) == 4 and {r.candidate_id for r, _ in both} >= {"d2-c4"}
    assert {r.candidate_id for r, _ in state.mission_rejections("m1", ["d1"], 2)} == {"d1-c3", "d1-c4"}
    assert state.mission_rejections("m1", [], 4) == [] and state.mission_rejections("m2", ["d1"], 4) == []


def test_each_vehicle_is_told_the_others_placed_rejections_newest_first_and_bounded(
    state: StateStore,
) -> None:
    """`fleet_order`'s rejections: the other vehicles' that carry a place (the companion excludes candidates
    standing there), newest first, a candidate rejected twice (the supervisor's, then its vehicle's report)
    once, at most FLEET_REJECTIONS_MAX."""
    store = SessionStore(state)
    for vehicle in ("d1", "d2"):
        store.set_status(vehicle, VehicleStatusIn(mission_id="m1", state="SEARCH"))
    crop = base64.b64encode(cv2.imencode(".jpg", np.full((32, 16, 3), 90, np.uint8))[1].tobytes()).decode()

    def reject(vehicle: str, candidate: str, position: list[float] | None) -> None:
        body = RejectionIn(vehicle_id=vehicle, candidate_id=candidate, crop_jpeg_b64=crop, position=position)
        store.add_rejection("m1", body)

    reject("d1", "a1", _at(10, 20))
    reject("d1", "a1", _at(10, 21))  # the vehicle's report of the supervisor's reject: listed once
    reject("d1", "a2", None)  # no place: nothing to exclude by
    reject("d2", "b1", _at(-5, 0))
    told = store.fleet_order("d2", "m1").rejections
    assert [(r.vehicle_id, r.candidate_id) for r in told] == [("d1", "a1")]
    assert distance_m(told[0].position, _at(10, 21)) < 0.01  # the newest of the two
    assert [r.candidate_id for r in store.fleet_order("d1", "m1").rejections] == ["b1"]  # not its own
    assert store.fleet_order("d3", "m2").rejections == []
    for i in range(FLEET_REJECTIONS_MAX + 4):
        reject("d1", f"x{i}", _at(i, 0))
    told = store.fleet_order("d2", "m1").rejections
    assert len(told) == FLEET_REJECTIONS_MAX and told[0].candidate_id == f"x{FLEET_REJECTIONS_MAX + 3}"
    assert [r.rejection_id for r in told] == sorted((r.rejection_id for r in told), reverse=True)


def test_a_vehicles_fleet_answer_lists_another_vehicles_rejection_with_its_place(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir))
    crop = base64.b64encode(cv2.imencode(".jpg", np.full((32, 16, 3), 90, np.uint8))[1].tobytes()).decode()
    with TestClient(app) as client:
        for vehicle in ("drone-1", "drone-2"):
            status = VehicleStatusIn(mission_id="9", state="SEARCH")
            client.post(
                f"/v1/vehicles/{vehicle}/status", json=status.model_dump(mode="json"), headers=auth(vehicle)
            )
        body = {
            "vehicle_id": "drone-1",
            "candidate_id": "k3-1",
            "crop_jpeg_b64": crop,
            "position": _at(-13, 23),
        }
        posted = client.post("/v1/missions/9/rejections", json=body, headers=auth("drone-1"))
        assert posted.status_code == 201, posted.text
        told = client.get("/v1/missions/9/fleet", headers=auth("drone-2")).json()
        assert told["rejections"] == [
            {
                "rejection_id": posted.json()["rejection_id"],
                "vehicle_id": "drone-1",
                "candidate_id": "k3-1",
                "position": _at(-13, 23),
            }
        ]
        assert client.get("/v1/missions/9/fleet", headers=auth("drone-1")).json()["rejections"] == []
