"""Where frames come from: a V4L2 camera, a video file, an RTSP/HTTP/GStreamer stream, or a frames folder.

`open_source(spec)` picks the transport:
- "0", "1" ...: V4L2 device index (live);
- "rtsp://...", "http(s)://...", "udp://...": a network stream through OpenCV/FFmpeg (live);
- "gst:PIPELINE" or any text containing " ! ": a GStreamer pipeline ending in appsink (live);
- a folder holding `frames/000001.jpg...` (the layout of ../shared/data/sequences) or the images
  themselves: every frame, in name order;
- any other existing file: a video file, every frame in order.
Other schemes are added with `register_scheme("sim", factory)`, or by an installed package through the
`cloudtrack.frame_sources` entry-point group (name: the scheme, value: the factory), looked up the first
time the scheme is asked for: the simulator's `sim+tcp://` comes in that way, so the companion never
imports the simulator.

Live sources are read by a thread that keeps only the newest frame and counts the ones the consumer never
saw (drops). A camera that fails to open, stops delivering (read fails) or stalls (no frame for
`stall_timeout_s`) is reported in the log and in `stats`, and reopened every `reconnect_interval_s`:
never a crash. Finite sources skip an unreadable image with a warning and count it.
"""

from __future__ import annotations

import importlib.metadata
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


@dataclass(frozen=True)
class Frame:
    frame_id: int  # 1-based, increasing; live sources skip ids of dropped frames
    capture_time: float  # time.monotonic() when the frame was read from the device or file
    image: np.ndarray  # BGR uint8


@dataclass
class SourceStats:
    frames: int = 0  # frames delivered to the consumer
    drops: int = 0  # live frames replaced by a newer one before the consumer read them
    skipped: int = 0  # unreadable images or frames skipped with a warning
    reconnects: int = 0  # successful re-openings after a failure
    failures: int = 0  # failed opens, failed reads and stalls
    last_error: str = ""
    connected: bool = False


class FrameSource(Protocol):
    """`read()` gives the next frame; None means the end of a finite source, or no new frame within
    `timeout_s` for a live one (check `live` and `stats`)."""

    live: bool
    stats: SourceStats

    def read(self, timeout_s: float = 1.0) -> Frame | None: ...

    def close(self) -> None: ...


class SourceError(Exception):
    """A source spec that cannot be opened at all (no such file, empty folder, unknown scheme)."""


class Capture(Protocol):
    """The part of cv2.VideoCapture a live source uses.

    A capture that numbers its own frames (the simulator's stream, whose ids name ground truth) also has
    an int `last_frame_id`, set by read(); other captures' frames are numbered by the live source.
    """

    def isOpened(self) -> bool: ...  # noqa: N802 - OpenCV's name

    def read(self) -> tuple[bool, Any]: ...

    def release(self) -> None: ...


class FolderSource:
    """Every image of a folder in name order; an unreadable file is skipped with a warning.

    Capture times are the read time, or with `fps` the recording's timing (frame n at (n - 1) / fps)."""

    live = False

    def __init__(self, folder: Path, stop_after: int | None = None, fps: float | None = None) -> None:
        root = folder / "frames" if (folder / "frames").is_dir() else folder
        self.paths = sorted(p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if stop_after is not None:
            self.paths = self.paths[:stop_after]
        if not self.paths:
            raise SourceError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
        self.stats = SourceStats(connected=True)
        self._next = 0
        self._fps = fps
        self._opened_at = time.monotonic()

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        while self._next < len(self.paths):
            path = self.paths[self._next]
            self._next += 1
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                self.stats.skipped += 1
                self.stats.last_error = f"{path}: unreadable image, skipped"
                log.warning("%s", self.stats.last_error)
                continue
            self.stats.frames += 1
            # With `fps` the capture time is the recording's (a replay keeps the sequence's timing).
            t = self._opened_at + (self._next - 1) / self._fps if self._fps else time.monotonic()
            # The frame id is the file's position so ground truth lines stay aligned after a skip.
            return Frame(self._next, t, image)
        return None

    def close(self) -> None:
        self._next = len(self.paths)


class VideoFileSource:
    """Every frame of a video file in order."""

    live = False

    def __init__(self, path: Path) -> None:
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            raise SourceError(f"{path}: OpenCV cannot open this video file")
        self.stats = SourceStats(connected=True)
        self._count = 0

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        ok, image = self._cap.read()
        if not ok or image is None:
            return None
        self._count += 1
        self.stats.frames += 1
        return Frame(self._count, time.monotonic(), image)

    def close(self) -> None:
        self._cap.release()


class LiveSource:
    """A camera or stream read by a background thread that keeps only the newest frame.

    `opener()` returns a Capture (cv2.VideoCapture or anything with isOpened/read/release). A failed open
    or read, or no frame for `stall_timeout_s`, is logged, counted, and followed by a reopen after
    `reconnect_interval_s`. A capture whose read() hangs cannot be interrupted: the stall is reported and
    a fresh capture is opened beside it.
    """

    live = True

    def __init__(
        self,
        opener: Callable[[], Capture],
        description: str,
        reconnect_interval_s: float = 1.0,
        stall_timeout_s: float = 2.0,
    ) -> None:
        self.description = description
        self.stats = SourceStats()
        self._opener = opener
        self._reconnect_interval_s = reconnect_interval_s
        self._stall_timeout_s = stall_timeout_s
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._next_id = 0
        self._last_frame_at = time.monotonic()
        self._stop = threading.Event()
        self._generation = 0  # bumped on a stall so a hung reader's late frames are ignored
        self._opened_once = False
        self._start_reader()

    def _start_reader(self) -> None:
        self._generation += 1
        thread = threading.Thread(
            target=self._run, args=(self._generation,), name=f"frames:{self.description}", daemon=True
        )
        thread.start()

    def _failure(self, message: str) -> None:
        with self._cond:
            self.stats.failures += 1
            self.stats.connected = False
            self.stats.last_error = message
        log.warning(
            "camera %s: %s; retrying every %.1f s", self.description, message, self._reconnect_interval_s
        )

    def _run(self, generation: int) -> None:
        while not self._stop.is_set() and generation == self._generation:
            try:
                cap = self._opener()
                opened = cap.isOpened()
            except Exception as exc:  # a broken driver or URL must not kill the reader
                cap, opened = None, False
                self._failure(f"open failed: {exc}")
            else:
                if not opened:
                    self._failure("cannot open")
            if opened and cap is not None:
                with self._cond:
                    if self._opened_once:
                        self.stats.reconnects += 1
                        log.info("camera %s: reconnected", self.description)
                    self._opened_once = True
                    self.stats.connected = True
                    self._last_frame_at = time.monotonic()
                self._read_until_failure(cap, generation)
                cap.release()
            self._stop.wait(self._reconnect_interval_s)

    def _read_until_failure(self, cap: Capture, generation: int) -> None:
        while not self._stop.is_set() and generation == self._generation:
            try:
                ok, image = cap.read()
            except Exception as exc:
                ok, image = False, None
                log.debug("camera %s: read raised %s", self.description, exc)
            if generation != self._generation:
                return  # this reader was declared stalled and replaced
            if not ok or image is None:
                self._failure("read failed (disconnected or end of stream)")
                return
            with self._cond:
                if generation != self._generation:
                    return
                stream_id = getattr(cap, "last_frame_id", None)
                self._next_id = stream_id if isinstance(stream_id, int) else self._next_id + 1
                if self._latest is not None:
                    self.stats.drops += 1
                self._latest = Frame(self._next_id, time.monotonic(), image)
                self._last_frame_at = self._latest.capture_time
                self._cond.notify_all()

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """The newest frame not yet returned, waiting up to `timeout_s`; None if none came."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._latest is None and not self._stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            frame, self._latest = self._latest, None
            stalled = (
                frame is None
                and self.stats.connected
                and time.monotonic() - self._last_frame_at > self._stall_timeout_s
            )
            if frame is not None:
                self.stats.frames += 1
        if stalled:
            self._failure(f"stalled: no frame for {self._stall_timeout_s:.1f} s")
            self._start_reader()
        return frame

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()


SourceFactory = Callable[[str, dict[str, Any]], FrameSource]
_SCHEMES: dict[str, SourceFactory] = {}


ENTRY_POINT_GROUP = "cloudtrack.frame_sources"


def register_scheme(scheme: str, factory: SourceFactory) -> None:
    """Make `open_source("SCHEME://...")` call `factory(spec, options)`; options are open_source's keywords."""
    _SCHEMES[scheme.lower()] = factory


def _plugin_factory(scheme: str) -> SourceFactory | None:
    """The factory an installed package declares for `scheme` in the entry-point group, loaded once."""
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP, name=scheme):
        factory: SourceFactory = entry.load()
        register_scheme(scheme, factory)
        return factory
    return None


def _capture_opener(target: int | str, api: int, options: dict[str, Any]) -> Callable[[], Capture]:
    def open_capture() -> Capture:
        params: list[int] = []
        if isinstance(target, str) and api == cv2.CAP_FFMPEG:
            # Bound how long a dead network stream can block open() and read().
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, 5000, cv2.CAP_PROP_READ_TIMEOUT_MSEC, 5000]
        cap = cv2.VideoCapture(target, api, params)
        if isinstance(target, int):
            if options.get("width"):
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, float(options["width"]))
            if options.get("height"):
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, float(options["height"]))
            if options.get("fps"):
                cap.set(cv2.CAP_PROP_FPS, float(options["fps"]))
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a queue of stale ones
        return cap

    return open_capture


def _live(target: int | str, api: int, spec: str, options: dict[str, Any]) -> FrameSource:
    return LiveSource(
        _capture_opener(target, api, options),
        spec,
        reconnect_interval_s=float(options.get("reconnect_interval_s", 1.0)),
        stall_timeout_s=float(options.get("stall_timeout_s", 2.0)),
    )


def _network(spec: str, options: dict[str, Any]) -> FrameSource:
    return _live(spec, cv2.CAP_FFMPEG, spec, options)


for _scheme in ("rtsp", "rtsps", "http", "https", "udp", "tcp", "rtmp"):
    register_scheme(_scheme, _network)


def open_source(
    spec: str,
    *,
    width: int | None = None,
    height: int | None = None,
    fps: float | None = None,
    reconnect_interval_s: float = 1.0,
    stall_timeout_s: float = 2.0,
) -> FrameSource:
    """Open a frame source from the camera.source text; SourceError when it cannot be opened at all."""
    options: dict[str, Any] = {
        "width": width,
        "height": height,
        "fps": fps,
        "reconnect_interval_s": reconnect_interval_s,
        "stall_timeout_s": stall_timeout_s,
    }
    text = spec.strip()
    if not text:
        raise SourceError("empty camera source")
    if text.isdigit():
        return _live(int(text), cv2.CAP_V4L2 if hasattr(cv2, "CAP_V4L2") else cv2.CAP_ANY, text, options)
    if text.startswith("gst:") or " ! " in text:
        pipeline = text[4:] if text.startswith("gst:") else text
        return _live(pipeline, cv2.CAP_GSTREAMER, text, options)
    if "://" in text:
        scheme = text.split("://", 1)[0].lower()
        factory = _SCHEMES.get(scheme) or _plugin_factory(scheme)
        if factory is None:
            raise SourceError(f"{spec}: unknown scheme {scheme!r}; known: {', '.join(sorted(_SCHEMES))}")
        return factory(text, options)
    path = Path(text).expanduser()
    if path.is_dir():
        return FolderSource(path)
    if path.is_file():
        return VideoFileSource(path)
    raise SourceError(
        f"{spec}: not a device index, URL, folder or file "
        "(examples: 0, rtsp://192.168.1.10:8554/cam, ../shared/data/sequences/otb_Crossing, video.mp4)"
    )
