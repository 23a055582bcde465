"""A drone that drops out of a fleet's search (issue 43 item 3), on the back-end: who has left (RTL or LAND,
the companion's abort, another mission, silent past `[fleet] dropout_s`) and the part of its area that no
vehicle covered. The geometry as a table; the store logic over both stores (SQLite, and Debian's real
redis-server as in test_fleet_mission); and a real back-end on loopback (uvicorn) with a small dropout_s,
waited on through what it reports."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import requests
from shapely.geometry import Polygon

from backend.app import create_app
from backend.fleet_dropout import leaving, unflown_part, unflown_parts
from backend.redis_store import RedisStore
from backend.schemas import SearchStatus, VehicleStatus, VehicleStatusIn
from backend.sessions import SessionStore
from backend.state_store import SqliteStore, StateStore
from backend_tools.fleet_services import RedisServer
from cloudtrack.coverage import LocalFrame
from tests.backend_fixtures import SUPERVISOR, TOKENS, backend_config
from tests.live_backend import serve

HERE = (47.0, 8.0)
FRAME = LocalFrame(*HERE)


def _at(east_m: float, north_m: float) -> list[float]:
    return [round(v, 8) for v in FRAME.latlon(east_m, north_m)]


def _rect(west: float, south: float, east: float, north: float) -> list[list[float]]:
    """Counter-clockwise [lat, lon] corners of a rectangle given in metres east and north of HERE."""
    return [_at(west, south), _at(east, south), _at(east, north), _at(west, north)]


def _metres(rings: list[list[list[float]]]) -> Polygon:
    assert len(rings) == 1
    return Polygon([FRAME.xy(lat, lon) for lat, lon in rings[0]])


# ------------------------------------------------------------------------------------------ geometry
PART = _rect(0, 0, 100, 40)  # the dropped vehicle's part: 100 m east-west, 40 m north-south


@pytest.mark.parametrize(
    ("case", "covered", "area_m2", "bounds"),
    [
        ("nothing covered", [], 4000.0, (0, 0, 100, 40)),
        ("the west 60 m covered", [[_rect(0, 0, 60, 40)]], 1600.0, (60, 0, 100, 40)),
        ("another vehicle covered the east 30 m", [[_rect(0, 0, 60, 40)], [_rect(70, -5, 130, 45)]], 400.0,
         (60, 0, 70, 40)),
        ("covered but for 2 m slivers along the edges", [[_rect(-5, 2, 60, 38)]], 1600.0, (60, 0, 100, 40)),
        ("covered in full", [[_rect(-1, -1, 101, 41)]], 0.0, None),
        ("only a scrap of 6 x 6 m left", [[_rect(-1, -1, 101, 41), _rect(94, 34, 100, 40)[::-1]]], 0.0, None),
    ],
)  # fmt: skip
def test_the_unflown_part_is_the_part_less_what_any_vehicle_covered(
    case: str, covered: list[list[list[list[float]]]], area_m2: float, bounds: tuple[float, ...] | None
) -> None:
    unflown = unflown_part(PART, covered)
    assert unflown.area_m2 == pytest.approx(area_m2, rel=0.01, abs=1.0), case
    if bounds is None:
        assert unflown.rings == [], case
    else:
        assert _metres(unflown.rings).bounds == pytest.approx(bounds, abs=0.1), case


def test_the_unflown_part_stays_bounded() -> None:
    # A hundred small covered squares leave a lattice: at most MAX_RINGS rings of MAX_VERTICES vertices.
    covered = [[_rect(x * 10 + 1, y * 10 + 1, x * 10 + 9, y * 10 + 9) for x in range(10) for y in range(4)]]
    unflown = unflown_part(PART, covered, sliver_m=0.1, min_piece_m2=1.0, max_rings=5, max_vertices=40)
    assert 1 <= len(unflown.rings) <= 5 and sum(len(r) for r in unflown.rings) <= 40
    assert unflown_part(PART[:2], []).rings == []  # no part: nothing unflown


def test_several_parts_at_once_meet_only_the_covered_areas_near_them() -> None:
    west, east = _rect(0, 0, 100, 40), _rect(1000, 0, 1100, 40)
    covered = [[_rect(0, 0, 60, 40)], [_rect(1000, 0, 1030, 40)], [_rect(5000, 0, 5100, 40)]]
    parts = unflown_parts([west, east, west[:2]], covered)
    assert [p.area_m2 for p in parts] == pytest.approx([1600.0, 2800.0, 0.0], rel=0.01)
    assert unflown_parts([], covered) == []


def _status(**fields: Any) -> VehicleStatus:
    base: dict[str, Any] = {"vehicle_id": "d1", "mission_id": "m1", "state": "SEARCHING", "updated_at": 100.0}
    return VehicleStatus(**{**base, **fields})


@pytest.mark.parametrize(
    ("status", "now", "expected"),
    [
        (_status(search=SearchStatus(mode="AUTO")), 110.0, None),
        (_status(search=SearchStatus(mode="GUIDED")), 110.0, None),  # tracking a candidate still searches
        (_status(search=SearchStatus(mode="RTL")), 101.0, ("mode", "mode RTL", 100.0)),
        (_status(search=SearchStatus(mode="SMART_RTL")), 101.0, ("mode", "mode SMART_RTL", 100.0)),
        (_status(search=SearchStatus(mode="LAND")), 101.0, ("mode", "mode LAND", 100.0)),
        (_status(search=SearchStatus(mode="RTGS")), 101.0, ("mode", "mode RTGS", 100.0)),  # PX4's
        (_status(search=SearchStatus(mode="Return")), 101.0, ("mode", "mode RETURN", 100.0)),  # as QGC says it
        (_status(state="ABORTED", reason="pilot takeover LOITER"), 101.0,
         ("aborted", "aborted: pilot takeover LOITER", 100.0)),
        (_status(mission_id="m2"), 101.0, ("moved", "now in mission m2", 100.0)),
        (_status(search=SearchStatus(mode="AUTO")), 131.0, ("silent", "silent for 31 s (over 30 s)", 100.0)),
        (None, 131.0, ("silent", "silent for 41 s (over 30 s)", 90.0)),  # no status kept: its map's time
    ],
)  # fmt: skip
def test_who_has_left_the_search(
    status: VehicleStatus | None, now: float, expected: tuple[str, str, float] | None
) -> None:
    left = leaving("m1", status, 90.0, now, 30.0)
    assert (None if left is None else (left.kind, left.reason, left.since)) == expected


# ---------------------------------------------------------------------------------- the session store
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
        store._redis.flushdb()
    yield store
    store.close()


def test_a_vehicle_going_home_and_one_gone_silent_are_marked_with_their_unflown_parts(
    state: StateStore,
) -> None:
    clock = [1000.0]
    store = SessionStore(state, dropout_s=30.0, clock=lambda: clock[0])
    west, middle, east = _rect(0, 0, 100, 40), _rect(100, 0, 200, 40), _rect(200, 0, 300, 40)
    reports = {
        "d1": SearchStatus(area=west, covered=[_rect(0, 0, 60, 40)], coverage=0.6, mode="AUTO"),
        "d2": SearchStatus(area=middle, covered=[_rect(100, 0, 130, 40)], coverage=0.3, mode="AUTO"),
        "d3": SearchStatus(area=east, covered=[], coverage=0.0, mode="AUTO"),
    }
    for vehicle, search in reports.items():
        store.set_status(vehicle, VehicleStatusIn(mission_id="m1", state="SEARCHING", search=search))
    answer = store.dropouts("m1")
    assert answer is not None and answer.dropouts == [] and answer.searching == ["d1", "d2", "d3"]
    clock[0] = 1010.0
    home = reports["d1"].model_copy(update={"mode": "RTL"})
    store.set_status("d1", VehicleStatusIn(mission_id="m1", state="SEARCHING", search=home))
    clock[0] = 1025.0
    store.set_status("d3", VehicleStatusIn(mission_id="m1", state="SEARCHING", search=reports["d3"]))
    answer = store.dropouts("m1")
    assert answer is not None
    assert [(d.vehicle_id, d.kind, d.reason, d.since) for d in answer.dropouts] == [
        ("d1", "mode", "mode RTL", 1010.0)
    ]
    assert answer.dropouts[0].area_m2 == pytest.approx(1600.0, rel=0.01)
    assert _metres(answer.dropouts[0].unflown).bounds == pytest.approx((60, 0, 100, 40), abs=0.1)
    assert answer.searching == ["d2", "d3"]
    clock[0] = 1031.0  # d2 last reported at 1000
    answer = store.dropouts("m1")
    assert answer is not None
    assert [(d.vehicle_id, d.kind, d.since) for d in answer.dropouts] == [
        ("d1", "mode", 1010.0),
        ("d2", "silent", 1000.0),
    ]
    assert answer.dropouts[1].area_m2 == pytest.approx(2800.0, rel=0.01)  # 70 of its 100 m unflown
    assert answer.searching == ["d3"]
    assert store.dropouts("m9") is None


def test_a_vehicle_that_left_before_reporting_its_part_is_listed_with_its_part_unknown_not_as_none_unflown(
    state: StateStore,
) -> None:
    """drone-3 of a fleet run went home before any status of it carried its search area: listed, its part
    unknown (never "0 m2 unflown", which tells the operator nothing is left), and not as searching."""
    clock = [1000.0]
    store = SessionStore(state, dropout_s=30.0, clock=lambda: clock[0])
    west = _rect(0, 0, 100, 40)
    store.set_status(
        "d1",
        VehicleStatusIn(mission_id="m1", state="SEARCHING", search=SearchStatus(area=west, mode="AUTO")),
    )
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="SEARCHING", search=SearchStatus(mode="AUTO"))
    )
    answer = store.dropouts("m1")
    assert answer is not None and answer.dropouts == [] and answer.searching == ["d1"]
    clock[0] = 1005.0
    store.set_status(
        "d2", VehicleStatusIn(mission_id="m1", state="SEARCHING", search=SearchStatus(mode="RTL"))
    )
    answer = store.dropouts("m1")
    assert answer is not None and answer.searching == ["d1"]
    assert [(d.vehicle_id, d.reason, d.area_known, d.unflown, d.since) for d in answer.dropouts] == [
        ("d2", "mode RTL", False, [], 1005.0)
    ]


# ---------------------------------------------------------------------------------- a real back-end
def _post(url: str, vehicle: str, body: dict[str, Any]) -> None:
    answer = requests.post(
        f"{url}/v1/vehicles/{vehicle}/status",
        json=body,
        headers={"Authorization": f"Bearer {TOKENS[vehicle]}"},
        timeout=10,
    )
    assert answer.status_code == 200, answer.text[:300]


def test_the_back_end_serves_the_dropouts_to_the_supervisor(models_dir: Path) -> None:
    app = create_app(backend_config(models_dir, "fleet.dropout_s=1"))
    west, east = _rect(0, 0, 100, 40), _rect(100, 0, 200, 40)
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    with serve(app) as url:

        def report(
            vehicle: str, area: list[list[float]], covered: list[list[list[float]]], mode: str
        ) -> None:
            search = {"area": area, "covered": covered, "coverage": 0.5, "mode": mode}
            _post(url, vehicle, {"mission_id": "m-43", "state": "SEARCHING", "search": search})

        report("drone-1", west, [_rect(0, 0, 50, 40)], "AUTO")
        report("drone-2", east, [_rect(100, 0, 150, 40)], "AUTO")
        report("drone-1", west, [_rect(0, 0, 50, 40)], "RTL")
        first = requests.get(f"{url}/v1/missions/m-43/dropouts", headers=supervisor, timeout=10)
        assert first.status_code == 200, first.text
        body = first.json()
        assert body["dropout_s"] == 1.0
        assert [(d["vehicle_id"], d["kind"], d["reason"]) for d in body["dropouts"]][:1] == [
            ("drone-1", "mode", "mode RTL")
        ]
        assert body["dropouts"][0]["area_m2"] == pytest.approx(2000.0, rel=0.01)
        assert _metres(body["dropouts"][0]["unflown"]).bounds == pytest.approx((50, 0, 100, 40), abs=0.1)
        # drone-2 says nothing more: the back-end marks it once dropout_s has passed by its own clock.
        deadline = time.monotonic() + 15
        while True:
            body = requests.get(f"{url}/v1/missions/m-43/dropouts", headers=supervisor, timeout=10).json()
            if len(body["dropouts"]) == 2 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert [(d["vehicle_id"], d["kind"]) for d in body["dropouts"]] == [
            ("drone-1", "mode"),
            ("drone-2", "silent"),
        ]
        assert body["dropouts"][1]["area_m2"] == pytest.approx(2000.0, rel=0.01)
        assert body["searching"] == []
        vehicle = {"Authorization": f"Bearer {TOKENS['drone-1']}"}
        assert (
            requests.get(f"{url}/v1/missions/m-43/dropouts", headers=vehicle, timeout=10).status_code == 403
        )
        assert (
            requests.get(f"{url}/v1/missions/m-9/dropouts", headers=supervisor, timeout=10).status_code == 404
        )
