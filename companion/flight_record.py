"""The flight record: one folder per mission, size-capped, that never stops the companion.

A mission folder `<dir>/<UTC start>_<vehicle>_<mission>/` holds:
  events.jsonl        one JSON object per line: {"t": UTC seconds, "kind": ..., ...fields}; state changes,
                      back-end answers, supervisor decisions, safety events and the behaviour steps that
                      `cloudtrack-companion replay` re-runs
  mavlink-NNN.tlog    every MAVLink message in the tlog format MAVProxy writes and pymavlink reads
                      (8-byte big-endian microseconds since the epoch, then the raw message)
  keyframes/NNNNNN.jpg  the keyframes sent to the back-end (the event log names them)
  video-NNN.mp4       optional camera video (H.264, plays in a browser) with the track box and state drawn
                      on it, encoded in a process of its own: the loop only queues frames, and a frame
                      that finds the encoder's queue full is dropped, never waited for

Size cap: the records directory as a whole (all missions) stays under `max_bytes`; what the other
missions hold is measured once, on a thread (never a walk of all records in the main loop). Over the cap the
oldest data goes first: whole older missions, then this mission's oldest keyframes and closed tlog/video
segments. The event log of the running mission is never rotated away. If the cap or the disk leaves no
room (ENOSPC, read-only, too little free space) recording stops with one warning and every later call
is a no-op; a flight must never end because its recorder failed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np

from behaviors import event_codec
from behaviors.actions import Action, Hold, ReleaseControl
from behaviors.events import (
    AutopilotLinkLost,
    BackendAnswer,
    BackendUnreachable,
    Event,
    GcsCommand,
    PilotTakeover,
)
from behaviors.geometry import Box
from behaviors.mission import State, initial_state
from behaviors.mission_commands import ConfirmCandidate, RejectCandidate, StartMission
from behaviors.mission_config import MissionConfig
from cloudtrack.h264_video import H264Writer
from cloudtrack.private_files import open_private, private_dir, private_file, write_private

log = logging.getLogger(__name__)

EVENTS_FILE = "events.jsonl"
KEYFRAMES_DIR = "keyframes"
# Below this much free space on the file system the recorder stops, leaving room for the OS and its logs.
DEFAULT_MIN_FREE_BYTES = 64 * 1024 * 1024
_FREE_CHECK_EVERY_BYTES = 1024 * 1024
_TLOG_FLUSH_S = 1.0
# Frames the video encoder may hold before the loop's frames are dropped (640x480: about 1 MB each).
_VIDEO_QUEUE_FRAMES = 8
# The video's growth is counted against the cap, as the encoder reports frames, in steps of this many bytes.
_VIDEO_ACCOUNT_BYTES = 64 * 1024
# The longest the loop waits for the walk of the other missions, and only when over the cap before it ends.
_MEASURE_WAIT_S = 0.25


class MissionRecord(Protocol):
    """What the companion's main loop writes to; `FlightRecorder` is the implementation."""

    def event(self, kind: str, **fields: Any) -> None: ...

    def mavlink(self, raw: bytes, time_s: float | None = None) -> None: ...

    def keyframe(self, jpeg: bytes, frame_id: int) -> str | None: ...

    def video_frame(self, image: np.ndarray, box: Box | None, state: str) -> None: ...

    def close(self) -> None: ...


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-")[:48] or "mission"


def _tree_size(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):  # a file rotated away while we walk
                total += os.lstat(os.path.join(root, name)).st_size
    return total


class FlightRecorder:
    """Writes one mission's record. Thread-safe: the main loop and the back-end worker both write events."""

    def __init__(
        self,
        root: Path,
        vehicle_id: str,
        mission_id: str,
        max_bytes: int,
        *,
        video: bool = False,
        video_fps: float = 10.0,
        min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.max_bytes = max_bytes
        self.segment_bytes = max(4096, max_bytes // 16)
        self.min_free_bytes = min_free_bytes
        self._clock = clock
        self._lock = threading.Lock()
        self._active = True
        self._events: IO[str] | None = None
        self._tlog: IO[bytes] | None = None
        self._tlog_index = 0
        self._tlog_bytes = 0
        self._tlog_flushed = 0.0
        self._video_wanted = video
        self._video_fps = video_fps
        self._video: H264Writer | None = None
        self._video_index = 0
        self._video_rotate = False  # set on the encoder's reports: the segment is full, start the next
        self._video_accounted: dict[Path, int] = {}  # bytes of each segment already counted in _used
        self._video_writers: list[H264Writer] = []
        # The video is declared at video_fps: frames coming faster (a loop outrunning the camera) are
        # skipped rather than encoded, so the encoder's CPU follows the camera's rate.
        self._video_period = 1.0 / video_fps if video_fps > 0 else 0.0
        self._video_due = 0.0
        self.video_frames_skipped = 0
        # Oldest first: files of this mission that rotation may delete (closed segments, keyframes).
        self._rotatable: deque[Path] = deque()
        self._since_free_check = 0
        self.root = Path(root).expanduser()
        started = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(clock()))
        self.folder = self.root / f"{started}_{_safe_name(vehicle_id)}_{_safe_name(mission_id)}"
        # Bytes under root: this mission's, counted as written, plus the rest, measured on a thread.
        self._used = 0
        self._others: dict[Path, int] = {}  # older mission folders and their sizes
        self._others_measured = threading.Event()
        self._others_counted = False
        self._others_total = 0
        try:
            # What the drone saw and did is its owner's alone, whatever the umask (0700 folders, 0600 files).
            private_dir(self.folder / KEYFRAMES_DIR)
            threading.Thread(target=self._measure_others, name="flight-record-measure", daemon=True).start()
            self._events = open_private(self.folder / EVENTS_FILE, "a", encoding="utf-8")
            self._check_free_space()
        except OSError as exc:
            self._stop(f"cannot create {self.folder}: {exc}")
            return
        self._write_event({"kind": "recording_started", "vehicle": vehicle_id, "mission": mission_id})
        if video and self._active:
            # The encoder process starts with the mission, not on its first frame: its start-up (a Python
            # loading FFmpeg, about a second of CPU) then overlaps the search, not the first followed frames.
            with self._lock:
                self._next_video_segment()

    @property
    def active(self) -> bool:
        """False once recording has stopped (disabled, disk full, cap reached, closed)."""
        return self._active

    # --- public writers -------------------------------------------------------------------------

    def event(self, kind: str, **fields: Any) -> None:
        """One line of the event log, stamped with the wall-clock time."""
        with self._lock:
            if self._active:
                self._write_event({"kind": kind, **fields})

    def mavlink(self, raw: bytes, time_s: float | None = None) -> None:
        """One MAVLink message as received or sent (e.g. `msg.get_msgbuf()`)."""
        with self._lock:
            if not self._active:
                return
            stamp = self._clock() if time_s is None or not 0 <= time_s < 1e11 else time_s
            record = struct.pack(">Q", int(stamp * 1e6)) + bytes(raw)
            try:
                if self._tlog is None or self._tlog_bytes >= self.segment_bytes:
                    self._roll_tlog()
                assert self._tlog is not None
                self._tlog.write(record)
                self._tlog_bytes += len(record)
                # Flushed about once a second: a power cut loses at most that much telemetry.
                now = time.monotonic()
                if now - self._tlog_flushed >= _TLOG_FLUSH_S:
                    self._tlog.flush()
                    self._tlog_flushed = now
            except OSError as exc:
                self._stop(f"tlog write failed: {exc}")
                return
            self._account(len(record))

    def keyframe(self, jpeg: bytes, frame_id: int) -> str | None:
        """Store a keyframe sent to the back-end; returns its path relative to the mission folder."""
        with self._lock:
            if not self._active:
                return None
            relative = f"{KEYFRAMES_DIR}/{frame_id:06d}.jpg"
            path = self.folder / relative
            try:
                write_private(path, jpeg)
            except OSError as exc:
                path.unlink(missing_ok=True)
                self._stop(f"keyframe write failed: {exc}")
                return None
            self._rotatable.append(path)
            self._write_event(
                {"kind": "keyframe", "frame_id": frame_id, "file": relative, "bytes": len(jpeg)}
            )
            self._account(len(jpeg))
            return relative if self._active else None

    def video_frame(self, image: np.ndarray, box: Box | None, state: str) -> None:
        """One camera frame for the overlay video (no-op unless video was asked for).

        Costs the caller a queue put: drawing and H.264 encoding happen in the encoder process. The image
        must not be modified afterwards (camera frames are fresh arrays)."""
        with self._lock:
            if not (self._active and self._video_wanted):
                return
            now = time.monotonic()
            if now + 0.5 * self._video_period < self._video_due:  # half a period of jitter is fine
                self.video_frames_skipped += 1
                return
            self._video_due = max(self._video_due, now - self._video_period) + self._video_period
            try:
                if self._video is None or self._video_rotate:
                    self._next_video_segment()
                assert self._video is not None
                stamp = time.strftime("%H:%M:%S", time.gmtime(self._clock()))
                self._video.write(image, partial(_draw_record_overlay, box=box, label=f"{stamp} {state}"))
            except Exception as exc:  # FFmpeg cannot open the file, ...: the flight goes on without video
                self._stop(f"video write failed: {exc}")

    def wait_video_ready(self, timeout_s: float) -> bool:
        """True once the video encoder takes frames (at once without video). Nothing in flight waits for
        it; the bench does, so that its timed passes measure recording, not the encoder's start-up."""
        video = self._video
        return video is None or video.wait_ready(timeout_s)

    @property
    def video_encode_cpu_s(self) -> float:
        """CPU seconds the encoders spent on this record's frames."""
        return sum(w.encode_cpu_s for w in self._video_writers)

    @property
    def video_frames(self) -> tuple[int, int]:
        """(encoded, dropped) over every segment: dropped frames found the encoder's queue full."""
        return (
            sum(w.frames_written for w in self._video_writers),
            sum(w.frames_dropped for w in self._video_writers),
        )

    def close(self) -> None:
        """Flush and close everything; safe to call twice and after a failure. Waits for the video to be
        encoded to its end (a few queued frames)."""
        with self._lock:
            if self._active:
                self._write_event({"kind": "recording_closed"})
            video, self._video = self._video, None
            self._close_files()
            self._active = False
        if video is not None:
            video.close()  # outside the lock: the encoder's reports take it to account what it wrote

    # --- internals (called with the lock held) --------------------------------------------------

    def _write_event(self, entry: Mapping[str, Any]) -> None:
        line = json.dumps({"t": round(self._clock(), 6), **entry}, default=str, separators=(",", ":")) + "\n"
        try:
            assert self._events is not None
            self._events.write(line)
            self._events.flush()  # events are rare and precious: on disk before the next one
        except OSError as exc:
            self._stop(f"event log write failed: {exc}")
            return
        self._account(len(line.encode()))

    def _roll_tlog(self) -> None:
        if self._tlog is not None:
            self._tlog.close()
            self._rotatable.append(self.folder / f"mavlink-{self._tlog_index:03d}.tlog")
            self._tlog_index += 1
        self._tlog = open_private(self.folder / f"mavlink-{self._tlog_index:03d}.tlog", "ab")
        self._tlog_bytes = 0

    def _next_video_segment(self) -> None:
        """Open video-NNN.mp4; the full segment before it is finished on a thread and becomes rotatable."""
        old = self._video
        if old is not None:
            self._rotatable.append(old.path)
            self._video_index += 1
            threading.Thread(
                target=self._finish_video_segment, args=(old,), name="flight-record-video-close", daemon=True
            ).start()
        self._video = None
        self._video_rotate = False
        path = private_file(self.folder / f"video-{self._video_index:03d}.mp4")  # FFmpeg keeps its mode
        # An encoder process, not a thread: the encoder must never hold the control loop's GIL.
        self._video = H264Writer(
            path,
            self._video_fps,
            queue_frames=_VIDEO_QUEUE_FRAMES,
            preset="ultrafast",
            on_frame_written=self._video_progress,
            process=True,
        )
        self._video_accounted[path] = 0
        self._video_writers.append(self._video)

    def _video_progress(self, writer: H264Writer) -> None:
        """Encoder thread, after each frame: one stat of the segment; once it has grown by
        _VIDEO_ACCOUNT_BYTES (or is full) count the growth and ask for the next segment when full."""
        size = writer.size_bytes
        if (
            size - self._video_accounted.get(writer.path, 0) < _VIDEO_ACCOUNT_BYTES
            and size < self.segment_bytes
        ):
            return
        with self._lock:
            if not self._active:
                return
            size = self._count_video_bytes(writer)
            if writer is self._video and size >= self.segment_bytes:
                self._video_rotate = True

    def _finish_video_segment(self, writer: H264Writer) -> None:
        writer.close()
        with self._lock:
            if self._active:
                self._count_video_bytes(writer)

    def _count_video_bytes(self, writer: H264Writer) -> int:
        size = writer.size_bytes
        if writer.path in self._video_accounted:
            grown = size - self._video_accounted[writer.path]
            self._video_accounted[writer.path] = size
            if grown > 0:
                self._account(grown)
        return size

    def _account(self, written: int) -> None:
        self._used += written
        self._since_free_check += written
        if self._since_free_check >= _FREE_CHECK_EVERY_BYTES:
            self._since_free_check = 0
            try:
                self._check_free_space()
            except OSError as exc:
                self._stop(str(exc))
                return
        if self._used > self.max_bytes:
            self._enforce_cap()

    def _check_free_space(self) -> None:
        free = shutil.disk_usage(self.root).free
        if free < self.min_free_bytes:
            raise OSError(f"only {free} bytes free on {self.root} (need {self.min_free_bytes})")

    def _measure_others(self) -> None:
        """Thread: the size of everything under root but this mission (walked once, off the main loop)."""
        others: dict[Path, int] = {}
        total = 0
        try:
            entries = list(os.scandir(self.root))
        except OSError:
            entries = []
        for entry in entries:
            path = Path(entry.path)
            if path == self.folder:
                continue
            try:
                size = (
                    _tree_size(path)
                    if entry.is_dir(follow_symlinks=False)
                    else entry.stat(follow_symlinks=False).st_size
                )
            except OSError:
                continue
            total += size
            if entry.is_dir(follow_symlinks=False) and (path / EVENTS_FILE).exists():
                others[path] = size
        self._others = others
        self._others_total = total
        self._others_measured.set()  # before taking the lock: _enforce_cap may be waiting for it, lock held
        with self._lock:
            self._count_others()
            if self._active and self._used > self.max_bytes:
                self._enforce_cap()

    def _count_others(self) -> None:
        if not self._others_counted:
            self._used += self._others_total
            self._others_counted = True

    def _enforce_cap(self) -> None:
        # Which older missions may go, and their sizes, come from the measuring thread. Only when over the
        # cap before it has finished (a tiny cap, a huge card) is it waited for, briefly: the loop must not
        # stall. Until then this mission's own oldest files go; the thread enforces the cap when it is done.
        measured = self._others_measured.wait(_MEASURE_WAIT_S)
        if measured:
            self._count_others()
        for victim in self._older_missions() if measured else []:
            if self._used <= self.max_bytes:
                return
            size = self._others.pop(victim, 0)
            shutil.rmtree(victim, ignore_errors=True)
            self._used -= size
            log.info(
                "flight record: removed old mission %s (%d bytes) to stay under the cap", victim.name, size
            )
        while self._used > self.max_bytes and self._rotatable:
            victim_file = self._rotatable.popleft()
            try:
                size = victim_file.stat().st_size
                victim_file.unlink()
            except OSError:
                continue
            self._used -= size
        if self._used > self.max_bytes and measured:
            self._stop(f"size cap of {self.max_bytes} bytes reached with nothing left to rotate")

    def _older_missions(self) -> list[Path]:
        """Other mission folders (ours: they hold an event log), oldest first by their UTC-stamped names."""
        return sorted(self._others, key=lambda p: p.name)

    def _stop(self, reason: str) -> None:
        if self._active:
            log.warning("flight record stopped, the mission continues without recording: %s", reason)
        self._active = False
        self._close_files()

    def _close_files(self) -> None:
        # Closing flushes, which a full disk may refuse too.
        if self._events is not None:
            with contextlib.suppress(OSError):
                self._events.close()
        if self._tlog is not None:
            with contextlib.suppress(OSError):
                self._tlog.close()
        if self._video is not None:
            # Never joined here: _stop may run on the writer's report thread, or with the lock it needs held.
            video = self._video
            threading.Thread(target=video.close, name="flight-record-video-close", daemon=True).start()
        self._events = None
        self._tlog = None
        self._video = None


def _draw_record_overlay(image: np.ndarray, box: Box | None, label: str) -> np.ndarray:
    """The record video's overlay, drawn in the encoder process on its own copy of the frame."""
    import cv2

    if box is not None and box.is_valid():
        x1, y1, x2, y2 = (int(round(v)) for v in box.xyxy())
        cv2.rectangle(image, (x1, y1), (x2, y2), (0, 255, 0), 2)
    cv2.putText(image, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 255, 255), 2)
    return image


class NoRecord:
    """The record when recording is disabled: every call does nothing."""

    active = False

    def event(self, kind: str, **fields: Any) -> None:
        pass

    def mavlink(self, raw: bytes, time_s: float | None = None) -> None:
        pass

    def keyframe(self, jpeg: bytes, frame_id: int) -> str | None:
        return None

    def video_frame(self, image: np.ndarray, box: Box | None, state: str) -> None:
        pass

    def close(self) -> None:
        pass


def records_dir(configured: str, environ: Mapping[str, str] | None = None) -> Path:
    """Where mission folders go: `[recording] dir` when set; else, under systemd, `records/` in the unit's
    state directory (`$STATE_DIRECTORY`, set by `StateDirectory=`; the first one when it lists several);
    else `$XDG_DATA_HOME/cloudtrack/records` (default `~/.local/share/cloudtrack/records`)."""
    env = os.environ if environ is None else environ
    if configured:
        return Path(configured).expanduser()
    state = env.get("STATE_DIRECTORY", "").split(":")[0]
    if state:
        return Path(state) / "records"
    data = env.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data) / "cloudtrack" / "records"


def open_record(
    enabled: bool,
    directory: str,
    max_bytes: int,
    video: bool,
    vehicle_id: str,
    mission_id: str,
    video_fps: float = 10.0,
) -> FlightRecorder | NoRecord:
    """The record for a mission from the `[recording]` configuration values (`video_fps`: the camera's
    rate, since every frame is written: the video then plays in real time)."""
    if not enabled:
        return NoRecord()
    return FlightRecorder(
        Path(directory), vehicle_id, mission_id, max_bytes, video=video, video_fps=video_fps
    )


def read_events(folder: Path) -> list[dict[str, Any]]:
    """The event log of a mission folder; a line cut short by a power loss is skipped, not fatal."""
    events: list[dict[str, Any]] = []
    with open(folder / EVENTS_FILE, encoding="utf-8") as f:
        for line in f:
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(entry, dict):
                events.append(entry)
    return events


class FlightRecordObserver:
    """The main loop's `LoopObserver` that writes the flight record: one record per mission.

    A record opens when a mission starts (a new `StartMission` in the behaviour state) and closes when
    the next one starts or at `close()`. It begins with a `replay_start` entry (the mission config and
    the full behaviour state just before the starting event, both in `behaviors.event_codec` form);
    then every `step` (event, the actions it produced, the resulting mode) follows, which is all
    `cloudtrack-companion replay` needs. Readable entries ride along: `state` changes, `backend_answer`,
    `supervisor_decision`, `safety` (holds, releases, watchdogs) and `health` changes.
    """

    def __init__(self, config: MissionConfig, open_mission: Callable[[str], MissionRecord]) -> None:
        self._config = config
        self._open_mission = open_mission
        self._record: MissionRecord | None = None
        self._mission: StartMission | None = None
        self._before: State = initial_state(config)
        self._healthy: bool | None = None
        self._lock = threading.Lock()  # the loop writes steps; link and worker threads write tlog/keyframes

    # --- LoopObserver --------------------------------------------------------------------------

    def on_event(self, event: Event) -> None:
        pass  # everything is written in on_step, with what the event led to

    def on_step(self, event: Event, state: State, actions: tuple[Action, ...]) -> None:
        with self._lock:
            if state.mission is not None and state.mission is not self._mission:
                self._start(state.mission)
            record = self._record
            if record is not None:
                self._write_step(record, event, state, actions)
            self._before = state

    def on_health(self, time_s: float, healthy: bool, reasons: tuple[str, ...]) -> None:
        with self._lock:
            if healthy is not self._healthy and self._record is not None:
                self._record.event("health", time_s=time_s, healthy=healthy, reasons=list(reasons))
            self._healthy = healthy

    # --- other sources -------------------------------------------------------------------------

    def mavlink(self, raw: bytes, time_s: float | None = None) -> None:
        record = self._record
        if record is not None:
            record.mavlink(raw, time_s)

    def keyframe(self, jpeg: bytes, frame_id: int) -> str | None:
        record = self._record
        return record.keyframe(jpeg, frame_id) if record is not None else None

    def video_frame(self, image: np.ndarray, box: Box | None, state: str) -> None:
        record = self._record
        if record is not None:
            record.video_frame(image, box, state)

    def close(self) -> None:
        with self._lock:
            if self._record is not None:
                self._record.close()
                self._record = None

    # --- internals -----------------------------------------------------------------------------

    def _start(self, mission: StartMission) -> None:
        if self._record is not None:
            self._record.close()
        self._mission = mission
        self._record = self._open_mission(mission.mission_id or "mission")
        self._record.event(
            "replay_start",
            prompt=mission.prompt,
            config=event_codec.encode(self._config),
            state=event_codec.encode(self._before),
        )

    def _write_step(
        self, record: MissionRecord, event: Event, state: State, actions: tuple[Action, ...]
    ) -> None:
        record.event(
            "step",
            event=event_codec.encode_event(event),
            actions=[event_codec.encode_action(a) for a in actions],
            mode=state.mode.value,
        )
        if state.mode is not self._before.mode:
            record.event(
                "state",
                time_s=state.now_s,
                old=self._before.mode.value,
                new=state.mode.value,
                reason=state.reason,
            )
        if isinstance(event, BackendAnswer):
            record.event(
                "backend_answer",
                time_s=event.time_s,
                query_id=event.query_id,
                keyframe_id=event.keyframe_id,
                candidates=[
                    {"id": c.candidate_id, "verdict": c.verdict.value, "justification": c.justification}
                    for c in event.candidates
                ],
            )
        elif isinstance(event, GcsCommand) and isinstance(event.command, (ConfirmCandidate, RejectCandidate)):
            record.event(
                "supervisor_decision",
                time_s=event.time_s,
                decision="confirm" if isinstance(event.command, ConfirmCandidate) else "reject",
                candidate_id=event.command.candidate_id,
            )
        elif isinstance(event, (AutopilotLinkLost, BackendUnreachable, PilotTakeover)):
            record.event("safety", time_s=event.time_s, what=type(event).__name__)
        for action in actions:
            if isinstance(action, (Hold, ReleaseControl)):
                record.event("safety", time_s=state.now_s, what=type(action).__name__, reason=action.reason)


def attach_tlog(connection: Any, sink: FlightRecordObserver | MissionRecord) -> None:
    """Copy every MAVLink message a pymavlink connection receives or sends into the record's tlog."""

    def received(_conn: Any, msg: Any) -> None:
        if msg.get_type() != "BAD_DATA":
            sink.mavlink(msg.get_msgbuf(), getattr(msg, "_timestamp", None))

    def sent(msg: Any) -> None:
        sink.mavlink(msg.get_msgbuf())

    connection.message_hooks.append(received)
    connection.mav.set_send_callback(sent)
