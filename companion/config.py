"""The companion's configuration schema: every section, key, default and allowed range.

The [camera] and [safety] sections live in `cloudtrack/vehicle_config.py`: the ground tool reads them too.
`config/companion.toml` mirrors these defaults; `tests/test_config_defaults.py` keeps the two in step key
by key. The control gains' defaults are the control law's own (`behaviors.control_law.ControlGains`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from behaviors.control_law import ControlGains
from cloudtrack.config_files import ConfigSection, default_config_files, load_config
from cloudtrack.vehicle_config import CameraConfig as CameraConfig  # re-exported: the companion imports
from cloudtrack.vehicle_config import KeyframeTiming, VerdictPolicy
from cloudtrack.vehicle_config import SafetyConfig as SafetyConfig  # every section from here
from cloudtrack.vehicle_config import SearchConfig as SearchConfig

TrackerName = Literal["nano", "vit", "dasiamrpn", "csrt", "kcf", "mil", "goturn"]


class VehicleConfig(ConfigSection):
    id: str = Field("drone-1", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")


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
    max_c_box_sizes: float = Field(
        3.0, gt=0, le=100
    )  # re-init gate: C_box over (w + h) of the last trusted box
    max_aspect_change: float = Field(2.0, gt=1, le=100)  # width/height change since (re)init: "collapsed"
    # Target classes (the candidate's detector label) the weak loss signals were measured on: for any other
    # target (a car turning under the camera, an animal, a ball) "collapsed" skips its aspect test and a
    # weak signal never untrusts the track, alone or with another (docs/tracking.md, "Loss evidence that is not
    # person-shaped").
    loss_model_classes: list[str] = Field(default_factory=lambda: ["person"], max_length=100)
    # What a re-detection answer may do (docs/tracking.md): "verified" moves the track only when a candidate
    # beats it on evidence reinit_confirmations keyframes in a row and otherwise waits; "c_box" is the
    # paper's (nearest candidate to the last trusted box whenever lost), "score" the reference code's.
    # Used by `eval` and in flight (the mission hands every answer for the track to this policy).
    reinit_policy: Literal["verified", "c_box", "score"] = "verified"
    reinit_confirmations: int = Field(2, ge=1, le=10)
    reinit_agree_iou: float = Field(0.5, gt=0, le=1)  # a candidate overlapping the track this much is its own
    reinit_appearance_margin: float = Field(0.1, ge=0, le=1)  # tie in verdicts: closer to the target by this
    # "verified": a track whose box is more than this many times the width or height of the object the
    # detector found on it is re-framed on that object (its scale drifted), alarm or not.
    reinit_max_framing_ratio: float = Field(1.5, gt=1, le=10)
    # "verified": seconds one weak alarm alone (weak_loss_signals) must persist before the track is
    # untrusted, and seconds without any alarm before a lost track is trusted again
    # (behaviors.loss_evidence). 0: per frame.
    loss_persistence_s: float = Field(1.0, ge=0, le=10)
    # The signals that untrust a track alone only after loss_persistence_s (or with a second signal): models
    # of the target (its colour, its shape since the start, the tracker's own score), which a pose or light
    # change sets off while the tracker is on the target. The others (no box, out of the image, a jump)
    # untrust at once.
    weak_loss_signals: list[str] = Field(default_factory=lambda: ["score", "collapsed", "appearance"])
    # "verified": a trusted track is untrusted ("not_detected") once the chance that the back-end's detector
    # missed a real target of its size in every answer since the last that found one on it falls below this,
    # over at least unsupported_min_s (behaviors.track_support; the POD from the detection curve). 0: off.
    unsupported_miss_chance: float = Field(0.001, ge=0, lt=1)
    unsupported_min_s: float = Field(2.0, ge=0, le=60)
    # Loss signals in use: tracker_failed, score, left_frame, collapsed, jump, appearance.
    loss_signals: list[str] = Field(
        default_factory=lambda: ["tracker_failed", "score", "left_frame", "collapsed", "jump", "appearance"]
    )


class BackendConfig(KeyframeTiming):  # search_interval_s, max_keyframe_width: the survey planner's too
    url: str = "http://127.0.0.1:8080"
    token: str = ""  # prefer the environment variable CLOUDTRACK_BACKEND__TOKEN
    keyframe_interval_s: float = Field(1.0, gt=0, le=60)
    # A search moves on the back-end's fast stage and the final verdicts confirm, move or end that track.
    early_answer: bool = True
    # Keyframes out at once (companion.cloud.backend_worker): a 2 s VLM keeps the 0.5 s search rate with 4.
    max_requests_in_flight: int = Field(4, ge=1, le=8)
    jpeg_quality: int = Field(80, ge=10, le=100)
    timeout_s: float = Field(5.0, gt=0, le=120)
    superset: str = ""  # empty: derived from the prompt by the back-end
    status_interval_s: float = Field(1.0, gt=0, le=60)  # status post + supervisor decisions poll
    # A GCS start waits this long for the back-end to say it can search for the prompt (DENIED with its
    # reason when it cannot); no answer in time: the start goes ahead and the search waits. 0: no check.
    start_check_s: float = Field(3.0, ge=0, le=30)
    # While the back-end is unreachable, search keyframes are kept (JPEG, as sent: 25-55 KB each from the dev
    # footage, at most 90 KB) and sent when it answers again, newest first (companion.cloud.keyframe_store);
    # past either bound the oldest are dropped and counted. 64 MB holds 10-20 min of a 0.5 s search (6 min at
    # 90 KB a keyframe): a 60 s outage needs at most 11 MB. 0 MB: none kept.
    outage_store_mb: int = Field(64, ge=0, le=4096)
    outage_store_max_age_s: float = Field(900.0, gt=0, le=86400)


class MavlinkConfig(ConfigSection):
    # pymavlink's format for every endpoint: udpin:127.0.0.1:14540 (default: the autopilot or mavlink-router
    # on this computer), udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyAMA0,921600. Never 0.0.0.0 unless set here.
    connection: str = "udpin:127.0.0.1:14540"
    target_system: int = Field(1, ge=1, le=255)  # the autopilot's system id: telemetry is read only from it
    source_component: int = Field(191, ge=1, le=255)  # MAV_COMP_ID_ONBOARD_COMPUTER
    # System ids whose mission and camera commands are obeyed; anyone else is answered MAV_RESULT_DENIED.
    gcs_system_ids: list[int] = Field(default_factory=lambda: [255], min_length=1, max_length=32)
    autopilot: Literal["auto", "ardupilot", "px4"] = "auto"
    setpoint_rate_hz: float = Field(15.0, ge=10, le=20)
    telemetry_rate_hz: float = Field(10.0, gt=0, le=50)
    # ArduPilot hold while the mission still owns the vehicle: zero velocity in GUIDED, or BRAKE or LOITER.
    # Letting go (abort) always leaves GUIDED: BRAKE or LOITER as set here, LOITER for guided_zero. PX4: HOLD.
    ardupilot_hold: Literal["guided_zero", "brake", "loiter"] = "guided_zero"
    signing_key: str = ""  # 64 hex chars (32 bytes); prefer CLOUDTRACK_MAVLINK__SIGNING_KEY
    # PX4 offboard through MAVSDK (pip install 'cloudtrack[mavsdk]'); its MAVLink goes over `connection`.
    use_mavsdk: bool = False
    # A second identity as a MAVLink camera (100-105 is where QGroundControl looks for tracking); 0: none.
    camera_component: int = Field(100, ge=0, le=255)

    @model_validator(mode="after")
    def _connections(self) -> MavlinkConfig:
        from cloudtrack.mavlink_connection import parse_connection

        parse_connection(self.connection)  # ValueError names the string and the allowed forms
        if any(not 1 <= sysid <= 255 for sysid in self.gcs_system_ids):
            raise ValueError("gcs_system_ids must be MAVLink system ids 1-255")
        return self

    @field_validator("signing_key")
    @classmethod
    def _signing_key(cls, value: str) -> str:
        """Empty (no signing) or 64 hex digits, checked by `config check`, not first in flight."""
        if value:
            from cloudtrack.mavlink_signing import parse_signing_key

            parse_signing_key(value)  # its error says what is expected, never the value
        return value


class BehaviorConfig(VerdictPolicy):  # accept_uncertain: the survey planner's too
    standoff_m: float = Field(12.0, gt=1, le=200)
    search_yaw_rate_deg_s: float = Field(0.0, ge=0, le=30)
    reverify_interval_s: float = Field(10.0, gt=0, le=600)
    lost_hold_after_s: float = Field(1.0, ge=0, le=60)
    lost_action_after_s: float = Field(30.0, gt=0, le=3600)
    lost_action: Literal["hold", "loiter", "rtl", "land"] = "hold"
    on_confirm: Literal["follow", "hold", "orbit", "survey"] = "follow"  # survey: report, search on
    # Along the autopilot's mission (auto: when it flies one at the start) or on the spot (docs/behavior.md)
    search: Literal["auto", "mission", "spot"] = "auto"
    lost_resume_after_s: float = Field(10.0, gt=0, le=600)  # along the mission: lost this long, fly on
    lost_looking_s: float = Field(2.0, gt=0, le=600)  # ... while only looking (not engaged)
    orbit_speed_m_s: float = Field(1.0, gt=0, le=10)
    acquire_timeout_s: float = Field(3.0, gt=0, le=60)  # tracker must lock on this soon after init
    arrive_tolerance_m: float = Field(2.0, gt=0, le=50)  # this close to the standoff: ask the supervisor
    approach_timeout_s: float = Field(60.0, gt=0, le=3600)  # ask anyway after following this long
    rejection_radius_m: float = Field(5.0, gt=0, le=500)  # a rejected person's neighbourhood
    redetect_roi_scale: float = Field(3.0, ge=1, le=100)  # lost: re-detect in the last box grown this much...
    redetect_full_frame_s: float = Field(4.0, gt=0, le=600)  # ...growing to the whole frame after this long


_GAINS = ControlGains()  # the control law's own defaults: the one place they are written


class ControlConfig(ConfigSection):
    yaw_kp: float = Field(_GAINS.yaw_kp, ge=0)
    yaw_ki: float = Field(_GAINS.yaw_ki, ge=0)
    forward_kp: float = Field(_GAINS.forward_kp, ge=0)
    forward_ki: float = Field(_GAINS.forward_ki, ge=0)
    lateral_kp: float = Field(_GAINS.lateral_kp, ge=0)
    yaw_dead_band_deg: float = Field(round(math.degrees(_GAINS.yaw_dead_band), 9), ge=0, le=30)
    distance_dead_band_m: float = Field(_GAINS.distance_dead_band_m, ge=0, le=20)
    filter_time_constant_s: float = Field(_GAINS.filter_time_constant_s, ge=0, le=5)
    max_accel_m_s2: float = Field(_GAINS.max_accel_m_s2, gt=0, le=20)
    max_yaw_accel_deg_s2: float = Field(round(math.degrees(_GAINS.max_yaw_accel), 9), gt=0, le=1000)


class RecordingConfig(ConfigSection):
    enabled: bool = True
    # Empty: $STATE_DIRECTORY/records under systemd, else $XDG_DATA_HOME/cloudtrack/records
    # (~/.local/share/cloudtrack/records); see companion.flight_record.records_dir.
    dir: str = ""
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
    search: SearchConfig = SearchConfig()
    control: ControlConfig = ControlConfig()
    recording: RecordingConfig = RecordingConfig()


ENV_PREFIX = "CLOUDTRACK_"
CONFIG_FILE_NAME = "companion.toml"  # looked up in /etc/cloudtrack/ and $XDG_CONFIG_HOME/cloudtrack/
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
    """Defaults, then FILE (without one: /etc/cloudtrack/companion.toml, then
    $XDG_CONFIG_HOME/cloudtrack/companion.toml, where they exist), then CLOUDTRACK_<SECTION>__<KEY>
    variables, then --set; ConfigError if not allowed."""
    full = os.environ if environ is None else environ
    return load_config(
        CompanionConfig,
        path,
        env_prefix=ENV_PREFIX,
        environ=companion_environment(full),
        assignments=assignments,
        default_files=default_config_files(CONFIG_FILE_NAME, full),
    )
