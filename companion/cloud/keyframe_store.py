"""Keyframes kept while the back-end is unreachable, to be sent when it answers again.

A search keyframe the back-end never analysed leaves its place unsearched on the POD map; one taken over a
person is a find lost. So the back-end worker (`companion.cloud.backend_worker`) keeps each full-frame
search keyframe whose request failed for want of a back-end here, JPEG-encoded exactly as it goes on the
wire, with the vehicle's pose when it was captured (a stored keyframe's answer comes back long after the
40 s of telemetry the main loop keeps). Bounded by bytes (`[backend] outage_store_mb`, the JPEG bytes) and
by age (`[backend] outage_store_max_age_s`, from capture): past either the oldest go first, counted. The
newest are sent first: the freshest search area is where a person seen is still nearest.

Thread-safe: the worker's threads put and take, the main loop reads the counts.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from behaviors.telemetry import Telemetry
from cloudtrack.api_client import EncodedKeyframe


@dataclass(frozen=True)
class StoredKeyframe:
    frame_id: int
    capture_time: float  # on the store's clock (the frames' monotonic clock)
    keyframe: EncodedKeyframe
    pose: Telemetry  # the vehicle when the keyframe was captured
    fields: dict[str, Any] = field(default_factory=dict)  # the request's fields (prompt, mission, query)
    mean_luma: float | None = None  # the keyframe's (cloudtrack.keyframe_light), for the map's low-light rule

    @property
    def size_bytes(self) -> int:
        return len(self.keyframe.jpeg)


@dataclass(frozen=True)
class StoreCounts:
    """Since the store was made: `stored` put in (each keyframe once), `sent` answered after the link came
    back, `dropped` given up (oldest first past a bound, or refused by the back-end when sent); `waiting`
    and `bytes` are in the store now (taken ones, out on a request, are in neither)."""

    stored: int = 0
    waiting: int = 0
    sent: int = 0
    dropped: int = 0
    bytes: int = 0


class KeyframeStore:
    def __init__(self, max_bytes: int, max_age_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if max_bytes < 1 or max_age_s <= 0:
            raise ValueError("the keyframe store needs max_bytes >= 1 and max_age_s > 0")
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self._clock = clock
        self._lock = threading.Lock()
        self._kept: list[StoredKeyframe] = []  # by capture time, oldest first
        self._bytes = 0
        self._stored = self._sent = self._dropped = 0

    def put(self, keyframe: StoredKeyframe) -> None:
        """Keep a keyframe the back-end could not be asked about (the oldest go past a bound)."""
        with self._lock:
            self._stored += 1
            self._insert(keyframe)

    def put_back(self, keyframe: StoredKeyframe) -> None:
        """A stored keyframe whose request failed again for want of a back-end: it waits again."""
        with self._lock:
            self._insert(keyframe)

    def take_newest(self) -> StoredKeyframe | None:
        """The newest keyframe in the store, taken out (`sent` or `put_back` or `refused` follows)."""
        with self._lock:
            self._expire()
            if not self._kept:
                return None
            keyframe = self._kept.pop()
            self._bytes -= keyframe.size_bytes
            return keyframe

    def sent(self) -> None:
        """A taken keyframe was answered."""
        with self._lock:
            self._sent += 1

    def refused(self) -> None:
        """A taken keyframe was refused by the back-end (not for want of it): it is given up."""
        with self._lock:
            self._dropped += 1

    def __len__(self) -> int:
        with self._lock:
            self._expire()
            return len(self._kept)

    def counts(self) -> StoreCounts:
        with self._lock:
            self._expire()
            return StoreCounts(self._stored, len(self._kept), self._sent, self._dropped, self._bytes)

    def _insert(self, keyframe: StoredKeyframe) -> None:
        bisect.insort(self._kept, keyframe, key=lambda k: k.capture_time)
        self._bytes += keyframe.size_bytes
        self._expire()

    def _expire(self) -> None:
        """Drop the oldest while past the byte or the age bound."""
        oldest_kept = self._clock() - self.max_age_s
        while self._kept and (self._bytes > self.max_bytes or self._kept[0].capture_time < oldest_kept):
            gone = self._kept.pop(0)
            self._bytes -= gone.size_bytes
            self._dropped += 1
