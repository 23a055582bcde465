"""`cloudtrack-gcs watch` and `status` against a vehicle's MAVLink traffic on loopback: watch prints the
events and a summary instead of the 10 Hz tracking status line by line, and forwards a find it hears
(STATUSTEXT `FOUND ...` and CAMERA_TRACKING_GEO_STATUS) as Cursor-on-Target to a TAK stand-in, read with
`takproto`. Select: -k "watch or cursor_on_target".
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from cloudtrack.gcs_protocol import statustext_chunks
from cloudtrack.mavlink_connection import MavlinkEndpoint
from gcs.watch_command import WatchSummary
from tests.test_finds_export import TakStandIn

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
