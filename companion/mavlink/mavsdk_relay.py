"""MAVSDK's MAVLink, carried over the companion's own link (only with `mavlink.use_mavsdk`).

MAVSDK runs in this process on a `raw://` connection: it sends and receives bytes, never a socket, so it
has no port anyone else could reach. The relay forwards what MAVSDK sends to the autopilot through the
companion's link (re-encoded as the companion, signed when signing is on) and hands it the autopilot's
messages. MAVSDK's own HEARTBEATs stay here: PX4 counts heartbeats when it decides whether links are
alive, and the only HEARTBEAT the autopilot should see from this computer is the companion's own
MAV_TYPE_ONBOARD_CONTROLLER one (same system id, component 191).

MAVSDK re-sends the last setpoint at 20 Hz until it notices the vehicle left OFFBOARD, which it learns
only from PX4's HEARTBEAT (1 Hz). After a pilot's takeover the companion knows within 100 ms (PX4's
CURRENT_MODE) and closes `setpoints_allowed`: MAVSDK's setpoints stop here until a mission enables
offboard control again. For the same reason it drops MAVSDK's setpoints once the last one the companion
handed it is older than `max_setpoint_age_s` (`[safety] setpoint_max_age_s`, as every setpoint of the
pymavlink path): after a freeze (SIGSTOP, swap) MAVSDK's timer wakes with the process and re-sent the
pre-freeze command 1 ms after SIGCONT, before the watchdog could set zero (measured on a real PX4). And it
forwards only the setpoint the companion handed MAVSDK last: the watchdog's zero after a freeze is fresh,
but MAVSDK's timer re-sent the pre-freeze command (1.52 m/s) 11 ms after SIGCONT, before the zero had reached
MAVSDK's offboard plugin (measured on a real PX4; a fresh time alone let it through).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from cloudtrack.mavlink_connection import MavlinkEndpoint, mavlink

log = logging.getLogger(__name__)


class MavsdkRelay:
    def __init__(
        self,
        endpoint: MavlinkEndpoint,
        max_setpoint_age_s: float = math.inf,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._endpoint = endpoint
        self._max_age = max_setpoint_age_s
        self._clock = clock
        self._setpoint_time = -math.inf  # when the companion last handed MAVSDK a setpoint
        self._setpoint: tuple[float, float, float, float] | None = None  # and which one
        self._mavsdk: Any = None
        self._subscription: Any = None
        self._parser = self._new_parser()
        self._lock = threading.Lock()  # MAVSDK calls back from its own threads
        self.heartbeats_dropped = 0
        self.setpoints_dropped = 0
        self.forwarded = 0
        self.setpoints_allowed = True

    def note_setpoint(self, velocity: tuple[float, float, float, float]) -> None:
        """The companion is handing MAVSDK `velocity` (forward, right, down in m/s, yaw rate in rad/s; BODY_NED):
        MAVSDK's sends of it are fresh for `max_setpoint_age_s`, any other setpoint is dropped."""
        with self._lock:
            self._setpoint_time = self._clock()
            self._setpoint = velocity

    def _setpoint_wanted(self, msg: Any) -> bool:
        """The one the companion handed last, fresh, and setpoints allowed (lock held)."""
        if not self.setpoints_allowed or self._setpoint is None:
            return False
        if self._clock() - self._setpoint_time > self._max_age:
            return False
        sent = (msg.vx, msg.vy, msg.vz, msg.yaw_rate)  # float32 on the wire
        return all(abs(a - b) <= 1e-3 * max(1.0, abs(b)) for a, b in zip(sent, self._setpoint, strict=True))

    @staticmethod
    def _new_parser() -> Any:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        return parser

    def attach(self, mavsdk: Any) -> None:
        """Start carrying bytes for `mavsdk` (a `mavsdk.Mavsdk` with a `raw://` connection)."""
        self._subscription = mavsdk.subscribe_raw_bytes_to_be_sent(self.from_mavsdk)
        self._mavsdk = mavsdk

    def detach(self) -> None:
        mavsdk, self._mavsdk = self._mavsdk, None
        if mavsdk is not None and self._subscription is not None:
            mavsdk.unsubscribe_raw_bytes_to_be_sent(self._subscription)
        self._subscription = None

    def to_mavsdk(self, msg: Any) -> None:
        """A message from the autopilot (called by the link's reader)."""
        mavsdk = self._mavsdk
        if mavsdk is not None:
            try:
                mavsdk.pass_received_raw_bytes(bytes(msg.get_msgbuf()))
            except Exception as exc:  # the link's reader must never die of it
                log.error("MAVSDK relay dropped a message from the autopilot: %s", exc)

    def from_mavsdk(self, data: bytes) -> None:
        """Bytes MAVSDK wants sent: everything but its HEARTBEATs goes to the autopilot as the companion."""
        try:
            with self._lock:
                messages = self._parser.parse_buffer(data) or []
                if self._parser.buf_len() > 0:
                    self._parser = self._new_parser()  # a partial frame never joins the next send
                wanted = [
                    msg.get_type() != "SET_POSITION_TARGET_LOCAL_NED" or self._setpoint_wanted(msg)
                    for msg in messages
                ]
            for msg, ok in zip(messages, wanted, strict=True):
                if msg.get_type() == "BAD_DATA":
                    continue
                if msg.get_type() == "HEARTBEAT":
                    self.heartbeats_dropped += 1
                    continue
                if not ok:
                    self.setpoints_dropped += 1
                    continue
                if self._endpoint.send(_resend(msg)):
                    self.forwarded += 1
        except Exception as exc:  # a C callback must never raise into MAVSDK
            log.error("MAVSDK relay dropped a send: %s", exc)


def _resend(msg: Any) -> Callable[[Any], None]:
    """Re-encode `msg` with the companion's encoder (its ids, sequence and signature)."""
    return lambda mav: mav.send(msg)
