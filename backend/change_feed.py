"""One watcher per process turns session-store changes into wake-ups for every open supervisor stream.

A daemon thread blocks in `StateStore.wait_change` (Redis: pub/sub; SQLite: reads a change counter a few
times a second) and wakes the streams waiting in `wait`, so a hundred open pages cost one watcher, not a
hundred pollers. Changes made by another replica arrive the same way, through the shared store.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading

from backend.state_store import StateStore

log = logging.getLogger(__name__)


class ChangeFeed:
    # One wait on the store lasts at most max_wait_s: stop() (at every shutdown) waits for it to end, and a
    # change wakes the watcher at once whatever its length, so short waits cost only an idle version read.
    def __init__(self, store: StateStore, max_wait_s: float = 0.25) -> None:
        self._store = store
        self._max_wait_s = max_wait_s
        self._lock = threading.Lock()
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.version = 0

    def start(self) -> ChangeFeed:
        self.version = self._store.version()
        self._thread = threading.Thread(target=self._watch, name="change-feed", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self._max_wait_s + 1)

    def _watch(self) -> None:
        while not self._stop.is_set():
            try:
                current = self._store.wait_change(self.version, self._max_wait_s)
            except Exception as exc:  # the store is down for a moment: the streams keep their last state
                log.warning("session store change watch failed: %s", exc)
                self._stop.wait(1.0)
                continue
            if current != self.version:
                self.version = current
                with self._lock:
                    waiters, self._waiters = self._waiters, []
                for loop, event in waiters:
                    loop.call_soon_threadsafe(event.set)

    def poke(self) -> None:
        """Wake every waiting stream without a store change: a mission's map was merged anew in this process
        (backend.merged_maps), off the request that read it; the streams build the page's state again."""
        with self._lock:
            waiters, self._waiters = self._waiters, []
        for loop, event in waiters:
            with contextlib.suppress(RuntimeError):  # that stream's loop is closed
                loop.call_soon_threadsafe(event.set)

    async def wait(self, last: int, timeout_s: float) -> int:
        """The version once it differs from `last`, or after `timeout_s`."""
        if self.version != last:
            return self.version
        event = asyncio.Event()
        with self._lock:
            self._waiters.append((asyncio.get_running_loop(), event))
        if self.version != last:  # changed while we registered
            return self.version
        try:
            await asyncio.wait_for(event.wait(), timeout_s)
        except asyncio.TimeoutError:
            with self._lock:
                self._waiters = [w for w in self._waiters if w[1] is not event]
        return self.version
