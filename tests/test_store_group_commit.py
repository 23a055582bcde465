"""Issue 43 item 5: a fleet's writes to the SQLite store are committed together (one commit, one fsync, for
the writes queued meanwhile, `SqliteStore._write`), each still on disk before its call returns; a write
that fails fails its own caller only; reads go through each thread's own connection and see every write
that returned."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest

from backend.state_store import SqliteStore
from cloudtrack.api_models import VehicleStatus


def _status(vehicle: str, n: int) -> VehicleStatus:
    return VehicleStatus(vehicle_id=vehicle, updated_at=float(n), state="SEARCHING", reason=f"report {n}")


def test_writes_of_many_threads_are_all_kept_and_each_read_back_at_once(tmp_path: Path) -> None:
    path = tmp_path / "s.sqlite3"
    store = SqliteStore(path)
    errors: list[str] = []

    def vehicle(i: int) -> None:
        for n in range(20):
            store.set_status(_status(f"v{i}", n))
            read = store.status(f"v{i}")  # another connection than the writer's: the write is visible
            if read is None or read.updated_at != float(n):
                errors.append(f"v{i} read {read} after report {n}")

    threads = [threading.Thread(target=vehicle, args=(i,)) for i in range(16)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    version = store.version()
    store.close()
    again = SqliteStore(path)  # what the calls acknowledged is in the file
    assert [s.updated_at for s in again.statuses()] == [19.0] * 16
    assert again.version() == version == 16 * 20
    again.close()


def test_a_failing_write_fails_its_caller_only(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "s.sqlite3")
    failed: list[Exception] = []
    start = threading.Barrier(9)

    def bad() -> None:
        start.wait()
        try:
            store._write([("INSERT INTO no_such_table VALUES (?)", (1,))])
        except sqlite3.Error as exc:
            failed.append(exc)

    def good(i: int) -> None:
        start.wait()
        store.set_status(_status(f"v{i}", 1))

    threads = [threading.Thread(target=bad), *(threading.Thread(target=good, args=(i,)) for i in range(8))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(failed) == 1 and "no_such_table" in str(failed[0])
    assert len(store.statuses()) == 8
    store.close()
    with pytest.raises(sqlite3.ProgrammingError):
        store.set_status(_status("v0", 2))
