"""The vehicle's camera and motion limits, and what its search is for: the [camera], [safety] and [search]
sections of the companion's configuration, the keyframe timing of its [backend] section and the verdicts its
[behavior] section counts as found.

They live here, not in `companion/config.py`, because the ground tool reads them too: `cloudtrack-gcs survey`
sizes its lanes from the camera's footprint, keeps the survey inside the altitude band and near the vehicle,
and plans for a probability of detection from the keyframes the companion will take (how often, how wide).
Defaults are mirrored in `config/companion.toml` (tests/test_config_defaults.py). `load_vehicle_sections`
reads just these from the companion's configuration file (and its CLOUDTRACK_<SECTION>__* variables), as
the companion would.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from cloudtrack.config_files import ConfigSection, default_config_files, load_config

COMPANION_CONFIG_NAME = "companion.toml"  # looked up in /etc/cloudtrack/ and $XDG_CONFIG_HOME/cloudtrack/


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
    # The far edge of the ground the camera searches (coverage, and a survey's lane spacing): beyond it the
    # pixels are too coarse to find a person (at 640 px and 70 deg a 1.7 m person is 18 px tall at 50 m).
    search_range_m: float = Field(50.0, gt=1, le=2000)
    # The shutter time a survey planned for a POD assumes (`cloudtrack-gcs survey --pod`): motion blur bounds
    # its speed. 1/500 s is a small camera's daylight auto-exposure; set the longer one of dusk or shade.
    exposure_s: float = Field(0.002, gt=0, le=1)
    # Lens calibration (OpenCV's model; companion/vision/camera_calibration.py). Empty: an ideal pinhole from
    # hfov_deg. Either a file (cv2.FileStorage YAML/XML/JSON, or a ROS camera_calibration YAML) or inline:
    # camera_matrix = [fx, 0, cx, 0, fy, cy, 0, 0, 1] at width x height, distortion = [k1, k2, p1, p2, k3].
    calibration_file: str = ""
    camera_matrix: list[float] = Field(default_factory=list)
    distortion: list[float] = Field(default_factory=list)

    @model_validator(mode="after")
    def _calibration_shape(self) -> CameraConfig:
        if len(self.camera_matrix) not in (0, 9):
            raise ValueError(f"camera_matrix takes 9 numbers (row-major 3x3), got {len(self.camera_matrix)}")
        if self.distortion and not self.camera_matrix:
            raise ValueError("distortion needs camera_matrix (or use calibration_file)")
        if len(self.distortion) not in (0, 4, 5, 8, 12):
            raise ValueError(f"distortion takes 4, 5, 8 or 12 coefficients, got {len(self.distortion)}")
        return self


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
    telemetry_stale_s: float = Field(1.0, gt=0, le=10)  # older altitude/position counts as missing: hold
    setpoint_max_age_s: float = Field(0.5, gt=0, le=5)  # older setpoints are never sent (zero instead)
    gcs_track_confirms: bool = False  # may a GCS track rectangle skip the supervisor's confirmation?
    # A GCS confirm/reject of "the candidate awaiting" (candidate 0) this soon after another came to await
    # is refused ("press again"): it was pressed for the one before.
    gcs_decision_guard_s: float = Field(0.75, ge=0, le=10)
    # `cloudtrack-gcs survey` refuses an area farther than this from the vehicle (a typo, or latitude and
    # longitude swapped, puts it in another country).
    max_survey_distance_m: float = Field(3000.0, gt=0, le=100_000)

    @model_validator(mode="after")
    def _altitude_band(self) -> SafetyConfig:
        if self.min_altitude_m >= self.max_altitude_m:
            raise ValueError(
                f"min_altitude_m ({self.min_altitude_m}) must be below max_altitude_m ({self.max_altitude_m})"
            )
        return self


class SearchConfig(ConfigSection):
    """What the search's probability-of-detection (POD) map is for (cloudtrack/pod_map.py): the companion lays
    it in flight and the survey planner plans for it, so both read this section."""

    # The class the map is for when the mission names no superset (the back-end then derives it).
    target_class: str = Field("person", min_length=1, max_length=64)
    # A person is found standing or lying; the curve was measured on upright people (docs/operations.md).
    posture: Literal["standing", "lying"] = "standing"
    target_height_m: float = Field(1.7, ge=0.3, le=3.0)  # a person's height (lying: their length)
    target_pod: float = Field(0.8, gt=0, lt=1)  # the POD the operator plans for: the share at/above it
    # A detection curve file of one's own (`cloudtrack-backend pod-curve`); empty: the shipped curve.
    curve_file: str = ""
    # A place not looked at for this long: the next look starts a new, independent pass.
    pass_gap_s: float = Field(10.0, ge=1, le=600)


class KeyframeTiming(ConfigSection):
    """The keys of the companion's [backend] section (`companion.config.BackendConfig` builds on this) that
    say which keyframes the back-end sees while searching: the survey planner lays them as the map will."""

    search_interval_s: float = Field(0.5, gt=0, le=60)  # queries while searching or lost
    max_keyframe_width: int = Field(640, ge=64, le=4096)


class _BackendKeyframes(KeyframeTiming):
    model_config = ConfigDict(extra="ignore", frozen=True)  # the rest of [backend] is the companion's


class VerdictPolicy(ConfigSection):
    """The key of the companion's [behavior] section (`companion.config.BehaviorConfig` builds on this) that
    says which verdicts count as found, on the map and so in the survey planner."""

    accept_uncertain: bool = False  # may an "uncertain" verdict start tracking (after every "yes")


class _BehaviorVerdicts(VerdictPolicy):
    model_config = ConfigDict(extra="ignore", frozen=True)  # the rest of [behavior] is the companion's


class VehicleSections(BaseModel):
    """The companion configuration's [camera], [safety], [search], [backend]'s keyframe timing and
    [behavior]'s verdict policy; its other sections and keys are not read here."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    camera: CameraConfig = CameraConfig()
    safety: SafetyConfig = SafetyConfig()
    search: SearchConfig = SearchConfig()
    backend: _BackendKeyframes = _BackendKeyframes()
    behavior: _BehaviorVerdicts = _BehaviorVerdicts()


def load_vehicle_sections(
    path: Path | None = None, environ: Mapping[str, str] | None = None
) -> VehicleSections:
    """`VehicleSections` as the companion reads them: defaults, then FILE (without one:
    /etc/cloudtrack/companion.toml, then $XDG_CONFIG_HOME/cloudtrack/companion.toml, where they exist), then
    the CLOUDTRACK_<SECTION>__* variables of those sections; ConfigError if not allowed."""
    import os

    full = os.environ if environ is None else environ
    prefixes = tuple(f"CLOUDTRACK_{name.upper()}__" for name in VehicleSections.model_fields)
    ours = {k: v for k, v in full.items() if k.startswith(prefixes)}
    return load_config(
        VehicleSections,
        path,
        environ=ours,
        default_files=default_config_files(COMPANION_CONFIG_NAME, full),
    )
