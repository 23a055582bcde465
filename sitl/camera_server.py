"""The simulated camera as a process part: follow the vehicle over MAVLink, render, serve frames over TCP.

`PoseFollower` connects to the autopilot like any ground station (so it works with the mock autopilot or
an external ArduPilot/PX4 SITL given by `--autopilot-url`), asks for ATTITUDE and LOCAL_POSITION_NED
streams with SET_MESSAGE_INTERVAL (ArduPilot sends nothing unasked) and keeps the latest pose.

`CameraServer` renders at the camera rate from that pose and serves the frames on `sim+tcp://HOST:PORT`
(protocol in `sitl.frame_transport`); every frame's ground truth stays in a ring, by frame id, for the
simulated detector and the metrics.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from pymavlink import mavutil

from behaviors.camera_model import CameraModel
from cloudtrack.mavlink_connection import use_mavlink2
from sitl.camera_render import FrameTruth, RenderedFrame, Renderer, VehiclePose
from sitl.frame_transport import encode_frame
from sitl.world import World

log = logging.getLogger(__name__)

MSG_ATTITUDE = 30
NO_THUMBNAIL = np.zeros((0, 0), np.uint8)
MSG_LOCAL_POSITION_NED = 32


class PoseFollower:
    """The vehicle pose from the autopilot's telemetry, read on a background thread."""

    def __init__(
        self,
        url: str,
        rate_hz: float = 30.0,
        source_system: int = 254,
        source_component: int = 100,
        initial: VehiclePose | None = None,
        origin: tuple[float, float] = (0.0, 0.0),
        on_text: Callable[[str], None] | None = None,
    ) -> None:
        self.url = url
        self.on_text = on_text  # every STATUSTEXT heard on the link (the companion's are broadcast)
        self.rate_hz = rate_hz
        self.origin = origin  # where this vehicle's home (LOCAL_POSITION_NED origin) lies in the world
        self._pose = initial or VehiclePose(0.0, 0.0, -10.0)
        self._pose_time = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conn = use_mavlink2(
            mavutil.mavlink_connection(url, source_system=source_system, source_component=source_component)
        )
        self._thread = threading.Thread(target=self._run, name="pose-follower", daemon=True)

    def start(self) -> PoseFollower:
        self._thread.start()
        return self

    def pose(self) -> VehiclePose:
        with self._lock:
            return self._pose

    def age_s(self) -> float:
        """Seconds since the last position/attitude message (inf before the first)."""
        with self._lock:
            return time.monotonic() - self._pose_time if self._pose_time else float("inf")

    def _request_streams(self) -> None:
        interval_us = int(1e6 / self.rate_hz)
        for msg_id in (MSG_ATTITUDE, MSG_LOCAL_POSITION_NED):
            self._conn.mav.command_long_send(
                self._conn.target_system or 1,
                self._conn.target_component or 1,
                mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                msg_id,
                interval_us,
                0,
                0,
                0,
                0,
                0,
            )

    def _run(self) -> None:
        last_hb = 0.0
        last_request = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_hb >= 1.0:
                self._conn.mav.heartbeat_send(
                    mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                )
                last_hb = now
            # Ask again while the pose is stale: the autopilot may have started after us or lost the request.
            if now - last_request >= 2.0 and self.age_s() > 1.0:
                self._request_streams()
                last_request = now
            try:
                msg = self._conn.recv_match(
                    type=["ATTITUDE", "LOCAL_POSITION_NED", "HEARTBEAT", "STATUSTEXT"],
                    blocking=True,
                    timeout=0.2,
                )
            except (OSError, ValueError) as exc:  # garbage or a closed socket: keep the last pose
                log.debug("pose follower: %s", exc)
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "STATUSTEXT":
                if self.on_text is not None:
                    self.on_text(str(msg.text))
                continue
            if kind == "HEARTBEAT" and not self._conn.target_system:
                self._conn.target_system = msg.get_srcSystem()
            with self._lock:
                p = self._pose
                if kind == "ATTITUDE":
                    self._pose = VehiclePose(p.north, p.east, p.down, msg.roll, msg.pitch, msg.yaw)
                    self._pose_time = time.monotonic()
                elif kind == "LOCAL_POSITION_NED":
                    self._pose = VehiclePose(
                        msg.x + self.origin[0], msg.y + self.origin[1], msg.z, p.roll, p.pitch, p.yaw
                    )
                    self._pose_time = time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._conn.close()


FrameHook = Callable[[RenderedFrame], None]


class CameraServer:
    """Renders the world from a pose source at `fps` and streams frames to every connected client."""

    def __init__(
        self,
        world: World,
        camera: CameraModel,
        pose_source: Callable[[], VehiclePose],
        fps: float = 30.0,
        host: str = "127.0.0.1",
        port: int = 0,
        clock: Callable[[], float] = time.monotonic,
        truth_frames: int = 300,
        frame_id_base: int = 0,
        past_frames: int = 3600,
    ) -> None:
        self.renderer = Renderer(world, camera)
        self.camera = camera
        self.pose_source = pose_source
        self.fps = fps
        self._clock = clock
        self.epoch = clock()  # world time zero (people start walking); the scenario moves it to mission start
        self.frame_id_base = frame_id_base  # several cameras in one world number their frames apart
        self._truth: OrderedDict[int, FrameTruth] = OrderedDict()
        self._truth_frames = truth_frames
        # Older frames' truth without the thumbnail (only a region of a recent keyframe needs placing): a
        # keyframe stored through a back-end outage is detected long after it was rendered.
        self._past: OrderedDict[int, FrameTruth] = OrderedDict()
        self._past_frames = past_frames
        self._latest: tuple[int, bytes] | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._hooks: list[FrameHook] = []
        self.frames_rendered = 0
        self.paused_until = 0.0  # world seconds; frames stop (camera outage) while now < paused_until
        self._listener = socket.create_server((host, port))
        self._listener.settimeout(0.2)
        self.address = self._listener.getsockname()[:2]
        self._threads = [
            threading.Thread(target=self._render_loop, name="camera-render", daemon=True),
            threading.Thread(target=self._accept_loop, name="camera-accept", daemon=True),
        ]

    @property
    def url(self) -> str:
        return f"sim+tcp://{self.address[0]}:{self.address[1]}"

    def world_time(self) -> float:
        """Seconds since world time zero; 0 (people at their start) while `epoch` is inf (not started)."""
        return max(0.0, self._clock() - self.epoch)

    def add_hook(self, hook: FrameHook) -> None:
        """Called on the render thread with every frame (video writer, metrics); keep it quick."""
        self._hooks.append(hook)

    def start(self) -> CameraServer:
        for t in self._threads:
            t.start()
        return self

    def truth(self, frame_id: int) -> FrameTruth | None:
        """Ground truth of a recent frame (the last `truth_frames`, then without the thumbnail the
        `past_frames` before them), None when unknown or too old."""
        with self._cond:
            return self._truth.get(frame_id) or self._past.get(frame_id)

    def _render_loop(self) -> None:
        period = 1.0 / self.fps
        frame_id = self.frame_id_base
        next_t = self._clock()
        while not self._stop.is_set():
            frame_id += 1
            t = self.world_time()
            frame = self.renderer.render(self.pose_source(), t, frame_id)
            packet = encode_frame(frame_id, t, time.time(), frame.image)
            record = frame.record()
            with self._cond:
                self._truth[frame_id] = record
                while len(self._truth) > self._truth_frames:
                    old_id, old = self._truth.popitem(last=False)
                    self._past[old_id] = replace(old, thumbnail=NO_THUMBNAIL)
                while len(self._past) > self._past_frames:
                    self._past.popitem(last=False)
                self._latest = (frame_id, packet)
                self._cond.notify_all()
            self.frames_rendered += 1
            for hook in self._hooks:
                try:
                    hook(frame)
                except Exception:  # a broken observer must not stop the camera
                    log.exception("frame hook failed")
            next_t += period
            delay = next_t - self._clock()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = self._clock()  # behind: drop the backlog rather than burst

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(
                target=self._serve_client, args=(conn,), name="camera-client", daemon=True
            ).start()

    def _serve_client(self, conn: socket.socket) -> None:
        sent = 0
        with conn:
            while not self._stop.is_set():
                with self._cond:
                    if self._latest is None or self._latest[0] <= sent:
                        self._cond.wait(0.5)
                    latest = self._latest
                if latest is None or latest[0] <= sent or self._stop.is_set():
                    continue
                if self.world_time() < self.paused_until:
                    sent = latest[0]
                    continue
                try:
                    conn.sendall(latest[1])
                except OSError:
                    return
                sent = latest[0]

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._listener.close()
        for t in self._threads:
            t.join(timeout=2)
