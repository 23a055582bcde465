"""`cloudtrack-gcs watch` and `status` against a vehicle's MAVLink traffic on loopback: watch prints the
events and a summary instead of the 10 Hz tracking status line by line, and forwards a find it hears
(STATUSTEXT `FOUND ...` and CAMERA_TRACKING_GEO_STATUS) as Cursor-on-Target to a TAK stand-in, read with
`takproto`. Select: -k "watch or cursor_on_target".
"""

from __future__ import annotations

import math
import re
import socket
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from cloudtrack.gcs_protocol import statustext_chunks
from cloudtrack.mavlink_connection import MavlinkEndpoint
from gcs.watch_command import WatchSummary
from tests.test_finds_export import TakStandIn, certificates  # noqa: F401 - the fixture, asked for by name

TRACKING_HZ = 10.0


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextmanager
def fake_vehicle(
    port: int, seconds: float, texts: dict[float, str] | None = None
) -> Iterator[dict[str, int]]:
    """System 1 talking to a GCS on udp `port`: the autopilot's HEARTBEAT (1/1), the companion's status
    lines (1/191) and its camera's tracking and find messages (1/100), as the companion sends them."""
    endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{port}", 1, 1)
    conn = endpoint.conn
    sent = {"messages": 0}
    stop = threading.Event()

    def as_component(component: int, send: object) -> None:
        conn.mav.srcComponent = component
        send()  # type: ignore[operator]
        sent["messages"] += 1

    def geo_status(nan: float = math.nan) -> None:
        conn.mav.camera_tracking_geo_status_send(
            1, 473978120, 85456120, 488.0, 2.5, nan, nan, nan, nan, nan, 14.0, nan, nan
        )

    def run() -> None:
        # The timeline starts once the ground station is there (it announces itself with a HEARTBEAT).
        while not stop.is_set():
            as_component(1, lambda: conn.mav.heartbeat_send(2, 3, 217, 4, 4))
            if endpoint.receive(timeout=0.5) is not None:
                break
        start = time.monotonic()
        timeline = (
            dict(texts)
            if texts is not None
            else {
                0.5: "SEARCHING: mission started",
                1.0: "CANDIDATE AWAITING c17 at 47.397812,8.545612",
                1.2: "CANDIDATE AWAITING c17 at 47.397812,8.545612",
                1.4: "CANDIDATE AWAITING c17 at 47.397812,8.545612",
                2.5: "FOUND 47.397812,8.545612 +-2.5m",
                2.6: "FOUND: a man in a red jacket (confirmed by gcs; seen 45 s before)",
            }
        )
        next_heartbeat = 0.0
        while not stop.is_set() and time.monotonic() - start < seconds:
            t = time.monotonic() - start
            if t >= next_heartbeat:
                as_component(1, lambda: conn.mav.heartbeat_send(2, 3, 217, 4, 4))  # ArduCopter, GUIDED
                next_heartbeat += 1.0
            for n, at in enumerate([a for a in timeline if a <= t]):
                chunks = statustext_chunks(timeline.pop(at))  # a line over 50 bytes goes as linked chunks
                text_id = (n + 1) * int(len(chunks) > 1)
                for piece, seq in chunks:
                    as_component(
                        191,
                        lambda piece=piece, seq=seq, text_id=text_id: conn.mav.statustext_send(
                            6, piece, text_id, seq
                        ),
                    )
            as_component(
                100,
                lambda: conn.mav.camera_tracking_image_status_send(
                    1, 2, 4, 0.5, 0.48, math.nan, 0.45, 0.4, 0.55, 0.6
                ),
            )
            if t >= 2.7:
                as_component(100, geo_status)
            time.sleep(1.0 / TRACKING_HZ)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield sent
    finally:
        stop.set()
        thread.join(timeout=5)
        endpoint.close()


def _gcs(port: int, *args: str) -> list[str]:
    """A cloudtrack-gcs command's output lines (exit 0 asserted)."""
    exe = [sys.executable, "-m", "gcs.cli", "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "10", *args]
    done = subprocess.run(exe, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_watch_summarises_and_forwards_the_find_as_cursor_on_target() -> None:
    port = _free_udp_port()
    with TakStandIn("udp") as tak:
        with fake_vehicle(port, 6.0) as sent:
            lines = _gcs(port, "watch", "--duration", "5", "--every", "2", "--cot-url", tak.url)
        assert sent["messages"] > 50
        assert len(lines) <= 16, lines  # was one line per message: 10 Hz of tracking alone
        text = "\n".join(lines)
        assert "[autopilot] mode GUIDED" in text and "[1/191] SEARCHING: mission started" in text
        events = [line for line in lines if not line.startswith("[summary]")]
        assert sum("CANDIDATE AWAITING c17" in line for line in events) == 1  # repeats counted, not printed
        assert "[1/100] tracking: target at (0.50, 0.48)" in text
        assert "find 1 at 47.397812,8.545612 +-2.5 m" in text and "[cot] find 1 sent to udp://" in text
        summaries = [line for line in lines if line.startswith("[summary]")]
        assert summaries and "tracking" in summaries[-1] and "mode GUIDED" in summaries[-1]
        messages = tak.messages(1)
    event = messages[-1].cotEvent
    assert (event.lat, event.lon) == (pytest.approx(47.397812), pytest.approx(8.545612))
    assert event.ce == pytest.approx(2.5) and event.uid == "cloudtrack-find-system-1-mavlink-find-1"
    callsigns = [m.cotEvent.detail.contact.callsign for m in messages]
    assert "FOUND: a man in a red jacket" in callsigns
    # The announcement said the position was seen 45 s before the confirmation: so does the TAK map.
    described = next(
        m for m in messages if m.cotEvent.detail.contact.callsign == "FOUND: a man in a red jacket"
    )
    assert "45 s before the confirmation" in described.cotEvent.detail.xmlDetail


def test_watch_verbose_prints_every_message() -> None:
    port = _free_udp_port()
    with fake_vehicle(port, 4.0):
        lines = _gcs(port, "watch", "--duration", "3", "--verbose")
    assert len([line for line in lines if "target at" in line]) >= 15


def test_watch_until_candidate_stops_when_one_awaits_the_supervisor() -> None:
    port = _free_udp_port()
    with fake_vehicle(port, 8.0):
        lines = _gcs(port, "watch", "--duration", "7", "--until-candidate")
    assert "[1/191] CANDIDATE AWAITING c17 at 47.397812,8.545612" in lines, lines
    assert lines[-1].startswith("[summary]") and "last: CANDIDATE AWAITING c17" in lines[-1], lines
    assert not any("FOUND" in line for line in lines), lines  # it stopped before the find at 2.5 s


def test_watch_until_candidate_exits_1_when_none_came() -> None:
    port = _free_udp_port()
    exe = [sys.executable, "-m", "gcs.cli", "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "10"]
    with fake_vehicle(port, 4.0, texts={0.5: "SEARCHING: mission started"}):
        done = subprocess.run(
            [*exe, "watch", "--duration", "2", "--until-candidate"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.splitlines()[-1].endswith("no candidate awaits the supervisor"), done.stdout


def _statustext(text: str) -> object:
    msg = mavlink.MAVLink_statustext_message(6, text.encode(), 0, 0)
    msg._header = mavlink.MAVLink_header(msg.id, srcSystem=1, srcComponent=191)
    return msg


@pytest.mark.parametrize(
    ("line", "confirmed_by", "seen_at"),
    [
        ("FOUND: a man in red (confirmed by gcs)", "gcs", 1000.0),  # no words: seen at the confirmation
        ("FOUND: a man in red (confirmed by gcs; seen 45 s before)", "gcs", 955.0),
        # A sender's absurd age is not a time: the words stay part of who confirmed, the age unknown as given.
        (
            "FOUND: a man in red (confirmed by gcs; seen 999999999999 s before)",
            "gcs; seen 999999999999 s before",
            1000.0,
        ),
    ],
)
def test_watch_reads_how_old_the_finds_position_is(line: str, confirmed_by: str, seen_at: float) -> None:
    summary = WatchSummary(1, wall_clock=lambda: 1000.0)
    found = "FOUND 47.397812,8.545612 +-2.5m"
    summary.feed(_statustext(found), found)
    summary.feed(_statustext(line), line)
    (find,) = summary.finds
    assert find.confirmed_by == confirmed_by and find.seen_at == seen_at
    summary.feed(_statustext("FOUND 47.397830,8.545612 +-2.0m"), "FOUND 47.397830,8.545612 +-2.0m")
    assert len(summary.finds) == 1 and summary.finds[0].sigma_m == 2.0  # moved 2 m: the same find


# Issue 44 item 7b: --cot-url checked before watching, "delivered" only when it was, no find off the globe.


@pytest.mark.parametrize(
    ("url", "said"),
    [
        ("udp://127.0.0.1:99999", "the port must be 1-65535"),
        ("tcp://127.0.0.1:0", "the port must be 1-65535"),
        ("tcp://no-such-host.invalid:8087", "cannot resolve the host"),
        ("udp://256.256.256.256:6969", "256.256.256.256 is no IPv4 address"),
        ("tcp//127.0.0.1:8087", "use tcp://host:port, udp://host:port or tls://host:port"),
        ("tcp://127.0.0.1:8087/path", "use tcp://host:port"),
        ("tls://127.0.0.1:8089", "needs --tls-cert and --tls-key"),
    ],
)
def test_watch_refuses_a_cot_url_that_cannot_work_in_one_line_before_watching(url: str, said: str) -> None:
    port = _free_udp_port()  # nobody talks there: the command must stop before it waits for a vehicle
    exe = [sys.executable, "-m", "gcs.cli", "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "10"]
    done = subprocess.run([*exe, "watch", "--cot-url", url], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("error: "), done.stderr
    assert said in done.stderr and "usage:" not in done.stderr, done.stderr
    assert done.stdout == ""  # nothing watched (waiting for a vehicle would end in a timeout error instead)


def test_watch_says_a_find_was_not_delivered_and_exits_1() -> None:
    """No TAK server listens on the port: the find is never "sent", the reason is said, the exit is 1."""
    port = _free_udp_port()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        closed = probe.getsockname()[1]
    exe = [sys.executable, "-m", "gcs.cli", "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "10"]
    with fake_vehicle(port, 5.0):
        done = subprocess.run(
            [*exe, "watch", "--duration", "4", "--cot-url", f"tcp://127.0.0.1:{closed}"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "find 1 at 47.397812,8.545612" in done.stdout
    assert "sent" not in done.stdout and "delivered to" not in done.stdout, done.stdout
    assert "[cot] not delivered yet to tcp://" in done.stdout, done.stdout
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: find 1 not delivered to tcp://127.0.0.1:{closed}"), done.stderr


def test_watch_delivers_a_find_over_tcp_as_a_well_formed_event_whatever_the_vehicle_wrote() -> None:
    """Item 4 through `watch --cot-url`: control characters and markup in the vehicle's announcement."""
    from lxml import etree

    port = _free_udp_port()
    texts = {
        0.5: "FOUND 47.397812,8.545612 +-2.5m",
        0.7: "FOUND: a man\x01 in a black & white <b>shirt</b> (confirmed by gcs\x0b]]>)",
    }
    with TakStandIn("tcp") as tak:
        with fake_vehicle(port, 5.0, texts=texts):
            lines = _gcs(port, "watch", "--duration", "4", "--cot-url", tak.url)
        assert f"[cot] find 1 delivered to {tak.url}" in lines, lines
        received = list(tak.received)
    assert received
    for data in received:
        assert not re.search(b"[\x00-\x08\x0b\x0c\x0e-\x1f]", data), data
        event = etree.fromstring(data, etree.XMLParser(recover=False))
        assert {e.tag for e in event.iter()} <= {
            "event",
            "point",
            "detail",
            "contact",
            "remarks",
            "__group",
            "track",
        }
    callsigns = [etree.fromstring(d).find("detail/contact").get("callsign") for d in received]
    assert "FOUND: a man in a black & white <b>shirt</b>" in callsigns, callsigns


def test_watch_takes_no_find_off_the_globe() -> None:
    summary = WatchSummary(1, wall_clock=lambda: 1000.0)
    for line in ("FOUND 999.0,-720.5 +-2.5m", "FOUND 47.0,-200.0 +-2.5m"):
        said = summary.feed(_statustext(line), line)
        assert any("off the globe" in s for s in said), said
    assert summary.finds == [] and summary.take_changed_finds() == []


def test_watch_delivers_a_find_over_tls_with_its_client_certificate(request: pytest.FixtureRequest) -> None:
    folder: Path = request.getfixturevalue("certificates")  # made by the TAK server tests' CA
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(folder / "server.pem", folder / "server.key")
    context.load_verify_locations(folder / "ca.pem")
    context.verify_mode = ssl.CERT_REQUIRED  # no client certificate, no connection
    port = _free_udp_port()
    with TakStandIn("tcp", tls=context) as tak:
        url = f"tls://127.0.0.1:{tak.port}"
        tls = ["--tls-cert", str(folder / "client.pem"), "--tls-key", str(folder / "client.key"),
               "--tls-ca", str(folder / "ca.pem")]  # fmt: skip
        with fake_vehicle(port, 5.0):
            lines = _gcs(port, "watch", "--duration", "4", "--cot-url", url, *tls)
        assert f"[cot] find 1 delivered to {url}" in lines, lines
        assert tak.messages(1)
