"""The one object the companion's main loop uses to talk to the autopilot and the GCS over MAVLink.

Threads (all owned here, started by `start()`):
- reader: decodes telemetry, follows the autopilot's mode, turns GCS messages into mission commands;
- streamer: sends the latest setpoint at `setpoint_rate_hz`, after `apply_limits`, only while the
  autopilot is in GUIDED (ArduPilot) / OFFBOARD (PX4) or, on PX4, while building the stream OFFBOARD needs;
- watchdog (`SafetyWatchdog`): stale frames, lost target, unreachable back-end, lost autopilot heartbeat,
  stalled main loop. Each ends motion with an explicit zero-velocity setpoint, then the configured hold.

Mode policy: the companion never arms, takes off or lands on its own. It asks for GUIDED/OFFBOARD only
after `request_offboard()` (the operator allowed it at mission start); after `enable_offboard()` it only
streams once the pilot or GCS selected that mode. When anyone else changes the mode away from
GUIDED/OFFBOARD, streaming stops at once and the event is reported; it resumes only when the main loop
enables offboard again.

The main loop proves it is alive with `kick()`; that also sends the companion's 1 Hz HEARTBEAT, so the
autopilot and the GCS stop hearing from the companion as soon as its loop stops.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import partial
from typing import Any

from behaviors.geometry import Box
from behaviors.mission_commands import MissionCommand
from behaviors.safety_limits import MotionLimits, apply_limits
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from companion.autopilot_modes import AutopilotKind, mode_for_action, offboard_mode, set_mode_params
from companion.config import MavlinkConfig, SafetyConfig
from companion.gcs_link import (
    CAMERA_CAP_FLAGS_HAS_TRACKING_POINT,
    CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
    GcsProtocol,
    statustext_chunks,
    value_name,
)
from companion.mavlink_connection import MavlinkEndpoint, mavlink
from companion.mavlink_signing import SigningGuard, parse_signing_key
from companion.mavsdk_offboard import MavsdkOffboard
from companion.offboard import PX4_MIN_PRESTREAM_S, encode_velocity
from companion.safety_watchdog import (
    BACKEND_UNREACHABLE,
    HEARTBEAT_LOST,
    LOOP_STALLED,
    STALE_FRAMES,
    TARGET_LOST,
    SafetyEvent,
    SafetyWatchdog,
)
from companion.telemetry import AutopilotHeartbeat, TelemetryDecoder, stream_intervals_us

log = logging.getLogger(__name__)

MODE_REQUEST_RETRY_S = 1.0
OWN_MODE_CHANGE_WINDOW_S = 5.0  # a mode we asked for that shows up this soon is our own change
STREAM_REQUEST_RETRY_S = 2.0
TRACKING_STATUS_PERIOD_S = 0.1


def _statustext(mav: Any, severity: int, text: bytes, text_id: int, seq: int) -> None:
    mav.statustext_send(severity, text, text_id, seq)


def _set_message_interval(mav: Any, target: int, msg_id: int, interval_us: float) -> None:
    mav.command_long_send(target, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0)


class VehicleLink:
    """Thread-safe facade over the MAVLink link; see the module docstring for the policy it enforces."""

    def __init__(
        self,
        mavlink_config: MavlinkConfig,
        safety: SafetyConfig,
        image_size: tuple[int, int] = (640, 480),
        on_safety_event: Callable[[SafetyEvent], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self._cfg = mavlink_config
        self._clock = clock
        self._limits = MotionLimits.from_degrees(
            safety.max_speed_m_s, safety.max_vertical_speed_m_s, safety.max_yaw_rate_deg_s,
            safety.min_altitude_m, safety.max_altitude_m,
        )  # fmt: skip
        self._signing_key = parse_signing_key(mavlink_config.signing_key) if mavlink_config.signing_key else None
        forced = None if mavlink_config.autopilot == "auto" else AutopilotKind(mavlink_config.autopilot)
        self._decoder = TelemetryDecoder(mavlink_config.target_system, forced)
        self._image_size = image_size
        self._on_safety_event = on_safety_event
        self._lock = threading.RLock()
        self._offboard_lock = threading.RLock()  # orders setpoints against stops (see _stream_once)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._endpoint: MavlinkEndpoint | None = None
        self._mavsdk: MavsdkOffboard | None = None  # PX4 offboard through MAVSDK (mavlink.use_mavsdk)
        self.signing = SigningGuard(on_refused=lambda text: self._record(SafetyEvent(self._clock(), "signing", "refused", text)))
        self._watchdog = SafetyWatchdog(safety, self._on_trip, self._on_clear, clock)
        self._camera_component = mavlink_config.camera_component
        self._gcs = GcsProtocol(
            mavlink_config.target_system, mavlink_config.source_component, self._camera_component,
            lambda: self._image_size, self,
        )  # fmt: skip

        self._setpoint = Setpoint.zero()
        self._descent_allowed = False
        self._held_reason = ""  # a hold the main loop asked for, until its next set_velocity
        self._enabled = False  # the mission wants offboard control
        self._engage = False  # and may select GUIDED/OFFBOARD itself
        self._mode = ""
        self._stream_since: float | None = None
        self._mode_request: tuple[str, float] | None = None
        self._streams_requested_at = -math.inf
        self._last_heartbeat_sent = -math.inf
        self._last_tracking_sent = -math.inf
        self._tracking_box: Box | None = None
        self._latest_status = "CloudTrack ready: no mission"
        self._text_id = 0
        self._commands: deque[MissionCommand] = deque(maxlen=100)
        self._events: deque[SafetyEvent] = deque(maxlen=1000)
        self.setpoints_sent = 0

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._endpoint = MavlinkEndpoint.open(self._cfg.connection, self._cfg.target_system, self._cfg.source_component)
        if self._signing_key is not None:
            self.signing.enable(self._endpoint.conn, self._signing_key)
        if self._camera_component:
            self._endpoint.add_identity(self._camera_component)
        if self._cfg.use_mavsdk:
            self._mavsdk = MavsdkOffboard(self._cfg.mavsdk_address)
            self._mavsdk.start()
        self._watchdog.seen(LOOP_STALLED)
        self._send_heartbeat(self._clock())  # opens udpout/tcp links so the autopilot learns where we are
        for target, name in ((self._reader, "mavlink-reader"), (self._streamer, "mavlink-streamer")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            self._threads.append(thread)
            thread.start()
        self._watchdog.start()

    def close(self) -> None:
        """Explicit stop and hold if we are flying the vehicle, then shut the threads and the link."""
        if self._endpoint is not None and self._enabled:
            self._stop_and_hold("companion link closing")
        self._stop.set()
        self._watchdog.close()
        for thread in self._threads:
            thread.join(timeout=2.0)
        if self._mavsdk is not None:
            self._mavsdk.close()
        if self._endpoint is not None:
            self._endpoint.close()

    def __enter__(self) -> VehicleLink:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def endpoint(self) -> MavlinkEndpoint:
        if self._endpoint is None:
            raise RuntimeError("VehicleLink.start() has not been called")
        return self._endpoint

    # --------------------------------------------------------------------------- main-loop interface
    @property
    def autopilot_kind(self) -> AutopilotKind | None:
        hb = self._decoder.heartbeat
        return hb.kind if hb else None

    def telemetry(self) -> Telemetry | None:
        return self._decoder.snapshot()

    def commands(self) -> list[MissionCommand]:
        """GCS commands received since the last call (already signature-checked when signing is on)."""
        with self._lock:
            drained = list(self._commands)
            self._commands.clear()
        return drained

    def safety_events(self) -> list[SafetyEvent]:
        """Watchdog and mode-policy events since the last call."""
        with self._lock:
            drained = list(self._events)
            self._events.clear()
        return drained

    def set_velocity(self, setpoint: Setpoint, descent_allowed: bool = False) -> None:
        """The latest body-frame command; streamed after `apply_limits`. Ends a hold the main loop asked for."""
        with self._lock:
            self._setpoint = setpoint
            self._descent_allowed = descent_allowed
            self._held_reason = ""

    def hold(self, reason: str) -> None:
        """Explicit zero-velocity stop now, then the configured hold, until the next `set_velocity`.

        Calling it again while holding changes nothing (the stop and the mode request go out once).
        """
        with self._lock:
            already = bool(self._held_reason)
            self._setpoint = Setpoint.zero()
            self._held_reason = reason or "hold"
        if not already:
            self._stop_and_hold(reason)

    def enable_offboard(self) -> None:
        """The mission may fly the vehicle once the pilot or GCS selects GUIDED/OFFBOARD."""
        with self._lock:
            self._enabled = True

    def request_offboard(self) -> None:
        """The operator allowed engagement: ask for GUIDED, or OFFBOARD after >= 1 s of setpoints (PX4)."""
        with self._lock:
            self._enabled = True
            self._engage = True

    def release_offboard(self, reason: str) -> None:
        """The mission no longer flies the vehicle: explicit stop, hold, stop streaming."""
        self.hold(reason)
        with self._lock:
            self._enabled = False
            self._engage = False

    def request_mode(self, action: str) -> None:
        """Ask for loiter / rtl / land / brake (the lost action). Requested, never forced; streaming ends."""
        kind = self.autopilot_kind
        if kind is None:
            log.warning("mode %s not requested: autopilot not detected yet", action)
            return
        with self._lock:
            self._enabled = False
            self._engage = False
        self._send_zero()
        self._request_mode(mode_for_action(kind, action))

    def kick(self) -> None:
        """Called by the main loop every iteration: feeds the stalled-loop watchdog, sends the 1 Hz HEARTBEAT."""
        now = self._clock()
        self._watchdog.seen(LOOP_STALLED, now)
        if now - self._last_heartbeat_sent >= 1.0:
            self._send_heartbeat(now)

    def report_frame(self, when: float | None = None) -> None:
        """A camera frame arrived (`when` on time.monotonic(); default now)."""
        self._watchdog.seen(STALE_FRAMES, when)

    def report_backend_ok(self, when: float | None = None) -> None:
        self._watchdog.seen(BACKEND_UNREACHABLE, when)

    def report_target(self, when: float | None = None) -> None:
        """The tracker trusts the target (arms the lost-target watchdog while following)."""
        self._watchdog.seen(TARGET_LOST, when)

    def clear_target(self) -> None:
        """No target is being followed any more (searching, holding for the supervisor, mission over)."""
        self._watchdog.disarm(TARGET_LOST)

    def send_status(self, text: str, severity: int = MAV_SEVERITY_INFO) -> None:
        """A line a person reads on the GCS (longer than 50 bytes goes out in linked chunks)."""
        with self._lock:
            self._latest_status = text
        self.status(text, severity)

    def send_value(self, name: str, value: float) -> None:
        """A number for the GCS (NAMED_VALUE_FLOAT; name at most 10 characters)."""
        encoded = value_name(name)
        boot_ms = self._boot_ms()
        self.endpoint.send(lambda m: m.named_value_float_send(boot_ms, encoded, float(value)))

    def report_tracking(self, box: Box | None, image_size: tuple[int, int]) -> None:
        """CAMERA_TRACKING_IMAGE_STATUS at up to 10 Hz while tracking; one IDLE status when it stops."""
        now = self._clock()
        with self._lock:
            self._image_size = image_size
            was_tracking = self._tracking_box is not None
            self._tracking_box = box
            if box is not None and now - self._last_tracking_sent < TRACKING_STATUS_PERIOD_S:
                return
            if box is None and not was_tracking:
                return
            self._last_tracking_sent = now
        w, h = image_size
        camera = self._camera_component or None
        if box is None:
            nan = math.nan
            self.endpoint.send(
                lambda m: m.camera_tracking_image_status_send(0, 0, 0, nan, nan, nan, nan, nan, nan, nan), camera
            )
            return
        status = mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
        self.endpoint.send(
            lambda m: m.camera_tracking_image_status_send(
                status, mavlink.CAMERA_TRACKING_MODE_RECTANGLE, mavlink.CAMERA_TRACKING_TARGET_DATA_IN_STATUS,
                box.cx / w, box.cy / h, math.nan, box.x / w, box.y / h, box.x2 / w, box.y2 / h,
            ),
            camera,
        )  # fmt: skip

    # ----------------------------------------------------------------- GcsReplies (for GcsProtocol)
    def deliver(self, command: MissionCommand) -> None:
        with self._lock:
            self._commands.append(command)

    def ack(self, msg: Any, result: int) -> None:
        self.endpoint.send(
            lambda m: m.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()),
            msg.target_component,
        )

    def status(self, text: str, severity: int = MAV_SEVERITY_INFO) -> None:
        chunks = statustext_chunks(text)
        text_id = 0
        if len(chunks) > 1:  # linked chunks share a non-zero id
            with self._lock:
                self._text_id = self._text_id % 65535 + 1
                text_id = self._text_id
        for piece, seq in chunks:
            self.endpoint.send(partial(_statustext, severity=severity, text=piece, text_id=text_id, seq=seq))

    def latest_status(self) -> None:
        with self._lock:
            text = self._latest_status
        self.status(text)

    def camera_information(self, image_size: tuple[int, int], component: int) -> None:
        flags = CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE | CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
        vendor = list(b"CloudTrack".ljust(32, b"\0"))
        model = list(b"companion tracker".ljust(32, b"\0"))
        boot_ms = self._boot_ms()
        self.endpoint.send(
            lambda m: m.camera_information_send(
                boot_ms, vendor, model, 0, math.nan, math.nan, math.nan, image_size[0], image_size[1], 0, flags, 0, b""
            ),
            component,
        )

    # --------------------------------------------------------------------------------- internals
    def _boot_ms(self) -> int:
        return int(self._clock() * 1000) & 0xFFFFFFFF

    def _record(self, event: SafetyEvent) -> None:
        with self._lock:
            self._events.append(event)
        if self._on_safety_event is not None:
            try:
                self._on_safety_event(event)
            except Exception:
                log.exception("safety event callback failed")

    def _send_heartbeat(self, now: float) -> None:
        self._last_heartbeat_sent = now
        if self._endpoint is None:
            return
        self._endpoint.send(
            lambda m: m.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )
        )
        if self._camera_component:  # the camera identity lives and dies with the loop too
            self._endpoint.send(
                lambda m: m.heartbeat_send(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE),
                self._camera_component,
            )

    def _send_setpoint(self, kind: AutopilotKind, setpoint: Setpoint) -> None:
        if self._mavsdk is not None and kind is AutopilotKind.PX4:
            self._mavsdk.set_velocity(setpoint)  # MAVSDK re-sends it at 20 Hz by itself
            self.setpoints_sent += 1
            return
        fields = encode_velocity(kind, setpoint)
        target, boot_ms = self._cfg.target_system, self._boot_ms()
        sent = self.endpoint.send(
            lambda m: m.set_position_target_local_ned_send(
                boot_ms, target, 1, fields.frame, fields.type_mask, 0, 0, 0,
                fields.vx, fields.vy, fields.vz, 0, 0, 0, 0, fields.yaw_rate,
            )
        )  # fmt: skip
        if sent:
            self.setpoints_sent += 1

    def _send_zero(self) -> None:
        kind = self.autopilot_kind
        if kind is not None and self._endpoint is not None:
            self._send_setpoint(kind, Setpoint.zero())

    def _request_mode(self, name: str) -> None:
        kind = self.autopilot_kind
        if kind is None:
            return
        params = set_mode_params(kind, name)
        with self._lock:
            self._mode_request = (name, self._clock())
        log.info("requesting mode %s", name)
        if self._mavsdk is not None and kind is AutopilotKind.PX4 and name == "OFFBOARD":
            self._mavsdk.start_offboard()
            return
        target = self._cfg.target_system
        self.endpoint.send(
            lambda m: m.command_long_send(
                target, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                params.base_mode, params.custom_mode, params.custom_sub_mode, 0, 0, 0, 0,
            )
        )  # fmt: skip

    def _stop_and_hold(self, reason: str) -> None:
        """The explicit stop: zero velocity now, then ArduPilot's configured hold or PX4 HOLD."""
        with self._offboard_lock:
            self._stop_and_hold_locked(reason)

    def _stop_and_hold_locked(self, reason: str) -> None:
        kind = self.autopilot_kind
        if kind is None:
            return
        with self._lock:
            flying_ours = self._mode == offboard_mode(kind) and self._enabled
        if not flying_ours:
            return  # the pilot or another mode has the vehicle; we were not commanding it
        if self._mavsdk is not None and kind is AutopilotKind.PX4:
            with self._lock:
                self._mode_request = ("HOLD", self._clock())
            self._mavsdk.stop(reason)  # zero, then offboard stop (HOLD): MAVSDK would keep re-sending otherwise
            log.warning("stop and hold: %s", reason)
            return
        self._send_zero()
        if kind is AutopilotKind.PX4:
            self._request_mode("HOLD")
        elif self._cfg.ardupilot_hold != "guided_zero":
            self._request_mode(mode_for_action(kind, self._cfg.ardupilot_hold))
        log.warning("stop and hold: %s", reason)

    def _on_trip(self, reason: str, now: float) -> None:
        self._record(SafetyEvent(now, reason, "stop"))
        self._stop_and_hold(reason)

    def _on_clear(self, reason: str, now: float) -> None:
        self._record(SafetyEvent(now, reason, "cleared"))

    # ---------------------------------------------------------------------------------- reader thread
    def _reader(self) -> None:
        while not self._stop.is_set():
            msg = self.endpoint.receive(timeout=0.05)
            if msg is None:
                continue
            now = self._clock()
            try:
                event = None
                with self._lock:
                    hb = self._decoder.feed(msg, now)
                    if hb is not None:
                        self._watchdog.seen(HEARTBEAT_LOST, now)
                        event = self._on_heartbeat(hb, now)
                if event is not None:
                    self._record(event)
                    if event.by_other_party:
                        self.status(f"OFFBOARD ENDED: {event.detail}", MAV_SEVERITY_WARNING)
                self._gcs.handle(msg, now)
            except Exception:  # a malformed but checksum-valid message must not end the reader
                log.exception("could not handle %s", msg.get_type())

    def _on_heartbeat(self, hb: AutopilotHeartbeat, now: float) -> SafetyEvent | None:
        """Follows the mode (called with the lock held); the event to report when offboard control ended."""
        previous, self._mode = self._mode, hb.mode
        telemetry = self._decoder.snapshot()
        silent = telemetry is None or now - telemetry.time_s > STREAM_REQUEST_RETRY_S
        never_asked = self._streams_requested_at == -math.inf
        if never_asked or (silent and now - self._streams_requested_at > STREAM_REQUEST_RETRY_S):
            # Always once (PX4's default HEARTBEAT rate, 1 Hz, would see a takeover too late), and again
            # while silent: ArduPilot sends nothing until asked, and forgets on reboot.
            self._streams_requested_at = now
            self._request_streams()
        ours = offboard_mode(hb.kind)
        if previous == hb.mode or previous != ours:
            return None
        requested = self._mode_request is not None and self._mode_request[0] == hb.mode and (
            now - self._mode_request[1] < OWN_MODE_CHANGE_WINDOW_S
        )
        if requested:
            return SafetyEvent(now, "mode_change", "offboard_ended", f"{previous} -> {hb.mode} (requested)")
        if not self._enabled:  # we were not flying it (e.g. the autopilot going on from our RTL to LAND)
            return SafetyEvent(now, "mode_change", "mode_change", f"{previous} -> {hb.mode}")
        # Someone else took the vehicle: stop streaming at once and say why.
        self._enabled = self._engage = False
        self._stream_since = None
        detail = f"{previous} -> {hb.mode} by pilot or GCS"
        log.warning("offboard control ended: %s", detail)
        return SafetyEvent(now, "mode_change", "offboard_ended", detail, by_other_party=True, mode=hb.mode)

    def _request_streams(self) -> None:
        target = self._cfg.target_system
        for msg_id, interval in stream_intervals_us(self._cfg.telemetry_rate_hz):
            self.endpoint.send(partial(_set_message_interval, target=target, msg_id=msg_id, interval_us=interval))

    # -------------------------------------------------------------------------------- streamer thread
    def _streamer(self) -> None:
        period = 1.0 / self._cfg.setpoint_rate_hz
        next_tick = self._clock()
        while not self._stop.is_set():
            next_tick += period
            now = self._clock()
            if next_tick < now - period:  # fell far behind (machine stalled): restart the schedule
                next_tick = now
            try:
                self._stream_once(now)
            except Exception:
                log.exception("setpoint streaming failed")
            self._stop.wait(max(0.0, next_tick - self._clock()))

    def _stream_once(self, now: float) -> None:
        # Deciding and sending happen under the offboard lock, so a stop from the watchdog thread can
        # never be followed by a setpoint decided before it.
        with self._offboard_lock:
            self._stream_once_locked(now)

    def _stream_once_locked(self, now: float) -> None:
        hb = self._decoder.heartbeat
        if hb is None:
            return
        kind = hb.kind
        request_mode = None
        setpoint = None
        with self._lock:
            ours = offboard_mode(kind)
            in_offboard = self._mode == ours
            stopped = bool(self._watchdog.active()) or bool(self._held_reason)
            # ArduPilot flies setpoints only in GUIDED; PX4 needs them before OFFBOARD may be selected.
            streaming = self._enabled and (in_offboard or kind is AutopilotKind.PX4)
            if not streaming:
                self._stream_since = None
            elif self._stream_since is None:
                self._stream_since = now
            if streaming and stopped and self._mavsdk is not None and kind is AutopilotKind.PX4:
                pass  # MAVSDK would re-send any setpoint forever: after its stop() it gets none while stopped
            elif streaming and stopped:
                setpoint = Setpoint.zero()
            elif streaming:
                telemetry = self._decoder.snapshot()
                height = telemetry.height_agl if telemetry is not None else None
                setpoint = apply_limits(self._setpoint, self._limits, height, self._descent_allowed)
            prestreamed = kind is AutopilotKind.ARDUPILOT or (
                self._stream_since is not None and now - self._stream_since >= PX4_MIN_PRESTREAM_S
            )
            recently = self._mode_request is not None and now - self._mode_request[1] < MODE_REQUEST_RETRY_S
            if self._enabled and self._engage and not in_offboard and not stopped and prestreamed and not recently:
                request_mode = ours
        if setpoint is not None:
            self._send_setpoint(kind, setpoint)
        if request_mode is not None:
            self._request_mode(request_mode)
