"""The companion's stop waits on nothing it does not need (the scenarios allow 2 s from SIGTERM to exit).

The back-end session's round in progress (a status POST that takes a second on a loaded machine) is not
waited for past the session's stop wait; the process ends with `exit_now` once everything is closed, its
exit handlers run and its output flushed, without the interpreter's teardown of every module.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from typing import Any

from companion.cloud.backend_session import BackendSession
from companion.run_command import SESSION_STOP_WAIT_S


class StuckClient:
    """A back-end whose status request hangs until released."""

    def __init__(self) -> None:
        self.in_request = threading.Event()
        self.release = threading.Event()

    def report_status(self, state: str, vehicle_id: str | None = None, **fields: Any) -> object:
        self.in_request.set()
        self.release.wait(10.0)
        return None

    def reject(self, *args: Any, **kwargs: Any) -> object:
        return None

    def decisions(self, after: int = 0, vehicle_id: str | None = None) -> list[Any]:
        return []

    def set_on_find(self, mission_id: str, on_find: str) -> object:
        return None

    def fleet_order(self, mission_id: str) -> Any:
        raise RuntimeError("not a fleet mission")


def test_session_stop_does_not_wait_for_a_request_in_flight() -> None:
    client = StuckClient()
    session = BackendSession(client, period_s=0.01)
    session.update({"state": "SEARCHING"})
    session.start()
    try:
        assert client.in_request.wait(5.0)
        started = time.monotonic()
        session.close(SESSION_STOP_WAIT_S)
        took = time.monotonic() - started
        assert took < SESSION_STOP_WAIT_S + 0.5, f"close waited {took:.2f} s on the request in flight"
    finally:
        client.release.set()


def test_exit_now_runs_exit_handlers_flushes_and_exits_with_the_code() -> None:
    code = (
        "import atexit, sys\n"
        "from companion.run_command import exit_now\n"
        "atexit.register(lambda: print('handler ran', flush=True))\n"
        "sys.stdout.write('buffered ')\n"
        "exit_now(3)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert done.stdout == "buffered handler ran\n"
