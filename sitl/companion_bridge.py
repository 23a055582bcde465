"""The companion's link to a real SITL autopilot, relayed through the runner: recorded, and cut on demand.

`CompanionBridge` relays the companion's UDP datagrams to the autopilot's companion port and back. The
autopilot side is a connected socket: ArduCopter's SERIAL2 is a TCP stream, PX4's onboard MAVLink
instance a UDP port (a connected UDP socket sends and receives whole datagrams with the same calls). It
records every SET_POSITION_TARGET_LOCAL_NED the companion sends (the metrics' "setpoints received",
with the autopilot's mode at that moment) and can cut the link both ways, the real-autopilot counterpart
of the mock's `set_link_down`.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink import mavutil


@dataclass(frozen=True)
class BridgedSetpoint:
    """One SET_POSITION_TARGET_LOCAL_NED the companion sent to the real autopilot (as `ReceivedSetpoint`)."""

    time: float
    link: str
    frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw_rate: float
    mode: str


class CompanionBridge:
    """UDP (companion side) <-> the autopilot's companion port, recording the companion's setpoints;
    `set_down(True)` drops both ways.

    `autopilot`: a socket connected to the autopilot's port (TCP stream or connected UDP); the bridge owns
    and closes it. `companion_port` None: the companion sends to us (`udpout:` to `udp_port`) and we answer
    its address; a port: the companion listens there (`udpin:`) and we send to it, as a flight controller's
    UDP output.
    """

    def __init__(
        self, autopilot: socket.socket, mode_of: Callable[[], str], companion_port: int | None = None
    ) -> None:
        self._autopilot = autopilot
        self._autopilot.settimeout(0.2)
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.bind(("127.0.0.1", 0))
        self._udp.settimeout(0.2)
        self.udp_port = int(self._udp.getsockname()[1])
        self._peer: tuple[str, int] | None = ("127.0.0.1", companion_port) if companion_port else None
        self._mode_of = mode_of
        self._parser = mavutil.mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self.setpoints: list[BridgedSetpoint] = []
        # The companion's commands, as the mock records them: (time, "companion", MAV_CMD); SET_MODE counts as
        # MAV_CMD_DO_SET_MODE (176). What a scenario looking only checks it never sent.
        self.commands: list[tuple[float, str, int]] = []
        self._down = threading.Event()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._up, name="bridge-up", daemon=True),
            threading.Thread(target=self._downlink, name="bridge-down", daemon=True),
        ]

    def start(self) -> CompanionBridge:
        for t in self._threads:
            t.start()
        return self

    def reset(self, companion_port: int | None) -> None:
        """For the next companion on a reused autopilot: its address learnt afresh (or its listening port),
        nothing recorded, the link up."""
        self._peer = ("127.0.0.1", companion_port) if companion_port else None
        self.setpoints = []
        self.commands = []
        self._down.clear()

    def set_down(self, down: bool) -> None:
        if down:
            self._down.set()
        else:
            self._down.clear()

    def _up(self) -> None:
        """Companion -> autopilot."""
        while not self._stop.is_set():
            try:
                data, addr = self._udp.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            if self._peer is None or self._peer[1] != addr[1]:
                if self._peer is None:
                    self._peer = addr
                else:
                    continue  # only the companion's own address speaks to the autopilot through us
            if self._down.is_set():
                continue
            now = time.monotonic()
            try:
                msgs = self._parser.parse_buffer(data) or []
            except Exception:  # the bridge only observes; the autopilot judges the bytes
                msgs = []
            for m in msgs:
                if m.get_type() in ("COMMAND_LONG", "COMMAND_INT"):
                    self.commands.append((now, "companion", int(m.command)))
                elif m.get_type() == "SET_MODE":
                    self.commands.append((now, "companion", mavutil.mavlink.MAV_CMD_DO_SET_MODE))
                if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                    self.setpoints.append(
                        BridgedSetpoint(
                            now,
                            "companion",
                            m.coordinate_frame,
                            m.type_mask,
                            m.vx,
                            m.vy,
                            m.vz,
                            m.yaw_rate,
                            self._mode_of(),
                        )
                    )
            try:
                self._autopilot.sendall(data)
            except ConnectionRefusedError:
                continue  # UDP: the autopilot's port was not open yet (or restarting); the next one may land
            except OSError:
                return

    def _downlink(self) -> None:
        """Autopilot -> companion (a TCP byte stream is forwarded in chunks: MAVLink framing survives)."""
        while not self._stop.is_set():
            try:
                data = self._autopilot.recv(65536)
            except TimeoutError:
                continue
            except ConnectionRefusedError:
                continue  # UDP: an ICMP "port unreachable" for an earlier datagram
            except OSError:
                return
            if not data:
                if self._autopilot.type == socket.SOCK_STREAM:
                    return  # TCP: the autopilot closed the stream
                continue
            if self._down.is_set() or self._peer is None:
                continue
            with contextlib.suppress(OSError):
                self._udp.sendto(data, self._peer)

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        for s in (self._autopilot, self._udp):
            s.close()
