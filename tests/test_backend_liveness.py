"""The lost-back-end watchdog is fed by real answers only, not by requests that keep failing."""

from __future__ import annotations

from typing import Any

from behaviors.mission_config import MissionConfig
from companion.cloud.backend_worker import WorkerHealth
from companion.mission_runner import MissionRunner


class _Vehicle:
    def __init__(self) -> None:
        self.backend_ok: list[float] = []

    def report_backend_ok(self, when: float | None = None) -> None:
        assert when is not None
        self.backend_ok.append(when)


class _Worker:
    def __init__(self) -> None:
        self.state = WorkerHealth(None, 0, "", False, 0, 0, 0)

    def health(self) -> WorkerHealth:
        return self.state


def _runner() -> tuple[MissionRunner, _Vehicle, _Worker]:
    vehicle, worker = _Vehicle(), _Worker()
    none: Any = None
    runner = MissionRunner(MissionConfig(), none, none, vehicle, worker)  # type: ignore[arg-type]
    return runner, vehicle, worker


def test_requests_failing_one_after_another_do_not_keep_the_backend_alive() -> None:
    runner, vehicle, worker = _runner()
    worker.state = WorkerHealth(100.0, 0, "", False, 1, 0, 1)  # answered at t=100
    runner._feed_watchdogs(100.5)
    assert vehicle.backend_ok[-1] == 100.5  # nothing out, nothing failed: alive
    # The back-end goes away: every second a keyframe goes out and is refused at once.
    for second in range(1, 6):
        runner._pending_since = 100.0 + second  # a new request went out
        worker.state = WorkerHealth(100.0, second, "ConnectionError", True, 1 + second, 0, 1)
        runner._feed_watchdogs(100.0 + second + 0.1)
        assert vehicle.backend_ok[-1] == 100.0, "a failing request fed the watchdog"


def test_a_slow_request_after_a_good_answer_is_not_overdue_yet() -> None:
    runner, vehicle, worker = _runner()
    runner._pending_since = 200.0
    worker.state = WorkerHealth(150.0, 0, "", True, 2, 0, 1)  # the VLM is slow, nothing failed
    runner._feed_watchdogs(203.0)
    assert vehicle.backend_ok[-1] == 200.0
