"""A confirmed find as a Cursor-on-Target event, sent to a TAK server or straight to ATAK devices.

One module for the back-end (each find it stores, `[tak] url`) and the ground tool (`cloudtrack-gcs watch
--cot-url`, finds heard over MAVLink, for a site without internet): `find_event` builds the CoT XML with
pytak's own builders (TAK protocol version 0, which TAK servers take on their streaming ports and ATAK
takes on its mesh multicast), and `CotSender` delivers it with pytak's transports: `tcp://host:port`,
`udp://host:port` (unicast, broadcast or multicast such as ATAK's udp://239.2.3.1:6969) and
`tls://host:port` with a client certificate.

The event: type `a-n-G` (a neutral ground point: the person found, not a team member), how `h-e` (a
person confirmed it; its place is an estimate), uid `cloudtrack-find-<vehicle>-<mission>-<candidate>`
(stable: a refined position moves the same marker), `ce` the find's 1-sigma error in metres (9999999,
CoT's "unknown", when not known), callsign `FOUND: <prompt>`, and remarks saying who found whom, when,
who confirmed it, and when the position was seen (a find reported where the track last saw the person
well can be minutes old).

Sending never blocks the caller and never loses a find to a passing outage: events wait in a bounded
queue and a background thread retries until the endpoint takes them (oldest dropped beyond
`max_queued`). pytak is imported when a sender starts, so the companion never needs it.
"""

from __future__ import annotations

import asyncio
import configparser
import contextlib
import ipaddress
import logging
import re
import socket
import threading
import time
import warnings
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, timezone
from typing import Any
from urllib.parse import urlsplit

from cloudtrack.plain_text import without_controls

log = logging.getLogger(__name__)

COT_TYPE = "a-n-G"
COT_HOW = "h-e"
UNKNOWN = 9999999.0  # CoT's value for an unknown ce / le / hae
SCHEMES = ("tcp", "udp", "tls")


@dataclass(frozen=True)
class FindReport:
    """What the rescuers' map needs of a find (the back-end's StoredFind, or a find heard over MAVLink)."""

    candidate_id: str
    lat: float
    lon: float
    sigma_m: float | None
    time: float  # Unix seconds of the confirmation
    prompt: str
    confirmed_by: str
    vehicle_id: str
    mission_id: str
    seen_at: float | None = None  # Unix seconds when the position was observed; None: not known


def seen_text(confirmed_at: float, seen_at: float | None) -> str:
    """How old a find's position is, for a person reading the map: a rescuer walks to where the person was."""
    if seen_at is None or not 0.0 <= seen_at <= 2**34:  # None, NaN or out of any clock's range
        return "when the position was seen is not known"
    when = datetime.fromtimestamp(seen_at, timezone.utc).strftime("%H:%M:%S UTC")
    gap = confirmed_at - seen_at
    if abs(gap) < 1.0:
        return f"position as seen at {when}, at the confirmation"
    span = f"{abs(gap):.0f} s" if abs(gap) < 120.0 else f"{abs(gap) / 60.0:.0f} min"
    return f"position as seen at {when}, {span} {'before' if gap > 0 else 'after'} the confirmation"


def find_uid(find: FindReport) -> str:
    return f"cloudtrack-find-{find.vehicle_id}-{find.mission_id}-{find.candidate_id}"


def _pytak() -> Any:
    """pytak, without its import-time warnings about optional extras (enrolment, HTTP) that are not used."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The '(cryptography|aiohttp)' package is required")
        import pytak
    return pytak


def find_event(find: FindReport, callsign: str = "CloudTrack", stale_s: float = 24 * 3600.0) -> bytes:
    """The find as one CoT event (XML bytes). Its text (the prompt, who confirmed it, the ids, the callsign)
    was written by a vehicle or an operator: it goes in without the characters XML 1.0 forbids, so the
    event is well-formed whatever they wrote, and as text (ElementTree escapes the markup)."""
    pytak = _pytak()

    find = replace(
        find,
        candidate_id=without_controls(find.candidate_id),
        prompt=without_controls(find.prompt),
        confirmed_by=without_controls(find.confirmed_by),
        vehicle_id=without_controls(find.vehicle_id),
        mission_id=without_controls(find.mission_id),
    )
    callsign = without_controls(callsign)

    when = datetime.fromtimestamp(find.time, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    sigma = f"±{find.sigma_m:.1f} m" if find.sigma_m is not None else "accuracy unknown"
    detail = pytak.cot_detail(flow_tag=False)
    pytak.add_remarks(
        detail,
        [
            f"{find.prompt!r} found by {find.vehicle_id} (mission {find.mission_id}, candidate "
            f"{find.candidate_id}) at {when}, confirmed by {find.confirmed_by}; {sigma}; "
            f"{seen_text(find.time, find.seen_at)}. Sent by {callsign}."
        ],
    )
    event = pytak.cot_event(
        uid=find_uid(find),
        cot_type=COT_TYPE,
        how=COT_HOW,
        stale=stale_s,
        point=pytak.cot_point(
            find.lat, find.lon, ce=find.sigma_m if find.sigma_m is not None else UNKNOWN, precision=7
        ),
        detail=detail,
        callsign=f"FOUND: {find.prompt}"[:80],
    )
    # pytak reads the clock once per attribute: one instant for all three, so stale - start is stale_s exactly.
    now = datetime.now(timezone.utc)
    for name, moment in (("time", now), ("start", now), ("stale", now + timedelta(seconds=int(stale_s)))):
        event.set(name, moment.strftime(pytak.W3C_XML_DATETIME))
    return bytes(pytak.serialize_cot(event))


def parse_find_event(data: bytes) -> ET.Element:
    """The `event` element of CoT XML bytes (for tools and tests that read what was sent)."""
    return ET.fromstring(data)


def check_url(url: str) -> str:
    """`url` if it is one CotSender can use; ValueError (one line: what is wrong, the allowed forms) otherwise.
    Nothing is looked up: a back-end starting before its network keeps retrying (`resolve_url` checks that)."""
    forms = "use tcp://host:port, udp://host:port or tls://host:port"
    parts = urlsplit(url)
    if "://" not in url or parts.scheme not in SCHEMES:
        raise ValueError(f"not a Cursor-on-Target address: {url!r}; {forms}")
    try:
        port = parts.port
    except ValueError:  # not a number, or over 65535
        port = -1
    if not parts.hostname or parts.username or parts.password or parts.path or parts.query or parts.fragment:
        raise ValueError(f"not a Cursor-on-Target address: {url!r}; {forms}")
    if port is None or not 1 <= port <= 65535:
        raise ValueError(f"not a Cursor-on-Target address: {url!r}: the port must be 1-65535; {forms}")
    if re.fullmatch(r"[0-9.]+", parts.hostname):
        try:
            ipaddress.IPv4Address(parts.hostname)
        except ValueError:
            raise ValueError(
                f"not a Cursor-on-Target address: {url!r}: {parts.hostname} is no IPv4 address"
            ) from None
    return url


def resolve_url(url: str) -> str:
    """`url` once checked and its host looked up (ValueError, one line, for a host that does not resolve):
    for a tool about to send, so that a typo is said before it runs, not as a find that never arrives."""
    parts = urlsplit(check_url(url))
    try:
        socket.getaddrinfo(parts.hostname, parts.port)
    except (OSError, UnicodeError) as exc:
        raise ValueError(
            f"cannot resolve the host of {url!r}: {getattr(exc, 'strerror', None) or exc}"
        ) from None
    return url


class CotSender:
    """Sends CoT events to one endpoint from a background thread, retrying until delivered.

    Delivered: written to the TCP or TLS connection the endpoint accepted (TAK answers nothing), or for UDP
    handed to the network as a datagram, which nobody confirms (`confirms_delivery` is False). A caller
    that wants to know tags its events (`send(event, tag)`) and takes the tags of those delivered since
    (`take_delivered()`); `last_error` says why the others wait."""

    def __init__(
        self,
        url: str,
        tls_cert: str = "",
        tls_key: str = "",
        tls_ca: str = "",
        retry_s: float = 5.0,
        max_queued: int = 100,
    ) -> None:
        self.url = check_url(url)
        # Write-only: pytak would otherwise also bind a UDP reader on the destination's own port.
        pytak_url = "udp+wo://" + url[len("udp://") :] if url.startswith("udp://") else url
        self._settings = {"COT_URL": pytak_url, "TAK_PROTO": "0"}
        if url.startswith("tls://"):
            self._settings.update(
                {
                    k: v
                    for k, v in (
                        ("PYTAK_TLS_CLIENT_CERT", tls_cert),
                        ("PYTAK_TLS_CLIENT_KEY", tls_key),
                        ("PYTAK_TLS_CLIENT_CAFILE", tls_ca),
                    )
                    if v
                }  # fmt: skip
            )
        self._retry_s = retry_s
        self.confirms_delivery = not url.startswith("udp://")
        self._queue: deque[tuple[bytes, object]] = deque(maxlen=max_queued)
        self._delivered: list[object] = []
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.sent = 0
        self.last_error = ""
        self._thread = threading.Thread(target=self._run, name="cursor-on-target", daemon=True)

    def start(self) -> CotSender:
        _pytak()  # fail at start-up, not at the first find

        self._thread.start()
        return self

    def send(self, event: bytes, tag: object = None) -> None:
        """Queue one event; returns at once. A `tag` comes back from `take_delivered` once it went out."""
        with self._lock:
            self._queue.append((event, tag))
        self._wake.set()

    def take_delivered(self) -> list[object]:
        """The tags of the events delivered since the last call, oldest first."""
        with self._lock:
            taken, self._delivered = self._delivered, []
        return taken

    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop after trying to deliver what is queued for up to `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while self.pending() and time.monotonic() < deadline and self._thread.is_alive():
            time.sleep(0.02)
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        pytak = _pytak()

        config = configparser.ConfigParser()
        config["cloudtrack"] = self._settings
        section = config["cloudtrack"]
        writer = None
        while not self._stop.is_set():
            if not self.pending():
                await asyncio.get_running_loop().run_in_executor(None, self._wake.wait, 1.0)
                self._wake.clear()
                continue
            try:
                if writer is None:
                    _, writer = await asyncio.wait_for(pytak.protocol_factory(section), timeout=10)
                with self._lock:
                    entry = self._queue[0]
                await asyncio.wait_for(
                    pytak.TXWorker(asyncio.Queue(), section, writer).send_data(entry[0]), 10
                )
                with self._lock:
                    if self._queue and self._queue[0] is entry:
                        self._queue.popleft()
                    if entry[1] is not None:
                        self._delivered.append(entry[1])
                self.sent += 1
                self.last_error = ""
            except Exception as exc:  # refused, unreachable, TLS: keep the event, try again later
                if str(exc) != self.last_error:
                    log.warning(
                        "Cursor-on-Target to %s failed (%s); retrying every %g s",
                        self.url,
                        exc,
                        self._retry_s,
                    )
                self.last_error = str(exc)
                _close(writer)
                writer = None
                await asyncio.get_running_loop().run_in_executor(None, self._stop.wait, self._retry_s)
        _close(writer)


def _close(writer: object) -> None:
    close = getattr(writer, "close", None)
    if close is not None:
        with contextlib.suppress(Exception):  # already gone
            close()
