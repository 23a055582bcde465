"""Issue 43 item 4, one picture: the supervisor page's state for a fleet. Each vehicle's view carries its
colour in its mission (the exports' colours, beside its id), its part and its bounded track; each mission
carries the merged map of its vehicles, merged again only when an area, coverage or POD map changed."""

from __future__ import annotations

import base64
from typing import Any

from backend import supervisor_view
from backend.sessions import SessionStore
from backend.supervisor_view import SupervisorView
from cloudtrack.api_models import VehicleStatusIn
from cloudtrack.vehicle_colours import vehicle_colours

LAT, LON = 47.3977, 8.5456
D = 0.0009  # about 100 m of latitude
WEST = [[LAT, LON], [LAT + D, LON], [LAT + D, LON + D], [LAT, LON + D]]
EAST = [[LAT, LON + D], [LAT + D, LON + D], [LAT + D, LON + 2 * D], [LAT, LON + 2 * D]]


def _report(
    store: SessionStore, vehicle: str, area: list[list[float]], position: list[float], **extra: Any
) -> None:
    # The western half of the part, counter-clockwise (clockwise rings are holes).
    covered = [[area[0], [area[0][0], area[0][1] + D / 2], [area[1][0], area[1][1] + D / 2], area[1]]]
    body = {
        "mission_id": "m-43",
        "state": "SEARCHING",
        "prompt": "a man in a gray shirt",
        "position": position,
        "search": {"area": area, "covered": covered, "coverage": 0.5},
        **extra,
    }
    store.set_status(vehicle, VehicleStatusIn.model_validate(body))


def test_the_fleet_in_one_state_each_vehicle_in_its_colour_and_one_merged_map() -> None:
    now = [1000.0]
    store = SessionStore(clock=lambda: now[0])
    view = SupervisorView(store, clock=lambda: now[0])
    for i in range(5):
        _report(store, "drone-2", EAST, [LAT + i * D / 5, LON + 1.5 * D])
        _report(store, "drone-1", WEST, [LAT + i * D / 5, LON + 0.5 * D])
    store.set_status("drone-3", VehicleStatusIn.model_validate({"mission_id": "other", "state": "IDLE"}))
    snapshot = view.snapshot()
    by_id = {v.id: v for v in snapshot.vehicles}
    colours = vehicle_colours(["drone-1", "drone-2"])  # as the exports colour the mission
    assert by_id["drone-1"].colour == colours["drone-1"] != by_id["drone-2"].colour == colours["drone-2"]
    assert by_id["drone-3"].colour == vehicle_colours(["drone-3"])["drone-3"]
    assert by_id["drone-1"].search is not None and by_id["drone-1"].search.area == WEST
    assert len(by_id["drone-1"].track) == 5 and by_id["drone-1"].track[-1] == [LAT + 4 * D / 5, LON + 0.5 * D]

    missions = {m.mission_id: m for m in snapshot.missions}
    assert sorted(missions) == ["m-43", "other"]
    fleet = missions["m-43"]
    assert fleet.vehicles == ["drone-1", "drone-2"]
    # The two parts merged into one area twice either's; each covered half of its own: half of the whole.
    assert len(fleet.area) == 1 and fleet.coverage is not None and abs(fleet.coverage - 0.5) < 0.02
    lons = [p[1] for p in fleet.area[0]]
    assert min(lons) < LON + 1e-9 and max(lons) > LON + 2 * D - 1e-9
    assert missions["other"].area == [] and missions["other"].coverage is None

    # A report that only moves a vehicle (its track) does not merge the map again ([fleet] merge_period_s
    # is 2 s: the map was due for a look, not for a merge).
    merges = store.merged_maps.merges
    now[0] += 2
    _report(store, "drone-1", WEST, [LAT + D, LON + 0.5 * D])
    assert view.snapshot().vehicles[0].track[-1] == [LAT + D, LON + 0.5 * D]
    assert store.merged_maps.merges == merges
    # One that covers more does.
    now[0] += 2
    _report(store, "drone-2", EAST, [LAT + D, LON + 1.5 * D], search={"area": EAST, "coverage": 1.0,
            "covered": [EAST[::-1]]})  # fmt: skip
    fleet = view.snapshot().missions[0]
    assert fleet.coverage is not None and abs(fleet.coverage - 0.75) < 0.02
    assert store.merged_maps.merges == merges + 1 and fleet.as_of == now[0]

    # No vehicle's credentials in the page's state.
    text = view.snapshot().model_dump_json()
    assert "token" not in text.lower()


def test_a_large_fleets_tracks_are_shown_coarser_but_bounded(monkeypatch: Any) -> None:
    monkeypatch.setattr(supervisor_view, "FLEET_TRACK_POINTS", 100)
    monkeypatch.setattr(supervisor_view, "TRACK_SHOWN_MIN", 10)
    now = [1000.0]
    store = SessionStore(clock=lambda: now[0])
    view = SupervisorView(store, clock=lambda: now[0])
    for i in range(200):  # 200 points 10 m apart
        now[0] += 1
        for v in range(4):
            _report(store, f"d{v}", WEST, [LAT + i * D / 10, LON + v * D / 4])
    snapshot = view.snapshot()
    for vehicle in snapshot.vehicles:  # 100 points among 4 vehicles: 25 each, the newest kept
        assert 10 <= len(vehicle.track) <= 26, len(vehicle.track)
        assert vehicle.track[-1] == [LAT + 199 * D / 10, vehicle.track[-1][1]]
    assert sum(len(v.track) for v in snapshot.vehicles) <= 104


def _grid(west: float, pod: float) -> dict[str, Any]:
    """A 10 x 10 grid of 10 m cells over a part, every cell at `pod`."""
    values = base64.b64encode(bytes([round(pod * 250)] * 100)).decode()
    return {
        "target": "person", "posture": "standing", "target_pod": 0.8, "origin": [LAT, west], "cell_m": 10.0,
        "rows": 10, "cols": 10, "values": values, "mean": pod, "at_target": 0.0, "looks": 3, "dark_looks": 1,
    }  # fmt: skip


def test_the_missions_pod_map_merges_every_vehicles() -> None:
    store = SessionStore()
    view = SupervisorView(store)
    for vehicle, area, grid in (("drone-1", WEST, _grid(LON, 0.5)), ("drone-2", EAST, _grid(LON + D, 0.6))):
        search = {"area": area, "coverage": 0.5, "pod": grid}
        _report(store, vehicle, area, [LAT, area[0][1]], search=search)
    snapshot = view.snapshot()
    assert all(v.pod is not None and v.pod.looks == 3 for v in snapshot.vehicles)
    (fleet,) = snapshot.missions
    assert fleet.pod is not None and fleet.pod.looks == 6 and fleet.pod.dark_looks == 2
    # (the grids, 100 m square, overlap where the parts meet: there the looks combine, 1 - 0.5 * 0.4)
    assert 0.5 < fleet.pod.mean < 0.8 and fleet.pod.at_target > 0 and fleet.pod.bands and fleet.pod.meaning


def test_a_vehicle_that_left_the_search_and_its_unflown_part() -> None:
    now = [1000.0]
    store = SessionStore(clock=lambda: now[0], dropout_s=30.0)
    view = SupervisorView(store, clock=lambda: now[0])
    _report(store, "drone-1", WEST, [LAT, LON + D / 4])
    _report(store, "drone-2", EAST, [LAT, LON + 1.5 * D])
    snapshot = view.snapshot()
    assert [v.left for v in snapshot.vehicles] == ["", ""] and snapshot.missions[0].unflown == []
    # drone-2 goes home: it has left (as backend.fleet_dropout says), the eastern half of its part unflown.
    now[0] += 5
    _report(store, "drone-2", EAST, [LAT, LON + 1.5 * D], search={"area": EAST, "coverage": 0.5, "mode": "RTL",
            "covered": _report_covered(EAST)})  # fmt: skip
    snapshot = view.snapshot()
    assert {v.id: v.left for v in snapshot.vehicles} == {"drone-1": "", "drone-2": "mode RTL"}
    (unflown,) = snapshot.missions[0].unflown
    assert unflown.vehicle_id == "drone-2" and unflown.rings
    half = D * 111_320 * D * 111_320 * 0.674 / 2  # half the part, m² (a degree of longitude at 47.4°)
    assert 0.8 * half < unflown.area_m2 < 1.1 * half, (unflown.area_m2, half)
    # drone-1 falls silent past [fleet] dropout_s: worded without the seconds, which the page counts.
    now[0] += 40
    store.set_status("drone-3", VehicleStatusIn.model_validate({"mission_id": "other", "state": "IDLE"}))
    snapshot = view.snapshot()
    assert {v.id: v.left for v in snapshot.vehicles}["drone-1"] == "silent over 30 s"
    assert sorted(u.vehicle_id for u in snapshot.missions[0].unflown) == ["drone-1", "drone-2"]


def _report_covered(area: list[list[float]]) -> list[list[list[float]]]:
    return [[area[0], [area[0][0], area[0][1] + D / 2], [area[1][0], area[1][1] + D / 2], area[1]]]
