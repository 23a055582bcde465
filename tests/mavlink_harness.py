"""Shared set-up for the MAVLink tests: the SITL autopilot and a VehicleLink (or a raw GCS) on loopback UDP.

Every socket is bound to port 0, so parallel runs never collide. Timing assertions are generous because
the test machine is loaded; they bound behaviour, they do not benchmark it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from cloudtrack.mavlink_connection import MavlinkEndpoint
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.vehicle_link import VehicleLink
from sitl.autopilot import AutopilotOptions, SimulatedAutopilot


def wait_for(predicate: Callable[[], Any], timeout: float = 5.0, period: float = 0.02) -> Any:
    """The predicate's first truthy value, or its last value after `timeout`."""
    deadline = time.monotonic() + timeout
    value = predicate()
    while not value and time.monotonic() < deadline:
        time.sleep(period)
        value = predicate()
    return value


class MainLoop:
    """Stands in for the companion's main loop: every 50 ms it kicks the link (and reports frames) and, like
    the real loop computing its command each iteration, gives the link the test's latest `set_velocity`
    again (setpoints older than `[safety] setpoint_max_age_s` are never sent). A `hold`, `release_offboard`
    or `request_mode` ends that command, as a new behaviour state would. `paused` freezes all of it."""

    def __init__(self, link: VehicleLink, frames: bool = False):
        self.link = link
        self.frames = frames
        self.paused = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._command: tuple[Any, bool] | None = None
        self._lock = threading.Lock()
        set_velocity = link.set_velocity

        def command(setpoint: Any, descent_allowed: bool = False) -> None:
            with self._lock:
                self._command = (setpoint, descent_allowed)
            set_velocity(setpoint, descent_allowed)

        self._set_velocity = set_velocity
        link.set_velocity = command  # type: ignore[method-assign]
        for name in ("hold", "release_offboard", "request_mode"):
            setattr(link, name, self._ending(getattr(link, name)))

    def _ending(self, method: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            with self._lock:
                self._command = None
            return method(*args, **kwargs)

        return call

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            if not self.paused.is_set():
                self.link.kick()
                if self.frames:
                    self.link.report_frame()
                with self._lock:
                    command = self._command
                if command is not None:
                    self._set_velocity(*command)

    def __enter__(self) -> MainLoop:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


@contextmanager
def autopilot(personality: str = "ardupilot", **options: Any) -> Iterator[SimulatedAutopilot]:
    sim = SimulatedAutopilot(
        AutopilotOptions(personality=personality, **options),
        {"gcs": "udpin:127.0.0.1:0", "companion": "udpin:127.0.0.1:0"},
    )
    sim.start()
    try:
        yield sim
    finally:
        sim.close()


@contextmanager
def vehicle_link(
    sim: SimulatedAutopilot, safety: dict[str, Any] | None = None, **mavlink: Any
) -> Iterator[VehicleLink]:
    """A started VehicleLink on the sim's companion link that has detected the autopilot and its telemetry."""
    config = MavlinkConfig(connection=f"udpout:127.0.0.1:{sim.link_port('companion')}", **mavlink)
    link = VehicleLink(config, SafetyConfig(**(safety or {})))
    link.start()
    try:
        link.kick()
        assert wait_for(lambda: link.autopilot_kind is not None and link.telemetry() is not None, 5.0), (
            "the companion never decoded the autopilot's heartbeat and telemetry"
        )
        yield link
    finally:
        link.close()


@contextmanager
def gcs(
    sim: SimulatedAutopilot, signing_key: bytes | None = None, system: int = 255
) -> Iterator[MavlinkEndpoint]:
    """A raw GCS endpoint on the sim's GCS link that the autopilot has already seen (so it routes to it)."""
    endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('gcs')}", system, 190)
    if signing_key is not None:
        # The autopilot's own traffic is unsigned; accept it so the GCS can see it.
        endpoint.conn.setup_signing(
            signing_key, sign_outgoing=True, allow_unsigned_callback=lambda mav, msg_id: True
        )
    try:
        endpoint.send(lambda m: m.heartbeat_send(6, 8, 0, 0, 0))
        assert wait_for(lambda: _heard_heartbeat(endpoint), 5.0), "the GCS never heard the autopilot"
        yield endpoint
    finally:
        endpoint.close()


def _heard_heartbeat(endpoint: MavlinkEndpoint) -> bool:
    endpoint.send(lambda m: m.heartbeat_send(6, 8, 0, 0, 0))
    msg = endpoint.receive(timeout=0.2)
    return msg is not None and msg.get_type() == "HEARTBEAT"


def receive_until(endpoint: MavlinkEndpoint, predicate: Callable[[Any], bool], timeout: float = 5.0) -> Any:
    """The first message from `endpoint` matching `predicate`, or None."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = endpoint.receive(timeout=0.1)
        if msg is not None and predicate(msg):
            return msg
    return None


def set_mode_from_gcs(endpoint: MavlinkEndpoint, custom_main: int, custom_sub: int = 0) -> Any:
    """MAV_CMD_DO_SET_MODE from the GCS to the autopilot; the COMMAND_ACK."""
    endpoint.send(lambda m: m.command_long_send(1, 1, 176, 0, 1, custom_main, custom_sub, 0, 0, 0, 0))
    return receive_until(endpoint, lambda m: m.get_type() == "COMMAND_ACK" and m.command == 176)
