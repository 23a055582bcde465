"""The onboard loop benchmark: how much of the bare tracker's rate the whole loop keeps.

One loop iteration is what the companion does per camera frame: take the frame from the source, run the
tracking front-end (tracker + every loss signal + ring buffer), the follow control law with the safety
limits, encode SET_POSITION_TARGET_LOCAL_NED and send it over MAVLink to a receiver on loopback UDP. The
bare pass runs only the OpenCV tracker's `update()` on the same frames. Passes alternate (bare, loop,
bare, loop ...) so machine load affects both alike; rates are medians over the passes.

With `recording`, every loop iteration also writes the flight record as a mission does with
`[recording] video = true`: one event-log line and the frame handed to the H.264 video encoder (which
runs in a process of its own and drops a frame rather than make the loop wait; drops are counted). The video
takes frames at `[camera] fps`, as in flight: the bench's loop runs faster than a camera delivers, and
the frames in between are skipped (counted too), not encoded. One record spans the whole bench, as one
spans a mission: its encoder process starts with it, and the first pass waits until that process is up,
so the passes time the recording itself, not the encoder's one-off start-up.

Frames are decoded and resized once before timing: a camera driver delivers decoded frames, and JPEG
decoding of the recorded sequence is not part of the onboard loop (its cost is reported separately).
"""

from __future__ import annotations

import resource
import socket
import statistics
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from behaviors.control_law import ControlGains, ControlState, FollowGoal, follow_step
from behaviors.safety_limits import MotionLimits
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from cloudtrack.autopilot_modes import AutopilotKind
from cloudtrack.mavlink_connection import MavlinkEndpoint
from companion.config import CompanionConfig
from companion.flight_record import FlightRecorder
from companion.mavlink.offboard import SetpointMessage, encode_velocity
from companion.vision.camera_calibration import camera_model
from companion.vision.frame_sources import FolderSource, Frame, SourceStats
from companion.vision.trackers import create_tracker
from companion.vision.tracking_frontend import TrackingFrontend
from companion_tools.tracking_eval import load_sequence


@dataclass(frozen=True)
class BenchResult:
    tracker: str
    sequence: str
    size: tuple[int, int]
    frames: int
    passes: int
    bare_fps: float  # median over passes of frames / time in update()
    loop_fps: float  # median over passes of frames / time of the whole loop
    overhead_ms: float  # median over passes of loop time outside the tracker's update(), per frame
    update_ms: float  # median over passes of the time inside update() within the loop, per frame
    latency_p50_ms: float  # per-frame loop latency, all loop passes pooled
    latency_p95_ms: float
    decode_ms: float  # mean JPEG decode + resize per frame (not in the loop: the camera delivers pixels)
    peak_rss_mib: float
    setpoints_sent: int
    setpoints_received: int
    trusted_frames: int
    recording: bool = False
    video_frames_encoded: int = 0  # with recording: frames in the videos, all loop passes
    video_frames_dropped: int = 0  # with recording: frames the encoder's full queue turned away
    video_frames_skipped: int = 0  # with recording: frames above [camera] fps, not encoded (loop > camera)
    recording_ms: float = 0.0  # with recording: median over passes of the loop's time in the record's calls
    encode_cpu_ms: float = 0.0  # with recording: encoder-thread CPU per encoded frame

    @property
    def ratio(self) -> float:
        return self.loop_fps / self.bare_fps if self.bare_fps > 0 else float("nan")

    @property
    def ratio_from_overhead(self) -> float:
        """update / (update + overhead) measured inside the same loop passes: the same ratio, far less
        sensitive to load that changes between the bare and the loop passes."""
        total = self.update_ms + self.overhead_ms
        return self.update_ms / total if total > 0 else float("nan")


class MemoryFrames:
    """A FrameSource over decoded frames in memory, with fresh capture times: the camera's side of the loop."""

    live = True

    def __init__(self, images: Sequence[np.ndarray]) -> None:
        self._images = images
        self._next = 0
        self._id = 0
        self.stats = SourceStats(connected=True)

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        if self._next >= len(self._images):
            return None
        image = self._images[self._next]
        self._next += 1
        self._id += 1
        self.stats.frames += 1
        return Frame(self._id, time.monotonic(), image)

    def close(self) -> None:
        self._next = len(self._images)


class _Receiver:
    """A loopback UDP socket standing in for the autopilot's MAVLink port: counts datagrams, keeps the first."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.count = 0
        self.first: bytes | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-mavlink-rx", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except OSError:
                continue
            self.count += 1
            if self.first is None:
                self.first = data

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


def load_frames(
    sequence: Path, size: tuple[int, int] | None, max_frames: int | None
) -> tuple[list[np.ndarray], float]:
    """Decoded (and resized) frames, and the mean decode+resize time per frame in ms."""
    source = FolderSource(sequence, stop_after=max_frames)
    images: list[np.ndarray] = []
    started = time.perf_counter()
    while (frame := source.read()) is not None:
        image = frame.image if size is None else cv2.resize(frame.image, size, interpolation=cv2.INTER_AREA)
        images.append(image)
    return images, (time.perf_counter() - started) * 1000.0 / max(1, len(images))


def run_bench(
    sequence: Path,
    model_dir: Path,
    config: CompanionConfig,
    tracker_name: str = "nano",
    size: tuple[int, int] | None = (640, 480),
    passes: int = 3,
    max_frames: int | None = None,
    recording: bool = False,
) -> BenchResult:
    seq = load_sequence(sequence)
    images, decode_ms = load_frames(sequence, size, max_frames)
    if len(images) < 2:
        raise ValueError(f"{sequence}: need at least two frames")
    h, w = images[0].shape[:2]
    first = seq.ground_truth[0]
    if first is None:
        raise ValueError(f"{sequence}: the first frame has no ground-truth box to start on")
    native = FolderSource(sequence).read()
    assert native is not None
    box = first.scaled(w / native.image.shape[1], h / native.image.shape[0]) if size is not None else first

    cam = config.camera
    camera = camera_model(cam.model_copy(update={"width": w, "height": h}))
    safety = config.safety
    limits = MotionLimits.from_degrees(
        safety.max_speed_m_s, safety.max_vertical_speed_m_s, safety.max_yaw_rate_deg_s,
        safety.min_altitude_m, safety.max_altitude_m,
    )  # fmt: skip
    gains = ControlGains()
    goal = FollowGoal(standoff_m=config.behavior.standoff_m)

    receiver = _Receiver()
    endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{receiver.port}", 255, config.mavlink.source_component)
    boot = time.monotonic()
    sent = 0
    bare_rates: list[float] = []
    loop_rates: list[float] = []
    latencies: list[float] = []
    overheads: list[float] = []
    updates: list[float] = []
    trusted = 0
    encoded = dropped = skipped = 0
    recording_times: list[float] = []
    encode_cpu_s = 0.0
    record_root = tempfile.TemporaryDirectory(prefix="cloudtrack-bench-records-") if recording else None
    record: FlightRecorder | None = None
    try:
        if record_root is not None:
            record = FlightRecorder(
                Path(record_root.name), "bench", "bench", 10**12, video=True, video_fps=cam.fps
            )
            if not record.wait_video_ready(60.0):
                raise RuntimeError("the flight record's video encoder did not start within 60 s")
        for _ in range(passes):
            # Bare: the OpenCV tracker alone on the same frames.
            tracker = create_tracker(tracker_name, model_dir)
            tracker.init(images[0], box)
            started = time.perf_counter()
            for image in images[1:]:
                tracker.update(image)
            bare_rates.append((len(images) - 1) / (time.perf_counter() - started))

            # The whole loop.
            frontend = TrackingFrontend.from_config(config.tracker, model_dir, tracker_name)
            source = MemoryFrames(images)
            frame = source.read()
            assert frame is not None
            frontend.feed(frame)
            frontend.start(frame.frame_id, box)
            state = ControlState()
            in_record = 0.0
            started = time.perf_counter()
            while (frame := source.read()) is not None:
                t0 = time.perf_counter()
                result = frontend.feed(frame)
                if record is not None:
                    r0 = time.perf_counter()
                    record.event("step", frame_id=frame.frame_id, trusted=result.trusted)
                    record.video_frame(frame.image, result.box, "FOLLOWING")
                    in_record += time.perf_counter() - r0
                if result.trusted and result.box is not None:
                    trusted += 1
                    telemetry = Telemetry(
                        time_s=frame.capture_time, height_agl=20.0, armed=True, offboard_active=True
                    )
                    setpoint, state = follow_step(
                        result.box, camera, telemetry, goal, gains, limits, state, frame.capture_time
                    )
                else:
                    setpoint, state = Setpoint.zero(), ControlState()
                if endpoint.send(
                    partial(_send_setpoint, encode_velocity(AutopilotKind.ARDUPILOT, setpoint), boot)
                ):
                    sent += 1
                latencies.append(time.perf_counter() - t0)
            loop_seconds = time.perf_counter() - started
            if record is not None:
                recording_times.append(in_record * 1000.0 / (len(images) - 1))
            loop_rates.append((len(images) - 1) / loop_seconds)
            inside = frontend.stats.tracker_seconds + frontend.stats.catch_up_seconds
            overheads.append((loop_seconds - inside) * 1000.0 / (len(images) - 1))
            updates.append(inside * 1000.0 / (len(images) - 1))
        if record is not None:
            record.close()  # after the timing: waits for the encoder to finish the queued frames
            (encoded, dropped), skipped = record.video_frames, record.video_frames_skipped
            encode_cpu_s = record.video_encode_cpu_s
        deadline = time.monotonic() + 2.0
        while receiver.count < sent and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        endpoint.close()
        receiver.close()
        if record is not None:
            record.close()
        if record_root is not None:
            record_root.cleanup()
    _check_first_message(receiver.first)
    lat_ms = np.asarray(latencies) * 1000.0
    return BenchResult(
        tracker=tracker_name,
        sequence=seq.name,
        size=(w, h),
        frames=len(images) - 1,
        passes=passes,
        bare_fps=statistics.median(bare_rates),
        loop_fps=statistics.median(loop_rates),
        overhead_ms=statistics.median(overheads),
        update_ms=statistics.median(updates),
        latency_p50_ms=float(np.percentile(lat_ms, 50)),
        latency_p95_ms=float(np.percentile(lat_ms, 95)),
        decode_ms=decode_ms,
        peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        setpoints_sent=sent,
        setpoints_received=receiver.count,
        trusted_frames=trusted,
        recording=recording,
        video_frames_encoded=encoded,
        video_frames_dropped=dropped,
        video_frames_skipped=skipped,
        recording_ms=statistics.median(recording_times) if recording_times else 0.0,
        encode_cpu_ms=encode_cpu_s * 1000.0 / encoded if encoded else 0.0,
    )


def _send_setpoint(fields: SetpointMessage, boot: float, mav: Any) -> None:
    boot_ms = int((time.monotonic() - boot) * 1000)
    mav.set_position_target_local_ned_send(
        boot_ms, 1, 1, fields.frame, fields.type_mask, 0, 0, 0,
        fields.vx, fields.vy, fields.vz, 0, 0, 0, 0, fields.yaw_rate,
    )  # fmt: skip


def _check_first_message(data: bytes | None) -> None:
    """The receiver really got SET_POSITION_TARGET_LOCAL_NED (decoded by pymavlink)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    if data is None:
        raise RuntimeError("no MAVLink message reached the loopback receiver")
    parser = mavlink.MAVLink(None)
    message = parser.parse_char(data)
    if message is None or message.get_type() != "SET_POSITION_TARGET_LOCAL_NED":
        raise RuntimeError(f"loopback receiver got {message!r}, not SET_POSITION_TARGET_LOCAL_NED")
