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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

import numpy as np

if TYPE_CHECKING:
    from companion.vision.frame_sources import FrameSource

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


class SimStreamCapture:
    """sim+tcp:// as a capture for `companion.vision.frame_sources.LiveSource`, which reads it in a background
    thread, keeps the newest frame, and reports and retries a lost or refused connection.

    Frames keep the stream's own ids (the renderer's), so a keyframe sent to the back-end names the
    frame whose ground truth the simulated detector looks up.
    """

    def __init__(self, url: str) -> None:
        self.last_frame_id: int | None = None
        try:
            self._reader: FrameStreamReader | None = FrameStreamReader(url)
        except OSError as exc:
            log.debug("camera %s: cannot connect: %s", url, exc)
            self._reader = None

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self._reader is not None

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self._reader is None:
            return False, None
        try:
            frame = self._reader.read()
        except (OSError, FrameStreamError) as exc:
            log.debug("camera stream: %s", exc)
            return False, None
        self.last_frame_id = frame.frame_id
        return True, frame.image

    def release(self) -> None:
        if self._reader is not None:
            self._reader.close()


def factory(spec: str, options: dict[str, Any]) -> FrameSource:
    """The companion's frame source for a sim+tcp:// URL: declared in pyproject.toml's
    `cloudtrack.frame_sources` entry points, so `open_source` finds it without importing the simulator."""
    from companion.vision.frame_sources import LiveSource

    parse_url(spec)  # fail at start-up on a malformed URL, not in the reader thread
    return LiveSource(
        lambda: SimStreamCapture(spec),
        spec,
        reconnect_interval_s=float(options.get("reconnect_interval_s") or 1.0),
        stall_timeout_s=float(options.get("stall_timeout_s") or 2.0),
    )
