"""Watchdogs that end motion when an input goes stale, in a thread of their own.

Five conditions, each armed by its first report (a watchdog cannot go stale on something it never saw):
- `stale_frames`: no camera frame for `frame_stale_s`;
- `target_lost`: while following, no trusted target for `target_lost_s`;
- `backend_unreachable`: no answer from the back-end for `backend_lost_s`;
- `autopilot_heartbeat_lost`: no autopilot HEARTBEAT for `heartbeat_timeout_s`;
- `main_loop_stalled`: the main loop has not called `kick()` for `loop_stall_s`.

The thread checks every `check_period_s`, independently of the main loop, so a hung main loop is caught
(and a frozen process too: a gap in the watchdog's checks longer than `loop_stall_s` counts as a stall; the
setpoint streamer checks too before each setpoint, so after a freeze whichever thread runs first stops):
on the rising edge of a condition it calls `on_trip(reason)` (the link sends an explicit zero-velocity
stop, then the configured hold) and on the falling edge `on_clear(reason)`. A condition trips at most
`threshold + check_period_s` after its input went silent.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from companion.config import SafetyConfig

log = logging.getLogger(__name__)

STALE_FRAMES = "stale_frames"
TARGET_LOST = "target_lost"
BACKEND_UNREACHABLE = "backend_unreachable"
HEARTBEAT_LOST = "autopilot_heartbeat_lost"
LOOP_STALLED = "main_loop_stalled"


@dataclass(frozen=True)
class SafetyEvent:
    """What a watchdog (or the mode policy) did: `action` is "stop", "cleared" or "offboard_ended".

    `by_other_party` marks a mode change made by the pilot or the GCS while we were flying (a takeover:
    the main loop gives up control on this flag, never on the wording of `detail`, which is for humans);
    `mode` is then the mode they selected.
    """

    time_s: float
    reason: str
    action: str
    detail: str = ""
    by_other_party: bool = False
    mode: str = ""


def thresholds(config: SafetyConfig) -> dict[str, float]:
    return {
        STALE_FRAMES: config.frame_stale_s,
        TARGET_LOST: config.target_lost_s,
        BACKEND_UNREACHABLE: config.backend_lost_s,
        HEARTBEAT_LOST: config.heartbeat_timeout_s,
        LOOP_STALLED: config.loop_stall_s,
    }


def stale_conditions(last_seen: dict[str, float], limits: dict[str, float], now: float) -> set[str]:
    """The armed conditions whose input is older than its limit."""
    return {reason for reason, seen in last_seen.items() if now - seen > limits[reason]}


class SafetyWatchdog:
    """Records when each input was last seen and runs the checking thread."""

    def __init__(
        self,
        config: SafetyConfig,
        on_trip: Callable[[str, float], None],
        on_clear: Callable[[str, float], None],
        clock: Callable[[], float] = time.monotonic,
        check_period_s: float = 0.02,
    ):
        self._limits = thresholds(config)
        self._on_trip = on_trip
        self._on_clear = on_clear
        self._clock = clock
        self._period = check_period_s
        self._lock = threading.Lock()
        self._last_seen: dict[str, float] = {}
        self._active: set[str] = set()
        self._last_check: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # Inputs; `when` defaults to now on the watchdog's clock.
    def seen(self, reason: str, when: float | None = None) -> None:
        with self._lock:
            self._last_seen[reason] = self._clock() if when is None else when

    def disarm(self, reason: str) -> None:
        """Stop watching an input (e.g. the target once the mission no longer follows one)."""
        with self._lock:
            self._last_seen.pop(reason, None)

    def active(self) -> set[str]:
        with self._lock:
            return set(self._active)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="safety-watchdog", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)

    def check(self) -> float:
        """One pass: trip new conditions, clear recovered ones. Returns the time it checked at."""
        now = self._clock()
        with self._lock:
            stale = stale_conditions(self._last_seen, self._limits, now)
            # The watchdog's own thread missed its checks for longer than the stall bound: the whole process
            # was frozen (SIGSTOP, swap, a blocked interpreter), even if the main loop kicked first on resume.
            frozen = self._last_check is not None and now - self._last_check > self._limits[LOOP_STALLED]
            self._last_check = now
            if frozen and LOOP_STALLED in self._last_seen:
                stale.add(LOOP_STALLED)
            tripped, cleared = stale - self._active, self._active - stale
            self._active = stale
        for reason in sorted(tripped):
            log.warning("watchdog: %s (limit %.2f s): stopping", reason, self._limits[reason])
            self._on_trip(reason, now)
        for reason in sorted(cleared):
            log.info("watchdog: %s recovered", reason)
            self._on_clear(reason, now)
        return now

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            try:
                self.check()
            except Exception:  # the watchdog must outlive any bug in a callback
                log.exception("watchdog check failed")
