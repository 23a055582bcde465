"""mavsdk_server's MAVLink, carried over the companion's own link (only with `mavlink.use_mavsdk`).

mavsdk_server 3.x always announces itself as a ground station (a MAV_TYPE_GCS HEARTBEAT from component
190, besides its own id), and PX4 counts GCS heartbeats when it decides whether the data link is lost
(`NAV_DLL_ACT`): a companion-side GCS would hide a real GCS loss. So mavsdk_server never talks to the
autopilot directly. It sends to a loopback UDP socket owned by this relay; the relay forwards everything
but its HEARTBEATs to the autopilot through the companion's link (re-encoded as the companion, signed when
signing is on), and forwards the autopilot's messages to it. The only HEARTBEAT the autopilot sees from
the companion is the companion's own MAV_TYPE_ONBOARD_CONTROLLER one (same system id, component 191).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections.abc import Callable
from typing import Any

from cloudtrack.mavlink_connection import MavlinkEndpoint, mavlink

log = logging.getLogger(__name__)


class MavsdkRelay:
    def __init__(self, endpoint: MavlinkEndpoint):
        self._endpoint = endpoint
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.1)
        self._server: tuple[str, int] | None = None  # mavsdk_server's address, from its first datagram
        self._parser = self._new_parser()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavsdk-relay", daemon=True)
        self.heartbeats_dropped = 0
        self.forwarded = 0

    @staticmethod
    def _new_parser() -> Any:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        return parser

    @property
    def url(self) -> str:
        """Where mavsdk_server sends (MAVSDK's connection URL)."""
        return f"udpout://127.0.0.1:{self._sock.getsockname()[1]}"

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def to_mavsdk(self, msg: Any) -> None:
        """A message from the autopilot (called by the link's reader)."""
        server = self._server
        if server is not None:
            with contextlib.suppress(OSError):  # mavsdk_server gone: nothing to tell it
                self._sock.sendto(msg.get_msgbuf(), server)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(65535)
            except (TimeoutError, OSError):
                continue
            if addr[0] != "127.0.0.1" or (self._server is not None and addr != self._server):
                continue  # only the mavsdk_server we started talks to us
            self._server = addr
            messages = self._parser.parse_buffer(data) or []
            if self._parser.buf_len() > 0:
                self._parser = self._new_parser()
            for msg in messages:
                if msg.get_type() == "BAD_DATA":
                    continue
                if msg.get_type() == "HEARTBEAT":
                    self.heartbeats_dropped += 1  # its GCS (and generic) identities stay on this computer
                    continue
                if self._endpoint.send(_resend(msg)):
                    self.forwarded += 1


def _resend(msg: Any) -> Callable[[Any], None]:
    """Re-encode `msg` with the companion's encoder (its ids, sequence and signature)."""
    return lambda mav: mav.send(msg)
