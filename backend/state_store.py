"""Where the back-end's session state lives: one interface, two stores.

`SqliteStore` (the default): one file in WAL mode for a single server; every write is committed with
`synchronous=FULL` before the call returns, so what the API acknowledged survives a SIGKILL or a power cut.
`RedisStore` (backend/redis_store.py): the state shared by several replicas behind a load balancer.

Missions are keyed by (vehicle, mission): MAVLink mission ids are 0-255, so two vehicles meet on the same
id by accident. Appearance vectors are stored as float32 bytes. Expiry touches only what expired (an
index on last_seen), never every mission. `version()` grows with every change the supervisor page shows
(statuses, decisions); `wait_change` is what one watcher per process blocks on (SQLite: polls the
counter; Redis: pub/sub).
"""

from __future__ import annotations

import math
import sqlite3
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from backend.parsed_records import ParsedRecords
from backend.schemas import KeyframeRecord, MissionMap, StoredFind
from cloudtrack.api_models import Decision, DecisionIn, Rejection, VehicleStatus
from cloudtrack.private_files import private_dir, private_file

CANDIDATES_PER_MISSION = 500
DECISIONS_KEPT_PER_VEHICLE = 1000
FINDS_PER_MISSION = 20


class QuotaExceededError(Exception):
    """A vehicle's quota is used up; `retry_after_s` says when to try again (HTTP 429 + Retry-After)."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__(message)
        self.retry_after_s = max(1.0, math.ceil(retry_after_s))


def vector_bytes(values: Iterable[float]) -> bytes:
    return np.asarray(list(values), np.float32).tobytes()


def vector_from(data: bytes) -> list[float]:
    return [float(v) for v in np.frombuffer(data, np.float32)]


class StateStore(ABC):
    """The operations the session logic needs; each one is atomic on its own."""

    @abstractmethod
    def touch_mission(self, vehicle: str, mission: str, now: float, ttl_s: float, max_missions: int) -> None:
        """Mark (vehicle, mission) alive; a new mission beyond `max_missions` live ones: QuotaExceededError."""

    @abstractmethod
    def expire(self, cutoff: float) -> int:
        """Forget missions last seen before `cutoff` (their candidates and rejections); how many."""

    @abstractmethod
    def mission_vehicles(self, mission: str, limit: int) -> list[str]:
        """The vehicles with a live search of this mission id (one mission of the fleet), the most recently
        seen first, at most `limit`."""

    @abstractmethod
    def set_fleet(self, mission: str, field: str, value: str) -> str:
        """Set the fleet mission's `field` ("on_find": what the fleet does on a confirmed find; "found": the
        first find, "<vehicle>/<candidate>") unless it is set already: the first value stands and is
        returned. Forgotten with the mission's last vehicle."""

    @abstractmethod
    def fleet(self, mission: str) -> dict[str, str]:
        """The fleet mission's fields set so far."""

    @abstractmethod
    def mission_rejections(
        self, mission: str, vehicles: list[str], limit: int
    ) -> list[tuple[Rejection, bytes]]:
        """The newest rejections of these vehicles' searches of the mission: at most `limit` (Redis: the
        newest limit / len(vehicles), at least one, of each vehicle)."""

    @abstractmethod
    def put_candidates(self, vehicle: str, mission: str, items: list[tuple[str, bytes]]) -> None: ...

    @abstractmethod
    def candidate(self, vehicle: str, mission: str, candidate_id: str) -> bytes | None: ...

    @abstractmethod
    def add_rejection(
        self, vehicle: str, mission: str, record: Rejection, appearance: bytes, limit: int
    ) -> Rejection:
        """Store it under a new rejection_id; the mission's `limit`-th + 1 rejection: QuotaExceededError."""

    @abstractmethod
    def rejections(self, vehicle: str, mission: str) -> list[tuple[Rejection, bytes]]: ...

    @abstractmethod
    def set_status(self, status: VehicleStatus) -> None: ...

    @abstractmethod
    def status(self, vehicle: str) -> VehicleStatus | None: ...

    @abstractmethod
    def statuses(self) -> list[VehicleStatus]: ...

    @abstractmethod
    def set_mission_map(self, vehicle: str, mission: str, record: MissionMap) -> None: ...

    @abstractmethod
    def mission_map(self, vehicle: str, mission: str) -> MissionMap | None: ...

    @abstractmethod
    def add_decision(
        self,
        vehicle: str,
        mission: str | None,
        decision: DecisionIn,
        created_at: float,
        source: str = "supervisor",
    ) -> tuple[Decision, bool]:
        """A supervisor's decision: the first on (vehicle, mission, candidate) wins, stored durably under a
        new decision_id before returning (created: True); when one stands already, that one (created:
        False). A vehicle's report of a decision taken at its GCS (source "vehicle") is kept in the vehicle's
        list and as its report on the candidate (the first report stays, created False for a repeat), never
        as the standing decision: what a vehicle says blocks no supervisor's decision. Atomic against
        concurrent callers, also across replicas."""

    @abstractmethod
    def standing_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        """The supervisor's decision that stands on the candidate (a vehicle's report is none)."""

    @abstractmethod
    def reported_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        """What the vehicle reported was decided on the candidate at its GCS (the first report)."""

    @abstractmethod
    def decisions(self, vehicle: str, after: int = 0) -> list[Decision]: ...

    @abstractmethod
    def decisions_dropped(self, vehicle: str) -> int:
        """The highest decision_id dropped from the vehicle's list (the oldest beyond
        DECISIONS_KEPT_PER_VEHICLE go); 0 when none was. Standing decisions are kept apart and never dropped."""

    @abstractmethod
    def put_find(self, find: StoredFind, replace_source: str | None = None) -> tuple[StoredFind, bool]:
        """Store a find once per (vehicle, mission, candidate) (changed: True); an existing one stays and is
        returned, unless its `source` is `replace_source`. At most FINDS_PER_MISSION per mission."""

    @abstractmethod
    def finds(self, vehicle: str, mission: str | None = None) -> list[StoredFind]:
        """A vehicle's finds (of one mission, or of all its live missions), oldest first."""

    @abstractmethod
    def set_keyframe(self, vehicle: str, record: KeyframeRecord, jpeg: bytes) -> None:
        """The vehicle's newest keyframe (not precious: kept in memory or with an expiry)."""

    @abstractmethod
    def keyframe(self, vehicle: str) -> KeyframeRecord | None: ...

    @abstractmethod
    def keyframe_jpeg(self, vehicle: str) -> tuple[KeyframeRecord, bytes] | None: ...

    @abstractmethod
    def rate_hit(self, vehicle: str, now: float, limit: int, window_s: float) -> float | None:
        """Count one request; None when within `limit` per fixed window, else seconds until the next window."""

    @abstractmethod
    def version(self) -> int:
        """A counter that grows with every status or decision change."""

    def wait_change(self, last: int, timeout_s: float) -> int:
        """Block until version() differs from `last` or `timeout_s` passes; the current version."""
        deadline = time.monotonic() + timeout_s
        while True:
            current = self.version()
            if current != last or time.monotonic() >= deadline:
                return current
            time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))

    def close(self) -> None:  # noqa: B027 - optional for stores without resources
        pass


_SCHEMA = """
CREATE TABLE IF NOT EXISTS missions (
    vehicle TEXT NOT NULL, mission TEXT NOT NULL, last_seen REAL NOT NULL, PRIMARY KEY (vehicle, mission));
CREATE INDEX IF NOT EXISTS missions_by_age ON missions (last_seen);
CREATE INDEX IF NOT EXISTS missions_by_id ON missions (mission, last_seen);
CREATE TABLE IF NOT EXISTS candidates (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, vehicle TEXT NOT NULL, mission TEXT NOT NULL,
    candidate_id TEXT NOT NULL, appearance BLOB NOT NULL, UNIQUE (vehicle, mission, candidate_id));
CREATE TABLE IF NOT EXISTS rejections (
    rejection_id INTEGER PRIMARY KEY AUTOINCREMENT, vehicle TEXT NOT NULL, mission TEXT NOT NULL,
    record TEXT NOT NULL, appearance BLOB NOT NULL);
CREATE INDEX IF NOT EXISTS rejections_by_mission ON rejections (vehicle, mission);
CREATE TABLE IF NOT EXISTS statuses (vehicle TEXT PRIMARY KEY, record TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS decisions (
    decision_id INTEGER PRIMARY KEY AUTOINCREMENT, vehicle TEXT NOT NULL, record TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS decisions_by_vehicle ON decisions (vehicle, decision_id);
CREATE TABLE IF NOT EXISTS decided (
    vehicle TEXT NOT NULL, mission TEXT NOT NULL, candidate_id TEXT NOT NULL, record TEXT NOT NULL,
    PRIMARY KEY (vehicle, mission, candidate_id));
CREATE TABLE IF NOT EXISTS reported (
    vehicle TEXT NOT NULL, mission TEXT NOT NULL, candidate_id TEXT NOT NULL, record TEXT NOT NULL,
    PRIMARY KEY (vehicle, mission, candidate_id));
CREATE TABLE IF NOT EXISTS finds (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, vehicle TEXT NOT NULL, mission TEXT NOT NULL,
    candidate_id TEXT NOT NULL, record TEXT NOT NULL, UNIQUE (vehicle, mission, candidate_id));
CREATE TABLE IF NOT EXISTS mission_maps (
    vehicle TEXT NOT NULL, mission TEXT NOT NULL, record TEXT NOT NULL, PRIMARY KEY (vehicle, mission));
CREATE TABLE IF NOT EXISTS fleet (
    mission TEXT NOT NULL, field TEXT NOT NULL, value TEXT NOT NULL, PRIMARY KEY (mission, field));
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
INSERT OR IGNORE INTO counters VALUES ('version', 0);
"""


@dataclass
class _Writes:
    """One caller's statements for the committer, and how their commit went."""

    statements: list[tuple[str, tuple[object, ...]]]
    done: threading.Event = field(default_factory=threading.Event)
    error: Exception | None = None


class SqliteStore(StateStore):
    """The state in one SQLite file (WAL, synchronous=FULL); ":memory:" for a throw-away store."""

    def __init__(self, path: str | Path = ":memory:") -> None:
        self.path = str(path)
        if self.path != ":memory:":
            # Decisions, rejections and positions are the operator's alone, whatever the umask: the file
            # is created 0600 in a 0700 folder, and SQLite gives its -wal and -shm the file's mode.
            db = Path(self.path)
            private_dir(db.parent)
            private_file(db)
            for suffix in ("-wal", "-shm", "-journal"):  # left by an earlier run, maybe wider
                side = db.with_name(db.name + suffix)
                if side.exists():
                    private_file(side)
        # One connection for the writes, used under a lock: handlers run on a thread pool.
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10)
        self._lock = threading.Lock()
        # Reads of a file go through a connection of each thread's own (WAL: a reader waits neither for the
        # writer nor for other readers). Through the one connection under its lock, a fleet's request
        # threads queued behind each other's every read, each hold stretched by waits for the GIL: at 50
        # vehicles reporting each second that queue was most of a report's time.
        self._readers = threading.local()
        self._reader_connections: list[sqlite3.Connection] = []
        with self._lock:
            if self.path != ":memory:":
                self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")  # a commit is on disk before the API answers
            self._db.executescript(_SCHEMA)
        # Rate windows: one server, so in memory, under their own lock (never waiting on a commit's fsync).
        self._windows: dict[str, tuple[float, int]] = {}
        self._windows_lock = threading.Lock()
        # The newest keyframe per vehicle: one server, and nothing lost in a restart, so in memory too.
        self._keyframes: dict[str, tuple[KeyframeRecord, bytes]] = {}
        self._memory_changes = 0
        # Statuses and maps are read far more often than written (every report reads its vehicle's back,
        # every build of the page all of them): each text is parsed once (backend.parsed_records).
        self._statuses: ParsedRecords[VehicleStatus] = ParsedRecords(VehicleStatus)
        self._maps: ParsedRecords[MissionMap] = ParsedRecords(MissionMap)
        # Writes queued for the committer thread (`_write`).
        self._pending: list[_Writes] = []
        self._pending_lock = threading.Condition()
        self._committer: threading.Thread | None = None
        self._closing = False

    def _write(self, sql_and_params: list[tuple[str, tuple[object, ...]]]) -> None:
        """The statements in one transaction, committed before this returns. In a file, with the writes other
        threads queued meanwhile: one commit (one fsync) for all of them, by one committer thread. A fleet's
        reports wrote a status and a map each, 100 commits a second at 50 vehicles, each holding the lock
        through its fsync and its turns for the GIL: every report queued behind all the others."""
        writes = _Writes(sql_and_params)
        if self.path == ":memory:":  # nothing to sync: as it comes
            self._commit([writes])
        else:
            with self._pending_lock:
                if self._closing:
                    raise sqlite3.ProgrammingError("Cannot operate on a closed database.")
                if self._committer is None:
                    self._committer = threading.Thread(
                        target=self._commit_pending, name="sqlite-commit", daemon=True
                    )
                    self._committer.start()
                self._pending.append(writes)
                self._pending_lock.notify()
            writes.done.wait()
        if writes.error is not None:
            raise writes.error

    def _commit_pending(self) -> None:
        while True:
            with self._pending_lock:
                while not self._pending and not self._closing:
                    self._pending_lock.wait()
                if not self._pending:
                    return
                group, self._pending = self._pending, []
            self._commit(group)

    def _commit(self, group: list[_Writes]) -> None:
        try:
            with self._lock:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    for writes in group:
                        for sql, params in writes.statements:
                            self._db.execute(sql, params)
                except BaseException:
                    self._db.execute("ROLLBACK")
                    raise
                self._db.execute("COMMIT")
        except Exception as exc:
            if len(group) > 1:  # one caller's failing statement is its own: the others commit alone
                for writes in group:
                    self._commit([writes])
                return
            group[0].error = exc
        for writes in group:
            writes.done.set()

    def _read(self, sql: str, params: tuple[object, ...] = ()) -> list[tuple[Any, ...]]:
        if self.path == ":memory:":  # one database per connection: read it through the writer's
            with self._lock:
                return list(self._db.execute(sql, params).fetchall())
        return list(self._reader().execute(sql, params).fetchall())

    def _reader(self) -> sqlite3.Connection:
        reader: sqlite3.Connection | None = getattr(self._readers, "db", None)
        if reader is None:
            # check_same_thread off only so that close() can close it; it is used by its thread alone.
            reader = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10)
            reader.execute("PRAGMA query_only=ON")
            with self._lock:
                self._reader_connections.append(reader)
            self._readers.db = reader
        return reader

    def touch_mission(self, vehicle: str, mission: str, now: float, ttl_s: float, max_missions: int) -> None:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                known = self._db.execute(
                    "SELECT 1 FROM missions WHERE vehicle = ? AND mission = ?", (vehicle, mission)
                ).fetchone()
                if known is None:
                    live, oldest = self._db.execute(
                        "SELECT count(*), min(last_seen) FROM missions WHERE vehicle = ? AND last_seen >= ?",
                        (vehicle, now - ttl_s),
                    ).fetchone()
                    if live >= max_missions:
                        raise QuotaExceededError(
                            f"vehicle {vehicle!r} already has {live} live missions (the limit)",
                            oldest + ttl_s - now,
                        )
                self._db.execute(
                    "INSERT INTO missions VALUES (?, ?, ?) ON CONFLICT (vehicle, mission) DO UPDATE SET last_seen = ?",
                    (vehicle, mission, now, now),
                )
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def expire(self, cutoff: float) -> int:
        with self._lock:
            stale = self._db.execute(
                "SELECT vehicle, mission FROM missions WHERE last_seen < ?", (cutoff,)
            ).fetchall()
            if not stale:
                return 0
            self._db.execute("BEGIN IMMEDIATE")
            for vehicle, mission in stale:
                for table in (
                    "missions",
                    "candidates",
                    "rejections",
                    "decided",
                    "reported",
                    "finds",
                    "mission_maps",
                ):
                    self._db.execute(
                        f"DELETE FROM {table} WHERE vehicle = ? AND mission = ?", (vehicle, mission)
                    )
                self._db.execute(  # the fleet's settings go with the mission's last vehicle
                    "DELETE FROM fleet WHERE mission = ? AND NOT EXISTS (SELECT 1 FROM missions WHERE mission = ?)",
                    (mission, mission),
                )
            self._db.execute("COMMIT")
            return len(stale)

    def mission_vehicles(self, mission: str, limit: int) -> list[str]:
        rows = self._read(
            "SELECT vehicle FROM missions WHERE mission = ? ORDER BY last_seen DESC, vehicle LIMIT ?",
            (mission, limit),
        )
        return [str(v) for (v,) in rows]

    def set_fleet(self, mission: str, field: str, value: str) -> str:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.execute("INSERT OR IGNORE INTO fleet VALUES (?, ?, ?)", (mission, field, value))
                (kept,) = self._db.execute(
                    "SELECT value FROM fleet WHERE mission = ? AND field = ?", (mission, field)
                ).fetchone()
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")
            return str(kept)

    def fleet(self, mission: str) -> dict[str, str]:
        return {
            str(f): str(v)
            for f, v in self._read("SELECT field, value FROM fleet WHERE mission = ?", (mission,))
        }

    def mission_rejections(
        self, mission: str, vehicles: list[str], limit: int
    ) -> list[tuple[Rejection, bytes]]:
        if not vehicles or limit < 1:
            return []
        marks = ", ".join("?" * len(vehicles))
        rows = self._read(
            f"SELECT record, appearance FROM rejections WHERE mission = ? AND vehicle IN ({marks}) "
            "ORDER BY rejection_id DESC LIMIT ?",
            (mission, *vehicles, limit),
        )
        return [(Rejection.model_validate_json(str(r)), bytes(a)) for r, a in rows]

    def put_candidates(self, vehicle: str, mission: str, items: list[tuple[str, bytes]]) -> None:
        if not items:
            return
        statements: list[tuple[str, tuple[object, ...]]] = [
            (
                "INSERT OR REPLACE INTO candidates (vehicle, mission, candidate_id, appearance) VALUES (?, ?, ?, ?)",
                (vehicle, mission, cid, blob),
            )
            for cid, blob in items
        ]
        statements.append(
            (
                "DELETE FROM candidates WHERE vehicle = ? AND mission = ? AND seq NOT IN "
                "(SELECT seq FROM candidates WHERE vehicle = ? AND mission = ? ORDER BY seq DESC LIMIT ?)",
                (vehicle, mission, vehicle, mission, CANDIDATES_PER_MISSION),
            )
        )
        self._write(statements)

    def candidate(self, vehicle: str, mission: str, candidate_id: str) -> bytes | None:
        rows = self._read(
            "SELECT appearance FROM candidates WHERE vehicle = ? AND mission = ? AND candidate_id = ?",
            (vehicle, mission, candidate_id),
        )
        return bytes(rows[0][0]) if rows else None

    def add_rejection(
        self, vehicle: str, mission: str, record: Rejection, appearance: bytes, limit: int
    ) -> Rejection:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                (count,) = self._db.execute(
                    "SELECT count(*) FROM rejections WHERE vehicle = ? AND mission = ?", (vehicle, mission)
                ).fetchone()
                if count >= limit:
                    raise QuotaExceededError(
                        f"mission {mission!r} of {vehicle!r} holds {count} rejections (the limit)", 60
                    )
                cursor = self._db.execute(
                    "INSERT INTO rejections (vehicle, mission, record, appearance) VALUES (?, ?, '', ?)",
                    (vehicle, mission, appearance),
                )
                stored = record.model_copy(update={"rejection_id": cursor.lastrowid})
                self._db.execute(
                    "UPDATE rejections SET record = ? WHERE rejection_id = ?",
                    (stored.model_dump_json(), cursor.lastrowid),
                )
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")
            return stored

    def rejections(self, vehicle: str, mission: str) -> list[tuple[Rejection, bytes]]:
        rows = self._read(
            "SELECT record, appearance FROM rejections WHERE vehicle = ? AND mission = ? ORDER BY rejection_id",
            (vehicle, mission),
        )
        return [(Rejection.model_validate_json(str(r)), bytes(a)) for r, a in rows]

    def set_status(self, status: VehicleStatus) -> None:
        text = status.model_dump_json()
        self._write(
            [
                ("INSERT OR REPLACE INTO statuses VALUES (?, ?)", (status.vehicle_id, text)),
                ("UPDATE counters SET value = value + 1 WHERE name = 'version'", ()),
            ]
        )
        self._statuses.remember(status.vehicle_id, text, status)

    def status(self, vehicle: str) -> VehicleStatus | None:
        rows = self._read("SELECT record FROM statuses WHERE vehicle = ?", (vehicle,))
        return self._statuses.parsed(vehicle, str(rows[0][0])) if rows else None

    def statuses(self) -> list[VehicleStatus]:
        return [
            self._statuses.parsed(str(v), str(r))
            for v, r in self._read("SELECT vehicle, record FROM statuses ORDER BY vehicle")
        ]

    def set_mission_map(self, vehicle: str, mission: str, record: MissionMap) -> None:
        text = record.model_dump_json()
        self._write([("INSERT OR REPLACE INTO mission_maps VALUES (?, ?, ?)", (vehicle, mission, text))])
        self._maps.remember((vehicle, mission), text, record)

    def mission_map(self, vehicle: str, mission: str) -> MissionMap | None:
        rows = self._read(
            "SELECT record FROM mission_maps WHERE vehicle = ? AND mission = ?", (vehicle, mission)
        )
        return self._maps.parsed((vehicle, mission), str(rows[0][0])) if rows else None

    def add_decision(
        self,
        vehicle: str,
        mission: str | None,
        decision: DecisionIn,
        created_at: float,
        source: str = "supervisor",
    ) -> tuple[Decision, bool]:
        key = (vehicle, mission or "", decision.candidate_id)
        table = "reported" if source == "vehicle" else "decided"
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")  # the check and the insert in one write transaction
            try:
                row = self._db.execute(
                    f"SELECT record FROM {table} WHERE vehicle = ? AND mission = ? AND candidate_id = ?", key
                ).fetchone()
                standing = Decision.model_validate_json(str(row[0])) if row is not None else None
                # A vehicle's report a store of an earlier version kept as the standing decision gives way.
                if standing is not None and (table == "reported" or standing.source != "vehicle"):
                    self._db.execute("ROLLBACK")
                    return standing, False
                cursor = self._db.execute(
                    "INSERT INTO decisions (vehicle, record) VALUES (?, '')", (vehicle,)
                )
                record = Decision(
                    decision_id=int(cursor.lastrowid or 0),
                    vehicle_id=vehicle,
                    mission_id=mission,
                    created_at=created_at,
                    source=source,
                    **decision.model_dump(),
                )
                self._db.execute(
                    "UPDATE decisions SET record = ? WHERE decision_id = ?",
                    (record.model_dump_json(), record.decision_id),
                )
                self._db.execute(
                    f"INSERT OR REPLACE INTO {table} VALUES (?, ?, ?, ?)", (*key, record.model_dump_json())
                )
                # The newest DECISIONS_KEPT_PER_VEHICLE stay listed; the highest id dropped is remembered.
                dropped = self._db.execute(
                    "SELECT decision_id FROM decisions WHERE vehicle = ? ORDER BY decision_id DESC LIMIT 1 OFFSET ?",
                    (vehicle, DECISIONS_KEPT_PER_VEHICLE),
                ).fetchone()
                if dropped is not None:
                    self._db.execute(
                        "DELETE FROM decisions WHERE vehicle = ? AND decision_id <= ?", (vehicle, dropped[0])
                    )
                    self._db.execute(
                        "INSERT INTO counters VALUES (?, ?) ON CONFLICT (name) DO UPDATE "
                        "SET value = max(value, excluded.value)",
                        (f"dropped:{vehicle}", dropped[0]),
                    )
                self._db.execute("UPDATE counters SET value = value + 1 WHERE name = 'version'")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")
            return record, True

    def _kept_decision(
        self, table: str, vehicle: str, mission: str | None, candidate_id: str
    ) -> Decision | None:
        rows = self._read(
            f"SELECT record FROM {table} WHERE vehicle = ? AND mission = ? AND candidate_id = ?",
            (vehicle, mission or "", candidate_id),
        )
        return Decision.model_validate_json(str(rows[0][0])) if rows else None

    def standing_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        standing = self._kept_decision("decided", vehicle, mission, candidate_id)
        return standing if standing is not None and standing.source != "vehicle" else None

    def reported_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        reported = self._kept_decision("reported", vehicle, mission, candidate_id)
        if reported is None:  # kept as the standing decision by an earlier version
            earlier = self._kept_decision("decided", vehicle, mission, candidate_id)
            reported = earlier if earlier is not None and earlier.source == "vehicle" else None
        return reported

    def decisions(self, vehicle: str, after: int = 0) -> list[Decision]:
        rows = self._read(
            "SELECT record FROM decisions WHERE vehicle = ? AND decision_id > ? ORDER BY decision_id",
            (vehicle, after),
        )
        return [Decision.model_validate_json(str(r)) for (r,) in rows]

    def decisions_dropped(self, vehicle: str) -> int:
        rows = self._read("SELECT value FROM counters WHERE name = ?", (f"dropped:{vehicle}",))
        return int(rows[0][0]) if rows else 0

    def put_find(self, find: StoredFind, replace_source: str | None = None) -> tuple[StoredFind, bool]:
        key = (find.vehicle_id, find.mission_id, find.candidate_id)
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                row = self._db.execute(
                    "SELECT record FROM finds WHERE vehicle = ? AND mission = ? AND candidate_id = ?", key
                ).fetchone()
                if row is not None:
                    kept = StoredFind.model_validate_json(str(row[0]))
                    if kept.source != replace_source:
                        self._db.execute("ROLLBACK")
                        return kept, False
                    self._db.execute(
                        "UPDATE finds SET record = ? WHERE vehicle = ? AND mission = ? AND candidate_id = ?",
                        (find.model_dump_json(), *key),
                    )
                else:
                    (count,) = self._db.execute(
                        "SELECT count(*) FROM finds WHERE vehicle = ? AND mission = ?", key[:2]
                    ).fetchone()
                    if count >= FINDS_PER_MISSION:
                        raise QuotaExceededError(
                            f"mission {find.mission_id!r} of {find.vehicle_id!r} holds {count} finds (the limit)",
                            60,
                        )
                    self._db.execute(
                        "INSERT INTO finds (vehicle, mission, candidate_id, record) VALUES (?, ?, ?, ?)",
                        (*key, find.model_dump_json()),
                    )
                self._db.execute("UPDATE counters SET value = value + 1 WHERE name = 'version'")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")
            return find, True

    def finds(self, vehicle: str, mission: str | None = None) -> list[StoredFind]:
        if mission is None:
            rows = self._read("SELECT record FROM finds WHERE vehicle = ? ORDER BY seq", (vehicle,))
        else:
            rows = self._read(
                "SELECT record FROM finds WHERE vehicle = ? AND mission = ? ORDER BY seq", (vehicle, mission)
            )
        return sorted((StoredFind.model_validate_json(str(r)) for (r,) in rows), key=lambda f: f.time)

    def set_keyframe(self, vehicle: str, record: KeyframeRecord, jpeg: bytes) -> None:
        with self._lock:
            self._keyframes[vehicle] = (record, jpeg)
            self._memory_changes += 1

    def keyframe(self, vehicle: str) -> KeyframeRecord | None:
        with self._lock:
            kept = self._keyframes.get(vehicle)
        return kept[0] if kept else None

    def keyframe_jpeg(self, vehicle: str) -> tuple[KeyframeRecord, bytes] | None:
        with self._lock:
            return self._keyframes.get(vehicle)

    def rate_hit(self, vehicle: str, now: float, limit: int, window_s: float) -> float | None:
        with self._windows_lock:
            start = math.floor(now / window_s) * window_s
            opened, count = self._windows.get(vehicle, (start, 0))
            if opened != start:
                opened, count = start, 0
            count += 1
            self._windows[vehicle] = (opened, count)
        return None if count <= limit else opened + window_s - now

    def version(self) -> int:
        rows = self._read("SELECT value FROM counters WHERE name = 'version'")
        return int(rows[0][0]) + self._memory_changes  # both only grow

    def close(self) -> None:
        with self._pending_lock:  # what is queued is committed first
            self._closing = True
            self._pending_lock.notify()
            committer = self._committer
        if committer is not None:
            committer.join()
        with self._lock:
            self._db.close()
            for reader in self._reader_connections:
                reader.close()
            self._reader_connections.clear()
