"""Fair sharing of the detector between vehicles: round-robin over per-vehicle queues.

A vehicle that floods the back-end waits behind its own requests, not in front of everyone else's:
when a slot frees up it goes to the next vehicle in turn that has a request waiting. Each vehicle may
have only `max_queued_per_key` requests waiting; one more is refused (`QueueFullError`, HTTP 429) -
the companion only needs its newest keyframe answered anyway.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict, deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager


class QueueFullError(Exception):
    pass


class FairScheduler:
    def __init__(self, slots: int, max_queued_per_key: int) -> None:
        self.slots = slots
        self.max_queued_per_key = max_queued_per_key
        self.running = 0
        self._queues: OrderedDict[str, deque[asyncio.Future[None]]] = OrderedDict()

    @property
    def queued(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def _hand_over(self) -> None:
        """Give free slots to waiting requests, one vehicle after another."""
        while self.running < self.slots and self._queues:
            key, queue = next(iter(self._queues.items()))
            self._queues.move_to_end(key)  # this vehicle goes to the back of the round
            future = queue.popleft()
            if not queue:
                del self._queues[key]
            if not future.done():
                self.running += 1
                future.set_result(None)

    @asynccontextmanager
    async def slot(self, key: str) -> AsyncIterator[None]:
        if self.running < self.slots and not self._queues:
            self.running += 1
        else:
            queue = self._queues.get(key)
            if queue is not None and len(queue) >= self.max_queued_per_key:
                raise QueueFullError(f"{key!r} already has {len(queue)} requests waiting")
            future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            self._queues.setdefault(key, deque()).append(future)
            try:
                await future
            except asyncio.CancelledError:
                if future.done() and not future.cancelled():
                    self.running -= 1  # granted just as the client went away: pass the slot on
                    self._hand_over()
                else:
                    queue = self._queues.get(key)
                    if queue is not None and future in queue:
                        queue.remove(future)
                        if not queue:
                            del self._queues[key]
                raise
        try:
            yield
        finally:
            self.running -= 1
            self._hand_over()
