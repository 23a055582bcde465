"""Offboard velocity through MAVSDK for PX4 users (`mavlink.use_mavsdk = true`).

MAVSDK's offboard plugin re-sends the last setpoint at 20 Hz by itself, even when the application that
set it has hung: a known fly-away cause. So this adapter is never the one deciding to keep flying:
`VehicleLink` keeps the mode policy and the watchdogs, and when a watchdog trips (the stalled main loop
above all) it calls `stop()` from the watchdog thread, which sets zero velocity and then stops offboard
(MAVSDK switches PX4 to HOLD).

MAVSDK 4 is the native library in this process (no `mavsdk_server`, no gRPC API, no port of its own). It
runs as the vehicle's onboard component (the vehicle's system id, component 191, MAV_TYPE_ONBOARD_CONTROLLER)
on a `raw://` connection: its bytes go through `MavsdkRelay` and the companion's own link, so it opens no
socket and nothing but the autopilot can reach it. Install with `pip install 'cloudtrack[mavsdk]'`.

MAVSDK's `Offboard.start()` and `stop()` wait for PX4's COMMAND_ACK: seconds (a TIMEOUT after about 2 s)
while the autopilot is unreachable, which is exactly when the watchdog stops the vehicle. They run on this
adapter's own thread, latest request first, so neither the watchdog nor the streamer nor the main loop
ever waits on the autopilot (on a real PX4 with its link cut, the companion's main loop used to stall
3.5 s inside two stop() calls). The zero velocity a stop sets is immediate.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from behaviors.setpoint import Setpoint
from companion.mavlink.mavsdk_relay import MavsdkRelay

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 15.0


class MavsdkOffboard:
    """Thread-safe wrapper around MAVSDK's blocking offboard calls."""

    def __init__(self, relay: MavsdkRelay, system_id: int = 1, component_id: int = 191):
        self._relay = relay
        self._ids = (system_id, component_id)
        self._mavsdk: Any = None
        self._offboard: Any = None
        self._active = False
        self._lock = threading.Lock()
        self._requests = threading.Condition()
        self._request: tuple[str, str] | None = None  # the latest ("start" | "stop", reason) not yet run
        self._closing = False
        self._running = False  # a request is being carried out
        self._worker = threading.Thread(target=self._run_requests, name="mavsdk-offboard", daemon=True)

    def start(self) -> None:
        """Start MAVSDK on the relay and wait until it sees the autopilot; TimeoutError if it does not."""
        from mavsdk import ComponentType, Configuration, Mavsdk
        from mavsdk.plugins.offboard import Offboard

        config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        config.system_id, config.component_id = self._ids
        self._mavsdk = Mavsdk(config)
        result = self._mavsdk.add_any_connection("raw://")
        if int(result) != 0:
            raise RuntimeError(f"MAVSDK refused its raw connection: {result!r}")
        self._relay.attach(self._mavsdk)
        system = self._mavsdk.first_autopilot(CONNECT_TIMEOUT_S)
        if system is None:
            raise TimeoutError(f"MAVSDK saw no autopilot in {CONNECT_TIMEOUT_S:.0f} s")
        self._offboard = Offboard(system)
        self._worker.start()

    @property
    def active(self) -> bool:
        return self._active

    def set_velocity(self, setpoint: Setpoint) -> None:
        """The body-frame velocity MAVSDK keeps sending (already limited by the caller)."""
        from mavsdk.plugins.offboard import VelocityBodyYawspeed

        # Before MAVSDK sends it: the relay lets this setpoint through, fresh, and no other.
        self._relay.note_setpoint((setpoint.forward, setpoint.right, setpoint.down, setpoint.yaw_rate))
        velocity = VelocityBodyYawspeed(
            setpoint.forward,
            setpoint.right,
            setpoint.down,
            float(setpoint.yaw_rate * 180.0 / 3.141592653589793),
        )
        self._offboard.set_velocity_body(velocity)

    def start_offboard(self) -> None:
        """Ask PX4 for OFFBOARD (MAVSDK has been streaming since the first set_velocity), on the adapter's
        thread; a refusal is logged."""
        self._submit("start", "")

    def stop(self, reason: str) -> None:
        """Zero velocity now, then stop offboard (PX4 goes to HOLD) so MAVSDK stops re-sending.

        Always, not only when MAVSDK started offboard itself: the pilot may have selected OFFBOARD, and a
        zero left re-sending in OFFBOARD is not the configured hold.
        """
        with self._lock:
            self._active = False
        try:
            self.set_velocity(Setpoint.zero())
        except Exception as exc:  # the watchdog calls this; it must report, not die
            log.error("MAVSDK zero velocity failed (%s): %s", reason, exc)
        self._submit("stop", reason)

    def _submit(self, request: str, reason: str) -> None:
        with self._requests:
            self._request = (request, reason)
            self._requests.notify_all()

    def _run_requests(self) -> None:
        from mavsdk.plugins.offboard import OffboardError

        while True:
            with self._requests:
                while self._request is None and not self._closing:
                    self._requests.wait()
                if self._request is None:  # closing, and the last request (the final stop) has run
                    return
                assert self._request is not None
                (request, reason), self._request = self._request, None
                self._running = True
            try:
                if request == "start":
                    self._offboard.start()
                    with self._lock, self._requests:
                        self._active = self._request is None  # unless a stop came meanwhile
                else:
                    self._offboard.stop()
                    log.warning("MAVSDK offboard stopped: %s", reason)
            except OffboardError as exc:
                log.warning("MAVSDK offboard %s refused (%s): %s", request, reason or "mission", exc)
            except Exception as exc:  # this thread must outlive any MAVSDK error
                log.error("MAVSDK offboard %s failed (%s): %s", request, reason or "mission", exc)
            with self._requests:
                self._running = False
                self._requests.notify_all()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until every request so far has been carried out (MAVSDK needs the link's reader for the
        autopilot's answer, so the link waits for this before it closes); False on timeout."""
        with self._requests:
            return self._requests.wait_for(lambda: self._request is None and not self._running, timeout_s)

    def close(self) -> None:
        with self._requests:
            self._closing = True
            self._requests.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=3.0)  # the final stop: MAVSDK gives up on a lost autopilot after ~2 s
        self._relay.detach()
        if self._mavsdk is not None:
            self._mavsdk.destroy()  # stops its threads now, not at interpreter exit
            self._mavsdk = None
            self._offboard = None
