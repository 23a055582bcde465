"""Frame sources: folders, video files, live captures that drop, disconnect, stall and come back."""

from __future__ import annotations

import logging
import shutil
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from companion.vision.frame_sources import (
    FolderSource,
    LiveSource,
    SourceError,
    VideoFileSource,
    open_source,
    register_scheme,
)


@pytest.fixture
def folder(sequences_dir: Path, tmp_path: Path) -> Path:
    frames = tmp_path / "seq" / "frames"
    frames.mkdir(parents=True)
    for i in range(1, 6):
        shutil.copy(sequences_dir / "otb_Crossing" / "frames" / f"{i:06d}.jpg", frames)
    return tmp_path / "seq"


@pytest.fixture
def video(folder: Path, tmp_path: Path) -> Path:
    path = tmp_path / "clip.avi"
    images = [cv2.imread(str(p)) for p in sorted((folder / "frames").iterdir())]
    h, w = images[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    for image in images:
        writer.write(image)
    writer.release()
    return path


def _wait_until(predicate: Any, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_folder_gives_every_frame_in_order(folder: Path) -> None:
    source = open_source(str(folder))
    assert isinstance(source, FolderSource) and not source.live
    ids = []
    while (frame := source.read()) is not None:
        ids.append(frame.frame_id)
        assert frame.image.shape == (240, 360, 3)
    assert ids == [1, 2, 3, 4, 5] and source.stats.frames == 5


def test_folder_replay_timing_follows_the_recording(folder: Path) -> None:
    source = FolderSource(folder, fps=10.0)
    a, b = source.read(), source.read()
    assert a is not None and b is not None
    assert b.capture_time - a.capture_time == pytest.approx(0.1)


def test_corrupt_image_is_skipped_with_a_warning(folder: Path, caplog: pytest.LogCaptureFixture) -> None:
    (folder / "frames" / "000003.jpg").write_bytes(b"\xff\xd8 truncated jpeg")
    source = FolderSource(folder)
    with caplog.at_level(logging.WARNING):
        ids = [f.frame_id for f in iter(source.read, None)]
    assert ids == [1, 2, 4, 5]  # ids stay the file positions so ground truth stays aligned
    assert source.stats.skipped == 1
    assert "000003.jpg" in caplog.text and "skipped" in caplog.text


def test_video_file_gives_every_frame(video: Path) -> None:
    source = open_source(str(video))
    assert isinstance(source, VideoFileSource)
    assert [f.frame_id for f in iter(source.read, None)] == [1, 2, 3, 4, 5]
    source.close()


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("", "empty camera source"),
        ("/no/such/place", "not a device index, URL, folder or file"),
        ("ftp://camera/stream", "unknown scheme 'ftp'"),
    ],
)
def test_unusable_specs_are_clear_errors(spec: str, message: str) -> None:
    with pytest.raises(SourceError, match=message):
        open_source(spec)


def test_empty_folder_and_unreadable_video(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no images"):
        open_source(str(tmp_path))
    bogus = tmp_path / "clip.mp4"
    bogus.write_bytes(b"not a video")
    with pytest.raises(SourceError, match="cannot open"):
        open_source(str(bogus))


def test_missing_camera_is_reported_and_retried_not_a_crash() -> None:
    source = open_source("97", reconnect_interval_s=0.05)  # no /dev/video97 here
    assert source.live
    assert source.read(timeout_s=0.3) is None
    assert _wait_until(lambda: source.stats.failures >= 2)  # it keeps trying
    assert not source.stats.connected and "cannot open" in source.stats.last_error
    source.close()


def test_live_reader_keeps_the_newest_frame_counts_drops_and_reconnects(video: Path) -> None:
    """A real OpenCV capture on a 5-frame clip: reading it faster than we consume drops frames; the end
    of the clip is a disconnect, and the reader reopens it (a camera that comes back)."""
    source = LiveSource(lambda: cv2.VideoCapture(str(video)), "clip", reconnect_interval_s=0.05)
    assert _wait_until(lambda: source.stats.reconnects >= 2)
    frame = source.read(timeout_s=2.0)
    assert frame is not None and frame.image.shape == (240, 360, 3)
    assert source.stats.drops > 0 and source.stats.failures >= 2
    assert "end of stream" in source.stats.last_error
    later = source.read(timeout_s=2.0)
    assert later is not None and later.frame_id > frame.frame_id  # only newer frames, never a repeat
    source.close()


class _SocketCapture:
    """A minimal network camera client: length-prefixed JPEG frames over TCP (blocking reads, like a driver)."""

    def __init__(self, port: int) -> None:
        self._sock: socket.socket | None = None
        try:
            self._sock = socket.create_connection(("127.0.0.1", port), timeout=1.0)
            self._sock.settimeout(None)  # a hung camera blocks forever
        except OSError:
            self._sock = None

    def isOpened(self) -> bool:  # noqa: N802
        return self._sock is not None

    def _exact(self, n: int) -> bytes:
        assert self._sock is not None
        data = b""
        while len(data) < n:
            chunk = self._sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def read(self) -> tuple[bool, Any]:
        try:
            (size,) = struct.unpack("!I", self._exact(4))
            image = cv2.imdecode(np.frombuffer(self._exact(size), np.uint8), cv2.IMREAD_COLOR)
        except (OSError, ConnectionError):
            return False, None
        return image is not None, image

    def release(self) -> None:
        if self._sock is not None:
            self._sock.close()


def test_stalled_camera_is_reported_and_a_new_connection_recovers(folder: Path) -> None:
    jpeg = (folder / "frames" / "000001.jpg").read_bytes()
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    port = server.getsockname()[1]
    stop = threading.Event()
    connections: list[socket.socket] = []

    def serve() -> None:
        # First client: three frames, then silence with the connection held open (a stalled camera).
        # Later clients: frames every 20 ms.
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                return
            connections.append(conn)
            count = 3 if len(connections) == 1 else 10**6
            try:
                for _ in range(count):
                    if stop.is_set():
                        break
                    conn.sendall(struct.pack("!I", len(jpeg)) + jpeg)
                    time.sleep(0.02)
            except OSError:
                continue

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    source = LiveSource(
        lambda: _SocketCapture(port), "tcp-cam", reconnect_interval_s=0.05, stall_timeout_s=0.3
    )
    try:
        assert source.read(timeout_s=2.0) is not None
        stalled_seen = False
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not (stalled_seen and len(connections) >= 2):
            source.read(timeout_s=0.2)
            stalled_seen = stalled_seen or "stalled" in source.stats.last_error
        assert stalled_seen and len(connections) >= 2
        assert source.read(timeout_s=2.0) is not None  # frames flow again from the new connection
        assert source.stats.reconnects >= 1
    finally:
        stop.set()
        source.close()
        server.close()
        for conn in connections:
            conn.close()


def test_installed_packages_plug_schemes_in_through_entry_points() -> None:
    """The simulator's sim+tcp:// reaches the companion as a declared plugin, never as an import of sitl."""
    import importlib.metadata

    from companion.vision.frame_sources import ENTRY_POINT_GROUP
    from sitl.frame_transport import factory

    (entry,) = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP, name="sim+tcp")
    assert entry.load() is factory
    with pytest.raises(SourceError, match="unknown scheme 'nosuch'"):
        open_source("nosuch://127.0.0.1:1")


def test_new_schemes_can_be_registered(folder: Path) -> None:
    register_scheme("replay", lambda spec, options: FolderSource(Path(spec.split("://", 1)[1])))
    source = open_source(f"replay://{folder}")
    frame = source.read()
    assert frame is not None and frame.frame_id == 1


@pytest.mark.slow
def test_sim_stream_keeps_the_renderers_frame_ids_and_survives_a_silent_camera(
    sequence_dirs: list[Path],
) -> None:
    """sim+tcp:// goes through the same LiveSource as real cameras, but its frames keep the stream's ids
    (the simulated detector looks ground truth up by them)."""
    from tests.camera_stream import CameraStream

    camera = CameraStream(sequence_dirs[0] / "frames", count=5)
    camera.frame_id = 1000  # the renderer has been running a while
    source = open_source(f"sim+tcp://127.0.0.1:{camera.port}", stall_timeout_s=0.5)
    try:
        first = source.read(timeout_s=5.0)
        assert first is not None and first.frame_id > 1000
        camera.paused.set()  # the camera goes silent: reported as a stall, not raised
        time.sleep(1.2)
        assert source.read(timeout_s=0.3) is None
        camera.paused.clear()
        later = source.read(timeout_s=5.0)
        assert later is not None and later.frame_id > first.frame_id and later.image.shape == (480, 640, 3)
        assert source.stats.failures >= 1
    finally:
        source.close()
        camera.close()
