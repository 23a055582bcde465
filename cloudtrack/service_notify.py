"""The systemd notification protocol (sd_notify) over $NOTIFY_SOCKET, with no dependency beyond the stdlib.

systemd starts a `Type=notify` service with NOTIFY_SOCKET naming a unix datagram socket (a path, or a
Linux abstract name when it starts with "@"); the service sends newline-separated KEY=VALUE datagrams:
READY=1 once it is useful, WATCHDOG=1 at least every WatchdogSec (given to the process as
WATCHDOG_USEC, for the process WATCHDOG_PID if set), STATUS=... for `systemctl status`, STOPPING=1 when
it begins to shut down. Outside systemd (no NOTIFY_SOCKET) every call is a no-op, so the same code runs
under systemd, in a terminal and in tests. A notification that cannot be sent is logged, never raised:
losing a watchdog ping must not take down a flying companion.

Watchdog pings are meant to be sent by the main loop itself, once per healthy iteration
(`watchdog()` rate-limits them), so a stalled or hung loop stops pinging and systemd restarts the
process. The back-end, whose main loop is asyncio, uses `ping_while_healthy`.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping
from typing import Protocol

log = logging.getLogger(__name__)

# Ping at this fraction of the watchdog period: systemd's own advice is "half", a quarter leaves room for
# a loaded Raspberry Pi.
_PING_FRACTION = 0.25
# Pinging interval when NOTIFY_SOCKET is set but the unit has no WatchdogSec (pings are then harmless).
_DEFAULT_PING_INTERVAL_S = 1.0


class Notifier(Protocol):
    """What a main loop needs from the service manager; `ServiceNotifier` is the systemd implementation."""

    def ready(self, status: str = "") -> None: ...

    def watchdog(self) -> None: ...

    def status(self, text: str) -> None: ...

    def stopping(self, status: str = "") -> None: ...


def _socket_address(name: str) -> str:
    # "@name" is the Linux abstract namespace, spelled with a leading NUL byte in the socket API.
    return "\0" + name[1:] if name.startswith("@") else name


def watchdog_interval_s(environ: Mapping[str, str], pid: int) -> float | None:
    """The watchdog period systemd gave this process in seconds, or None when there is none for it."""
    raw_usec = environ.get("WATCHDOG_USEC", "")
    raw_pid = environ.get("WATCHDOG_PID", "")
    if raw_pid:
        try:
            if int(raw_pid) != pid:
                return None  # the variable was inherited from a parent; the watchdog is not ours
        except ValueError:
            return None
    try:
        usec = int(raw_usec)
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


class ServiceNotifier:
    """sd_notify client. `ServiceNotifier.from_environment()` is the normal way to make one."""

    def __init__(
        self,
        socket_name: str | None,
        watchdog_period_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._address = _socket_address(socket_name) if socket_name else None
        self._sock: socket.socket | None = None
        self._clock = clock
        self.watchdog_period_s = watchdog_period_s
        self.ping_interval_s = (
            watchdog_period_s * _PING_FRACTION if watchdog_period_s else _DEFAULT_PING_INTERVAL_S
        )
        self._last_ping: float | None = None
        self._failed_once = False

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None) -> ServiceNotifier:
        env = os.environ if environ is None else environ
        return cls(env.get("NOTIFY_SOCKET") or None, watchdog_interval_s(env, os.getpid()))

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def notify(self, *assignments: str) -> bool:
        """Send one datagram of KEY=VALUE lines; True when it was sent (False outside systemd or on error)."""
        if self._address is None:
            return False
        payload = "\n".join(assignments).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(payload, self._address)
        except OSError as exc:
            # Log the first failure loudly, the rest quietly: a dead notify socket must not flood the log.
            (log.debug if self._failed_once else log.warning)("sd_notify %s failed: %s", assignments, exc)
            self._failed_once = True
            return False
        return True

    def ready(self, status: str = "") -> None:
        self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> None:
        self.notify(f"STATUS={text}")

    def watchdog(self) -> None:
        """Ping the watchdog if the last ping is older than the ping interval. Call once per healthy loop."""
        now = self._clock()
        if self._last_ping is not None and now - self._last_ping < self.ping_interval_s:
            return
        if self.notify("WATCHDOG=1"):
            self._last_ping = now

    def stopping(self, status: str = "") -> None:
        self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


async def ping_while_healthy(notifier: ServiceNotifier, healthy: Callable[[], bool] = lambda: True) -> None:
    """Ping from an asyncio task: it runs only while the event loop turns, so a blocked loop stops pinging."""
    while True:
        if healthy():
            notifier.watchdog()
        await asyncio.sleep(notifier.ping_interval_s)
