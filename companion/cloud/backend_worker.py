"""Back-end requests off the frame loop: the loop submits keyframes and polls for answers, never waits.

One request is in flight at a time. `submit` never blocks: while a request is running the new keyframe
replaces any keyframe still waiting (the newest one is the useful one) and `submit` returns False.
Answers come back through `poll()`, tagged with the keyframe they refer to so the tracking front-end can
fast-forward from it. `health()` gives what the "lost back-end" watchdog needs: time of the last success,
consecutive failures and the last error.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from behaviors.detection import Detection

log = logging.getLogger(__name__)


class DetectionService(Protocol):
    """The back-end as the companion sees it (`cloudtrack.api_client.BackendClient` implements it).

    `detect` sends one keyframe with the request fields (prompt, superset, frame_id, ...) and returns the
    candidates with boxes in the pixels of `image` as passed; it raises on any failure (timeout, HTTP
    error, bad answer).
    """

    def detect(self, image: np.ndarray, **fields: Any) -> list[Detection]: ...


@dataclass(frozen=True)
class BackendAnswer:
    frame_id: int  # the keyframe the detections refer to
    capture_time: float
    detections: tuple[Detection, ...]
    latency_s: float  # submit to answer
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class WorkerHealth:
    last_success_time: float | None  # clock() of the last answer, None before the first
    consecutive_failures: int
    last_error: str
    busy: bool
    submitted: int
    replaced: int  # keyframes replaced by a newer one before they were sent
    answered: int


@dataclass
class _Request:
    frame_id: int
    image: np.ndarray
    capture_time: float
    fields: dict[str, Any]
    submitted_at: float


class BackendWorker:
    """A background thread that sends keyframes to a DetectionService one at a time."""

    def __init__(self, service: DetectionService, clock: Callable[[], float] = time.monotonic) -> None:
        self._service = service
        self._clock = clock
        self._cond = threading.Condition()
        self._pending: _Request | None = None
        self._answer: BackendAnswer | None = None
        self._busy = False
        self._stopping = False
        self._last_success: float | None = None
        self._failures = 0
        self._last_error = ""
        self._submitted = self._replaced = self._answered = 0
        self._thread = threading.Thread(target=self._run, name="backend-worker", daemon=True)
        self._thread.start()

    def submit(self, frame_id: int, image: np.ndarray, capture_time: float, **fields: Any) -> bool:
        """Queue a keyframe; True if it goes out next, False if a request is still running (it will
        still be sent afterwards unless replaced by a newer keyframe)."""
        request = _Request(frame_id, image, capture_time, dict(fields), self._clock())
        with self._cond:
            if self._stopping:
                return False
            self._submitted += 1
            if self._pending is not None:
                self._replaced += 1
            self._pending = request
            idle = not self._busy
            self._cond.notify_all()
        return idle

    def poll(self) -> BackendAnswer | None:
        """The newest answer not yet taken, or None."""
        with self._cond:
            answer, self._answer = self._answer, None
        return answer

    def health(self) -> WorkerHealth:
        with self._cond:
            return WorkerHealth(
                self._last_success,
                self._failures,
                self._last_error,
                self._busy or self._pending is not None,
                self._submitted,
                self._replaced,
                self._answered,
            )

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until nothing is pending or running (for tools and tests, never the frame loop)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._busy or self._pending is not None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop taking work; a request in flight finishes in the background (its thread is a daemon)."""
        with self._cond:
            self._stopping = True
            self._pending = None
            self._cond.notify_all()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                request, self._pending = self._pending, None
                self._busy = True
            assert request is not None
            try:
                detections = self._service.detect(request.image, frame_id=request.frame_id, **request.fields)
            except Exception as exc:  # any back-end failure is reported, never raised into the loop
                with self._cond:
                    self._failures += 1
                    self._last_error = f"{type(exc).__name__}: {exc}"
                    self._busy = False
                    self._cond.notify_all()
                log.warning("back-end request for frame %d failed: %s", request.frame_id, exc)
                continue
            now = self._clock()
            answer = BackendAnswer(
                request.frame_id,
                request.capture_time,
                tuple(detections),
                now - request.submitted_at,
                request.fields,
            )
            with self._cond:
                self._answer = answer
                self._answered += 1
                self._last_success = now
                self._failures = 0
                self._last_error = ""
                self._busy = False
                self._cond.notify_all()
