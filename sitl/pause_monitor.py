"""Pauses of the runner's own process: the camera, the autopilot bridge and the scripted pilot are its
threads, so a pause here (a garbage collection, a starved machine) is the simulated world stopping, which
the companion and the autopilot see as a dead camera and a dead link. A failed flight names such a pause,
so it is not mistaken for the companion's fault."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

CHECK_PERIOD_S = 0.02
NOTED_PAUSE_S = 0.25  # the longest pause the flights' checks tolerate is half a second (frame watchdog, PX4)


@dataclass(frozen=True)
class Pause:
    began: float  # time.monotonic()
    length_s: float


class PauseMonitor:
    def __init__(self) -> None:
        self._pauses: list[Pause] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="runner-pause-monitor", daemon=True)

    def start(self) -> PauseMonitor:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)

    def pauses(self) -> list[Pause]:
        return list(self._pauses)

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(CHECK_PERIOD_S):
            now = time.monotonic()
            if now - last - CHECK_PERIOD_S > NOTED_PAUSE_S:
                self._pauses.append(Pause(last, round(now - last, 3)))
            last = now
