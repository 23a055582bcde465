"""Issue 43 item 5: the server merges a mission's map in a worker process (`backend.merge_worker`), so that a
merge never holds the server's GIL; the map is the one merged in the server, and a worker that cannot run
costs a merge nothing (it runs in the server then). Its store parses a status or map text once
(`backend.parsed_records`): what a read returns is what was written, also after another writer's change."""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from typing import Any

import pytest

from backend import merge_worker
from backend.merge_worker import MergeWorker
from backend.mission_merge import merged_map
from backend.schemas import MissionMap
from backend.sessions import SessionStore
from backend.state_store import SqliteStore
from cloudtrack.api_models import VehicleStatusIn

LAT, LON = 47.3977, 8.5456
D = 0.0009


def _maps(n: int) -> list[tuple[str, MissionMap]]:
    maps = []
    for i in range(n):
        west = LON + i * D
        area = [[LAT, west], [LAT, west + D], [LAT + D, west + D], [LAT + D, west]]
        covered = [[area[0], area[1], [LAT + D / 2, west + D], [LAT + D / 2, west]]]
        maps.append((f"d{i}", MissionMap(area=area, covered=covered, coverage=0.5, updated_at=1.0)))
    return maps


def test_a_merge_in_the_worker_process_is_the_merge_in_the_server() -> None:
    maps = _maps(3)
    worker = MergeWorker()
    try:
        merged = worker("m-1", maps, 5.0)
        assert merged == merged_map("m-1", maps, 5.0)
        assert worker._pool is not None  # a process of its own, kept for the next merge
        assert worker("m-1", maps[:1], 6.0) == merged_map("m-1", maps[:1], 6.0)
    finally:
        worker.close()
    assert worker._pool is None


def test_a_worker_that_cannot_start_or_dies_costs_no_merge(monkeypatch: Any) -> None:
    maps = _maps(2)

    def no_process(*args: Any, **kwargs: Any) -> Any:
        raise OSError("no processes here")

    monkeypatch.setattr(merge_worker, "ProcessPoolExecutor", no_process)
    assert MergeWorker()("m-1", maps, 5.0) == merged_map("m-1", maps, 5.0)

    class Broken(concurrent.futures.ProcessPoolExecutor):
        def submit(self, *args: Any, **kwargs: Any) -> Any:
            raise concurrent.futures.process.BrokenProcessPool("the worker died")

    monkeypatch.setattr(merge_worker, "ProcessPoolExecutor", Broken)
    worker = MergeWorker()
    assert worker("m-1", maps, 5.0) == merged_map("m-1", maps, 5.0)
    assert worker._pool is None  # the next merge tries a new worker


def test_a_read_returns_what_was_written_last_whoever_wrote_it(tmp_path: Any) -> None:
    path = tmp_path / "s.sqlite3"
    mine, theirs = SqliteStore(path), SqliteStore(path)  # two processes' stores on one file, as it were
    store = SessionStore(mine)
    body = {"mission_id": "m-1", "state": "SEARCHING", "position": [LAT, LON]}
    store.set_status("d1", VehicleStatusIn.model_validate(body))
    first = mine.status("d1")
    assert first is not None and first.position == [LAT, LON]
    assert mine.status("d1") is first  # parsed once: the same text read again
    changed = first.model_copy(update={"position": [LAT + D, LON], "updated_at": first.updated_at + 1})
    theirs.set_status(changed)
    again = mine.status("d1")
    assert again is not None and again.position == [LAT + D, LON]  # the text read decides
    assert [s.position for s in mine.statuses()] == [[LAT + D, LON]]
    kept = mine.mission_map("d1", "m-1")
    assert kept is not None and kept.track[-1][:2] == [LAT, LON]
    theirs.set_mission_map("d1", "m-1", kept.model_copy(update={"coverage": 0.25}))
    read = mine.mission_map("d1", "m-1")
    assert read is not None and read.coverage == 0.25


@pytest.fixture(autouse=True)
def _no_worker_left() -> Any:
    yield
    for child in multiprocessing.active_children():
        child.join(timeout=5)
