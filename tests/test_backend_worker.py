"""The background back-end worker with real threads and an in-process DetectionService that is slow or fails."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import pytest

from behaviors.detection import Detection
from behaviors.geometry import Box
from companion.cloud.backend_worker import BackendAnswer, BackendWorker


class GatedService:
    """Answers only when the test opens the gate, so 'busy' is deterministic; can be told to fail."""

    def __init__(self) -> None:
        self.gate = threading.Semaphore(0)
        self.calls: list[dict[str, Any]] = []
        self.fail_with: Exception | None = None
        self.entered = threading.Event()

    def detect(self, image: np.ndarray, **fields: Any) -> list[Detection]:
        self.calls.append(dict(fields, shape=image.shape))
        self.entered.set()
        assert self.gate.acquire(timeout=10)
        if self.fail_with is not None:
            raise self.fail_with
        return [Detection(Box(1, 2, 3, 4), 0.8, candidate_id=f"c{fields['frame_id']}")]


def _image() -> np.ndarray:
    return np.zeros((8, 8, 3), np.uint8)


def _poll(worker: BackendWorker, timeout_s: float = 10.0) -> BackendAnswer:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        answer = worker.poll()
        if answer is not None:
            return answer
        time.sleep(0.01)
    raise AssertionError("no answer")


def test_submit_never_waits_and_the_newest_keyframe_replaces_the_waiting_one() -> None:
    service = GatedService()
    worker = BackendWorker(service)
    assert worker.submit(1, _image(), 10.0, prompt="a man in a gray shirt") is True
    assert service.entered.wait(5)
    # The service is blocked inside detect(): these calls return at once.
    assert worker.submit(2, _image(), 10.1, prompt="p") is False
    assert worker.submit(3, _image(), 10.2, prompt="p") is False
    assert worker.poll() is None
    health = worker.health()
    assert health.busy and health.submitted == 3 and health.replaced == 1
    service.gate.release()
    first = _poll(worker)
    assert first.frame_id == 1 and first.capture_time == 10.0 and first.detections[0].candidate_id == "c1"
    assert first.fields == {"prompt": "a man in a gray shirt"} and first.latency_s >= 0
    service.gate.release()
    second = _poll(worker)
    assert second.frame_id == 3  # frame 2 was replaced before it was sent
    assert [c["frame_id"] for c in service.calls] == [1, 3]
    assert worker.wait_idle(5)
    assert worker.health().last_success_time is not None and worker.health().answered == 2
    worker.close()


def test_failures_are_counted_for_the_watchdog_and_a_success_clears_them() -> None:
    service = GatedService()
    worker = BackendWorker(service)
    service.fail_with = TimeoutError("back-end did not answer in 5 s")
    for frame_id in (1, 2):
        worker.submit(frame_id, _image(), 0.0)
        service.gate.release()
        assert worker.wait_idle(5)
    health = worker.health()
    assert health.consecutive_failures == 2 and health.last_success_time is None
    assert "did not answer" in health.last_error
    assert worker.poll() is None  # a failure is never an answer
    service.fail_with = None
    worker.submit(3, _image(), 0.0)
    service.gate.release()
    assert _poll(worker).frame_id == 3
    assert worker.health().consecutive_failures == 0 and worker.health().last_error == ""
    worker.close()


def test_slow_service_with_a_live_frame_loop() -> None:
    """A 30 Hz loop submitting every frame to a 150 ms service: answers arrive in order, refer to the
    keyframes actually sent, and the backlog never grows (busy keyframes are replaced)."""

    class Slow:
        def detect(self, image: np.ndarray, **fields: Any) -> list[Detection]:
            time.sleep(0.15)
            return [Detection(Box(0, 0, 1, 1), 1.0, candidate_id=str(fields["frame_id"]))]

    worker = BackendWorker(Slow())
    answers = []
    for frame_id in range(1, 31):
        worker.submit(frame_id, _image(), frame_id / 30.0)
        answer = worker.poll()
        if answer is not None:
            answers.append(answer.frame_id)
        time.sleep(1 / 30)
    assert worker.wait_idle(5)
    final = worker.poll()
    if final is not None:
        answers.append(final.frame_id)
    assert answers and answers == sorted(answers) and len(answers) < 30
    assert worker.health().replaced > 0  # keyframes arriving while busy were replaced, not queued
    worker.close()


def test_closed_worker_refuses_work() -> None:
    worker = BackendWorker(GatedService())
    worker.close()
    assert worker.submit(1, _image(), 0.0) is False


@pytest.mark.parametrize("error", [ConnectionRefusedError("refused"), ValueError("bad JSON from back-end")])
def test_any_exception_from_the_service_is_reported(error: Exception) -> None:
    service = GatedService()
    service.fail_with = error
    worker = BackendWorker(service)
    worker.submit(1, _image(), 0.0)
    service.gate.release()
    assert worker.wait_idle(5)
    assert type(error).__name__ in worker.health().last_error
    worker.close()


def test_two_requests_in_flight_then_the_newest_keyframe_waits() -> None:
    """A hosted VLM answers in about 2 s: with two requests out, a 1 s keyframe rate is kept."""
    service = GatedService()
    worker = BackendWorker(service, max_in_flight=2)
    assert worker.submit(1, _image(), 0.0) is True
    assert worker.submit(2, _image(), 0.1) is True  # a second slot is free: 1 is not replaced
    deadline = time.monotonic() + 5
    while len(service.calls) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sorted(c["frame_id"] for c in service.calls) == [1, 2]
    assert worker.submit(3, _image(), 0.2) is False
    assert worker.submit(4, _image(), 0.3) is False  # both slots busy: 4 replaces 3
    service.gate.release()
    first = _poll(worker)
    service.gate.release()
    second = _poll(worker)
    assert {first.frame_id, second.frame_id} <= {1, 2, 4}
    service.gate.release()
    assert worker.wait_idle(5)
    answered = {first.frame_id, second.frame_id}
    leftover = worker.poll()
    if leftover is not None:
        answered.add(leftover.frame_id)
    assert answered == {1, 2, 4} and worker.poll() is None  # every answer kept, oldest first, none lost
    assert sorted(c["frame_id"] for c in service.calls) == [1, 2, 4]
    assert worker.health().replaced == 1 and worker.health().answered == 3
    worker.close()


def test_max_in_flight_must_be_positive() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        BackendWorker(GatedService(), max_in_flight=0)


class StagedService:
    """A back-end with (or without) a slower stage behind its fast one; records which stage was asked."""

    def __init__(self, has_slow_stage: bool) -> None:
        self.has_slow_stage = has_slow_stage
        self.calls: list[tuple[str, dict[str, Any]]] = []

    def detect(self, image: np.ndarray, **fields: Any) -> list[Detection]:
        self.calls.append(("final", fields))
        return [Detection(Box(1, 2, 3, 4), 0.8, candidate_id="slow")]

    def detect_early(self, image: np.ndarray, **fields: Any) -> tuple[list[Detection], bool]:
        self.calls.append(("early", fields))
        return [Detection(Box(1, 2, 3, 4), 0.8, candidate_id="fast")], not self.has_slow_stage


def test_an_early_request_is_answered_by_the_fast_stage_then_in_full() -> None:
    service = StagedService(has_slow_stage=True)
    worker = BackendWorker(service)
    worker.submit(7, _image(), 1.0, prompt="p", query_id=3, early_answer=True)
    first, second = _poll(worker), _poll(worker)
    assert (first.frame_id, first.final, first.detections[0].candidate_id) == (7, False, "fast")
    assert (second.frame_id, second.final, second.detections[0].candidate_id) == (7, True, "slow")
    assert first.fields["query_id"] == second.fields["query_id"] == 3
    assert [stage for stage, _ in service.calls] == ["early", "final"]
    assert all("early_answer" not in fields for _, fields in service.calls)  # never sent on the wire
    worker.close()


def test_a_back_end_without_a_slower_stage_answers_an_early_request_once() -> None:
    service = StagedService(has_slow_stage=False)
    worker = BackendWorker(service)
    worker.submit(7, _image(), 1.0, prompt="p", early_answer=True)
    assert worker.wait_idle(5)
    answer = _poll(worker)
    assert answer.final and answer.detections[0].candidate_id == "fast" and worker.poll() is None
    assert [stage for stage, _ in service.calls] == ["early"]
    worker.close()
