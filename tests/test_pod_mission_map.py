"""The back-end keeps each mission's POD map beside its search area, durable like the finds (SQLite across a
reopen without close, as a SIGKILL leaves it; Redis shared by a second replica), and keeps the map of an
area the mission's survey was replaced by as an earlier area (the last `EARLIER_AREAS_KEPT`). The grids are
real `PodMap` reports. Select: -k pod_mission_map."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from backend.mission_map import EARLIER_AREAS_KEPT, updated_map
from backend.redis_store import RedisStore
from backend.sessions import SessionStore
from backend.state_store import SqliteStore
from backend_tools.fleet_services import RedisServer
from cloudtrack.api_models import PodGrid, SearchStatus, VehicleStatusIn
from tests.pod_fixtures import AREA, NEXT_AREA, pod_report

COVERED = [[[47.3970, 8.5450], [47.3980, 8.5450], [47.3980, 8.5453], [47.3970, 8.5453]]]


def _search(area: list[list[float]], pod: dict[str, Any] | None, coverage: float = 0.3) -> SearchStatus:
    return SearchStatus(
        area=area, coverage=coverage, covered=COVERED, pod=PodGrid.model_validate(pod) if pod else None
    )


def test_pod_mission_map_keeps_the_grid_and_moves_a_replaced_area_to_the_earlier_ones() -> None:
    first, more = pod_report(lanes=1), pod_report(lanes=3)
    start = updated_map(None, [47.397, 8.545], _search(AREA, first), 10.0)
    assert start is not None and start.pod == PodGrid.model_validate(first) and start.area_since == 10.0
    grown = updated_map(start, None, _search(AREA, more, 0.5), 11.0)
    assert grown is not None and grown.pod is not None and grown.pod.looks == more["looks"]
    # A status without a grid says nothing of it: the area keeps the one it has.
    kept = updated_map(grown, None, _search(AREA, None, 0.5), 12.0)
    assert kept is None  # nothing changed
    # The survey is replaced: the old area goes, with its covered area and grid, to the earlier ones.
    replaced = updated_map(grown, None, _search(NEXT_AREA, None, 0.0), 20.0)
    assert replaced is not None
    assert replaced.area == NEXT_AREA and replaced.pod is None and replaced.coverage == 0.0
    assert replaced.area_since == 20.0 and replaced.track == grown.track
    (earlier,) = replaced.earlier
    assert earlier.area == AREA and earlier.pod == grown.pod and earlier.coverage == 0.5
    assert earlier.covered == COVERED and (earlier.since, earlier.replaced_at) == (10.0, 20.0)
    # Only the last few areas are kept.
    current = replaced
    for i in range(EARLIER_AREAS_KEPT + 2):
        area = [[lat + 0.001 * (i + 1), lon] for lat, lon in NEXT_AREA]
        changed = updated_map(current, None, _search(area, first), 30.0 + i)
        assert changed is not None
        current = changed
    assert len(current.earlier) == EARLIER_AREAS_KEPT
    assert current.earlier[-1].replaced_at == 30.0 + EARLIER_AREAS_KEPT + 1
    # Kept: the last 8 of 11 (the first area, the one without a grid, and the first shifted one went).
    assert [e.replaced_at for e in current.earlier] == [32.0 + i for i in range(EARLIER_AREAS_KEPT)]
    assert all(e.pod is not None for e in current.earlier)


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer() as server:
        yield server


def _fly_two_areas(sessions: SessionStore) -> None:
    for area, lanes in ((AREA, 2), (NEXT_AREA, 1)):
        status = VehicleStatusIn(
            mission_id="m-pod",
            state="SEARCHING",
            position=[area[0][0], area[0][1]],
            search=_search(area, pod_report(area, lanes)),
        )
        sessions.set_status("drone-1", status)


def _assert_two_areas(sessions: SessionStore) -> None:
    kept = sessions.mission_map("drone-1", "m-pod")
    assert kept is not None and kept.area == NEXT_AREA
    assert kept.pod == PodGrid.model_validate(pod_report(NEXT_AREA, 1))
    (earlier,) = kept.earlier
    assert earlier.area == AREA and earlier.pod == PodGrid.model_validate(pod_report(AREA, 2))


def test_pod_mission_map_survives_a_sqlite_reopen_without_close(tmp_path: Path) -> None:
    path = tmp_path / "sessions.sqlite3"
    _fly_two_areas(SessionStore(SqliteStore(path)))
    _assert_two_areas(SessionStore(SqliteStore(path)))  # no close(): what a SIGKILL leaves behind


def test_pod_mission_map_is_shared_by_replicas_on_one_redis(redis_server: RedisServer) -> None:
    writer = RedisStore(redis_server.url)
    writer._redis.flushdb()
    _fly_two_areas(SessionStore(writer))
    reader = RedisStore(redis_server.url)
    try:
        _assert_two_areas(SessionStore(reader))
    finally:
        reader.close()
        writer.close()
