"""H.264 video files (MP4, yuv420p: what browsers play) written through PyAV off the caller's thread.

`write()` hands a frame to a bounded queue and returns at once: the caller (the companion's control loop,
the simulator's camera thread) never waits for the encoder. A full queue drops the frame and counts it
rather than block. A thread of the writer takes the frames from the queue and either encodes them itself
or, with `process=True`, feeds them through a pipe to an encoder process (the control loop's choice: the
encoder then never holds the loop's GIL). `close()` drains the queue, flushes the encoder and finishes
the file. An encoder failure stops the writer (later frames are dropped) and is kept in `error`; it
never reaches the caller's thread as an exception.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import queue
import signal
import threading
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
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
        process: bool = False,
    ) -> None:
        self.path = Path(path)
        self.fps = fps
        self.frames_written = 0
        self.frames_dropped = 0
        self.encode_cpu_s = 0.0  # the encoder's CPU time on frames (draw, convert, encode)
        self.error: str | None = None
        self._rate = Fraction(fps).limit_denominator(1001)
        self._options = {"preset": preset, "crf": str(crf)}
        self._threads = threads
        self._on_frame_written = on_frame_written
        self._process = process
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max(1, queue_frames))
        self._closed = False
        self._ready = threading.Event()  # the encoder can take frames (or failed to start: see `error`)
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

    def wait_ready(self, timeout_s: float) -> bool:
        """True once the encoder is up (with `process=True`: its process started and FFmpeg loaded, about a
        second of CPU on a small board), or has failed to start (`error` says why); False after `timeout_s`.
        Nothing needs to wait: frames written before are queued (or dropped when the queue is full)."""
        return self._ready.wait(timeout_s)

    @property
    def size_bytes(self) -> int:
        try:
            return self.path.stat().st_size
        except OSError:
            return 0

    # --- encoder thread --------------------------------------------------------------------------

    def _run(self) -> None:
        if self._process:
            self._run_process()
            return
        try:
            # On this thread: loading FFmpeg (a first import takes a few hundred ms) and opening the file
            # never cost the caller's loop.
            encoder = _Encoder(self.path, self._rate, self._options, self._threads)
        except Exception as exc:
            self.error = f"cannot open {self.path}: {type(exc).__name__}: {exc}"
            log.warning("video stopped: %s", self.error)
            self._ready.set()
            self._drain()
            return
        self._ready.set()
        try:
            while (item := self._queue.get()) is not _STOP:
                if self.error is None:
                    started = time.thread_time()
                    try:
                        encoder.encode(*item)
                    finally:
                        self.encode_cpu_s += time.thread_time() - started
                    self.frames_written = encoder.frames
                    if self._on_frame_written is not None:
                        self._on_frame_written(self)
            encoder.flush()
        except Exception as exc:  # FFmpeg, disk full, bad frame: stop recording video, never the caller
            self.error = f"{type(exc).__name__}: {exc}"
            log.warning("video %s stopped: %s", self.path, self.error)
        finally:
            try:
                encoder.close()
            except Exception as exc:  # a full disk may refuse the trailer too
                self.error = self.error or f"{type(exc).__name__}: {exc}"
            self._drain()

    def _run_process(self) -> None:
        """This thread feeds an encoder process through a pipe: only the copy of each frame into the pipe
        happens in the caller's process, so the encoder never holds the caller's GIL."""
        context = multiprocessing.get_context("spawn")  # never fork a process that runs threads
        frames_out, frames_in = context.Pipe(duplex=False)
        events_out, events_in = context.Pipe(duplex=False)
        process = context.Process(
            target=_encoder_process,
            args=(frames_out, events_in, str(self.path), self._rate, self._options, self._threads),
            name=f"h264-{self.path.name}",
            daemon=True,
        )
        try:
            process.start()
        except Exception as exc:
            self.error = f"cannot start the encoder process: {type(exc).__name__}: {exc}"
            log.warning("video %s stopped: %s", self.path, self.error)
            self._ready.set()
            self._drain()
            return
        frames_out.close()
        events_in.close()
        reader = threading.Thread(target=self._read_events, args=(events_out,), name=f"h264-events-{self.path.name}",
                                  daemon=True)  # fmt: skip
        reader.start()
        try:
            while (item := self._queue.get()) is not _STOP:
                if self.error is not None:
                    self.frames_dropped += 1
                    continue
                image, draw = item
                pixels = np.ascontiguousarray(image)
                frames_in.send((pixels.shape, pixels.dtype.str, draw))
                frames_in.send_bytes(pixels.reshape(-1).data)  # 1-D: the pipe counts bytes by length
            frames_in.send(None)
        except Exception as exc:  # the encoder process is gone, or a draw function that cannot be pickled
            self.error = self.error or f"encoder process: {type(exc).__name__}: {exc}"
            log.warning("video %s stopped: %s", self.path, self.error)
        finally:
            frames_in.close()
            reader.join(60.0)
            process.join(5.0)
            if process.is_alive():
                process.kill()
            self._drain()

    def _read_events(self, events: Any) -> None:
        try:
            self._read_events_until_done(events)
        finally:
            self._ready.set()  # whatever happened, nobody waits for an encoder that is gone

    def _read_events_until_done(self, events: Any) -> None:
        while True:
            try:
                kind, *values = events.recv()
            except (EOFError, OSError):
                self.error = self.error or "the encoder process ended before finishing the file"
                return
            if kind == "ready":
                self._ready.set()
            elif kind == "written":
                self.frames_written, self.encode_cpu_s = values
                if self._on_frame_written is not None:
                    self._on_frame_written(self)
            elif kind == "error":
                self.error = self.error or values[0]
                log.warning("video %s stopped: %s", self.path, values[0])
            elif kind == "done":
                return

    def _drain(self) -> None:
        """After a failure: count what is still queued as dropped, so close() never waits on a full queue."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                self.frames_dropped += 1


class _Encoder:
    """One file's container and H.264 stream: what the encoder thread or the encoder process runs."""

    def __init__(self, path: Path, rate: Fraction, options: dict[str, str], threads: int) -> None:
        import av  # here: only processes that record video pay for loading FFmpeg

        self._av = av
        self._rate, self._options, self._threads = rate, options, threads
        path.parent.mkdir(parents=True, exist_ok=True)
        # faststart: the index goes first, so a browser plays the file before it has all of it.
        self._container: Any = av.open(str(path), "w", options={"movflags": "faststart"})
        self._stream: Any = None
        self.frames = 0

    def encode(self, image: np.ndarray, draw: Draw | None) -> None:
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
        # OpenCV's BGR -> I420 is about 0.25 ms a 640x480 frame cheaper than FFmpeg's swscale from bgr24.
        bgr = np.ascontiguousarray(image[:height, :width])
        yuv = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420), np.uint8)
        frame = self._av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        frame.pts = self.frames
        frame.time_base = 1 / self._rate
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def flush(self) -> None:
        if self._stream is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)

    def close(self) -> None:
        self._container.close()


def _encoder_process(
    frames: Any, events: Any, path: str, rate: Fraction, options: dict[str, str], threads: int
) -> None:
    """The encoder process: frames in through one pipe, progress out through the other.

    It ends when its feeder sends None or closes the pipe (or dies), and on SIGTERM (systemd signals the
    whole unit at stop; multiprocessing at interpreter exit) once no frame is waiting, always after
    writing the file's index so the video plays. SIGINT (Ctrl-C in a terminal) is the feeder's to handle.
    """
    terminated: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, _frame: terminated.append(signum))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import av  # noqa: F401 - loaded before "ready"; the file itself is opened on the first frame

    events.send(("ready",))
    encoder: _Encoder | None = None  # none until a frame comes: a writer closed unused leaves no file
    cpu_s = 0.0
    try:
        while True:
            try:
                if not frames.poll(0.2):
                    if terminated:
                        break
                    continue
                header = frames.recv()
            except EOFError:  # the feeder died: finish what there is
                break
            if header is None:
                break
            shape, dtype, draw = header
            image = np.frombuffer(frames.recv_bytes(), np.dtype(dtype)).reshape(shape)
            if encoder is None:
                try:
                    encoder = _Encoder(Path(path), rate, options, threads)
                except Exception as exc:
                    events.send(("error", f"cannot open {path}: {type(exc).__name__}: {exc}"))
                    return
            started = time.process_time()
            encoder.encode(image, draw)
            cpu_s += time.process_time() - started
            events.send(("written", encoder.frames, cpu_s))
        if encoder is not None:
            encoder.flush()
    except Exception as exc:
        events.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        try:
            if encoder is not None:
                encoder.close()
        except Exception as exc:
            events.send(("error", f"{type(exc).__name__}: {exc}"))
        with contextlib.suppress(OSError):
            events.send(("done",))
