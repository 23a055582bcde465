"""A mission's merge in a process of its own, so that it never holds the server's GIL.

One merge of 50 vehicles' maps costs about half a second of CPU (`backend.mission_merge`), most of it Python
and shapely calls that keep the GIL. In the server's merge thread (`backend.merged_maps`) it made the event
loop and every request thread take turns with it: while a merge ran, a vehicle's status report waited for
the GIL at each step. Here the merge runs in one worker process (started on the first merge, with "spawn":
the server's threads are not forked), and the server's thread only waits on it. A worker that cannot be
started or dies is reported and the merge runs in the calling thread instead (and a new worker is tried on
the next merge): a map is never lost for it.
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor

from backend.mission_merge import merged_map
from backend.schemas import MergedMap, MissionMap

log = logging.getLogger(__name__)

MERGE_TIMEOUT_S = 60.0  # a merge taking longer than this is given up and run here (the worker is replaced)


class MergeWorker:
    """`merged_map` in a worker process; callable as `merged_map` is."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def __call__(self, mission_id: str, maps: Sequence[tuple[str, MissionMap]], now: float) -> MergedMap:
        pool = self._worker()
        if pool is not None:
            try:
                return pool.submit(merged_map, mission_id, list(maps), now).result(MERGE_TIMEOUT_S)
            except Exception:  # a dead or hung worker: this merge runs here, the next gets a new worker
                log.exception("the merge worker failed on mission %s; merging in the server", mission_id)
                self._discard(pool)
        return merged_map(mission_id, maps, now)

    def _worker(self) -> ProcessPoolExecutor | None:
        with self._lock:
            if self._pool is None:
                try:
                    self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
                except (OSError, ValueError):
                    log.exception("no merge worker process; merging in the server")
            return self._pool

    def _discard(self, pool: ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is pool:
                self._pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        """Stop the worker (a later merge starts another: the store may serve another app)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
