"""Offboard velocity through MAVSDK for PX4 users (`mavlink.use_mavsdk = true`).

MAVSDK's offboard plugin re-sends the last setpoint at 20 Hz by itself, even when the application that
set it has hung: a known fly-away cause. So this adapter is never the one deciding to keep flying:
`VehicleLink` keeps the mode policy and the watchdogs, and when a watchdog trips (the stalled main loop
above all) it calls `stop()` from the watchdog thread, which sets zero velocity and then stops offboard
(MAVSDK switches PX4 to HOLD). MAVSDK runs in its own asyncio thread, so none of this waits for the main
loop. The wheel ships `mavsdk_server`; `System.connect` starts it on a free gRPC port, as the vehicle's
system id and component 191, with its MAVLink carried over the companion's link by `MavsdkRelay` (which
keeps its ground-station HEARTBEAT away from the autopilot). Its gRPC API listens on every interface: the
3.x binary has no option to bind it to loopback (docs/safety.md, threat model). Install with
`pip install 'cloudtrack[mavsdk]'`.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import warnings
from collections.abc import Coroutine
from concurrent.futures import Future
from typing import Any

from behaviors.setpoint import Setpoint

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 15.0
CALL_TIMEOUT_S = 3.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class MavsdkOffboard:
    """Thread-safe wrapper: blocking calls that run MAVSDK coroutines on a private event loop."""

    def __init__(self, address: str, system_id: int = 1, component_id: int = 191):
        self._address = address  # MAVSDK's URL form (the relay's udpout://127.0.0.1:PORT)
        self._ids = (system_id, component_id)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="mavsdk", daemon=True)
        self._drone: Any = None
        self._active = False
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start mavsdk_server and wait until it sees the autopilot; TimeoutError if it does not."""
        self._thread.start()
        self._call(self._connect(), CONNECT_TIMEOUT_S)

    async def _connect(self) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # the 3.x gRPC wrapper announces its rename
            from mavsdk import System

        self._drone = System(port=_free_port(), sysid=self._ids[0], compid=self._ids[1])
        await self._drone.connect(system_address=self._address)
        async for state in self._drone.core.connection_state():
            if state.is_connected:
                return

    def _call(self, coro: Coroutine[Any, Any, Any], timeout: float = CALL_TIMEOUT_S) -> Any:
        future: Future[Any] = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return future.result(timeout)

    @property
    def active(self) -> bool:
        return self._active

    def set_velocity(self, setpoint: Setpoint) -> None:
        """The body-frame velocity MAVSDK keeps sending (already limited by the caller)."""
        from mavsdk.offboard import VelocityBodyYawspeed

        velocity = VelocityBodyYawspeed(
            setpoint.forward,
            setpoint.right,
            setpoint.down,
            float(setpoint.yaw_rate * 180.0 / 3.141592653589793),
        )
        self._call(self._drone.offboard.set_velocity_body(velocity))

    def start_offboard(self) -> bool:
        """Ask PX4 for OFFBOARD (MAVSDK has been streaming since the first set_velocity); False if refused."""
        from mavsdk.offboard import OffboardError

        try:
            self._call(self._drone.offboard.start())
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
            self._call(self._drone.offboard.stop())
            log.warning("MAVSDK offboard stopped: %s", reason)
        except Exception as exc:  # the watchdog calls this; it must report, not die
            log.error("MAVSDK offboard stop failed (%s): %s", reason, exc)

    def close(self) -> None:
        if self._drone is not None:
            self._drone._stop_mavsdk_server()
            self._drone = None  # collected now, not at interpreter exit where its __del__ fails
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=2.0)
