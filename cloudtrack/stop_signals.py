"""Stop signals that set a `threading.Event` without deadlocking the thread that waits on it.

A handler runs in the main thread between two bytecodes, wherever it was: also inside `Event.wait()` while
it holds the event's lock (between taking it and handing it to the condition's waiter). A handler that calls
`event.set()` there waits for that same lock forever: `cloudtrack-gcs replan --watch` ignored a SIGTERM
that way once in CI (its loop waits on the event twice a second). The handler here sets the event from a
short-lived thread of its own, which waits until the main thread lets go of the lock.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterable


def set_on_signals(
    event: threading.Event, signals: Iterable[signal.Signals] = (signal.SIGINT, signal.SIGTERM)
) -> None:
    """Each of `signals` sets `event` (from the main thread only, where Python allows handlers)."""

    def handler(*_: object) -> None:
        threading.Thread(target=event.set, name="stop-signal", daemon=True).start()

    for sig in signals:
        signal.signal(sig, handler)
