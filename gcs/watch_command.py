"""`cloudtrack-gcs watch`: what the vehicle says, summarised for a person, and its finds to the team's map.

Events are printed as they happen: the companion's status lines (a repeat of the same line within
`REPEAT_S` is counted, not printed), the autopilot's mode changes, tracking starting and stopping, and
each find (`FOUND <lat>,<lon> +-<sigma>m`, its description, CAMERA_TRACKING_GEO_STATUS). Every `--every`
seconds one summary line says what goes on (tracking for how long and where, the autopilot's mode, the
last status line); the 10 Hz tracking status and the numbers are never printed one by one (`--verbose`
prints every message, as before). `--until-candidate` stops once a candidate awaits the supervisor (the
next thing to do is to decide). With `--cot-url`, each find heard is forwarded as a Cursor-on-Target
event (`cloudtrack/cursor_on_target.py`) to ATAK devices on the ground station's own network or a TAK
server: a site with no internet still gets the find on its map. The address is checked and its host
looked up before the link opens (`check_arguments`); a find is said "delivered" once the TCP/TLS
connection took it, "sent, delivery not confirmed" for UDP, and `watch` exits 1 when a find heard was never
delivered. A position off the globe (a STATUSTEXT `FOUND 999.0,-720.5 ...`) is said, not taken as a find.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from cloudtrack.autopilot_modes import detect_autopilot, mode_name
from cloudtrack.cursor_on_target import CotSender, FindReport, find_event, resolve_url
from cloudtrack.mavlink_connection import mavlink

REPEAT_S = 10.0
SAME_FIND_M = 5.0
_FOUND = re.compile(r"^FOUND (-?\d+(?:\.\d+)?),(-?\d+(?:\.\d+)?) \+-(\d+(?:\.\d+)?)m$")
_FOUND_TEXT = re.compile(r"^FOUND: (.*) \(confirmed by (.*?)(?:; seen (\d{1,5}) s before)?\)$")
_AWAITING = re.compile(r"^CANDIDATE (?:AWAITING|REVERIFIED) (\S+)")


@dataclass(frozen=True)
class HeardFind:
    number: int
    lat: float
    lon: float
    sigma_m: float | None
    time: float
    prompt: str = ""
    confirmed_by: str = ""
    seen_at: float | None = None  # when the position was observed (Unix s); None: not known


def _metres(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = (a[0] - b[0]) * 111_320.0
    east = (a[1] - b[1]) * 111_320.0 * math.cos(math.radians(a[0]))
    return math.hypot(north, east)


class WatchSummary:
    """Turns the vehicle's MAVLink messages into the lines `watch` prints; knows the finds heard."""

    def __init__(
        self,
        system: int,
        every_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.system = system
        self.every_s = every_s
        self._clock = clock
        self._wall = wall_clock
        self._next_summary = clock() + every_s
        self._mode = ""
        self._last_text: tuple[str, float] | None = None
        self._repeats = 0
        self._tracking_since: float | None = None
        self._target: tuple[float, float] | None = None
        self._values: dict[str, float] = {}
        self.finds: list[HeardFind] = []
        self.awaiting: str | None = None  # the candidate the companion last said awaits the supervisor
        self.changed_finds: list[HeardFind] = []  # new or updated since the caller last took them

    def feed(self, msg: Any, text: str | None = None) -> list[str]:
        """Lines for one message; `text` is a STATUSTEXT's whole line (its chunks joined), None until then."""
        if msg.get_srcSystem() != self.system:
            return []
        mtype = msg.get_type()
        src = f"{msg.get_srcSystem()}/{msg.get_srcComponent()}"
        if mtype == "HEARTBEAT" and msg.get_srcComponent() == 1:
            kind = detect_autopilot(msg.autopilot)
            mode = mode_name(kind, msg.custom_mode, msg.type) if kind else str(msg.custom_mode)
            if mode != self._mode:
                self._mode = mode
                return [f"[autopilot] mode {mode}"]
            return []
        if mtype == "STATUSTEXT":
            return [] if text is None else self._status(src, text)
        if mtype == "CAMERA_TRACKING_IMAGE_STATUS":
            return self._tracking(src, msg)
        if mtype == "CAMERA_TRACKING_GEO_STATUS":
            if msg.tracking_status & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE:
                sigma = msg.h_acc if math.isfinite(msg.h_acc) else None
                return self._find(src, msg.lat / 1e7, msg.lon / 1e7, sigma, quiet=True)
            return []
        if mtype == "NAMED_VALUE_FLOAT":
            name = (
                msg.name.rstrip("\0") if isinstance(msg.name, str) else bytes(msg.name).rstrip(b"\0").decode()
            )
            self._values[name] = float(msg.value)
        return []

    def _status(self, src: str, text: str) -> list[str]:
        now = self._clock()
        awaiting = _AWAITING.match(text)
        if awaiting:
            self.awaiting = awaiting.group(1)
        if self._last_text is not None and self._last_text[0] == text and now - self._last_text[1] < REPEAT_S:
            self._repeats += 1
            return []
        self._last_text, self._repeats = (text, now), 0
        lines = [f"[{src}] {text}"]
        found = _FOUND.match(text)
        if found:
            lat, lon, sigma = (float(v) for v in found.groups())
            lines += self._find(src, lat, lon, sigma, quiet=True)
        described = _FOUND_TEXT.match(text)
        if described and self.finds:
            # The announcement says how long before the confirmation the position was seen (no words: at it).
            before = float(described.group(3) or 0.0)
            last = replace(
                self.finds[-1],
                prompt=described.group(1),
                confirmed_by=described.group(2),
                seen_at=self.finds[-1].time - before,
            )
            self.finds[-1] = last
            self.changed_finds.append(last)
        return lines

    def _tracking(self, src: str, msg: Any) -> list[str]:
        active = bool(msg.tracking_status & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE)
        if active:
            self._target = (msg.point_x, msg.point_y)
            if self._tracking_since is None:
                self._tracking_since = self._clock()
                return [f"[{src}] tracking: target at ({msg.point_x:.2f}, {msg.point_y:.2f})"]
            return []
        if self._tracking_since is not None:
            held = self._clock() - self._tracking_since
            self._tracking_since = None
            return [f"[{src}] tracking stopped after {held:.1f} s"]
        return []

    def _find(self, src: str, lat: float, lon: float, sigma: float | None, quiet: bool) -> list[str]:
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return [f"[{src}] not a find: {lat:g},{lon:g} is off the globe (lat -90..90, lon -180..180)"]
        if sigma is not None and not (math.isfinite(sigma) and sigma >= 0.0):
            sigma = None  # an accuracy that is no distance is not known
        for i, known in enumerate(self.finds):
            if _metres((known.lat, known.lon), (lat, lon)) <= SAME_FIND_M:
                if (known.lat, known.lon, known.sigma_m) != (lat, lon, sigma):
                    # A find moves only to the track's newest estimate (behaviors.target_fix): seen about now.
                    self.finds[i] = replace(known, lat=lat, lon=lon, sigma_m=sigma, seen_at=self._wall())
                    self.changed_finds.append(self.finds[i])
                return []
        find = HeardFind(len(self.finds) + 1, lat, lon, sigma, self._wall())
        self.finds.append(find)
        self.changed_finds.append(find)
        accuracy = f" +-{sigma:.1f} m" if sigma is not None else ""
        return [f"[{src}] find {find.number} at {lat:.6f},{lon:.6f}{accuracy}"]

    def take_changed_finds(self) -> list[HeardFind]:
        """Finds new or updated since the last call, each once, latest state."""
        latest = {f.number: self.finds[f.number - 1] for f in self.changed_finds}
        self.changed_finds = []
        return list(latest.values())

    def tick(self) -> list[str]:
        """The summary line, once every `every_s`."""
        now = self._clock()
        if now < self._next_summary:
            return []
        self._next_summary = now + self.every_s
        return [self.line()]

    def line(self) -> str:
        """The summary line now: tracking for how long and where, the mode, the finds, the last line."""
        now = self._clock()
        parts = []
        if self._tracking_since is not None and self._target is not None:
            parts.append(
                f"tracking {now - self._tracking_since:.0f} s, target at ({self._target[0]:.2f}, {self._target[1]:.2f})"
            )
        else:
            parts.append("not tracking")
        if self._mode:
            parts.append(f"mode {self._mode}")
        if self.finds:
            parts.append(f"{len(self.finds)} find(s)")
        if self._values:
            parts.append(" ".join(f"{k}={v:g}" for k, v in sorted(self._values.items())))
        if self._last_text is not None:
            repeated = f" (x{self._repeats + 1})" if self._repeats else ""
            parts.append(f"last: {self._last_text[0]}{repeated}")
        return f"[summary] {'; '.join(parts)}"


def add_arguments(watch: argparse.ArgumentParser) -> None:
    watch.add_argument(
        "--duration",
        type=float,
        default=0.0,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    watch.add_argument(
        "--every", type=float, default=10.0, metavar="S", help="a summary line every S seconds (default 10)"
    )
    watch.add_argument(
        "--until-candidate",
        action="store_true",
        help="stop once a candidate awaits the supervisor (exit 0), or exit 1 if none did within --duration",
    )
    watch.add_argument("--verbose", action="store_true", help="print every message, the 10 Hz tracking too")
    watch.add_argument(
        "--cot-url",
        metavar="URL",
        help="forward each find heard as a Cursor-on-Target event: udp://239.2.3.1:6969 (ATAK devices on "
        "this network), tcp://host:8087 or tls://host:8089 (a TAK server, with --tls-cert and --tls-key); "
        "checked and its host looked up before watching; default: none",
    )
    for flag, what in (
        ("--tls-cert", "client certificate (PEM) a TAK server's tls:// port asks for"),
        ("--tls-key", "the client certificate's private key (PEM)"),
        ("--tls-ca", "CA certificate (PEM) the TAK server's certificate is checked against (default: none)"),
    ):
        watch.add_argument(flag, metavar="FILE", default="", help=f"with a tls:// --cot-url: the {what}")
    watch.add_argument(
        "--callsign", default="CloudTrack GCS", help="the sender's name in the event (default CloudTrack GCS)"
    )


def check_arguments(args: argparse.Namespace) -> None:
    """ValueError (one line) for a --cot-url or certificate that cannot work, before the link opens."""
    tls_files = {"--tls-cert": args.tls_cert, "--tls-key": args.tls_key, "--tls-ca": args.tls_ca}
    if not args.cot_url:
        given = [flag for flag, path in tls_files.items() if path]
        if given:
            raise ValueError(f"{given[0]} is for a tls:// --cot-url, and none is given")
        return
    try:
        resolve_url(args.cot_url)
    except ValueError as exc:
        raise ValueError(f"--cot-url: {exc}") from None
    tls = args.cot_url.startswith("tls://")
    if not tls:
        given = [flag for flag, path in tls_files.items() if path]
        if given:
            raise ValueError(f"{given[0]} is for a tls:// --cot-url, not {args.cot_url}")
        return
    if not args.tls_cert or not args.tls_key:
        raise ValueError(
            "a tls:// --cot-url needs --tls-cert and --tls-key (the client certificate a TAK server asks for)"
        )
    for flag, path in tls_files.items():
        if path and not os.access(path, os.R_OK):
            raise ValueError(f"{flag} {path}: not a readable file")


class _Delivery:
    """What became of the finds sent: said once each, and which never went out."""

    def __init__(self, sender: CotSender, url: str) -> None:
        self.sender = sender
        self.url = url
        self.waiting: set[int] = set()
        self._error = ""

    def sent(self, number: int) -> None:
        self.waiting.add(number)

    def lines(self) -> list[str]:
        lines = []
        for number in self.sender.take_delivered():
            self.waiting.discard(number)
            if self.sender.confirms_delivery:
                lines.append(f"[cot] find {number} delivered to {self.url}")
            else:
                lines.append(f"[cot] find {number} sent to {self.url}, delivery not confirmed (UDP)")
        error = self.sender.last_error
        if self.waiting and error and error != self._error:
            lines.append(f"[cot] not delivered yet to {self.url}: {error}; retrying")
        self._error = error
        return lines


def run_watch(session: Any, args: argparse.Namespace) -> int:
    summary = WatchSummary(session.target[0], args.every)
    sender = (
        CotSender(args.cot_url, args.tls_cert, args.tls_key, args.tls_ca).start() if args.cot_url else None
    )
    delivery = _Delivery(sender, args.cot_url) if sender is not None else None
    deadline = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    last_heartbeat = 0.0
    result: int | None = None
    try:
        while time.monotonic() < deadline:
            if time.monotonic() - last_heartbeat >= 1.0:
                session.heartbeat()
                last_heartbeat = time.monotonic()
            msg = session.endpoint.receive(timeout=0.2)
            lines: list[str] = []
            if msg is not None:
                text = session.join_statustext(msg) if msg.get_type() == "STATUSTEXT" else None
                lines = summary.feed(msg, text)
                if args.verbose:
                    line = session.describe(msg, text)
                    lines = [line] if line is not None else lines
            lines += summary.tick()
            for line in lines:
                print(line, flush=True)
            for find in summary.take_changed_finds():
                if sender is not None and delivery is not None:
                    sender.send(find_event(_report(find, session.target[0]), args.callsign), find.number)
                    delivery.sent(find.number)
            for line in delivery.lines() if delivery is not None else []:
                print(line, flush=True)
            if args.until_candidate and summary.awaiting is not None:
                print(summary.line(), flush=True)
                result = 0
                break
    except KeyboardInterrupt:
        pass
    finally:
        if sender is not None:
            sender.close()
    if delivery is not None:
        for line in delivery.lines():
            print(line, flush=True)
        if delivery.waiting:
            numbers = ", ".join(str(n) for n in sorted(delivery.waiting))
            why = f": {sender.last_error}" if sender is not None and sender.last_error else ""
            print(f"error: find {numbers} not delivered to {args.cot_url}{why}", file=sys.stderr, flush=True)
            return 1
    if result is not None:
        return result
    if args.until_candidate:
        print(f"{summary.line()}; no candidate awaits the supervisor", flush=True)
        return 1
    return 0


def _report(find: HeardFind, system: int) -> FindReport:
    return FindReport(
        candidate_id=f"find-{find.number}",
        lat=find.lat,
        lon=find.lon,
        sigma_m=find.sigma_m,
        time=find.time,
        prompt=find.prompt or "person found",
        # The vehicle's words for who confirmed it (its GCS line names the way: "supervisor page", "Ops via
        # back-end API", "gcs"), said to be its announcement.
        confirmed_by=f"{find.confirmed_by or 'nobody named'}, as announced by system {system} over MAVLink",
        vehicle_id=f"system-{system}",
        mission_id="mavlink",
        seen_at=find.seen_at,
    )
