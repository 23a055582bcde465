"""The flight record: contents of a mission folder, the size cap, and failure that never crashes."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from behaviors.geometry import Box
from companion.flight_record import (
    EVENTS_FILE,
    FlightRecorder,
    NoRecord,
    attach_tlog,
    open_record,
    read_events,
)

START = 1_790_000_000.0  # a fixed UTC time, so the test knows the mission folder's name


def fixed_clock(start: float = START, step: float = 0.01):
    now = [start]

    def clock() -> float:
        now[0] += step
        return now[0]

    return clock


def heartbeat_bytes(seq: int) -> bytes:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    mav.seq = seq % 256
    msg = mav.heartbeat_encode(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return bytes(msg.pack(mav))


def jpeg(seed: int, size: int = 160) -> bytes:
    rng = np.random.default_rng(seed)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 255, (size, size, 3), dtype=np.uint8))
    assert ok
    return buf.tobytes()


def test_mission_folder_holds_events_tlog_keyframes_and_video(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path, "drone-1", "m 42/x", 50_000_000, video=True, clock=fixed_clock())
    rec.event("state", old="IDLE", new="SEARCHING", time_s=0.0)
    rec.event("backend_answer", candidates=[{"id": "c1", "verdict": "yes"}])
    for seq in range(20):
        rec.mavlink(heartbeat_bytes(seq))
    name = rec.keyframe(jpeg(1), 7)
    frame = np.full((120, 160, 3), 80, np.uint8)
    for _ in range(12):
        rec.video_frame(frame, Box(40, 30, 50, 60), "TRACKING")
    rec.close()

    assert rec.folder.name.startswith("20260921T") and rec.folder.name.endswith("_drone-1_m-42-x")
    events = read_events(rec.folder)
    kinds = [e["kind"] for e in events]
    assert kinds == ["recording_started", "state", "backend_answer", "keyframe", "recording_closed"]
    assert all(START < e["t"] < START + 10 for e in events)
    assert events[1]["new"] == "SEARCHING" and events[2]["candidates"][0]["verdict"] == "yes"
    assert name == "keyframes/000007.jpg" and events[3]["file"] == name
    assert (
        cv2.imdecode(np.frombuffer((rec.folder / name).read_bytes(), np.uint8), cv2.IMREAD_COLOR) is not None
    )

    # pymavlink reads the tlog back, timestamps included.
    log = mavutil.mavlink_connection(str(rec.folder / "mavlink-000.tlog"))
    received = []
    while (msg := log.recv_match(type="HEARTBEAT")) is not None:
        received.append(msg)
    assert len(received) == 20
    assert START < received[0]._timestamp < START + 10
    assert received[0].type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER

    # H.264 that decodes; the loop never waited for the encoder, so a frame may have been dropped.
    import av

    with av.open(str(rec.folder / "video-000.mp4")) as container:
        assert container.streams.video[0].codec_context.name == "h264"
        decoded = sum(1 for _ in container.decode(video=0))
    encoded, dropped = rec.video_frames
    assert decoded == encoded >= 1 and encoded + dropped + rec.video_frames_skipped == 12


def test_video_takes_frames_at_the_camera_rate_not_faster(tmp_path: Path) -> None:
    """A loop outrunning the camera's fps: frames in between are skipped (not encoded, not drops)."""
    import time

    import av

    rec = FlightRecorder(
        tmp_path, "drone-1", "m", 50_000_000, video=True, video_fps=20.0, clock=fixed_clock()
    )
    frame = np.full((120, 160, 3), 80, np.uint8)
    started, offered = time.monotonic(), 0
    while time.monotonic() - started < 1.0:  # up to 200 frames a second for one second
        rec.video_frame(frame, None, "TRACKING")
        offered += 1
        time.sleep(0.005)
    rec.close()
    encoded, dropped = rec.video_frames
    assert 15 <= encoded + dropped <= 23, (encoded, dropped)  # 20 FPS of the loop's frames
    # How many the loop offered depends on the machine's load; every one beyond the camera rate is skipped.
    assert offered > 60 and rec.video_frames_skipped == offered - encoded - dropped, offered
    with av.open(str(rec.folder / "video-000.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == encoded


def test_size_cap_rotates_older_missions_then_oldest_keyframes(tmp_path: Path) -> None:
    older = tmp_path / "20200101T000000Z_drone-1_old"
    older.mkdir()
    (older / EVENTS_FILE).write_text('{"t":0,"kind":"recording_started"}\n')
    (older / "mavlink-000.tlog").write_bytes(b"\0" * 50_000)
    unrelated = tmp_path / "operator-notes"  # not a mission folder: never touched
    unrelated.mkdir()
    (unrelated / "notes.txt").write_text("keep me")

    cap = 200_000
    rec = FlightRecorder(tmp_path, "drone-1", "m", cap, clock=fixed_clock())
    frames = [jpeg(i, 120) for i in range(40)]
    assert sum(map(len, frames)) > 2 * cap
    for i, data in enumerate(frames):
        rec.keyframe(data, i)
    for seq in range(3000):
        rec.mavlink(heartbeat_bytes(seq))
    assert rec.active
    rec.close()

    total = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert total <= cap
    assert not older.exists()
    assert (unrelated / "notes.txt").read_text() == "keep me"
    kept = sorted(p.name for p in (rec.folder / "keyframes").iterdir())
    assert kept and kept[-1] == "000039.jpg" and "000000.jpg" not in kept
    assert len(list(rec.folder.glob("mavlink-*.tlog"))) >= 1
    kinds = [e["kind"] for e in read_events(rec.folder)]
    assert kinds[0] == "recording_started" and kinds[-1] == "recording_closed"
    assert kinds.count("keyframe") == 40  # the event log itself is never rotated away


def test_disk_full_degrades_to_no_recording_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """/dev/full answers every write with ENOSPC, exactly as a full SD card does."""
    clock = fixed_clock()
    probe = FlightRecorder(tmp_path / "probe", "drone-1", "m", 10_000_000, clock=fixed_clock())
    folder = tmp_path / "records" / probe.folder.name
    probe.close()
    folder.mkdir(parents=True)
    os.symlink("/dev/full", folder / "mavlink-000.tlog")

    with caplog.at_level(logging.WARNING):
        rec = FlightRecorder(tmp_path / "records", "drone-1", "m", 10_000_000, clock=clock)
        rec.event("state", new="SEARCHING")
        assert rec.active
        rec.mavlink(heartbeat_bytes(0))  # ENOSPC here
        assert not rec.active
        rec.event("state", new="TRACKING")
        rec.mavlink(heartbeat_bytes(1))
        assert rec.keyframe(jpeg(0), 1) is None
        rec.video_frame(np.zeros((48, 64, 3), np.uint8), None, "TRACKING")
        rec.close()
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "No space left" in warnings[0].getMessage()
    # What was written before the failure is still there.
    assert [e["kind"] for e in read_events(folder)] == ["recording_started", "state"]


def test_event_log_on_full_disk(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    probe = FlightRecorder(tmp_path / "probe", "drone-1", "m", 10_000_000, clock=fixed_clock())
    folder = tmp_path / "records" / probe.folder.name
    probe.close()
    folder.mkdir(parents=True)
    os.symlink("/dev/full", folder / EVENTS_FILE)
    rec = FlightRecorder(tmp_path / "records", "drone-1", "m", 10_000_000, clock=fixed_clock())
    assert not rec.active
    rec.event("safety", reason="heartbeat lost")
    rec.close()
    assert "No space left" in caplog.text


def test_unusable_directory_and_low_free_space_stop_recording_not_the_mission(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    rec = FlightRecorder(blocker / "records", "drone-1", "m", 10_000_000)
    assert not rec.active
    rec.event("state", new="SEARCHING")
    rec.close()
    assert "cannot create" in caplog.text

    # /proc is a file system where nothing can be created, even by root.
    assert not FlightRecorder(Path("/proc/cloudtrack-records"), "drone-1", "m", 10_000_000).active

    starved = FlightRecorder(tmp_path / "records", "drone-1", "m", 10_000_000, min_free_bytes=1 << 62)
    assert not starved.active
    assert "bytes free" in caplog.text


def test_cap_with_nothing_left_to_rotate_stops(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rec = FlightRecorder(tmp_path, "drone-1", "m", 2_000, clock=fixed_clock())
    for i in range(100):
        rec.event("state", new=f"S{i}", padding="x" * 40)
    assert not rec.active
    assert "size cap" in caplog.text
    assert (rec.folder / EVENTS_FILE).stat().st_size <= 2_200


def test_disabled_recording_and_torn_last_line(tmp_path: Path) -> None:
    none = open_record(False, str(tmp_path), 10_000_000, False, "drone-1", "m")
    assert isinstance(none, NoRecord) and not none.active
    none.event("state")
    assert list(tmp_path.iterdir()) == []

    rec = open_record(True, str(tmp_path), 10_000_000, False, "drone-1", "m")
    assert isinstance(rec, FlightRecorder)
    rec.event("state", new="SEARCHING")
    rec.close()
    with open(rec.folder / EVENTS_FILE, "a") as f:
        f.write('{"t": 1, "kind": "sta')  # power lost mid-line
    assert [e["kind"] for e in read_events(rec.folder)] == ["recording_started", "state", "recording_closed"]
    json.loads((rec.folder / EVENTS_FILE).read_text().splitlines()[0])


def test_attach_tlog_records_messages_sent_and_received_over_a_real_link(tmp_path: Path) -> None:
    """Two pymavlink endpoints on loopback UDP: the companion's sends and receives both land in the tlog."""
    from tests.live_backend import free_port

    port = free_port()
    companion = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191)
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    rec = FlightRecorder(tmp_path, "drone-1", "link", 10_000_000)
    try:
        attach_tlog(companion, rec)
        autopilot.mav.heartbeat_send(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0
        )
        assert companion.recv_match(type="HEARTBEAT", blocking=True, timeout=5) is not None
        companion.mav.statustext_send(mavlink2.MAV_SEVERITY_INFO, b"companion up")
    finally:
        rec.close()
        companion.close()
        autopilot.close()
    log = mavutil.mavlink_connection(str(rec.folder / "mavlink-000.tlog"))
    types = []
    while (msg := log.recv_match()) is not None:
        types.append((msg.get_type(), msg.get_srcComponent()))
    assert ("HEARTBEAT", 1) in types and ("STATUSTEXT", 191) in types


def test_a_nonsense_message_time_falls_back_to_the_clock(tmp_path: Path) -> None:
    rec = FlightRecorder(tmp_path, "drone-1", "m", 10_000_000, clock=fixed_clock())
    rec.mavlink(heartbeat_bytes(0), time_s=-5.0)
    rec.mavlink(heartbeat_bytes(1), time_s=float("nan"))
    rec.close()
    log = mavutil.mavlink_connection(str(rec.folder / "mavlink-000.tlog"))
    stamps = []
    while (msg := log.recv_match(type="HEARTBEAT")) is not None:
        stamps.append(msg._timestamp)
    assert len(stamps) == 2 and all(START < t < START + 10 for t in stamps)


def test_records_are_measured_off_the_main_loop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A slow file system (a big records card): opening a record and writing video never waits for the
    walk of the other missions; the cap still removes the oldest mission once the walk is done."""
    import time

    from companion import flight_record

    older = tmp_path / "20200101T000000Z_drone-1_old"
    older.mkdir()
    (older / EVENTS_FILE).write_text('{"t":0,"kind":"recording_started"}\n')
    (older / "mavlink-000.tlog").write_bytes(b"\0" * 400_000)
    walked = flight_record._tree_size

    def slow_walk(path: Path) -> int:
        time.sleep(1.0)
        return walked(path)

    monkeypatch.setattr(flight_record, "_tree_size", slow_walk)
    started = time.perf_counter()
    rec = FlightRecorder(tmp_path, "drone-1", "m", 300_000, video=True, clock=fixed_clock())
    frame = np.full((120, 160, 3), 80, np.uint8)
    for _ in range(60):
        rec.video_frame(frame, Box(40, 30, 50, 60), "TRACKING")
        rec.event("step", n=1)
    elapsed = time.perf_counter() - started
    assert elapsed < 0.5, f"the loop's calls took {elapsed:.2f} s: they waited for the walk"
    deadline = time.monotonic() + 10
    while older.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    rec.close()
    assert not older.exists() and rec.folder.exists()


@pytest.mark.slow
def test_video_segments_rotate_under_the_cap_from_the_encoder_thread(tmp_path: Path) -> None:
    """Incompressible video into an 8 MB cap (segments of 0.5 MB, a few frames each): the encoder's size
    reports roll segments and the oldest go, the recording stays on and near the cap, and close() returns
    (no lock held across threads)."""
    import threading
    import time

    cap = 8_000_000
    rec = FlightRecorder(tmp_path, "drone-1", "m", cap, video=True, video_fps=1000.0, clock=fixed_clock())
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, (480, 640, 3), dtype=np.uint8) for _ in range(4)]
    deadline = time.monotonic() + 60
    i = 0
    while not (rec.folder / "video-001.mp4").exists() or (rec.folder / "video-000.mp4").exists():
        assert time.monotonic() < deadline, "the first segment was never rotated away"
        rec.video_frame(noise[i % 4], None, "TRACKING")
        i += 1
        time.sleep(0.01)
    assert rec.active
    closer = threading.Thread(target=rec.close)
    closer.start()
    closer.join(30)
    assert not closer.is_alive(), "close() deadlocked"
    total = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    # Counted as the encoder reports each frame: the segments still being written may run a little past.
    assert total <= cap * 1.3, total
