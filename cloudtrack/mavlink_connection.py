"""Opening a MAVLink 2 link with pymavlink, and a send/receive wrapper safe to share between threads.

Connection strings (pymavlink's own format, the one format for every MAVLink endpoint in `[mavlink]`):
  udpin:127.0.0.1:14540        listen for UDP on loopback (the default: the autopilot or mavlink-router on
                               the same computer); the peer is the sender of the autopilot's HEARTBEAT
  udpout:127.0.0.1:14550       send UDP to host:port; only datagrams from that address are read
  /dev/ttyAMA0,921600          serial device and baud rate (MAVProxy's form; `serial:/dev/ttyAMA0:921600`
                               is accepted as the same thing)
  tcp:127.0.0.1:5760           connect to a TCP server;  tcpin:127.0.0.1:5760 waits for one

A UDP link talks to exactly one peer (`PeerUdp`): the autopilot's address, configured (udpout) or learned
from the first HEARTBEAT of the autopilot's system id (udpin). Datagrams from anyone else are dropped before
they are parsed, counted per address in a bounded table that ages out, and nothing is ever sent to them.
pymavlink's own `udpin` adds every sender to a client set from the reader thread while `write()` iterates
it from another thread, never forgets a client and replies to all of them; this class replaces that.

Importing this module changes no environment variable and no pymavlink global: the MAVLink 2 ardupilotmega
dialect is imported directly and installed on each connection it opens.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import select
import socket
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as _dialect

mavlink: Any = _dialect
MAVLinkMessage = Any  # pymavlink's generated message classes have no usable static type

log = logging.getLogger(__name__)

_KINDS = ("serial", "udpin", "udpout", "tcp", "tcpin")
DEFAULT_CONNECTION = "udpin:127.0.0.1:14540"
PEER_TIMEOUT_S = 5.0  # a learned UDP peer silent this long may be replaced by the next autopilot HEARTBEAT
MAX_REFUSED_PEERS = 64  # refused addresses remembered (for counting and log rate), oldest forgotten first
REFUSED_LOG_PERIOD_S = 10.0
UDP_MAX_DATAGRAM = 65535


@dataclass(frozen=True)
class ConnectionSpec:
    kind: str
    device: str  # what pymavlink's mavlink_connection takes
    baud: int = 115200


def parse_connection(url: str) -> ConnectionSpec:
    """A connection string checked and split; ValueError says what is wrong and what is allowed."""
    if url.startswith("/dev/") or url.startswith("COM"):  # pymavlink's serial device, MAVProxy's ",BAUD"
        device, sep, baud = url.partition(",")
        if sep and (not baud.isdigit() or int(baud) <= 0):
            raise ValueError(
                f"MAVLink connection {url!r}: expected DEVICE or DEVICE,BAUD, e.g. /dev/ttyAMA0,921600"
            )
        return ConnectionSpec("serial", device, int(baud) if sep else 115200)
    kind, sep, rest = url.partition(":")
    if not sep or kind not in _KINDS:
        raise ValueError(
            f"MAVLink connection {url!r}: expected one of udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
            "tcpin:HOST:PORT, /dev/DEVICE,BAUD (or serial:DEVICE:BAUD)"
        )
    if kind == "serial":
        device, sep, baud = rest.rpartition(":")
        if not sep or not device or not baud.isdigit() or int(baud) <= 0:
            raise ValueError(
                f"MAVLink connection {url!r}: expected serial:DEVICE:BAUD, e.g. serial:/dev/ttyAMA0:921600"
            )
        return ConnectionSpec(kind, device, int(baud))
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"MAVLink connection {url!r}: expected {kind}:HOST:PORT with a port 0-65535")
    return ConnectionSpec(kind, url)


def use_mavlink2(conn: Any) -> Any:
    """Give a pymavlink connection a MAVLink 2 ardupilotmega encoder/parser of its own (no global dialect)."""
    conn.mav = _dialect.MAVLink(conn, srcSystem=conn.source_system, srcComponent=conn.source_component)
    conn.mav.robust_parsing = True
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    conn.first_byte = False  # pymavlink would otherwise "auto-switch" by setting MAVLINK20 and the dialect
    return conn


class PeerUdp(mavutil.mavudp):  # type: ignore[misc]
    """A UDP MAVLink link with one peer. Sending and the peer table are thread-safe.

    `peer` given (udpout): only that address is read and written. Otherwise (udpin) the peer is learned
    from the first HEARTBEAT of `autopilot_system`'s autopilot (component 1) and may be replaced only after
    PEER_TIMEOUT_S of silence. Until a peer is known nothing is sent.
    """

    def __init__(self, device: str, source_system: int, source_component: int, autopilot_system: int | None,
                 peer: tuple[str, int] | None = None):  # fmt: skip
        super().__init__(
            device, input=peer is None, source_system=source_system, source_component=source_component
        )
        if peer is not None:
            host = socket.gethostbyname(peer[0])
            peer = (host, peer[1])
        self.fixed_peer = peer is not None
        self.peer: tuple[str, int] | None = peer
        self.autopilot_system = autopilot_system
        self._peer_seen = time.monotonic() if peer is not None else -math.inf
        self._lock = threading.Lock()
        self._candidate: tuple[str, int] | None = None
        self.refused: OrderedDict[tuple[str, int], list[float]] = OrderedDict()  # addr -> [count, last log]
        self.refused_datagrams = 0
        self.send_errors = 0
        self._reader = DatagramReader(self, self._note)

    # ------------------------------------------------------------------------------------------ peers
    def recv(self, n: int | None = None) -> bytes:
        try:
            data, addr = self.port.recvfrom(UDP_MAX_DATAGRAM)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise
        now = time.monotonic()
        with self._lock:
            if addr == self.peer:
                self._peer_seen = now
                self._candidate = None
                return bytes(data)
            if not self.fixed_peer and now - self._peer_seen > PEER_TIMEOUT_S:
                self._candidate = addr  # parsed: it becomes the peer if it carries the autopilot's HEARTBEAT
                return bytes(data)
            self._refuse(addr, now)
        return b""

    def _refuse(self, addr: tuple[str, int], now: float) -> None:
        self.refused_datagrams += 1
        entry = self.refused.pop(addr, None) or [0.0, -math.inf]
        entry[0] += 1
        self.refused[addr] = entry  # most recent last
        while len(self.refused) > MAX_REFUSED_PEERS:
            self.refused.popitem(last=False)
        if now - entry[1] >= REFUSED_LOG_PERIOD_S:
            entry[1] = now
            log.warning(
                "MAVLink: refused %d datagram(s) from %s:%d (not the autopilot's address)",
                int(entry[0]),
                *addr,
            )

    def _note(self, msg: Any) -> None:
        """Learn the peer from the autopilot's HEARTBEAT (called for each message parsed from a datagram)."""
        with self._lock:
            candidate = self._candidate
            if candidate is None or msg.get_type() != "HEARTBEAT" or msg.get_srcComponent() != 1:
                return
            if self.autopilot_system is not None and msg.get_srcSystem() != self.autopilot_system:
                return
            if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type == mavlink.MAV_TYPE_GCS:
                return
            if candidate != self.peer:
                log.info("MAVLink: autopilot at %s:%d", *candidate)
            self.peer, self._peer_seen, self._candidate = candidate, time.monotonic(), None

    def write(self, buf: bytes) -> None:
        with self._lock:
            peer = self.peer
        if peer is None:
            return
        try:
            self.port.sendto(buf, peer)
        except OSError:
            self.send_errors += 1

    def receive(self, timeout: float) -> MAVLinkMessage | None:
        """The next message of the peer (possibly BAD_DATA), or None after `timeout`."""
        msg = self._reader.receive(timeout)
        with self._lock:
            self._candidate = None
        return msg


class DatagramReader:
    """Messages from a pymavlink UDP connection, one datagram at a time, through a parser of its own.

    Every datagram carries whole messages: a partial frame left at its end (garbage that looked like a
    header) is dropped with its parser, so it cannot swallow the next datagram's real messages. Only
    pymavlink's public API is used (a new `MAVLink` parser sharing the link's signing state).
    """

    def __init__(self, conn: Any, on_message: Callable[[Any], None] | None = None):
        self._conn = conn
        self._on_message = on_message
        self._rx = self._parser()
        self._pending: deque[Any] = deque()

    def _parser(self) -> Any:
        conn = self._conn
        parser = _dialect.MAVLink(conn, srcSystem=conn.source_system, srcComponent=conn.source_component)
        parser.robust_parsing = True
        parser.signing = conn.mav.signing  # one signing state: setup_signing on the link covers receiving
        return parser

    def receive(self, timeout: float) -> MAVLinkMessage | None:
        conn = self._conn
        deadline = time.monotonic() + timeout
        while not self._pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([conn.port], [], [], remaining)[0]:
                return None
            data = conn.recv()
            if not data:
                continue
            messages = self._rx.parse_buffer(bytes(data)) or []
            if self._rx.buf_len() > 0:
                self._rx = self._parser()
            for msg in messages:
                if self._on_message is not None and msg.get_type() != "BAD_DATA":
                    self._on_message(msg)
            self._pending.extend(messages)
        msg = self._pending.popleft()
        conn.post_message(msg)
        return msg


def open_connection(
    url: str, source_system: int, source_component: int, autopilot_system: int | None = None
) -> Any:
    """A pymavlink connection speaking MAVLink 2 as (source_system, source_component).

    UDP links are `PeerUdp`; `autopilot_system` is the system id whose autopilot HEARTBEAT a udpin link
    learns its peer from (None: any autopilot's).
    """
    spec = parse_connection(url)
    if spec.kind == "serial":
        conn = mavutil.mavlink_connection(
            spec.device, baud=spec.baud, source_system=source_system, source_component=source_component,
            autoreconnect=True,
        )  # fmt: skip
    elif spec.kind in ("udpin", "udpout"):
        host, _, port = url.partition(":")[2].rpartition(":")
        peer = (host, int(port)) if spec.kind == "udpout" else None
        bind = f"{host}:{port}" if spec.kind == "udpin" else "0.0.0.0:0"
        conn = PeerUdp(bind, source_system, source_component, autopilot_system, peer)
    else:
        conn = mavutil.mavlink_connection(
            spec.device, source_system=source_system, source_component=source_component
        )
    use_mavlink2(conn)
    if isinstance(conn, PeerUdp):
        conn._reader = DatagramReader(conn, conn._note)  # parse with the MAVLink 2 signing state
    return conn


def receive_message(conn: Any, timeout: float) -> MAVLinkMessage | None:
    """The next message (possibly BAD_DATA) from a pymavlink connection, or None after `timeout`."""
    if isinstance(conn, PeerUdp):
        return conn.receive(timeout)
    if isinstance(conn, mavutil.mavudp):  # pymavlink's own UDP (the simulator's multi-client links)
        reader = getattr(conn, "_datagram_reader", None)
        if reader is None:
            reader = DatagramReader(conn)
            conn._datagram_reader = reader
        return reader.receive(timeout)
    return conn.recv_match(blocking=True, timeout=timeout)


class MavlinkEndpoint:
    """One pymavlink connection shared by several threads: sends are serialised (sequence numbers and
    signing timestamps live in the encoder), receiving belongs to one reader thread. No exception from the
    link leaves `send` or `receive`: a hostile peer or an unplugged cable is logged, never fatal."""

    def __init__(self, conn: Any):
        self.conn = conn
        self._send_lock = threading.Lock()
        self._identities: dict[int, Any] = {}
        self.bad_data = 0
        self.send_failures = 0
        self._last_send_log = -math.inf

    @classmethod
    def open(
        cls, url: str, source_system: int, source_component: int, autopilot_system: int | None = None
    ) -> MavlinkEndpoint:
        return cls(open_connection(url, source_system, source_component, autopilot_system))

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
        """Run `build(mav)` (e.g. `lambda m: m.heartbeat_send(...)`) under the send lock; False if it failed.

        `component` picks an identity added with `add_identity`; default the connection's own. `build` may
        return False to send nothing (e.g. a setpoint found too old at the moment of encoding).
        """
        encoder = self._identities.get(component, self.conn.mav) if component is not None else self.conn.mav
        with self._send_lock:
            try:
                return build(encoder) is not False
            except Exception as exc:  # noqa: BLE001 - the link must never end a caller's loop
                self.send_failures += 1
                now = time.monotonic()
                if now - self._last_send_log >= REFUSED_LOG_PERIOD_S:
                    self._last_send_log = now
                    log.warning("MAVLink send failed (%d so far): %s", self.send_failures, exc)
                return False

    def receive(self, timeout: float) -> MAVLinkMessage | None:
        """The next valid message, or None after `timeout`. Garbage becomes BAD_DATA, counted and dropped."""
        try:
            msg = receive_message(self.conn, timeout)
        except Exception as exc:  # a broken peer or a serial unplug must not end the reader thread
            log.warning("MAVLink receive error: %s", exc)
            time.sleep(min(timeout, 0.05))
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
