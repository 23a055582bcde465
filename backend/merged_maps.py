"""A mission's merged map, kept per mission and merged again at most once per `[fleet] merge_period_s`.

Merging a mission's map (`backend.mission_merge`) costs about 8 ms of CPU per vehicle (0.4 s at 50): run on
every read of `GET /v1/missions/{m}/map` and every build of the supervisor page's state, it made every
reader wait for the whole fleet, and with 50 vehicles reporting each second it ran all the time. Here one
merge per mission serves every reader (the map endpoint and the page alike):

- a read returns the map kept for the mission, however old, and says when its vehicles' maps were read
  (`MergedMap.as_of`); only the very first read of a mission (nothing kept yet) waits for a merge;
- a read of a map read more than `period_s` ago has it refreshed, off the request and the event loop, by
  one worker thread (`background=True`, what the server uses); a read sooner has its refresh scheduled for
  when the period is over, so the last reports always reach the map;
- a refresh reads the vehicles' maps and merges only if what the merge depends on changed
  (`mission_merge.merge_key`: area, covered area, POD grid; not the track), so a quiet mission costs reads;
- merges of one mission start at least `period_s` apart, and at least twice the last merge's time apart,
  so merging takes at most half of one core however many vehicles report and readers read.

`background=False` (the default, for tests and tools): the refresh runs in the read that finds it due,
the same rules otherwise. `merge`: what merges (the server's runs in a process of its own,
`backend.merge_worker`, so a merge never holds the server's GIL). `merges` counts the merges; `on_merged` is told of each new map (the server wakes
the supervisor pages' streams with it).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from backend.mission_merge import merge_key, merged_map
from backend.schemas import MergedMap, MissionMap

log = logging.getLogger(__name__)

KEEP_UNREAD_S = 600.0  # a mission's map nobody read for this long is forgotten (read again: merged again)

MapsReader = Callable[[str], Sequence[tuple[str, MissionMap]]]
Merge = Callable[[str, Sequence[tuple[str, MissionMap]], float], MergedMap]


@dataclass
class _Kept:
    merged: MergedMap | None = None
    key: tuple[object, ...] | None = None
    checked_at: float = float("-inf")  # when its vehicles' maps were last read
    merge_started: float = float("-inf")
    merge_took_s: float = 0.0
    read_at: float = 0.0
    due: float | None = None  # a refresh scheduled for then
    lock: threading.Lock = field(default_factory=threading.Lock)  # one refresh of the mission at a time


class MergedMaps:
    def __init__(
        self,
        read_maps: MapsReader,
        period_s: float = 2.0,
        clock: Callable[[], float] = time.time,
        background: bool = False,
        on_merged: Callable[[str], None] | None = None,
        merge: Merge | None = None,
    ) -> None:
        self._read_maps = read_maps
        self._merge = merge  # None: `merged_map` here; the server's in a process (backend.merge_worker)
        self.period_s = period_s
        self._clock = clock
        self.background = background
        self.on_merged = on_merged
        self.merges = 0  # merges run so far, all missions
        self.generation = 0  # bumped on every new merged map (the page's snapshot cache keys on it)
        self._kept: dict[str, _Kept] = {}
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._worker: threading.Thread | None = None
        self._stop = False

    # Reading

    def get(self, mission_id: str) -> MergedMap | None:
        """The mission's merged map as kept (None: no vehicle has reported a map of it); see the module doc."""
        now = self._clock()
        with self._lock:
            kept = self._kept.get(mission_id)
            if kept is None:
                self._forget_unread(now)
                kept = self._kept[mission_id] = _Kept()
            kept.read_at = now
            first = kept.checked_at == float("-inf")
        if first or kept.merged is None:
            # Nothing to serve yet (or no map at the last look, which is cheap: no merge): read now.
            self._refresh(mission_id, kept)
            return kept.merged
        due = self._next_due(kept)
        if due <= now:
            if self.background:
                self._schedule(mission_id, kept, now)
            else:
                self._refresh(mission_id, kept)
        elif self.background:
            self._schedule(mission_id, kept, due)
        return kept.merged

    def _next_due(self, kept: _Kept) -> float:
        return max(kept.checked_at + self.period_s, kept.merge_started + 2 * kept.merge_took_s)

    def _forget_unread(self, now: float) -> None:
        for mission in [
            m for m, k in self._kept.items() if now - k.read_at > KEEP_UNREAD_S and k.due is None
        ]:
            del self._kept[mission]

    # Refreshing

    def _refresh(self, mission_id: str, kept: _Kept) -> None:
        with kept.lock:
            now = self._clock()
            if kept.merged is not None and self._next_due(kept) > now:
                # Refreshed meanwhile (by another reader, or while this refresh was scheduled): what was
                # reported since is looked at when the period is over.
                if self.background:
                    self._schedule(mission_id, kept, self._next_due(kept))
                return
            maps = sorted(self._read_maps(mission_id), key=lambda vm: vm[0])
            kept.checked_at = now
            if not maps:
                kept.merged, kept.key = None, None
                return
            key = tuple(merge_key(v, m) for v, m in maps)
            if key == kept.key and kept.merged is not None:
                kept.merged = kept.merged.model_copy(update={"as_of": now})
                return
            started = time.monotonic()
            merge = self._merge or merged_map
            merged = merge(mission_id, maps, max(m.updated_at for _, m in maps))
            kept.merge_took_s = time.monotonic() - started
            kept.merge_started = now
            kept.merged, kept.key = merged.model_copy(update={"as_of": now}), key
            with self._lock:
                self.merges += 1
                self.generation += 1
        if self.on_merged is not None:
            try:
                self.on_merged(mission_id)
            except Exception:
                log.exception("told of mission %s's new map, the listener failed", mission_id)

    def _schedule(self, mission_id: str, kept: _Kept, when: float) -> None:
        with self._lock:
            if kept.due is not None and kept.due <= when:
                return  # one refresh of the mission scheduled is enough
            kept.due = when
            if self._worker is None:
                self._worker = threading.Thread(target=self._work, name="mission-merge", daemon=True)
                self._worker.start()
            self._wake.notify()

    def _work(self) -> None:
        while True:
            with self._lock:
                while True:
                    if self._stop:
                        return
                    now = self._clock()
                    pending = [(k.due, m, k) for m, k in self._kept.items() if k.due is not None]
                    ready = [(d, m, k) for d, m, k in pending if d <= now]
                    if ready:
                        _, mission_id, kept = min(ready, key=lambda p: p[0])
                        kept.due = None
                        break
                    wait = min((d for d, _, _ in pending), default=now + 60.0) - now
                    self._wake.wait(timeout=max(0.01, min(wait, 60.0)))
            try:
                self._refresh(mission_id, kept)
            except Exception:  # the store down for a moment: the map kept is served, the next read retries
                log.exception("merging mission %s's map failed", mission_id)

    def close(self) -> None:
        with self._lock:
            self._stop = True
            self._wake.notify_all()
        if self._worker is not None:
            self._worker.join(timeout=5)
        with self._lock:  # a later read (the store reused by another app) starts a worker again
            self._worker, self._stop = None, False
        close = getattr(self._merge, "close", None)  # a merge worker's process
        if close is not None:
            close()
