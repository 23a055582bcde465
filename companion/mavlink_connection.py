"""Opening a MAVLink 2 link with pymavlink, and a send/receive wrapper safe to share between threads.

Connection strings:
  serial:/dev/ttyAMA0:921600   serial port and baud rate (pyserial)
  udpin:0.0.0.0:14540          listen for UDP; replies go to every peer that sent to us
  udpout:127.0.0.1:14550       send UDP to host:port, receive the replies on the same socket
  tcp:127.0.0.1:5760           connect to a TCP server;  tcpin:0.0.0.0:5760 waits for one
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

os.environ["MAVLINK20"] = "1"  # pymavlink reads this when choosing the wire protocol
from pymavlink import mavutil  # noqa: E402

mavutil.set_dialect("ardupilotmega")
mavlink: Any = mavutil.mavlink
MAVLinkMessage = Any  # pymavlink's generated message classes have no usable static type

log = logging.getLogger(__name__)

_KINDS = ("serial", "udpin", "udpout", "tcp", "tcpin")
_EMPTY_PARSER_EXPECTS = 8  # pymavlink's MAVLink.expected_length for an empty buffer (v1 header + CRC)


@dataclass(frozen=True)
class ConnectionSpec:
    kind: str
    device: str  # what pymavlink's mavlink_connection takes
    baud: int = 115200


def parse_connection(url: str) -> ConnectionSpec:
    """A connection string checked and split; ValueError says what is wrong and what is allowed."""
    kind, sep, rest = url.partition(":")
    if not sep or kind not in _KINDS:
        raise ValueError(
            f"MAVLink connection {url!r}: expected one of serial:DEVICE:BAUD, udpin:HOST:PORT, "
            "udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT"
        )
    if kind == "serial":
        device, sep, baud = rest.rpartition(":")
        if not sep or not device or not baud.isdigit() or int(baud) <= 0:
            raise ValueError(f"MAVLink connection {url!r}: expected serial:DEVICE:BAUD, e.g. serial:/dev/ttyAMA0:921600")
        return ConnectionSpec(kind, device, int(baud))
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"MAVLink connection {url!r}: expected {kind}:HOST:PORT with a port 0-65535")
    return ConnectionSpec(kind, url)


def open_connection(url: str, source_system: int, source_component: int) -> Any:
    """A pymavlink connection speaking MAVLink 2 as (source_system, source_component)."""
    spec = parse_connection(url)
    if spec.kind == "serial":
        return mavutil.mavlink_connection(
            spec.device, baud=spec.baud, source_system=source_system, source_component=source_component,
            dialect="ardupilotmega", autoreconnect=True,
        )  # fmt: skip
    return mavutil.mavlink_connection(
        spec.device, source_system=source_system, source_component=source_component, dialect="ardupilotmega"
    )


def receive_message(conn: Any, timeout: float) -> MAVLinkMessage | None:
    """The next message (possibly BAD_DATA) from a pymavlink connection, or None after `timeout`.

    On UDP every datagram carries whole messages, so an incomplete frame left at the end of one datagram
    (garbage that looked like a header) is discarded instead of swallowing the next datagram's real
    messages, which pymavlink's byte-stream parser would do. Other links use pymavlink's own loop.
    """
    if not isinstance(conn, mavutil.mavudp):
        return conn.recv_match(blocking=True, timeout=timeout)
    mav = conn.mav
    deadline = time.monotonic() + timeout
    while True:
        msg = mav.parse_char(b"")  # further complete messages from the last datagram
        if msg is None and mav.buf_len() > 0:
            mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, _EMPTY_PARSER_EXPECTS
        if msg is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([conn.port], [], [], remaining)[0]:
                return None
            data = conn.recv()
            if not data:
                continue
            msg = mav.parse_char(data)
            if msg is None:
                continue
        conn.post_message(msg)
        return msg


class MavlinkEndpoint:
    """One pymavlink connection shared by several threads: sends are serialised (sequence numbers and
    signing timestamps live in the encoder), receiving belongs to one reader thread."""

    def __init__(self, conn: Any):
        self.conn = conn
        self._send_lock = threading.Lock()
        self._identities: dict[int, Any] = {}
        self.bad_data = 0

    @classmethod
    def open(cls, url: str, source_system: int, source_component: int) -> MavlinkEndpoint:
        return cls(open_connection(url, source_system, source_component))

    @property
    def mav(self) -> Any:
        return self.conn.mav

    def add_identity(self, component: int) -> None:
        """Also send as `component` of the same system on this link (sequence numbers of its own, the
        connection's signing key)."""
        encoder = mavlink.MAVLink(self.conn, self.conn.mav.srcSystem, component)
        encoder.signing = self.conn.mav.signing  # one signing state: setup_signing later applies to both
        self._identities[component] = encoder

    def send(self, build: Callable[[Any], Any], component: int | None = None) -> bool:
        """Run `build(mav)` (e.g. `lambda m: m.heartbeat_send(...)`) under the send lock; False on OSError.

        `component` picks an identity added with `add_identity`; default the connection's own.
        """
        encoder = self._identities.get(component, self.conn.mav) if component is not None else self.conn.mav
        with self._send_lock:
            try:
                build(encoder)
                return True
            except OSError as exc:
                log.warning("MAVLink send failed: %s", exc)
                return False

    def receive(self, timeout: float) -> MAVLinkMessage | None:
        """The next valid message, or None after `timeout`. Garbage becomes BAD_DATA, counted and dropped."""
        try:
            msg = receive_message(self.conn, timeout)
        except Exception as exc:  # a broken peer or a serial unplug must not end the reader thread
            log.warning("MAVLink receive error: %s", exc)
            return None
        if msg is not None and msg.get_type() == "BAD_DATA":
            self.bad_data += 1
            log.debug("MAVLink: dropped bad data (%s)", getattr(msg, "reason", ""))
            return None
        return msg

    def local_port(self) -> int:
        sock = getattr(self.conn, "port", None)
        if sock is None or not hasattr(sock, "getsockname"):
            raise ValueError("this connection has no local socket")
        return int(sock.getsockname()[1])

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()
