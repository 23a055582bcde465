"""The session state in Redis, shared by every replica behind the load balancer (docs/backend.md).

Keys (prefix `ct:`): `mission:<v>:<m>` nothing but its place in the sorted sets `missions` (all, by last
seen: expiry reads only the expired range) and `vmissions:<v>` (one vehicle's, for its quota) and `mvehicles:<m>` (the vehicles searching a mission id, by last seen: the
fleet's mission), `fleet:<m>` hash field -> value (the fleet mission's `on_find` and first `found`);
`cand:<v>:<m>` hash id -> float32 bytes with `candseq:<v>:<m>` ordering them; `rej:<v>:<m>` and
`rejapp:<v>:<m>` lists of rejection records and their appearance bytes; `status` hash vehicle -> record;
`dec:<v>` list of decisions (the newest 1,000; `decdropped:<v>` the highest id dropped from it),
`decided:<v>:<m>` hash candidate -> the supervisor's standing decision (first wins) and `reported:<v>:<m>`
hash candidate -> what the vehicle reported was decided at its GCS (never standing);
`finds:<v>:<m>` hash candidate -> find; `map:<v>:<m>` the mission's map; `keyframe:<v>` and
`keyframemeta:<v>` the newest keyframe (expiring); `ids:rejection`, `ids:decision`, `version` counters;
`rate:<v>:<window>`.
Changes the supervisor page shows are published on `changes` (one subscriber per process).
Durability is the server's: run it with `appendonly yes` and `appendfsync always` (make backend-redis).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import redis

from backend.parsed_records import ParsedRecords
from backend.schemas import KeyframeRecord, MissionMap, StoredFind
from backend.state_store import (
    CANDIDATES_PER_MISSION,
    DECISIONS_KEPT_PER_VEHICLE,
    FINDS_PER_MISSION,
    QuotaExceededError,
    StateStore,
)
from cloudtrack.api_models import Decision, DecisionIn, Rejection, VehicleStatus

PREFIX = "ct:"
CHANNEL = PREFIX + "changes"
KEYFRAME_TTL_S = 600  # a vehicle silent this long shows no picture


class RedisStore(StateStore):
    def __init__(self, url: str, client: redis.Redis | None = None) -> None:
        # Any: redis-py's command types are unions of sync and async results.
        self._redis: Any = client or redis.Redis.from_url(
            url, socket_timeout=5, socket_connect_timeout=5, health_check_interval=30
        )
        self._redis.ping()  # fail at start-up, not on the first request
        self._pubsub: Any = None
        self._pubsub_lock = threading.Lock()
        # Each status and map text parsed once, whichever replica wrote it (backend.parsed_records).
        self._statuses: ParsedRecords[VehicleStatus] = ParsedRecords(VehicleStatus)
        self._maps: ParsedRecords[MissionMap] = ParsedRecords(MissionMap)

    @staticmethod
    def _k(*parts: str) -> str:
        return PREFIX + ":".join(parts)

    def touch_mission(self, vehicle: str, mission: str, now: float, ttl_s: float, max_missions: int) -> None:
        per_vehicle = self._k("vmissions", vehicle)
        member = f"{vehicle}\x00{mission}"
        # WATCH makes the count-then-add one atomic step against other replicas.
        with self._redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(per_vehicle)
                    if pipe.zscore(per_vehicle, mission) is None:
                        live = int(pipe.zcount(per_vehicle, now - ttl_s, "+inf"))
                        if live >= max_missions:
                            oldest = pipe.zrangebyscore(
                                per_vehicle, now - ttl_s, "+inf", start=0, num=1, withscores=True
                            )
                            first = float(oldest[0][1]) if oldest else now
                            raise QuotaExceededError(
                                f"vehicle {vehicle!r} already has {live} live missions (the limit)",
                                first + ttl_s - now,
                            )
                    pipe.multi()
                    pipe.zadd(per_vehicle, {mission: now})
                    pipe.zadd(self._k("missions"), {member: now})
                    pipe.zadd(self._k("mvehicles", mission), {vehicle: now})
                    pipe.execute()
                    return
                except redis.WatchError:
                    continue

    def expire(self, cutoff: float) -> int:
        stale = self._redis.zrangebyscore(self._k("missions"), "-inf", f"({cutoff}")
        for raw in stale:
            vehicle, _, mission = raw.decode().partition("\x00")
            with self._redis.pipeline() as pipe:
                pipe.zrem(self._k("missions"), raw)
                pipe.zrem(self._k("vmissions", vehicle), mission)
                pipe.zrem(self._k("mvehicles", mission), vehicle)
                pipe.zcard(self._k("mvehicles", mission))
                for name in ("cand", "candseq", "rej", "rejapp", "decided", "reported", "finds", "map"):
                    pipe.delete(self._k(name, vehicle, mission))
                left = pipe.execute()[3]
            if int(left) == 0:  # the fleet's settings go with the mission's last vehicle
                self._redis.delete(self._k("fleet", mission))
        return len(stale)

    def mission_vehicles(self, mission: str, limit: int) -> list[str]:
        if limit < 1:
            return []
        return [v.decode() for v in self._redis.zrevrange(self._k("mvehicles", mission), 0, limit - 1)]

    def set_fleet(self, mission: str, field: str, value: str) -> str:
        key = self._k("fleet", mission)
        with self._redis.pipeline(transaction=True) as pipe:  # HSETNX: the first value stands
            pipe.hsetnx(key, field, value)
            pipe.hget(key, field)
            _, kept = pipe.execute()
        return str(kept.decode())

    def fleet(self, mission: str) -> dict[str, str]:
        return {k.decode(): v.decode() for k, v in self._redis.hgetall(self._k("fleet", mission)).items()}

    def mission_rejections(
        self, mission: str, vehicles: list[str], limit: int
    ) -> list[tuple[Rejection, bytes]]:
        if not vehicles or limit < 1:
            return []
        each = max(1, limit // len(vehicles))
        with self._redis.pipeline(transaction=True) as pipe:  # one round trip for the whole fleet
            for vehicle in vehicles:
                pipe.lrange(self._k("rej", vehicle, mission), -each, -1)
                pipe.lrange(self._k("rejapp", vehicle, mission), -each, -1)
            values = pipe.execute()
        return [
            (Rejection.model_validate_json(r), bytes(v))
            for records, vectors in zip(values[::2], values[1::2], strict=True)
            for r, v in zip(records, vectors, strict=False)
        ]

    def put_candidates(self, vehicle: str, mission: str, items: list[tuple[str, bytes]]) -> None:
        if not items:
            return
        cand, seq = self._k("cand", vehicle, mission), self._k("candseq", vehicle, mission)
        now = time.time()
        with self._redis.pipeline() as pipe:
            pipe.hset(cand, mapping=dict(items))
            pipe.zadd(seq, {cid: now + i * 1e-6 for i, (cid, _) in enumerate(items)})
            pipe.zrange(seq, 0, -(CANDIDATES_PER_MISSION + 1))
            *_, dropped = pipe.execute()
        if dropped:
            with self._redis.pipeline() as pipe:
                pipe.hdel(cand, *dropped)
                pipe.zrem(seq, *dropped)
                pipe.execute()

    def candidate(self, vehicle: str, mission: str, candidate_id: str) -> bytes | None:
        value = self._redis.hget(self._k("cand", vehicle, mission), candidate_id)
        return bytes(value) if value is not None else None

    def add_rejection(
        self, vehicle: str, mission: str, record: Rejection, appearance: bytes, limit: int
    ) -> Rejection:
        records, vectors = self._k("rej", vehicle, mission), self._k("rejapp", vehicle, mission)
        with self._redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(records)
                    count = int(pipe.llen(records))
                    if count >= limit:
                        raise QuotaExceededError(
                            f"mission {mission!r} of {vehicle!r} holds {count} rejections (the limit)", 60
                        )
                    stored = record.model_copy(
                        update={"rejection_id": int(self._redis.incr(self._k("ids", "rejection")))}
                    )
                    pipe.multi()
                    pipe.rpush(records, stored.model_dump_json())
                    pipe.rpush(vectors, appearance)
                    pipe.execute()
                    return stored
                except redis.WatchError:
                    continue

    def rejections(self, vehicle: str, mission: str) -> list[tuple[Rejection, bytes]]:
        with self._redis.pipeline(transaction=True) as pipe:
            pipe.lrange(self._k("rej", vehicle, mission), 0, -1)
            pipe.lrange(self._k("rejapp", vehicle, mission), 0, -1)
            records, vectors = pipe.execute()
        return [(Rejection.model_validate_json(r), bytes(v)) for r, v in zip(records, vectors, strict=False)]

    def _changed(self, pipe: Any) -> None:
        pipe.incr(self._k("version"))
        pipe.publish(CHANNEL, b"1")

    def set_status(self, status: VehicleStatus) -> None:
        text = status.model_dump_json().encode()  # as redis-py reads it back
        with self._redis.pipeline() as pipe:
            pipe.hset(self._k("status"), status.vehicle_id, text)
            self._changed(pipe)
            pipe.execute()
        self._statuses.remember(status.vehicle_id, text, status)

    def status(self, vehicle: str) -> VehicleStatus | None:
        value = self._redis.hget(self._k("status"), vehicle)
        return self._statuses.parsed(vehicle, value) if value is not None else None

    def statuses(self) -> list[VehicleStatus]:
        values = self._redis.hgetall(self._k("status"))
        return sorted(
            (self._statuses.parsed(_text(k), v) for k, v in values.items()), key=lambda s: s.vehicle_id
        )

    def set_mission_map(self, vehicle: str, mission: str, record: MissionMap) -> None:
        text = record.model_dump_json().encode()
        self._redis.set(self._k("map", vehicle, mission), text)
        self._maps.remember((vehicle, mission), text, record)

    def mission_map(self, vehicle: str, mission: str) -> MissionMap | None:
        value = self._redis.get(self._k("map", vehicle, mission))
        return self._maps.parsed((vehicle, mission), value) if value is not None else None

    def add_decision(
        self,
        vehicle: str,
        mission: str | None,
        decision: DecisionIn,
        created_at: float,
        source: str = "supervisor",
    ) -> tuple[Decision, bool]:
        vehicle_report = source == "vehicle"
        decided = self._k("reported" if vehicle_report else "decided", vehicle, mission or "")
        listed, dropped_key = self._k("dec", vehicle), self._k("decdropped", vehicle)
        # WATCH: two replicas deciding on one candidate at once; the second's EXEC fails, it reads the first's.
        with self._redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(decided, listed)
                    value = pipe.hget(decided, decision.candidate_id)
                    standing = Decision.model_validate_json(value) if value is not None else None
                    # A vehicle's report an earlier version kept as the standing decision gives way.
                    if standing is not None and (vehicle_report or standing.source != "vehicle"):
                        pipe.unwatch()
                        return standing, False
                    # The newest DECISIONS_KEPT_PER_VEHICLE stay listed; the highest id dropped is remembered.
                    over = int(pipe.llen(listed)) + 1 - DECISIONS_KEPT_PER_VEHICLE
                    leaving = (
                        [Decision.model_validate_json(v) for v in pipe.lrange(listed, 0, over - 1)]
                        if over > 0
                        else []
                    )
                    record = Decision(
                        decision_id=int(self._redis.incr(self._k("ids", "decision"))),
                        vehicle_id=vehicle,
                        mission_id=mission,
                        created_at=created_at,
                        source=source,
                        **decision.model_dump(),
                    )
                    highest = max((d.decision_id for d in leaving), default=0)
                    highest = max(highest, int(pipe.get(dropped_key) or 0))
                    pipe.multi()
                    pipe.hset(decided, decision.candidate_id, record.model_dump_json())
                    pipe.rpush(listed, record.model_dump_json())
                    pipe.ltrim(listed, -DECISIONS_KEPT_PER_VEHICLE, -1)
                    if highest:
                        pipe.set(dropped_key, highest)
                    self._changed(pipe)
                    pipe.execute()
                    return record, True
                except redis.WatchError:
                    continue

    def standing_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        value = self._redis.hget(self._k("decided", vehicle, mission or ""), candidate_id)
        standing = Decision.model_validate_json(value) if value is not None else None
        return standing if standing is not None and standing.source != "vehicle" else None

    def reported_decision(self, vehicle: str, mission: str | None, candidate_id: str) -> Decision | None:
        value = self._redis.hget(self._k("reported", vehicle, mission or ""), candidate_id)
        if value is None:  # kept as the standing decision by an earlier version
            earlier = self._redis.hget(self._k("decided", vehicle, mission or ""), candidate_id)
            value = (
                earlier
                if earlier is not None and Decision.model_validate_json(earlier).source == "vehicle"
                else None
            )
        return Decision.model_validate_json(value) if value is not None else None

    def decisions_dropped(self, vehicle: str) -> int:
        return int(self._redis.get(self._k("decdropped", vehicle)) or 0)

    def put_find(self, find: StoredFind, replace_source: str | None = None) -> tuple[StoredFind, bool]:
        key = self._k("finds", find.vehicle_id, find.mission_id)
        with self._redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    existing = pipe.hget(key, find.candidate_id)
                    if existing is not None:
                        kept = StoredFind.model_validate_json(existing)
                        if kept.source != replace_source:
                            pipe.unwatch()
                            return kept, False
                    elif int(pipe.hlen(key)) >= FINDS_PER_MISSION:
                        pipe.unwatch()
                        raise QuotaExceededError(
                            f"mission {find.mission_id!r} of {find.vehicle_id!r} holds {FINDS_PER_MISSION} finds "
                            "(the limit)",
                            60,
                        )
                    pipe.multi()
                    pipe.hset(key, find.candidate_id, find.model_dump_json())
                    self._changed(pipe)
                    pipe.execute()
                    return find, True
                except redis.WatchError:
                    continue

    def finds(self, vehicle: str, mission: str | None = None) -> list[StoredFind]:
        if mission is not None:
            missions = [mission]
        else:
            missions = [m.decode() for m in self._redis.zrange(self._k("vmissions", vehicle), 0, -1)]
        with self._redis.pipeline(transaction=False) as pipe:
            for m in missions:
                pipe.hvals(self._k("finds", vehicle, m))
            values = pipe.execute()
        found = [StoredFind.model_validate_json(v) for group in values for v in group]
        return sorted(found, key=lambda f: f.time)

    def set_keyframe(self, vehicle: str, record: KeyframeRecord, jpeg: bytes) -> None:
        with self._redis.pipeline() as pipe:
            pipe.set(self._k("keyframe", vehicle), jpeg, ex=KEYFRAME_TTL_S)
            pipe.set(self._k("keyframemeta", vehicle), record.model_dump_json(), ex=KEYFRAME_TTL_S)
            self._changed(pipe)
            pipe.execute()

    def keyframe(self, vehicle: str) -> KeyframeRecord | None:
        value = self._redis.get(self._k("keyframemeta", vehicle))
        return KeyframeRecord.model_validate_json(value) if value is not None else None

    def keyframe_jpeg(self, vehicle: str) -> tuple[KeyframeRecord, bytes] | None:
        with self._redis.pipeline(transaction=True) as pipe:
            pipe.get(self._k("keyframemeta", vehicle))
            pipe.get(self._k("keyframe", vehicle))
            meta, jpeg = pipe.execute()
        if meta is None or jpeg is None:
            return None
        return KeyframeRecord.model_validate_json(meta), bytes(jpeg)

    def decisions(self, vehicle: str, after: int = 0) -> list[Decision]:
        records = [
            Decision.model_validate_json(r) for r in self._redis.lrange(self._k("dec", vehicle), 0, -1)
        ]
        return [d for d in records if d.decision_id > after]

    def rate_hit(self, vehicle: str, now: float, limit: int, window_s: float) -> float | None:
        window = math.floor(now / window_s)
        key = self._k("rate", vehicle, str(window))
        with self._redis.pipeline() as pipe:
            pipe.incr(key)
            pipe.expire(key, max(1, math.ceil(window_s)) + 1)
            count, _ = pipe.execute()
        return None if int(count) <= limit else (window + 1) * window_s - now

    def version(self) -> int:
        return int(self._redis.get(self._k("version")) or 0)

    def wait_change(self, last: int, timeout_s: float) -> int:
        """Blocks on the `changes` channel (one subscription per store), not on polling."""
        with self._pubsub_lock:
            if self._pubsub is None:
                self._pubsub = self._redis.pubsub(ignore_subscribe_messages=True)
                self._pubsub.subscribe(CHANNEL)
            current = self.version()
            if current != last:
                return current
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                message = self._pubsub.get_message(timeout=max(0.01, deadline - time.monotonic()))
                if message is not None:
                    # Drain what else arrived: one wake-up for a burst of changes.
                    while self._pubsub.get_message(timeout=0) is not None:
                        pass
                    break
            return self.version()

    def close(self) -> None:
        with self._pubsub_lock:
            if self._pubsub is not None:
                self._pubsub.close()
        self._redis.close()


def _text(key: bytes | str) -> str:
    """A hash field's name as stored: redis-py reads bytes (str with decode_responses)."""
    return key.decode() if isinstance(key, bytes) else key
