"""H.264 video files (MP4, yuv420p: what browsers play) written through PyAV on a thread of their own.

`write()` hands a frame to a bounded queue and returns at once: the caller (the companion's control loop,
the simulator's camera thread) never waits for the encoder. A full queue drops the frame and counts it
rather than block. The encoder thread converts, encodes and muxes; `close()` drains the queue, flushes the
encoder and finishes the file. An encoder failure stops the writer (later frames are dropped) and is
kept in `error`; it never reaches the caller's thread as an exception.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# A frame to write: the image and, optionally, a function drawing on a copy of it in the encoder thread.
Draw = Callable[[np.ndarray], np.ndarray]
_STOP = object()


class H264Writer:
    """One MP4 file, frames BGR uint8 of one size (odd sizes lose their last row/column: yuv420p)."""

    def __init__(
        self,
        path: Path,
        fps: float,
        *,
        queue_frames: int = 8,
        preset: str = "veryfast",
        crf: int = 23,
        threads: int = 1,
        on_frame_written: Callable[[H264Writer], None] | None = None,
    ) -> None:
        self.path = Path(path)
        self.fps = fps
        self.frames_written = 0
        self.frames_dropped = 0
        self.encode_cpu_s = 0.0  # CPU time of the encoder thread spent on frames (draw, convert, encode)
        self.error: str | None = None
        self._rate = Fraction(fps).limit_denominator(1001)
        self._options = {"preset": preset, "crf": str(crf)}
        self._threads = threads
        self._on_frame_written = on_frame_written
        self._av: Any = None
        self._container: Any = None
        self._stream: Any = None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max(1, queue_frames))
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"h264-{self.path.name}", daemon=True)
        self._thread.start()

    def write(self, image: np.ndarray, draw: Draw | None = None, *, wait: bool = False) -> bool:
        """Queue one frame; False when it was dropped (queue full, writer closed or failed).

        Never blocks unless `wait` (for a flush outside any loop, e.g. at shutdown). The image is read later,
        in the encoder thread: the caller must not modify it afterwards (camera frames are fresh arrays).
        `draw` runs there too, on a copy, for overlays that need not cost the caller's time.
        """
        if self._closed or self.error is not None:
            self.frames_dropped += 1
            return False
        try:
            self._queue.put((image, draw), block=wait, timeout=30.0 if wait else None)
        except queue.Full:
            self.frames_dropped += 1
            return False
        return True

    def close(self, timeout_s: float = 30.0) -> None:
        """Encode what is queued, flush the encoder and close the file; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(queue.Full):  # waits only while the encoder drains a full queue
            self._queue.put(_STOP, timeout=timeout_s)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning(
                "video %s: encoder still busy after %.0f s; the file may be cut short", self.path, timeout_s
            )

    @property
    def size_bytes(self) -> int:
        try:
            return self.path.stat().st_size
        except OSError:
            return 0

    # --- encoder thread --------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            # On this thread: loading FFmpeg (a first import takes a few hundred ms) and opening the file
            # never cost the caller's loop. faststart puts the index first: a browser plays the file
            # before it has all of it.
            import av

            self._av = av
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._container = av.open(str(self.path), "w", options={"movflags": "faststart"})
        except Exception as exc:
            self.error = f"cannot open {self.path}: {type(exc).__name__}: {exc}"
            log.warning("video stopped: %s", self.error)
            self._drain()
            return
        try:
            while (item := self._queue.get()) is not _STOP:
                if self.error is None:
                    self._encode(*item)
            if self._stream is not None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
        except Exception as exc:  # FFmpeg, disk full, bad frame: stop recording video, never the caller
            self.error = f"{type(exc).__name__}: {exc}"
            log.warning("video %s stopped: %s", self.path, self.error)
        finally:
            try:
                self._container.close()
            except Exception as exc:  # a full disk may refuse the trailer too
                self.error = self.error or f"{type(exc).__name__}: {exc}"
            self._drain()

    def _encode(self, image: np.ndarray, draw: Draw | None) -> None:
        started = time.thread_time()
        try:
            self._encode_frame(image, draw)
        finally:
            self.encode_cpu_s += time.thread_time() - started

    def _encode_frame(self, image: np.ndarray, draw: Draw | None) -> None:
        if draw is not None:
            image = draw(image.copy())
        height, width = (image.shape[0] // 2) * 2, (image.shape[1] // 2) * 2
        if self._stream is None:
            self._stream = self._container.add_stream("libx264", rate=self._rate)
            self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, "yuv420p"
            self._stream.options = self._options
            self._stream.codec_context.thread_count = self._threads
        elif (width, height) != (self._stream.width, self._stream.height):
            raise ValueError(
                f"frame size {width}x{height} differs from the video's {self._stream.width}x{self._stream.height}"
            )
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(image[:height, :width]), format="bgr24")
        frame.pts = self.frames_written
        frame.time_base = 1 / self._rate
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames_written += 1
        if self._on_frame_written is not None:
            self._on_frame_written(self)

    def _drain(self) -> None:
        """After a failure: count what is still queued as dropped, so close() never waits on a full queue."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                self.frames_dropped += 1
