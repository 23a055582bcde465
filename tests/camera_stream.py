"""A live `sim+tcp://` camera for end-to-end tests: real frames of a shared sequence at a steady rate."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import cv2

from sitl.frame_transport import encode_frame

CAMERA_FPS = 15.0


class CameraStream:
    """The `sim+tcp://` camera server. It plays the first `count` frames forwards then backwards, so the
    person never jumps; `paused` silences it (a camera outage)."""

    def __init__(self, frames_dir: Path, count: int = 60) -> None:
        paths = sorted(frames_dir.glob("*.jpg"))[:count]
        images = [cv2.imread(str(p)) for p in paths]
        forwards = [cv2.resize(image, (640, 480)) for image in images if image is not None]
        assert forwards, f"no frames in {frames_dir}"
        self.frames = forwards + forwards[-2:0:-1]
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.2)
        self.port = self.server.getsockname()[1]
        self.paused = threading.Event()
        self.frame_id = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            with conn:
                self._serve(conn)

    def _serve(self, conn: socket.socket) -> None:
        while not self._stop.is_set():
            time.sleep(1.0 / CAMERA_FPS)
            if self.paused.is_set():
                continue
            # Frame ids keep counting across reconnections, as a camera server's clock does.
            self.frame_id += 1
            image = self.frames[self.frame_id % len(self.frames)]
            try:
                conn.sendall(encode_frame(self.frame_id, self.frame_id / CAMERA_FPS, time.time(), image))
            except OSError:
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.server.close()

    def __enter__(self) -> CameraStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
