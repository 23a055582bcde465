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

With a `KeyframeStore`, outages lose nothing: a keyframe submitted with its capture-time `pose` (a
full-frame search keyframe) whose request fails for want of a back-end (refused, reset, timed out, 5xx,
429; not a 4xx refusal of the request itself) is encoded on the failing thread and kept; while the
back-end stays unreachable one request at a time tries the link and other such keyframes go straight into
the store. Once a request succeeds again, stored keyframes are sent newest first, only when no live
keyframe waits and never on the last free slot (with `max_in_flight` 1: on the one slot when no live
keyframe waits); their answers come back marked `stored`, with the pose.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np

from behaviors.detection import Detection
from behaviors.telemetry import Telemetry
from cloudtrack.api_client import BackendError, EncodedKeyframe
from cloudtrack.keyframe_light import mean_luma
from companion.cloud.keyframe_store import KeyframeStore, StoredKeyframe

log = logging.getLogger(__name__)


class DetectionService(Protocol):
    """The back-end as the companion sees it (`cloudtrack.api_client.BackendClient` implements it).

    `detect` sends one keyframe with the request fields (prompt, superset, frame_id, ...) and returns the
    candidates with boxes in the pixels of `image` as passed; it raises on any failure (timeout, HTTP
    error, bad answer).
    """

    def detect(self, image: np.ndarray | EncodedKeyframe, **fields: Any) -> list[Detection]: ...

    def detect_early(
        self, image: np.ndarray | EncodedKeyframe, **fields: Any
    ) -> tuple[list[Detection], bool]:
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
    pose: Telemetry | None = None  # the vehicle at capture time, as submitted
    stored: bool = False  # the keyframe waited out a back-end outage in the store
    # A stored keyframe's pixels (the caller's size) when its answer has candidates: the live ones are gone.
    image: np.ndarray | None = None
    mean_luma: float | None = None  # a search keyframe's (cloudtrack.keyframe_light): too dark, no POD


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
    image: np.ndarray | EncodedKeyframe
    capture_time: float
    fields: dict[str, Any]
    submitted_at: float
    pose: Telemetry | None = None  # given: a full-frame search keyframe, kept through an outage
    stored: StoredKeyframe | None = None  # sent from the store
    mean_luma: float | None = None

    @property
    def storable(self) -> bool:
        return self.pose is not None and self.stored is None and self.fields.get("roi") is None


def unreachable(error: BaseException) -> bool:
    """A failure for want of a back-end (the same request may succeed later), not a refusal of the request."""
    if isinstance(error, BackendError):
        return error.retryable
    return isinstance(error, (ConnectionError, TimeoutError))


class BackendWorker:
    """Background threads that send keyframes to a DetectionService, at most `max_in_flight` at a time."""

    def __init__(
        self,
        service: DetectionService,
        clock: Callable[[], float] = time.monotonic,
        max_in_flight: int = 1,
        on_result: Callable[[BaseException | None], None] | None = None,
        store: KeyframeStore | None = None,
        encode: Callable[[np.ndarray], EncodedKeyframe] | None = None,
    ) -> None:
        """`on_result(None)` after each answer, `on_result(error)` after each failure (the operator's
        notices say why, once). `store` keeps keyframes through an outage, encoded by `encode` (the
        client's own, `BackendClient.encode`, so a stored keyframe goes out as it would have)."""
        self._on_result = on_result
        if max_in_flight < 1:
            raise ValueError("max_in_flight must be at least 1")
        if store is not None and encode is None:
            raise ValueError("a keyframe store needs the client's encode")
        self.store = store
        self._encode = encode
        self._unreachable = False  # the last request failed for want of a back-end, none succeeded since
        # Slots a stored keyframe leaves free for live ones.
        self._live_reserve = 1 if max_in_flight > 1 else 0
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

    def submit(
        self,
        frame_id: int,
        image: np.ndarray,
        capture_time: float,
        pose: Telemetry | None = None,
        **fields: Any,
    ) -> bool:
        """Queue a keyframe; True if it goes out now, False if every slot is busy (it will still be sent
        when one frees unless replaced by a newer keyframe). `pose` (the vehicle at capture time) is given
        for full-frame search keyframes: those are kept through an outage when there is a store."""
        luma = mean_luma(image) if pose is not None else None
        request = _Request(frame_id, image, capture_time, dict(fields), self._clock(), pose, mean_luma=luma)
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
            if not self._answers:
                return None
            self._cond.notify_all()  # room for a stored keyframe's answer (`_next`)
            return self._answers.popleft()

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
                request = self._next()
                while request is None and not self._stopping:
                    self._cond.wait()
                    request = self._next()
                if request is None:
                    return
                # While the back-end is unreachable one request at a time tries the link; other search
                # keyframes go into the store untried.
                keep_untried = request.storable and self._unreachable and self._in_flight > 0
                if not keep_untried:
                    self._in_flight += 1
            if keep_untried:
                self._keep(request)
                continue
            try:
                detections, final = self._ask(request)
            except Exception as exc:  # any back-end failure is reported, never raised into the loop
                self._failed(request, exc)
                continue
            if request.stored is not None and self.store is not None:
                self.store.sent()
            self._post(request, detections, final=final, done=True)
            if self._on_result is not None:
                self._on_result(None)

    def _next(self) -> _Request | None:
        """The work a free thread takes (under the lock): a live keyframe first; else, the link up, a slot
        left for live ones and the loop keeping up with the answers, the newest stored keyframe."""
        if self._stopping:
            return None
        if self._pending:
            return self._pending.popleft()
        link_up = self._last_success is not None and self._failures == 0
        if self.store is None or not link_up or self._in_flight >= self.max_in_flight - self._live_reserve:
            return None
        if len(self._answers) >= self.max_in_flight:  # the loop takes one answer an iteration: never flood it
            return None
        kept = self.store.take_newest()
        if kept is None:
            return None
        fields = {k: v for k, v in kept.fields.items() if k != "early_answer"}  # final verdicts only
        return _Request(
            kept.frame_id,
            kept.keyframe,
            kept.capture_time,
            fields,
            self._clock(),
            kept.pose,
            kept,
            kept.mean_luma,
        )

    def _ask(self, request: _Request) -> tuple[list[Detection], bool]:
        """The final detections for a request (after posting the fast stage's, when asked for early)."""
        fields = {k: v for k, v in request.fields.items() if k != "early_answer"}
        if request.fields.get("early_answer"):
            detections, final = self._service.detect_early(request.image, frame_id=request.frame_id, **fields)
            if final:
                return detections, True
            self._post(request, detections, final=False)
        return self._service.detect(request.image, frame_id=request.frame_id, **fields), True

    def _failed(self, request: _Request, exc: BaseException) -> None:
        gone = unreachable(exc)
        with self._cond:  # known before the keyframe is kept: the next ones go into the store untried
            self._failures += 1
            self._last_error = f"{type(exc).__name__}: {exc}"
            self._unreachable = gone
        if request.stored is not None and self.store is not None:
            if gone:
                self.store.put_back(request.stored)
            else:
                self.store.refused()
                log.warning("stored keyframe %d refused by the back-end: %s", request.frame_id, exc)
        elif gone and request.storable:
            self._keep(request)
        with self._cond:
            self._in_flight -= 1
            self._cond.notify_all()
        log.debug("back-end request for frame %d failed: %s", request.frame_id, exc)
        if self._on_result is not None:
            self._on_result(exc)

    def _keep(self, request: _Request) -> None:
        """Encode a search keyframe (on this thread, never the frame loop's) into the store."""
        if self.store is None or self._encode is None or request.pose is None:
            return
        if isinstance(request.image, EncodedKeyframe):
            encoded = request.image
        else:
            try:
                encoded = self._encode(request.image)
            except ValueError as exc:  # not an image the client could send either
                log.warning("keyframe %d not stored: %s", request.frame_id, exc)
                return
        self.store.put(
            StoredKeyframe(
                request.frame_id,
                request.capture_time,
                encoded,
                request.pose,
                request.fields,
                request.mean_luma,
            )
        )
        with self._cond:
            self._cond.notify_all()

    def _post(self, request: _Request, detections: list[Detection], final: bool, done: bool = False) -> None:
        now = self._clock()
        image = None
        if request.stored is not None and detections:  # for the supervisor's crop of its candidates
            image = _decoded(request.stored.keyframe)
        answer = BackendAnswer(
            request.frame_id,
            request.capture_time,
            tuple(detections),
            now - request.submitted_at,
            request.fields,
            final,
            request.pose,
            request.stored is not None,
            image,
            request.mean_luma,
        )
        with self._cond:
            self._answers.append(answer)
            self._answered += 1
            self._last_success = now
            self._failures = 0
            self._last_error = ""
            self._unreachable = False
            if done:
                self._in_flight -= 1
            self._cond.notify_all()


def _decoded(keyframe: EncodedKeyframe) -> np.ndarray | None:
    """A stored keyframe's pixels at the size it was captured (its candidates' boxes are in those)."""
    image = cv2.imdecode(np.frombuffer(keyframe.jpeg, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        return None
    if (image.shape[1], image.shape[0]) != keyframe.size:
        image = cv2.resize(image, keyframe.size, interpolation=cv2.INTER_LINEAR)
    return image
