"""sd_notify over a real unix datagram socket bound by the test, standing in for systemd's."""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.service_notify import ServiceNotifier, ping_while_healthy, watchdog_interval_s


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(5.0)
    yield sock, path
    sock.close()


def receive(sock: socket.socket, timeout: float = 5.0) -> list[str]:
    sock.settimeout(timeout)
    return sock.recv(4096).decode().split("\n")


def drain(sock: socket.socket) -> list[str]:
    sock.settimeout(0)
    out: list[str] = []
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        return out


def test_outside_systemd_every_call_is_a_quiet_no_op() -> None:
    notifier = ServiceNotifier.from_environment({})
    assert not notifier.enabled
    notifier.ready("up")
    notifier.watchdog()
    notifier.stopping()
    assert notifier.notify("READY=1") is False


def test_ready_status_watchdog_stopping_arrive_as_datagrams(notify_socket: tuple[socket.socket, str]) -> None:
    sock, path = notify_socket
    notifier = ServiceNotifier.from_environment({"NOTIFY_SOCKET": path})
    notifier.ready("autopilot and camera up")
    assert receive(sock) == ["READY=1", "STATUS=autopilot and camera up"]
    notifier.watchdog()
    assert receive(sock) == ["WATCHDOG=1"]
    notifier.status("searching")
    assert receive(sock) == ["STATUS=searching"]
    notifier.stopping()
    assert receive(sock) == ["STOPPING=1"]
    notifier.close()


def test_abstract_namespace_socket() -> None:
    name = f"cloudtrack-test-{os.getpid()}-{time.monotonic_ns()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    try:
        ServiceNotifier.from_environment({"NOTIFY_SOCKET": "@" + name}).ready()
        assert receive(sock) == ["READY=1"]
    finally:
        sock.close()


def test_watchdog_pings_are_rate_limited_to_a_quarter_period(notify_socket: tuple[socket.socket, str]) -> None:
    sock, path = notify_socket
    now = [100.0]
    notifier = ServiceNotifier(path, watchdog_period_s=2.0, clock=lambda: now[0])
    for _ in range(8):  # a loop turning faster than the watchdog needs; steps exact in binary
        notifier.watchdog()
        now[0] += 0.125
    assert drain(sock) == ["WATCHDOG=1", "WATCHDOG=1"]  # t=100.0 and t=100.5


def test_watchdog_period_is_ours_only_when_watchdog_pid_matches() -> None:
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000"}, 42) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "42"}, 42) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "7"}, 42) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "garbage"}, 42) is None
    assert watchdog_interval_s({}, 42) is None


def test_vanished_socket_is_logged_not_raised(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    notifier = ServiceNotifier(str(tmp_path / "nobody-listens"))
    notifier.ready()
    notifier.watchdog()
    assert "sd_notify" in caplog.text


def test_event_loop_pinger_stops_when_unhealthy(notify_socket: tuple[socket.socket, str]) -> None:
    sock, path = notify_socket
    notifier = ServiceNotifier(path, watchdog_period_s=0.2)
    healthy = [True]

    async def scenario() -> None:
        task = asyncio.create_task(ping_while_healthy(notifier, lambda: healthy[0]))
        await asyncio.sleep(0.5)
        healthy[0] = False
        await asyncio.sleep(0.15)  # let a ping already in flight land
        drain(sock)
        await asyncio.sleep(0.5)
        task.cancel()

    asyncio.run(scenario())
    assert drain(sock) == []


def test_a_child_process_inherits_the_socket_from_the_environment(notify_socket: tuple[socket.socket, str]) -> None:
    """The way systemd hands the socket over: an environment variable read by a separate process."""
    sock, path = notify_socket
    code = "from companion.service_notify import ServiceNotifier as N; n = N.from_environment(); n.ready(); n.watchdog()"
    env = {**os.environ, "NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=60)
    assert receive(sock) == ["READY=1"]
    assert receive(sock) == ["WATCHDOG=1"]
