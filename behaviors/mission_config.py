"""Everything the mission state machine and the control law are tuned by, as one frozen value.

It mirrors the companion's `[behavior]`, `[control]`, `[safety]`, `[camera]` and `[backend]` sections;
`MissionConfig.from_sections` takes those sections as plain mappings (e.g. pydantic `model_dump()`), so
this package needs neither pydantic nor the companion. Angles are stored in radians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from behaviors.camera_model import CameraModel
from behaviors.control_law import ControlGains
from behaviors.safety_limits import MotionLimits


class LostAction(str, Enum):
    """What to request from the autopilot when the target stays lost (`[behavior] lost_action`)."""

    HOLD = "hold"
    LOITER = "loiter"
    RTL = "rtl"
    LAND = "land"


class ConfirmAction(str, Enum):
    """What to do once the supervisor confirms (`[behavior] on_confirm`)."""

    FOLLOW = "follow"
    HOLD = "hold"
    ORBIT = "orbit"
    SURVEY = (
        "survey"  # report the find and go on searching (back to the autopilot's mission, if it flies one)
    )


class SearchMode(str, Enum):
    """Where a search looks (`[behavior] search`): along the autopilot's own mission, or on the spot."""

    AUTO = "auto"  # along the mission when the autopilot flies it (AUTO / MISSION) at the start, else on the spot
    MISSION = "mission"  # always along the mission: the companion commands nothing until a candidate
    SPOT = "spot"  # on the spot: the companion holds the vehicle (zero or a yaw scan) while it looks


@dataclass(frozen=True)
class MissionConfig:
    camera: CameraModel = field(default_factory=lambda: CameraModel.from_hfov(640, 480, 70.0, -45.0))
    limits: MotionLimits = field(default_factory=lambda: MotionLimits.from_degrees(3.0, 1.0, 45.0, 5.0, 60.0))
    gains: ControlGains = field(default_factory=ControlGains)
    standoff_m: float = 12.0
    search_yaw_rate: float = 0.0  # rad/s, 0: no scan
    query_interval_s: float = 1.0  # keyframes to the back-end while checking a followed track
    # ... while searching or lost: with nothing trusted, a keyframe is the only way to find the target
    search_interval_s: float = 0.5
    # A search asks the back-end's fast stage first and starts a provisional track on its choice; the final
    # verdicts on the same keyframe then confirm it, move it or end it (see behaviors.mission).
    early_answer: bool = True
    # ... and when those final verdicts have not come this long after the early start (the worker sends
    # the early and the full request one after the other, each bounded by [backend] timeout_s), the
    # provisional track ends: a failed verification is not a verified target.
    final_answer_timeout_s: float = 10.0
    reverify_interval_s: float = 10.0
    lost_hold_after_s: float = 1.0
    lost_action_after_s: float = 30.0
    lost_action: LostAction = LostAction.HOLD
    on_confirm: ConfirmAction = ConfirmAction.FOLLOW
    search: SearchMode = SearchMode.AUTO
    # A search along the mission: a candidate lost this long (and not confirmed) ends, and the vehicle goes
    # back to the mission.
    lost_resume_after_s: float = 10.0
    # ... and while only looking (not engaged) this soon: the survey flies on and takes it out of view.
    lost_looking_s: float = 2.0
    orbit_speed_m_s: float = 1.0
    frame_stale_s: float = 0.5  # no tracker result for this long counts as lost
    accept_uncertain: bool = False  # may an "uncertain" verdict start tracking (after every "yes")?
    acquire_timeout_s: float = 3.0  # tracker must report a trusted box this soon after init
    arrive_tolerance_m: float = 2.0  # within this of the standoff the supervisor is asked
    approach_timeout_s: float = 60.0  # ask the supervisor anyway after following this long
    redetect_roi_scale: float = (
        3.0  # re-detection ROI on losing the target: the last box grown this many times
    )
    redetect_full_frame_s: float = 4.0  # ... growing with time lost to the whole frame after this long
    reinit_gate: float = 0.5  # largest C_box for re-initialisation, as a fraction of (width + height)
    # The tracking front-end judges every answer ([tracker] reinit_policy = "verified"; the runner sets this
    # from the front-end): the mission hands it what it accepts instead of choosing a re-init box itself.
    verified_reinit: bool = False
    rejection_radius_m: float = 5.0
    # A GCS track rectangle skips the supervisor's confirmation ([safety] gcs_track_confirms).
    operator_box_confirms: bool = False
    # A GCS decision for "the candidate awaiting" this soon after another came to await is refused: it was
    # pressed for the one before ([safety] gcs_decision_guard_s; behaviors.decision_guard).
    gcs_decision_guard_s: float = 0.75
    signature_threshold: float = 0.95

    @classmethod
    def from_sections(
        cls,
        *,
        behavior: Mapping[str, Any],
        control: Mapping[str, Any],
        safety: Mapping[str, Any],
        camera: Mapping[str, Any],
        backend: Mapping[str, Any],
    ) -> MissionConfig:
        """Build from the companion's configuration sections; missing keys keep the defaults above."""
        d = cls()
        g = ControlGains()
        cam = CameraModel.from_hfov(
            _int(camera, "width", d.camera.width),
            _int(camera, "height", d.camera.height),
            _float(camera, "hfov_deg", 70.0),
            _float(camera, "mount_pitch_deg", math.degrees(d.camera.mount_pitch)),
            _bool(camera, "stabilised", d.camera.stabilised),
        )
        limits = MotionLimits.from_degrees(
            _float(safety, "max_speed_m_s", d.limits.max_speed),
            _float(safety, "max_vertical_speed_m_s", d.limits.max_vertical_speed),
            _float(safety, "max_yaw_rate_deg_s", math.degrees(d.limits.max_yaw_rate)),
            _float(safety, "min_altitude_m", d.limits.min_altitude),
            _float(safety, "max_altitude_m", d.limits.max_altitude),
        )
        gains = ControlGains(
            yaw_kp=_float(control, "yaw_kp", g.yaw_kp),
            yaw_ki=_float(control, "yaw_ki", g.yaw_ki),
            forward_kp=_float(control, "forward_kp", g.forward_kp),
            forward_ki=_float(control, "forward_ki", g.forward_ki),
            lateral_kp=_float(control, "lateral_kp", g.lateral_kp),
            yaw_dead_band=math.radians(_float(control, "yaw_dead_band_deg", math.degrees(g.yaw_dead_band))),
            distance_dead_band_m=_float(control, "distance_dead_band_m", g.distance_dead_band_m),
            filter_time_constant_s=_float(control, "filter_time_constant_s", g.filter_time_constant_s),
            max_accel_m_s2=_float(control, "max_accel_m_s2", g.max_accel_m_s2),
            max_yaw_accel=math.radians(
                _float(control, "max_yaw_accel_deg_s2", math.degrees(g.max_yaw_accel))
            ),
        )
        return cls(
            camera=cam,
            limits=limits,
            gains=gains,
            standoff_m=_float(behavior, "standoff_m", d.standoff_m),
            search_yaw_rate=math.radians(_float(behavior, "search_yaw_rate_deg_s", 0.0)),
            query_interval_s=_float(backend, "keyframe_interval_s", d.query_interval_s),
            search_interval_s=_float(backend, "search_interval_s", d.search_interval_s),
            early_answer=_bool(backend, "early_answer", d.early_answer),
            final_answer_timeout_s=2.0 * _float(backend, "timeout_s", d.final_answer_timeout_s / 2.0),
            reverify_interval_s=_float(behavior, "reverify_interval_s", d.reverify_interval_s),
            lost_hold_after_s=_float(behavior, "lost_hold_after_s", d.lost_hold_after_s),
            lost_action_after_s=_float(behavior, "lost_action_after_s", d.lost_action_after_s),
            lost_action=LostAction(_str(behavior, "lost_action", d.lost_action.value)),
            on_confirm=ConfirmAction(_str(behavior, "on_confirm", d.on_confirm.value)),
            search=SearchMode(_str(behavior, "search", d.search.value)),
            lost_resume_after_s=_float(behavior, "lost_resume_after_s", d.lost_resume_after_s),
            lost_looking_s=_float(behavior, "lost_looking_s", d.lost_looking_s),
            orbit_speed_m_s=_float(behavior, "orbit_speed_m_s", d.orbit_speed_m_s),
            frame_stale_s=_float(safety, "frame_stale_s", d.frame_stale_s),
            accept_uncertain=_bool(behavior, "accept_uncertain", d.accept_uncertain),
            acquire_timeout_s=_float(behavior, "acquire_timeout_s", d.acquire_timeout_s),
            arrive_tolerance_m=_float(behavior, "arrive_tolerance_m", d.arrive_tolerance_m),
            approach_timeout_s=_float(behavior, "approach_timeout_s", d.approach_timeout_s),
            rejection_radius_m=_float(behavior, "rejection_radius_m", d.rejection_radius_m),
            redetect_roi_scale=_float(behavior, "redetect_roi_scale", d.redetect_roi_scale),
            redetect_full_frame_s=_float(behavior, "redetect_full_frame_s", d.redetect_full_frame_s),
            operator_box_confirms=_bool(safety, "gcs_track_confirms", d.operator_box_confirms),
            gcs_decision_guard_s=_float(safety, "gcs_decision_guard_s", d.gcs_decision_guard_s),
        )


def _float(section: Mapping[str, Any], key: str, default: float) -> float:
    value = section.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{key}: expected a finite number, got {value!r}")
    return float(value)


def _int(section: Mapping[str, Any], key: str, default: int) -> int:
    value = section.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{key}: expected an integer, got {value!r}")
    return value


def _bool(section: Mapping[str, Any], key: str, default: bool) -> bool:
    value = section.get(key, default)
    if not isinstance(value, bool):
        raise ValueError(f"{key}: expected true or false, got {value!r}")
    return value


def _str(section: Mapping[str, Any], key: str, default: str) -> str:
    value = section.get(key, default)
    if not isinstance(value, str):
        raise ValueError(f"{key}: expected a string, got {value!r}")
    return value
