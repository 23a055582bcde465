"""The one object the companion's main loop uses to talk to the autopilot and the GCS over MAVLink.

Threads (all owned here, started by `start()`):
- reader: decodes telemetry, follows the autopilot's mode, turns GCS messages into mission commands;
- streamer: sends the latest setpoint at `setpoint_rate_hz`, after `apply_limits`, only while the
  autopilot is in GUIDED (ArduPilot) / OFFBOARD (PX4) or, on PX4, while building the stream OFFBOARD needs;
- watchdog (`SafetyWatchdog`): stale frames, lost target, unreachable back-end, lost autopilot heartbeat,
  stalled main loop. Each ends motion with an explicit zero-velocity setpoint, then the configured hold.

Two ways to stop. `hold()` keeps the vehicle while the mission still owns it (lost target, back-end
unreachable): an explicit zero, then zeros in GUIDED or the configured BRAKE/LOITER. `release_offboard()` lets
go (every abort, a pilot's takeover): an explicit zero, the hold mode requested (PX4 HOLD, ArduPilot BRAKE or
LOITER) unless the pilot already chose a mode, then silence; zeros go on only while GUIDED/OFFBOARD remains,
at most RELEASE_TIMEOUT_S, after which the GCS is told the hold mode was not set and the companion falls
silent.

Every setpoint carries the time it was computed (in time_boot_ms) and is never encoded once older than
`[safety] setpoint_max_age_s`: after a freeze the first message out is a fresh zero, not the old command.
Telemetry older than `[safety] telemetry_stale_s` counts as missing: zeros (hold), never extrapolation.

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
from cloudtrack.autopilot_modes import (
    QUADROTOR,
    AutopilotKind,
    mission_mode,
    mode_for_action,
    offboard_mode,
    set_mode_params,
)
from cloudtrack.gcs_protocol import (
    CAMERA_CAP_FLAGS_HAS_TRACKING_POINT,
    CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE,
    MAV_SEVERITY_CRITICAL,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
    GcsProtocol,
    StartGate,
    statustext_chunks,
    value_name,
)
from cloudtrack.mavlink_connection import MavlinkEndpoint, mavlink
from cloudtrack.mavlink_signing import SigningGuard, parse_signing_key
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.mavsdk_offboard import MavsdkOffboard
from companion.mavlink.mavsdk_relay import MavsdkRelay
from companion.mavlink.offboard import PX4_MIN_PRESTREAM_S, encode_velocity
from companion.mavlink.telemetry_decoder import AutopilotHeartbeat, TelemetryDecoder, stream_intervals_us
from companion.safety_watchdog import (
    BACKEND_UNREACHABLE,
    HEARTBEAT_LOST,
    LOOP_STALLED,
    STALE_FRAMES,
    TARGET_LOST,
    SafetyEvent,
    SafetyWatchdog,
)

log = logging.getLogger(__name__)

MODE_REQUEST_RETRY_S = 1.0
MISSION_QUEUE = 256  # the autopilot's mission-protocol messages kept for a transfer (bounded)
RELEASE_TIMEOUT_S = 3.0  # after letting go, zeros in GUIDED/OFFBOARD at most this long, then silence
OWN_MODE_CHANGE_WINDOW_S = 5.0  # a mode we asked for that shows up this soon is our own change
STREAM_REQUEST_RETRY_S = 2.0
TRACKING_STATUS_PERIOD_S = 0.1
THREAD_STOP_WAIT_S = (
    2.0  # close(): the most it waits for its threads (reader, streamer, watchdog), all together
)


def _statustext(mav: Any, severity: int, text: bytes, text_id: int, seq: int) -> None:
    mav.statustext_send(severity, text, text_id, seq)


def _set_message_interval(mav: Any, target: int, msg_id: int, interval_us: float) -> None:
    mav.command_long_send(
        target, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0
    )


class VehicleLink:
    """Thread-safe facade over the MAVLink link; see the module docstring for the policy it enforces."""

    def __init__(
        self,
        mavlink_config: MavlinkConfig,
        safety: SafetyConfig,
        image_size: tuple[int, int] = (640, 480),
        on_safety_event: Callable[[SafetyEvent], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        start_gate: StartGate | None = None,
    ):
        self._cfg = mavlink_config
        self._clock = clock
        self._limits = MotionLimits.from_degrees(
            safety.max_speed_m_s, safety.max_vertical_speed_m_s, safety.max_yaw_rate_deg_s,
            safety.min_altitude_m, safety.max_altitude_m,
        )  # fmt: skip
        self._signing_key = (
            parse_signing_key(mavlink_config.signing_key) if mavlink_config.signing_key else None
        )
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
        self._relay: MavsdkRelay | None = None  # MAVSDK's MAVLink over our link
        self.signing = SigningGuard(
            on_refused=lambda text: self._record(SafetyEvent(self._clock(), "signing", "refused", text))
        )
        self._watchdog = SafetyWatchdog(safety, self._on_trip, self._on_clear, clock)
        self._camera_component = mavlink_config.camera_component
        self._gcs = GcsProtocol(
            mavlink_config.target_system, mavlink_config.source_component, self._camera_component,
            lambda: self._image_size, self, frozenset(mavlink_config.gcs_system_ids), start_gate,
        )  # fmt: skip
        self._setpoint_max_age = safety.setpoint_max_age_s
        self._telemetry_stale = safety.telemetry_stale_s

        self._setpoint = Setpoint.zero()
        self._setpoint_time = -math.inf  # when the main loop computed `_setpoint`
        # Letting go (the hold mode) or handing back to the mission: (mode requested, since, what it is).
        self._release: tuple[str, float, str] | None = None
        self._telemetry_missing = False
        self._descent_allowed = False
        self._held_reason = ""  # a hold the main loop asked for, until its next set_velocity
        self._enabled = False  # the mission wants offboard control
        self._engage = False  # and may select GUIDED/OFFBOARD itself
        self._mode = ""
        self._stream_since: float | None = None
        self._mode_request: tuple[str, float] | None = None  # the latest, for the retry
        # Every mode we asked for, when: a HOLD we asked for stays ours when OFFBOARD was asked for after it
        # but before the autopilot's HOLD showed (a watchdog's stop, then the mission's resume).
        self._own_requests: dict[str, float] = {}
        self._streams_requested_at = -math.inf
        self._last_heartbeat_sent = -math.inf
        self._last_tracking_sent = -math.inf
        self._tracking_box: Box | None = None
        self._latest_status = ("CloudTrack ready: no mission", MAV_SEVERITY_INFO)
        self._text_id = 0
        self._commands: deque[MissionCommand] = deque(maxlen=100)
        self._mission_messages: deque[Any] = deque(maxlen=MISSION_QUEUE)
        self._mission_arrived = threading.Condition(self._lock)
        self._events: deque[SafetyEvent] = deque(maxlen=1000)
        self.setpoints_sent = 0
        self.stale_setpoints_dropped = 0

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._endpoint = MavlinkEndpoint.open(
            self._cfg.connection, self._cfg.target_system, self._cfg.source_component, self._cfg.target_system
        )
        if self._signing_key is not None:
            self.signing.enable(self._endpoint.conn, self._signing_key)
        if self._camera_component:
            self._endpoint.add_identity(self._camera_component)
        if self._cfg.use_mavsdk:
            self._relay = MavsdkRelay(self._endpoint, self._setpoint_max_age, self._clock)
            ids = (self._cfg.target_system, self._cfg.source_component)
            self._mavsdk = MavsdkOffboard(self._relay, *ids)
        self._watchdog.seen(LOOP_STALLED)
        self._send_heartbeat(self._clock())  # opens udpout/tcp links so the autopilot learns where we are
        for target, name in ((self._reader, "mavlink-reader"), (self._streamer, "mavlink-streamer")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            self._threads.append(thread)
            thread.start()
        if self._mavsdk is not None:
            self._mavsdk.start()  # needs the reader: it discovers the autopilot through the relay
        self._watchdog.start()

    def close(self) -> None:
        """Explicit stop and hold if we are flying the vehicle, then shut the threads and the link."""
        if self._endpoint is not None and self._enabled:
            self.release_offboard("companion link closing")
        if self._mavsdk is not None:
            self._mavsdk.wait_idle(2.5)  # its stop needs the reader below for PX4's COMMAND_ACK
        self._stop.set()
        # One deadline for all of them (each loop ends within a receive timeout or a setpoint period once
        # told), not one per thread in turn.
        deadline = time.monotonic() + THREAD_STOP_WAIT_S
        self._watchdog.close(timeout_s=THREAD_STOP_WAIT_S)  # its loop wakes on the stop at once
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
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
            self._setpoint_time = self._clock()
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
            self._release = None  # a new mission ends the letting-go of the last one
            self._allow_mavsdk_setpoints(True)

    def request_offboard(self) -> None:
        """The operator allowed engagement: ask for GUIDED, or OFFBOARD after >= 1 s of setpoints (PX4)."""
        with self._lock:
            self._enabled = True
            self._engage = True
            self._release = None
            self._allow_mavsdk_setpoints(True)

    def release_offboard(self, reason: str) -> None:
        """Let go: explicit zero, the hold mode requested if we were flying it, then silence (bounded).

        After a pilot's takeover the mode is already theirs: nothing is requested, nothing more is sent.
        """
        with self._offboard_lock:
            kind = self.autopilot_kind
            with self._lock:
                flying = kind is not None and self._enabled and self._mode == offboard_mode(kind)
                self._enabled = self._engage = False
                self._held_reason = ""
                self._setpoint = Setpoint.zero()
                self._stream_since = None
            if not flying or kind is None:
                return
            log.warning("letting go: %s", reason)
            if self._mavsdk is not None and kind is AutopilotKind.PX4:
                with self._lock:
                    self._note_mode_request("HOLD")
                self._mavsdk.stop(reason)  # zero, then HOLD; MAVSDK would keep re-sending otherwise
                return
            mode = self._release_mode(kind)
            with self._lock:
                self._release = (mode, self._clock(), "HOLD MODE")
            self._send_zero()
            self._request_mode(mode)

    def resume_mission(self, item: int | None, reason: str = "") -> None:
        """Hand the vehicle back to the autopilot's own mission (ArduPilot AUTO, PX4 MISSION) at mission item
        `item`, the one it broke off at: the current item is set first only when the autopilot has moved on
        from it (both resume the current item when their mission mode is selected again). Like letting go:
        an explicit zero, the mode requested (repeated while GUIDED/OFFBOARD remains, at most
        RELEASE_TIMEOUT_S), then silence; nothing is requested if the mode is no longer ours (the pilot chose
        one meanwhile) or the autopilot never left its mission."""
        with self._offboard_lock:
            kind = self.autopilot_kind
            with self._lock:
                ours = kind is not None and self._mode == offboard_mode(kind)
                self._enabled = self._engage = False
                self._held_reason = ""
                self._setpoint = Setpoint.zero()
                self._stream_since = None
            if kind is None or not ours:
                log.info(
                    "mission not requested (%s): the autopilot is in %s", reason, self._mode or "no mode"
                )
                return
            mode = mission_mode(kind)
            current = self._decoder.mission_item()
            log.info("handing back to the mission at item %s (%s; current %s)", item, reason, current)
            mavsdk = self._mavsdk is not None and kind is AutopilotKind.PX4
            if self._mavsdk is not None and mavsdk:
                self._mavsdk.stop(reason)  # MAVSDK would keep re-sending the last setpoint otherwise
            else:
                self._send_zero()
            if item is not None and current is not None and item != current:
                self._set_mission_current(item)
            if not mavsdk:  # MAVSDK gets no more setpoints: the request goes once
                with self._lock:
                    self._release = (mode, self._clock(), "MISSION MODE")
            self._request_mode(mode)

    def _set_mission_current(self, item: int) -> None:
        """MISSION_SET_CURRENT (ArduPilot and PX4 alike, as `cloudtrack.mission_protocol` sets it): the item
        the mission resumes at."""
        target = self._cfg.target_system
        self.endpoint.send(lambda m: m.mission_set_current_send(target, 1, item))

    def _release_mode(self, kind: AutopilotKind) -> str:
        if kind is AutopilotKind.PX4:
            return "HOLD"
        hold = self._cfg.ardupilot_hold
        return mode_for_action(kind, "loiter" if hold == "guided_zero" else hold)

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

    def mission_link(self) -> MissionMessages:
        """The mission protocol over this link (`cloudtrack.mission_protocol.MissionClient` runs over it):
        sends through the endpoint, receives the autopilot's MISSION_* messages the reader hands over. One
        transfer at a time; a new one starts from an empty queue."""
        with self._lock:
            self._mission_messages.clear()
        return MissionMessages(self)

    def _next_mission_message(self, timeout: float) -> Any | None:
        deadline = self._clock() + timeout
        with self._mission_arrived:
            while not self._mission_messages:
                left = deadline - self._clock()
                if left <= 0 or self._stop.is_set():
                    return None
                self._mission_arrived.wait(min(left, 0.05))
            return self._mission_messages.popleft()

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
            self._latest_status = (text, severity)
        self.status(text, severity)

    def send_value(self, name: str, value: float) -> None:
        """A number for the GCS (NAMED_VALUE_FLOAT; name at most 10 characters)."""
        encoded = value_name(name)
        boot_ms = self._boot_ms()
        self.endpoint.send(lambda m: m.named_value_float_send(boot_ms, encoded, float(value)))

    def announce_find(
        self,
        lat: float,
        lon: float,
        sigma_m: float,
        slant_range_m: float,
        prompt: str,
        confirmed_by: str,
        seen_before_s: float | None = None,
    ) -> None:
        """A confirmed find: STATUSTEXT at CRITICAL, which QGroundControl pops up (`FOUND <lat>,<lon>
        +-<sigma>m`, at most 50 bytes), a second line with the prompt, who confirmed and, when the position
        was seen a second or more before the confirmation, how long before (`; seen 45 s before`), and the
        position as CAMERA_TRACKING_GEO_STATUS (which has no time field)."""
        self.send_status(f"FOUND {lat:.6f},{lon:.6f} +-{min(sigma_m, 9999.0):.1f}m", MAV_SEVERITY_CRITICAL)
        seen = ""
        if seen_before_s is not None and math.isfinite(seen_before_s) and seen_before_s >= 1.0:
            seen = f"; seen {min(seen_before_s, 99_999.0):.0f} s before"
        self.status(f"FOUND: {prompt} (confirmed by {confirmed_by or 'supervisor'}{seen})", MAV_SEVERITY_INFO)
        self.send_find_position(lat, lon, sigma_m, slant_range_m)

    def send_find_position(self, lat: float, lon: float, sigma_m: float, slant_range_m: float) -> None:
        """CAMERA_TRACKING_GEO_STATUS (from the camera identity) with the find's position: ground altitude
        AMSL from the autopilot's home, horizontal accuracy the geolocation's sigma, unknowns NaN."""
        ground = self._decoder.ground_amsl()
        alt = ground if ground is not None else math.nan
        nan = math.nan
        lat_e7, lon_e7 = int(round(lat * 1e7)), int(round(lon * 1e7))
        status = mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
        self.endpoint.send(
            lambda m: m.camera_tracking_geo_status_send(
                status, lat_e7, lon_e7, alt, sigma_m, nan, nan, nan, nan, nan, slant_range_m, nan, nan
            ),
            self._camera_component or None,
        )

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
                lambda m: m.camera_tracking_image_status_send(0, 0, 0, nan, nan, nan, nan, nan, nan, nan),
                camera,
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
            lambda m: m.command_ack_send(
                msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            ),
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
            text, severity = self._latest_status
        self.status(text, severity)

    def camera_information(self, image_size: tuple[int, int], component: int) -> None:
        flags = CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE | CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
        vendor = list(b"CloudTrack".ljust(32, b"\0"))
        model = list(b"companion tracker".ljust(32, b"\0"))
        boot_ms = self._boot_ms()
        self.endpoint.send(
            lambda m: m.camera_information_send(
                boot_ms,
                vendor,
                model,
                0,
                math.nan,
                math.nan,
                math.nan,
                image_size[0],
                image_size[1],
                0,
                flags,
                0,
                b"",
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
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink.MAV_STATE_ACTIVE,
            )
        )
        if self._camera_component:  # the camera identity lives and dies with the loop too
            self._endpoint.send(
                lambda m: m.heartbeat_send(
                    mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
                ),
                self._camera_component,
            )

    def _send_setpoint(
        self, kind: AutopilotKind, setpoint: Setpoint, computed_at: float | None = None
    ) -> None:
        """Send `setpoint`, computed at `computed_at` (default now), unless it is older than the bound by the
        time it is encoded (checked under the send lock, the last moment before it leaves)."""
        computed = self._clock() if computed_at is None else computed_at
        if self._mavsdk is not None and kind is AutopilotKind.PX4:
            if self._clock() - computed <= self._setpoint_max_age:
                self._mavsdk.set_velocity(setpoint)  # MAVSDK re-sends it at 20 Hz by itself
                self.setpoints_sent += 1
            return
        fields = encode_velocity(kind, setpoint)
        target, boot_ms = self._cfg.target_system, int(computed * 1000) & 0xFFFFFFFF

        def build(m: Any) -> bool:
            if self._clock() - computed > self._setpoint_max_age:
                self.stale_setpoints_dropped += 1
                return False
            m.set_position_target_local_ned_send(
                boot_ms, target, 1, fields.frame, fields.type_mask, 0, 0, 0,
                fields.vx, fields.vy, fields.vz, 0, 0, 0, 0, fields.yaw_rate,
            )  # fmt: skip
            return True

        if self.endpoint.send(build):
            self.setpoints_sent += 1

    def _send_zero(self) -> None:
        kind = self.autopilot_kind
        if kind is not None and self._endpoint is not None:
            self._send_setpoint(kind, Setpoint.zero())

    def _request_mode(self, name: str) -> None:
        kind = self.autopilot_kind
        if kind is None:
            return
        hb = self._decoder.heartbeat
        try:
            params = set_mode_params(kind, name, hb.vehicle_type if hb is not None else QUADROTOR)
        except ValueError as exc:  # e.g. BRAKE on a Plane: say so instead of failing in a watchdog thread
            log.error("mode %s not requested: %s", name, exc)
            self.status(f"MODE {name} UNAVAILABLE", MAV_SEVERITY_WARNING)
            return
        with self._lock:
            self._note_mode_request(name)
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

    def _note_mode_request(self, name: str) -> None:
        """Remember a mode we asked for (lock held)."""
        now = self._clock()
        self._mode_request = (name, now)
        self._own_requests[name] = now

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
                self._note_mode_request("HOLD")
            self._mavsdk.stop(
                reason
            )  # zero, then offboard stop (HOLD): MAVSDK would keep re-sending otherwise
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
        if reason == LOOP_STALLED and self._endpoint is not None:
            # The real cause, not only the LOST/link-lost that follow from it.
            self.status("COMPANION STALLED: stopping", MAV_SEVERITY_WARNING)

    def _on_clear(self, reason: str, now: float) -> None:
        self._record(SafetyEvent(now, reason, "cleared"))
        if reason == LOOP_STALLED and self._endpoint is not None:
            self.status("companion running again", MAV_SEVERITY_WARNING)
        elif reason == HEARTBEAT_LOST and self._endpoint is not None:
            self.latest_status()  # a notice sent while the link was down (an abort) was lost: say it again

    # ---------------------------------------------------------------------------------- reader thread
    def _reader(self) -> None:
        while not self._stop.is_set():
            msg = self.endpoint.receive(timeout=0.05)
            if msg is None:
                continue
            now = self._clock()
            if self._relay is not None and msg.get_srcSystem() == self._cfg.target_system:
                self._relay.to_mavsdk(msg)
            try:
                event = None
                with self._lock:
                    if (
                        msg.get_type().startswith("MISSION_")
                        and msg.get_srcSystem() == self._cfg.target_system
                    ):
                        self._mission_messages.append(msg)
                        self._mission_arrived.notify_all()
                    hb = self._decoder.feed(msg, now)
                    if hb is not None or self._from_autopilot(msg):
                        # Any message from the autopilot proves the link: PX4's HEARTBEAT is fixed at 1 Hz
                        # (gaps up to 1.3 s measured), too slow for a limit under a second.
                        self._watchdog.seen(HEARTBEAT_LOST, now)
                    if hb is not None:
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
        asked_at = self._own_requests.get(hb.mode)
        # The autopilot's failsafe (PX4's offboard loss: HOLD with OFFBOARD still intended) is never our hold,
        # even where we asked for the same mode: PX4 would fly OFFBOARD again once setpoints resume.
        requested = not hb.failsafe and asked_at is not None and now - asked_at < OWN_MODE_CHANGE_WINDOW_S
        if requested:
            return SafetyEvent(now, "mode_change", "offboard_ended", f"{previous} -> {hb.mode} (requested)")
        if not self._enabled:  # we were not flying it (e.g. the autopilot going on from our RTL to LAND)
            return SafetyEvent(now, "mode_change", "mode_change", f"{previous} -> {hb.mode}")
        # Someone else took the vehicle: stop streaming at once and say why.
        self._enabled = self._engage = False
        self._stream_since = None
        self._allow_mavsdk_setpoints(False)  # MAVSDK would re-send until PX4's next 1 Hz HEARTBEAT
        detail = f"{previous} -> {hb.mode} by {'the autopilot failsafe' if hb.failsafe else 'pilot or GCS'}"
        log.warning("offboard control ended: %s", detail)
        return SafetyEvent(now, "mode_change", "offboard_ended", detail, by_other_party=True, mode=hb.mode)

    def _from_autopilot(self, msg: Any) -> bool:
        return bool(
            msg.get_srcSystem() == self._cfg.target_system
            and msg.get_srcComponent() == 1
            and msg.get_type() != "BAD_DATA"
        )

    def _allow_mavsdk_setpoints(self, allowed: bool) -> None:
        if self._relay is not None:
            self._relay.setpoints_allowed = allowed

    def _request_streams(self) -> None:
        target = self._cfg.target_system
        for msg_id, interval in stream_intervals_us(self._cfg.telemetry_rate_hz, self.autopilot_kind):
            self.endpoint.send(
                partial(_set_message_interval, target=target, msg_id=msg_id, interval_us=interval)
            )

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
                self._stream_once()
            except Exception:
                log.exception("setpoint streaming failed")
            self._stop.wait(max(0.0, next_tick - self._clock()))

    def _stream_once(self) -> None:
        # Deciding and sending happen under the offboard lock, so a stop from the watchdog thread can
        # never be followed by a setpoint decided before it. The watchdog's check runs here first: after a
        # freeze of the whole process the main loop may set a fresh command (from a pre-freeze frame) before
        # the watchdog's own thread runs, and the freeze must stop the vehicle before any command goes out.
        with self._offboard_lock:
            self._stream_once_locked(self._watchdog.check())

    def _stream_once_locked(self, now: float) -> None:
        hb = self._decoder.heartbeat
        if hb is None:
            return
        kind = hb.kind
        request_mode = None
        setpoint = None
        computed_at = now
        gave_up = ""
        with self._lock:
            ours = offboard_mode(kind)
            in_offboard = self._mode == ours
            if self._release is not None:
                setpoint, request_mode, gave_up = self._releasing(in_offboard, now)
            else:
                stopped = bool(self._watchdog.active()) or bool(self._held_reason)
                # ArduPilot flies setpoints only in GUIDED; PX4 needs them before OFFBOARD may be selected.
                streaming = self._enabled and (in_offboard or kind is AutopilotKind.PX4)
                if not streaming:
                    self._stream_since = None
                elif self._stream_since is None:
                    self._stream_since = now
                height = self._fresh_height(now)
                if streaming and stopped and self._mavsdk is not None and kind is AutopilotKind.PX4:
                    pass  # MAVSDK re-sends any setpoint forever: after its stop() it gets none while stopped
                elif streaming and (stopped or self._telemetry_missing):
                    setpoint = Setpoint.zero()
                elif streaming and now - self._setpoint_time > self._setpoint_max_age:
                    setpoint = Setpoint.zero()  # the main loop's command is too old to fly: hold instead
                elif streaming:
                    setpoint = apply_limits(self._setpoint, self._limits, height, self._descent_allowed)
                    # Its age at sending counts from the earlier of its computing and this decision: a freeze
                    # between the two leaves a command that the encoder drops.
                    computed_at = min(self._setpoint_time, now)
                prestreamed = kind is AutopilotKind.ARDUPILOT or (
                    self._stream_since is not None and now - self._stream_since >= PX4_MIN_PRESTREAM_S
                )
                request = self._mode_request
                recently = request is not None and now - request[1] < MODE_REQUEST_RETRY_S
                may_engage = self._enabled and self._engage and not in_offboard and not stopped
                if may_engage and prestreamed and not recently:
                    request_mode = ours
        if setpoint is not None:
            self._send_setpoint(kind, setpoint, computed_at)
        if request_mode is not None:
            self._request_mode(request_mode)
        if gave_up:
            log.warning("%s", gave_up)
            self.status(gave_up, MAV_SEVERITY_WARNING)

    def _releasing(self, in_offboard: bool, now: float) -> tuple[Setpoint | None, str | None, str]:
        """While letting go (lock held): zeros and the hold-mode request until the mode leaves GUIDED/OFFBOARD
        or RELEASE_TIMEOUT_S passes; then nothing more. Returns (setpoint, mode to request, notice)."""
        assert self._release is not None
        mode, since, what = self._release
        if not in_offboard:
            self._release = None  # the autopilot holds (or the pilot chose a mode): silence
            return None, None, ""
        if now - since > RELEASE_TIMEOUT_S:
            self._release = None
            return None, None, f"{what} {mode} NOT SET: companion silent in {self._mode}"
        recently = self._mode_request is not None and now - self._mode_request[1] < MODE_REQUEST_RETRY_S
        return Setpoint.zero(), (None if recently else mode), ""

    def _fresh_height(self, now: float) -> float | None:
        """The height above ground if the position telemetry is recent (lock held); notes when it is not."""
        height, when = self._decoder.height()
        missing = when is None or now - when > self._telemetry_stale
        if missing != self._telemetry_missing:
            self._telemetry_missing = missing
            if missing and self._enabled:
                log.warning("position telemetry older than %.1f s: holding", self._telemetry_stale)
        return None if missing else height


class MissionMessages:
    """A `cloudtrack.mission_protocol.MissionLink` on the companion's own link (`VehicleLink.mission_link`)."""

    def __init__(self, link: VehicleLink) -> None:
        self._link = link

    def send(self, build: Callable[[Any], Any]) -> bool:
        return self._link.endpoint.send(build)

    def receive(self, timeout: float) -> Any | None:
        return self._link._next_mission_message(timeout)
