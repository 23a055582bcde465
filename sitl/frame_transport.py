"""The `sim+tcp://HOST:PORT` frame stream from the simulated camera to the companion.

One packet per frame: a 32-byte header (magic b"CTF1", frame id, world time, wall time, width, height,
payload length) then raw BGR pixels, row-major. Raw pixels because both ends sit on one machine and
JPEG coding would cost more CPU than the copy. The reader checks every field and raises
`FrameStreamError` on anything malformed instead of handing garbage to the tracker.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import numpy as np

log = logging.getLogger(__name__)

MAGIC = b"CTF1"
HEADER = struct.Struct("!4sIddHHI")
MAX_PIXELS = 4096 * 4096
SCHEME = "sim+tcp"


class FrameStreamError(Exception):
    """The stream sent something that is not a frame (wrong magic, sizes that do not add up)."""


@dataclass(frozen=True)
class StreamFrame:
    frame_id: int
    world_time_s: float
    wall_time_s: float
    image: np.ndarray


def encode_frame(frame_id: int, world_time_s: float, wall_time_s: float, image: np.ndarray) -> bytes:
    h, w = image.shape[:2]
    payload = np.ascontiguousarray(image, dtype=np.uint8).tobytes()
    return HEADER.pack(MAGIC, frame_id, world_time_s, wall_time_s, w, h, len(payload)) + payload


def parse_url(url: str) -> tuple[str, int]:
    """(host, port) of a sim+tcp:// URL; ValueError with the expected form otherwise."""
    parsed = urlparse(url)
    if parsed.scheme != SCHEME or not parsed.hostname or not parsed.port:
        raise ValueError(f"not a simulated camera URL: {url!r} (expected sim+tcp://HOST:PORT)")
    return parsed.hostname, parsed.port


class FrameStreamReader:
    """Blocking reader of one sim+tcp stream; `read()` returns the next frame or raises."""

    def __init__(self, url: str, timeout_s: float = 2.0) -> None:
        host, port = parse_url(url)
        self.url = url
        self._sock = socket.create_connection((host, port), timeout=timeout_s)
        self._sock.settimeout(timeout_s)

    def _exact(self, n: int) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = self._sock.recv_into(view[got:], n - got)
            if k == 0:
                raise ConnectionError(f"{self.url}: stream closed")
            got += k
        return bytes(buf)

    def read(self) -> StreamFrame:
        magic, frame_id, world_t, wall_t, w, h, length = HEADER.unpack(self._exact(HEADER.size))
        if magic != MAGIC:
            raise FrameStreamError(f"{self.url}: bad magic {magic!r}, not a CloudTrack frame stream")
        if w == 0 or h == 0 or w * h > MAX_PIXELS or length != w * h * 3:
            raise FrameStreamError(f"{self.url}: bad frame header {w}x{h}, {length} bytes")
        image = np.frombuffer(self._exact(length), np.uint8).reshape(h, w, 3)
        return StreamFrame(frame_id, world_t, wall_t, image)

    def close(self) -> None:
        self._sock.close()


class SimStreamSource:
    """The companion's frame source for sim+tcp://: the newest frame, read by a background thread.

    Frames keep the stream's own ids (the renderer's), so a keyframe sent to the back-end names the
    frame whose ground truth the simulated detector looks up. A lost or refused connection is logged,
    counted in `stats` and retried every `reconnect_interval_s`, never raised into the main loop.
    """

    live = True

    def __init__(self, url: str, reconnect_interval_s: float = 1.0) -> None:
        from companion.frame_sources import SourceStats

        parse_url(url)  # fail at start-up on a malformed URL, not in the reader thread
        self.url = url
        self.stats = SourceStats()
        self._reconnect_interval_s = reconnect_interval_s
        self._cond = threading.Condition()
        self._latest: Any = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"frames:{url}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from companion.frame_sources import Frame

        while not self._stop.is_set():
            try:
                reader = FrameStreamReader(self.url)
            except OSError as exc:
                self._failure(f"cannot connect: {exc}")
                self._stop.wait(self._reconnect_interval_s)
                continue
            with self._cond:
                if self.stats.failures:
                    self.stats.reconnects += 1
                self.stats.connected = True
            try:
                while not self._stop.is_set():
                    sf = reader.read()
                    with self._cond:
                        if self._latest is not None:
                            self.stats.drops += 1
                        self._latest = Frame(sf.frame_id, time.monotonic(), sf.image)
                        self._cond.notify_all()
            except (OSError, FrameStreamError) as exc:
                self._failure(str(exc))
            finally:
                reader.close()
            self._stop.wait(self._reconnect_interval_s)

    def _failure(self, message: str) -> None:
        with self._cond:
            self.stats.failures += 1
            self.stats.connected = False
            self.stats.last_error = message
        log.warning("camera %s: %s; retrying every %.1f s", self.url, message, self._reconnect_interval_s)

    def read(self, timeout_s: float = 1.0) -> Any:
        """The newest frame not yet returned (a `companion.frame_sources.Frame`), or None after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._latest is None and not self._stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            frame, self._latest = self._latest, None
            if frame is not None:
                self.stats.frames += 1
        return frame

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()


def register() -> None:
    """Teach `companion.frame_sources.open_source` the sim+tcp:// scheme."""
    from companion.frame_sources import register_scheme

    def factory(spec: str, options: dict[str, Any]) -> SimStreamSource:
        return SimStreamSource(spec, float(options.get("reconnect_interval_s") or 1.0))

    register_scheme(SCHEME, factory)
