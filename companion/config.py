"""The companion's configuration schema: every section, key, default and allowed range.

`config/companion.toml` mirrors these defaults; `tests/test_config.py` keeps the two in step.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from cloudtrack.config_files import ConfigSection, load_config

TrackerName = Literal["nano", "vit", "dasiamrpn", "csrt", "kcf", "mil", "goturn"]


class VehicleConfig(ConfigSection):
    id: str = Field("drone-1", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")


class CameraConfig(ConfigSection):
    # V4L2 index ("0"), video file, RTSP/GStreamer URL, or a folder of frames (000001.jpg ...).
    source: str = "0"
    width: int = Field(640, ge=64, le=7680)
    height: int = Field(480, ge=48, le=4320)
    fps: float = Field(30.0, gt=0, le=240)
    hfov_deg: float = Field(70.0, gt=1, lt=179)
    # Negative looks down. With `stabilised` a gimbal holds this pitch against the vehicle's attitude.
    mount_pitch_deg: float = Field(-45.0, ge=-90, le=30)
    stabilised: bool = True
    reconnect_interval_s: float = Field(1.0, gt=0, le=60)


class TrackerConfig(ConfigSection):
    name: TrackerName = "nano"
    model_dir: str = ""  # empty: --model-dir, then $CLOUDTRACK_MODEL_DIR, then the user cache
    # t_c per tracker: re-initialise below this score (paper's best values for nano, vit, dasiamrpn).
    score_threshold: dict[str, float] = Field(
        default_factory=lambda: {"nano": 0.7, "vit": 0.4, "dasiamrpn": 0.9}
    )
    max_jump_fraction: float = Field(0.35, gt=0, le=2.0)  # centre jump per frame, fraction of image diagonal
    min_box_px: float = Field(4.0, ge=1)
    appearance_drift_threshold: float = Field(0.6, ge=0, le=1)
    ring_buffer_frames: int = Field(90, ge=1, le=1000)
    max_fast_forward_frames: int = Field(45, ge=0, le=1000)
    max_jump_box_sizes: float = Field(1.5, gt=0, le=20)  # centre jump per frame, in box sizes (sqrt area)
    max_scale_change: float = Field(3.0, gt=1, le=100)  # box area ratio per frame beyond which it "collapsed"
    min_visible_fraction: float = Field(0.5, ge=0, le=1)  # less of the box inside the image: "left_frame"
    catch_up_per_frame: int = Field(4, ge=1, le=100)  # fast-forward updates per live frame after a re-init
    max_c_box_sizes: float = Field(3.0, gt=0, le=100)  # re-init gate: C_box over (w + h) of the last trusted box
    max_aspect_change: float = Field(2.0, gt=1, le=100)  # width/height change since (re)init: "collapsed"
    # What a re-detection answer may do (docs/tracking.md): "verified" moves the track only when a candidate
    # beats it on evidence reinit_confirmations keyframes in a row and otherwise waits; "c_box" is the
    # paper's (nearest candidate to the last trusted box whenever lost), "score" the reference code's.
    # Used by `eval`; in flight the mission behaviour still picks the re-detection candidate itself.
    reinit_policy: Literal["verified", "c_box", "score"] = "verified"
    reinit_confirmations: int = Field(2, ge=1, le=10)
    reinit_agree_iou: float = Field(0.5, gt=0, le=1)  # a candidate overlapping the track this much is its own
    reinit_appearance_margin: float = Field(0.1, ge=0, le=1)  # tie in verdicts: closer to the target by this
    # Loss signals in use: tracker_failed, score, left_frame, collapsed, jump, appearance.
    loss_signals: list[str] = Field(
        default_factory=lambda: ["tracker_failed", "score", "left_frame", "collapsed", "jump", "appearance"]
    )


class BackendConfig(ConfigSection):
    url: str = "http://127.0.0.1:8080"
    token: str = ""  # prefer the environment variable CLOUDTRACK_BACKEND__TOKEN
    keyframe_interval_s: float = Field(1.0, gt=0, le=60)
    jpeg_quality: int = Field(80, ge=10, le=100)
    max_keyframe_width: int = Field(640, ge=64, le=4096)
    timeout_s: float = Field(5.0, gt=0, le=120)
    superset: str = ""  # empty: derived from the prompt by the back-end
    status_interval_s: float = Field(1.0, gt=0, le=60)  # status post + supervisor decisions poll


class MavlinkConfig(ConfigSection):
    # serial:/dev/ttyAMA0:921600, udpin:0.0.0.0:14540, udpout:127.0.0.1:14550, tcp:127.0.0.1:5760
    connection: str = "udpin:0.0.0.0:14540"
    target_system: int = Field(1, ge=1, le=255)
    source_component: int = Field(191, ge=1, le=255)  # MAV_COMP_ID_ONBOARD_COMPUTER
    autopilot: Literal["auto", "ardupilot", "px4"] = "auto"
    setpoint_rate_hz: float = Field(15.0, ge=10, le=20)
    telemetry_rate_hz: float = Field(10.0, gt=0, le=50)
    # ArduPilot hold: zero velocity in GUIDED, or switch to BRAKE or LOITER. PX4 always uses HOLD.
    ardupilot_hold: Literal["guided_zero", "brake", "loiter"] = "guided_zero"
    signing_key: str = ""  # 64 hex chars (32 bytes); prefer CLOUDTRACK_MAVLINK__SIGNING_KEY
    use_mavsdk: bool = False
    mavsdk_address: str = "udp://:14541"
    # A second identity as a MAVLink camera (100-105 is where QGroundControl looks for tracking); 0: none.
    camera_component: int = Field(100, ge=0, le=255)


class SafetyConfig(ConfigSection):
    """The one place every motion limit lives; the control law's output is clamped to these."""

    max_speed_m_s: float = Field(3.0, gt=0, le=15)
    max_vertical_speed_m_s: float = Field(1.0, ge=0, le=5)
    max_yaw_rate_deg_s: float = Field(45.0, gt=0, le=180)
    min_altitude_m: float = Field(5.0, ge=1, le=500)
    max_altitude_m: float = Field(60.0, ge=2, le=1000)
    frame_stale_s: float = Field(0.5, gt=0, le=10)
    backend_lost_s: float = Field(10.0, gt=0, le=600)
    heartbeat_timeout_s: float = Field(2.0, gt=0, le=30)
    loop_stall_s: float = Field(0.5, gt=0, le=10)
    target_lost_s: float = Field(1.0, gt=0, le=60)  # while following: no trusted target this long -> hold

    @model_validator(mode="after")
    def _altitude_band(self) -> SafetyConfig:
        if self.min_altitude_m >= self.max_altitude_m:
            raise ValueError(
                f"min_altitude_m ({self.min_altitude_m}) must be below max_altitude_m ({self.max_altitude_m})"
            )
        return self


class BehaviorConfig(ConfigSection):
    standoff_m: float = Field(12.0, gt=1, le=200)
    search_yaw_rate_deg_s: float = Field(0.0, ge=0, le=30)
    reverify_interval_s: float = Field(10.0, gt=0, le=600)
    lost_hold_after_s: float = Field(1.0, ge=0, le=60)
    lost_action_after_s: float = Field(30.0, gt=0, le=3600)
    lost_action: Literal["hold", "loiter", "rtl", "land"] = "hold"
    on_confirm: Literal["follow", "hold", "orbit"] = "follow"
    orbit_speed_m_s: float = Field(1.0, gt=0, le=10)
    accept_uncertain: bool = False  # may an "uncertain" verdict start tracking (after every "yes")
    acquire_timeout_s: float = Field(3.0, gt=0, le=60)  # tracker must lock on this soon after init
    arrive_tolerance_m: float = Field(2.0, gt=0, le=50)  # this close to the standoff: ask the supervisor
    approach_timeout_s: float = Field(60.0, gt=0, le=3600)  # ask anyway after following this long
    rejection_radius_m: float = Field(5.0, gt=0, le=500)  # a rejected person's neighbourhood
    redetect_roi_scale: float = Field(3.0, ge=1, le=100)  # lost: re-detect in the last box grown this much...
    redetect_full_frame_s: float = Field(4.0, gt=0, le=600)  # ...growing to the whole frame after this long


class ControlConfig(ConfigSection):
    yaw_kp: float = Field(1.2, ge=0)
    yaw_ki: float = Field(0.05, ge=0)
    forward_kp: float = Field(0.8, ge=0)
    forward_ki: float = Field(0.1, ge=0)
    lateral_kp: float = Field(0.0, ge=0)
    yaw_dead_band_deg: float = Field(1.5, ge=0, le=30)
    distance_dead_band_m: float = Field(0.5, ge=0, le=20)
    filter_time_constant_s: float = Field(0.15, ge=0, le=5)
    max_accel_m_s2: float = Field(2.0, gt=0, le=20)
    max_yaw_accel_deg_s2: float = Field(90.0, gt=0, le=1000)


class RecordingConfig(ConfigSection):
    enabled: bool = True
    dir: str = "~/.local/share/cloudtrack/records"
    max_bytes: int = Field(2_000_000_000, ge=1_000_000)
    video: bool = False


class CompanionConfig(ConfigSection):
    vehicle: VehicleConfig = VehicleConfig()
    camera: CameraConfig = CameraConfig()
    tracker: TrackerConfig = TrackerConfig()
    backend: BackendConfig = BackendConfig()
    mavlink: MavlinkConfig = MavlinkConfig()
    safety: SafetyConfig = SafetyConfig()
    behavior: BehaviorConfig = BehaviorConfig()
    control: ControlConfig = ControlConfig()
    recording: RecordingConfig = RecordingConfig()


ENV_PREFIX = "CLOUDTRACK_"
# The back-end's variables (CLOUDTRACK_BACKEND_<SECTION>__<KEY>) share our prefix; one shell or host may
# hold both processes' settings, so they are not ours to validate. Our own [backend] section is
# CLOUDTRACK_BACKEND__<KEY> (two underscores) and stays.
_BACKEND_SERVICE_PREFIX = "CLOUDTRACK_BACKEND_"


def companion_environment(environ: Mapping[str, str]) -> dict[str, str]:
    return {
        k: v
        for k, v in environ.items()
        if not (k.startswith(_BACKEND_SERVICE_PREFIX) and not k.startswith("CLOUDTRACK_BACKEND__"))
    }


def load_companion_config(
    path: Path | None = None, assignments: Iterable[str] = (), environ: Mapping[str, str] | None = None
) -> CompanionConfig:
    """Defaults, then FILE, then CLOUDTRACK_<SECTION>__<KEY> variables, then --set; ConfigError if not allowed."""
    env = companion_environment(os.environ if environ is None else environ)
    return load_config(CompanionConfig, path, env_prefix=ENV_PREFIX, environ=env, assignments=assignments)
