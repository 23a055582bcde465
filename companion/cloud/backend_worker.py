"""Back-end requests off the frame loop: the loop submits keyframes and polls for answers, never waits.

At most `max_in_flight` requests are out at a time ([backend] max_requests_in_flight), each on its own
thread (the client keeps one HTTP session per thread). A hosted VLM answers in about 2 s; with one request
out, a keyframe every second would be answered every 2 s, halving the evidence the re-initialisation
policy waits for. `submit` never blocks: while every slot is busy the new keyframe replaces any keyframe
still waiting (the newest one is the useful one) and `submit` returns False. Answers come back through
`poll()`, oldest first, tagged with the keyframe they refer to so the tracking front-end can fast-forward
from it. A request with `early_answer=True` is asked twice in its slot: first for the back-end's fast
stage (its local verifier, answered while a hosted VLM still thinks), posted with `final=False`, then in
full; a back-end without a slower stage answers the first in full and the second is not sent.
`health()` gives what the "lost back-end" watchdog needs: time of the last success, consecutive failures
and the last error.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
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

    def detect_early(self, image: np.ndarray, **fields: Any) -> tuple[list[Detection], bool]:
        """As `detect` with the back-end's fast stage only; also whether the answer is final (no slower
        stage exists)."""
        ...


@dataclass(frozen=True)
class BackendAnswer:
    frame_id: int  # the keyframe the detections refer to
    capture_time: float
    detections: tuple[Detection, ...]
    latency_s: float  # submit to answer
    fields: dict[str, Any] = field(default_factory=dict)
    final: bool = True  # false: the fast stage's verdicts; the final answer to the same keyframe follows


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
    """Background threads that send keyframes to a DetectionService, at most `max_in_flight` at a time."""

    def __init__(
        self,
        service: DetectionService,
        clock: Callable[[], float] = time.monotonic,
        max_in_flight: int = 1,
        on_result: Callable[[BaseException | None], None] | None = None,
    ) -> None:
        """`on_result(None)` after each answer, `on_result(error)` after each failure (the operator's
        notices say why, once)."""
        self._on_result = on_result
        if max_in_flight < 1:
            raise ValueError("max_in_flight must be at least 1")
        self._service = service
        self._clock = clock
        self._cond = threading.Condition()
        self._pending: deque[_Request] = deque()  # keyframes not yet taken by a thread, oldest first
        self._answers: deque[BackendAnswer] = deque(maxlen=4 * max_in_flight)  # bounded: oldest dropped
        self._in_flight = 0
        self.max_in_flight = max_in_flight
        self._stopping = False
        self._last_success: float | None = None
        self._failures = 0
        self._last_error = ""
        self._submitted = self._replaced = self._answered = 0
        self._threads = [
            threading.Thread(target=self._run, name=f"backend-worker-{i}", daemon=True)
            for i in range(max_in_flight)
        ]
        for thread in self._threads:
            thread.start()

    def submit(self, frame_id: int, image: np.ndarray, capture_time: float, **fields: Any) -> bool:
        """Queue a keyframe; True if it goes out now, False if every slot is busy (it will still be sent
        when one frees unless replaced by a newer keyframe)."""
        request = _Request(frame_id, image, capture_time, dict(fields), self._clock())
        with self._cond:
            if self._stopping:
                return False
            self._submitted += 1
            self._pending.append(request)
            # As many wait as there are free slots, at least the newest one; older ones are replaced.
            while len(self._pending) > max(1, self.max_in_flight - self._in_flight):
                self._pending.popleft()
                self._replaced += 1
            idle = self._in_flight < self.max_in_flight
            self._cond.notify_all()
        return idle

    def poll(self) -> BackendAnswer | None:
        """The oldest answer not yet taken, or None."""
        with self._cond:
            return self._answers.popleft() if self._answers else None

    def health(self) -> WorkerHealth:
        with self._cond:
            return WorkerHealth(
                self._last_success,
                self._failures,
                self._last_error,
                self._in_flight > 0 or bool(self._pending),
                self._submitted,
                self._replaced,
                self._answered,
            )

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until nothing is pending or running (for tools and tests, never the frame loop)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._in_flight > 0 or self._pending:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop taking work; requests in flight finish in the background (their threads are daemons)."""
        with self._cond:
            self._stopping = True
            self._pending.clear()
            self._cond.notify_all()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                request = self._pending.popleft()
                self._in_flight += 1
            early = bool(request.fields.get("early_answer"))
            fields = {k: v for k, v in request.fields.items() if k != "early_answer"}
            final = not early
            try:
                if early:
                    detections, final = self._service.detect_early(
                        request.image, frame_id=request.frame_id, **fields
                    )
                    if not final:
                        self._post(request, detections, final=False)
                        detections = self._service.detect(request.image, frame_id=request.frame_id, **fields)
                        final = True
                else:
                    detections = self._service.detect(request.image, frame_id=request.frame_id, **fields)
            except Exception as exc:  # any back-end failure is reported, never raised into the loop
                with self._cond:
                    self._failures += 1
                    self._last_error = f"{type(exc).__name__}: {exc}"
                    self._in_flight -= 1
                    self._cond.notify_all()
                log.debug("back-end request for frame %d failed: %s", request.frame_id, exc)
                if self._on_result is not None:
                    self._on_result(exc)
                continue
            self._post(request, detections, final=final, done=True)
            if self._on_result is not None:
                self._on_result(None)

    def _post(self, request: _Request, detections: list[Detection], final: bool, done: bool = False) -> None:
        now = self._clock()
        answer = BackendAnswer(
            request.frame_id,
            request.capture_time,
            tuple(detections),
            now - request.submitted_at,
            request.fields,
            final,
        )
        with self._cond:
            self._answers.append(answer)
            self._answered += 1
            self._last_success = now
            self._failures = 0
            self._last_error = ""
            if done:
                self._in_flight -= 1
            self._cond.notify_all()
