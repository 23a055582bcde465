"""sd_notify over a real unix datagram socket bound by the test, standing in for systemd's.

The last test runs the whole companion (`cloudtrack-companion run`) that way, with the SITL autopilot as
MAVLink peer, a live camera stream of real frames, and a GCS on the autopilot's other link.

It must send READY once the autopilot and the camera are up, WATCHDOG pings only while the main loop is
healthy (none while the process is frozen, none while the camera is silent), and on SIGTERM: STOPPING,
an explicit zero-velocity setpoint the autopilot receives, a status line the GCS receives, no further
setpoints, and exit within the unit's stop budget.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest

from cloudtrack.gcs_protocol import CMD_START, encode_prompt
from cloudtrack.service_notify import ServiceNotifier, ping_while_healthy, watchdog_interval_s
from companion.flight_record import read_events
from gcs.cli import _tunnel
from tests.camera_stream import CAMERA_FPS, CameraStream
from tests.live_backend import free_port
from tests.mavlink_harness import autopilot, gcs, receive_until, wait_for


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


def test_watchdog_pings_are_rate_limited_to_a_quarter_period(
    notify_socket: tuple[socket.socket, str],
) -> None:
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


def test_a_child_process_inherits_the_socket_from_the_environment(
    notify_socket: tuple[socket.socket, str],
) -> None:
    """The way systemd hands the socket over: an environment variable read by a separate process."""
    sock, path = notify_socket
    code = "from cloudtrack.service_notify import ServiceNotifier as N; n = N.from_environment(); n.ready(); n.watchdog()"
    env = {**os.environ, "NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000"}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=60)
    assert receive(sock) == ["READY=1"]
    assert receive(sock) == ["WATCHDOG=1"]


# --- the whole companion under the stand-in for systemd ------------------------------------------------

WATCHDOG_USEC = 2_000_000  # pings every 0.5 s (a quarter period)


class NotifyListener:
    """systemd's side of NOTIFY_SOCKET: every datagram with the time it arrived."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.messages.extend((time.monotonic(), line) for line in data.decode().split("\n"))

    def times(self, line: str, since: float = 0.0) -> list[float]:
        return [t for t, text in list(self.messages) if text == line and t >= since]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


@pytest.fixture
def camera(sequences_dir: Path) -> Iterator[CameraStream]:
    stream = CameraStream(sequences_dir / "uav123_person12_1" / "frames")
    yield stream
    stream.close()


def longest_gap(times: list[float], start: float, end: float) -> float:
    points = [start, *[t for t in times if start <= t <= end], end]
    return max(b - a for a, b in zip(points, points[1:], strict=False))


@pytest.mark.slow
def test_companion_speaks_sd_notify_and_stops_setpoints_on_sigterm(
    tmp_path: Path, models_dir: Path, camera: CameraStream
) -> None:
    listener = NotifyListener(tmp_path / "notify")
    with autopilot("ardupilot") as sim, gcs(sim) as ground:
        env = {
            **os.environ,
            "NOTIFY_SOCKET": str(listener.path),
            "WATCHDOG_USEC": str(WATCHDOG_USEC),
            "PYTHONUNBUFFERED": "1",
        }
        env.pop("WATCHDOG_PID", None)
        settings = {
            "mavlink.connection": f"udpout:127.0.0.1:{sim.link_port('companion')}",
            "camera.source": f"sim+tcp://127.0.0.1:{camera.port}",
            "camera.fps": CAMERA_FPS,
            "backend.url": f"http://127.0.0.1:{free_port()}",  # nothing listens: the loop must not care
            "recording.dir": str(tmp_path / "records"),
            "tracker.name": "nano",
            "behavior.search_yaw_rate_deg_s": 10.0,  # searching turns the vehicle: non-zero setpoints
        }
        command = [sys.executable, "-m", "companion.cli", "run", "--model-dir", str(models_dir)]
        for key, value in settings.items():
            command += ["--set", f"{key}={value}"]
        log_path = tmp_path / "companion.log"
        with open(log_path, "w") as log:
            proc = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            # READY once the autopilot's heartbeat and the first camera frame are in.
            assert wait_for(lambda: listener.times("READY=1"), 60.0), log_path.read_text()[-3000:]
            ready = listener.times("READY=1")[0]
            assert wait_for(lambda: len(listener.times("WATCHDOG=1", ready)) >= 3, 15.0), "no watchdog pings"

            # A frozen process (a hung driver, a stuck GIL) pings nothing; it pings again once it runs.
            os.kill(proc.pid, signal.SIGSTOP)
            frozen = time.monotonic()
            time.sleep(2.5)
            os.kill(proc.pid, signal.SIGCONT)
            thawed = time.monotonic()
            # (0.5 s of slack: a ping sent just before the freeze may be timestamped late on a loaded machine)
            assert not [t for t in listener.times("WATCHDOG=1", frozen + 0.5) if t < thawed]
            assert wait_for(lambda: listener.times("WATCHDOG=1", thawed), 10.0), "no pings after SIGCONT"

            # The loop keeps turning but is unhealthy without frames: the pings stop until frames return.
            camera.paused.set()
            silent = time.monotonic()
            time.sleep(4.5)
            camera.paused.clear()
            resumed = time.monotonic()
            gap = longest_gap(listener.times("WATCHDOG=1"), silent, resumed)
            assert gap >= 2.0, f"watchdog kept pinging without frames (longest gap {gap:.2f} s)"
            assert wait_for(lambda: listener.times("WATCHDOG=1", resumed), 15.0), (
                "no pings after frames returned"
            )
            assert proc.poll() is None, "the companion must survive a camera outage"

            # The GCS starts a mission; searching, the companion turns the vehicle with yaw-rate setpoints.
            prompt = encode_prompt(7, "person", "a person in a red shirt")
            for payload in prompt:
                ground.send(partial(_tunnel, target=(1, 191), payload=payload))
            length = sum(len(p) - 4 for p in prompt)
            ground.send(
                lambda m: m.command_long_send(1, 191, CMD_START, 0, 7, len(prompt), 0, length, 0, 0, 0)
            )
            ack = receive_until(  # after IN_PROGRESS (5) while the companion asks the back-end
                ground,
                lambda m: m.get_type() == "COMMAND_ACK" and m.command == CMD_START and m.result != 5,
                10.0,
            )
            assert ack is not None and ack.result == 0, ack
            turning = wait_for(
                lambda: [s for s in sim.setpoints if s.src_component == 191 and s.yaw_rate > 0.1], 15.0
            )
            assert turning, "no yaw-rate setpoints while searching"
            proc.send_signal(signal.SIGTERM)
            sent = time.monotonic()
            returncode = proc.wait(timeout=15)
            took = time.monotonic() - sent
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            listener.close()
        print(f"companion exited {took:.2f} s after SIGTERM")
        assert returncode == 0, log_path.read_text()[-3000:]
        assert took < 5.0, f"took {took:.2f} s to stop (the unit allows TimeoutStopSec=5)"
        assert listener.times("STOPPING=1", sent), "no STOPPING=1"

        ours = [s for s in sim.setpoints if s.src_component == 191]
        last = ours[-1]
        assert (last.vx, last.vy, last.vz, last.yaw_rate) == (0.0, 0.0, 0.0, 0.0), last
        count = len(ours)
        time.sleep(0.5)
        assert len([s for s in sim.setpoints if s.src_component == 191]) == count, "setpoints after exit"
        stopping = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and "stopping" in str(m.text), 3.0
        )
        assert stopping is not None, "the GCS was not told"
        # The mission's flight record was flushed and closed on the way out.
        (folder,) = [p for p in (tmp_path / "records").iterdir() if p.is_dir()]
        entries = read_events(folder)
        assert entries[-1]["kind"] == "recording_closed"
        assert any(e["kind"] == "state" and e["new"] == "SEARCHING" for e in entries)


@pytest.mark.slow
def test_backend_speaks_sd_notify_and_stops_on_sigterm(tmp_path: Path, models_dir: Path) -> None:
    """`cloudtrack-backend serve` as config/cloudtrack-backend.service runs it (Type=notify)."""
    listener = NotifyListener(tmp_path / "notify")
    port = free_port()
    env = {**os.environ, "NOTIFY_SOCKET": str(listener.path), "WATCHDOG_USEC": str(WATCHDOG_USEC)}
    env.pop("WATCHDOG_PID", None)
    command = [
        sys.executable, "-m", "backend.cli", "serve", "--set", f"server.port={port}",
        "--set", f"detector.model_dir={models_dir}", "--set", "verifier.kind=none",
    ]  # fmt: skip
    log_path = tmp_path / "backend.log"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        assert wait_for(lambda: listener.times("READY=1"), 60.0), log_path.read_text()[-3000:]
        ready = listener.times("READY=1")[0]
        health = wait_for(lambda: _health(port), 10.0)
        assert health and health["status"] == "ok"
        assert wait_for(lambda: len(listener.times("WATCHDOG=1", ready)) >= 3, 15.0), "no watchdog pings"
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        returncode = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        listener.close()
    assert listener.times("STOPPING=1", sent), "no STOPPING=1"
    # uvicorn re-raises the SIGTERM it handled once it has shut down; systemd counts SIGTERM as a clean
    # exit (so Restart=on-failure does not restart a stopped service).
    assert returncode in (0, -signal.SIGTERM), log_path.read_text()[-3000:]
    assert "Application shutdown complete" in log_path.read_text()


def _health(port: int) -> dict[str, object] | None:
    import httpx

    try:
        response = httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
    except httpx.HTTPError:
        return None
    return response.json() if response.status_code == 200 else None
