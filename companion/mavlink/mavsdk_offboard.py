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

    @property
    def active(self) -> bool:
        return self._active

    def set_velocity(self, setpoint: Setpoint) -> None:
        """The body-frame velocity MAVSDK keeps sending (already limited by the caller)."""
        from mavsdk.plugins.offboard import VelocityBodyYawspeed

        velocity = VelocityBodyYawspeed(
            setpoint.forward,
            setpoint.right,
            setpoint.down,
            float(setpoint.yaw_rate * 180.0 / 3.141592653589793),
        )
        self._offboard.set_velocity_body(velocity)

    def start_offboard(self) -> bool:
        """Ask PX4 for OFFBOARD (MAVSDK has been streaming since the first set_velocity); False if refused."""
        from mavsdk.plugins.offboard import OffboardError

        try:
            self._offboard.start()
        except OffboardError as exc:
            log.warning("MAVSDK offboard start refused: %s", exc)
            return False
        with self._lock:
            self._active = True
        return True

    def stop(self, reason: str) -> None:
        """Zero velocity, then stop offboard (PX4 goes to HOLD) so MAVSDK stops re-sending.

        Always, not only when MAVSDK started offboard itself: the pilot may have selected OFFBOARD, and a
        zero left re-sending in OFFBOARD is not the configured hold.
        """
        with self._lock:
            self._active = False
        try:
            self.set_velocity(Setpoint.zero())
            self._offboard.stop()
            log.warning("MAVSDK offboard stopped: %s", reason)
        except Exception as exc:  # the watchdog calls this; it must report, not die
            log.error("MAVSDK offboard stop failed (%s): %s", reason, exc)

    def close(self) -> None:
        self._relay.detach()
        if self._mavsdk is not None:
            self._mavsdk.destroy()  # stops its threads now, not at interpreter exit
            self._mavsdk = None
            self._offboard = None
