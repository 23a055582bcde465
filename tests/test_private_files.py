"""The back-end's session store and the companion's flight record are their owner's alone (0600 files in
0700 folders) whatever the umask of whoever started the process (issue 31; systemd's UMask=0027 hid it)."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from backend.state_store import SqliteStore
from cloudtrack.api_models import DecisionIn, VehicleStatus
from companion.flight_record import FlightRecorder


@pytest.fixture
def loose_umask() -> Iterator[None]:
    """The common interactive umask, under which files come out world-readable (0644, 0755)."""
    previous = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(previous)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_sqlite_store_and_its_wal_are_private(tmp_path: Path, loose_umask: None) -> None:
    db = tmp_path / "state" / "cloudtrack" / "sessions.sqlite3"
    store = SqliteStore(db)
    store.set_status(VehicleStatus(vehicle_id="d1", updated_at=1.0, state="SEARCH", position=[47.0, 8.0]))
    store.add_decision("d1", "m1", DecisionIn(candidate_id="c1", action="reject"), 2.0)
    files = {p.name: _mode(p) for p in db.parent.iterdir()}
    assert {"sessions.sqlite3", "sessions.sqlite3-wal", "sessions.sqlite3-shm"} <= set(files), files
    assert set(files.values()) == {0o600}, {n: oct(m) for n, m in files.items()}
    assert _mode(db.parent) == 0o700 and _mode(db.parent.parent) == 0o700  # the folders it created
    store.close()


def test_a_store_left_world_readable_is_narrowed(tmp_path: Path, loose_umask: None) -> None:
    db = tmp_path / "sessions.sqlite3"
    SqliteStore(db).close()
    for path in tmp_path.iterdir():
        path.chmod(0o644)
    before = _mode(tmp_path)
    SqliteStore(db).close()
    assert {p.name: _mode(p) for p in tmp_path.iterdir()} == {p.name: 0o600 for p in tmp_path.iterdir()}
    assert _mode(tmp_path) == before  # not ours to change (it may be /tmp)


def test_flight_record_events_keyframes_and_tlogs_are_private(tmp_path: Path, loose_umask: None) -> None:
    root = tmp_path / "records"
    record = FlightRecorder(root, "drone-1", "m-7", max_bytes=10_000_000)
    record.event("state", state="SEARCH")
    relative = record.keyframe(b"\xff\xd8\xff\xe0 not really a jpeg", 12)
    record.mavlink(b"\xfd" + bytes(20))
    record.close()
    assert relative is not None
    folders = [root, record.folder, record.folder / "keyframes"]
    assert [oct(_mode(f)) for f in folders] == [oct(0o700)] * 3
    files = sorted(p for p in record.folder.rglob("*") if p.is_file())
    assert {p.name for p in files} >= {"events.jsonl", "000012.jpg", "mavlink-000.tlog"}
    assert {p.name: oct(_mode(p)) for p in files} == {p.name: oct(0o600) for p in files}
