"""cloudtrack.stop_signals: a stop signal that arrives while the main thread holds the event's own lock (inside
`Event.wait()`) still sets the event, and the handler returns at once (`event.set()` in the handler waited
for that lock forever)."""

from __future__ import annotations

import signal
import threading

from cloudtrack.stop_signals import set_on_signals


def test_a_signal_inside_the_events_wait_sets_it_without_a_deadlock() -> None:
    stop = threading.Event()
    before = signal.getsignal(signal.SIGUSR1)
    try:
        set_on_signals(stop, (signal.SIGUSR1,))
        with stop._cond:  # type: ignore[attr-defined]  # inside Event.wait(), before the waiter has the lock
            signal.raise_signal(signal.SIGUSR1)  # the handler runs here, in this thread, and returns
            assert not stop.is_set()  # set() is waiting for the lock this thread holds
        assert stop.wait(10)  # the lock let go: set
    finally:
        signal.signal(signal.SIGUSR1, before)
