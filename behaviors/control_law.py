"""The follow control law: body velocity and yaw rate that keep a tracked person centred at a standoff.

Yaw rate comes from the box centre's horizontal angle off the optical axis; forward speed from the ground
distance to the box's foot point (flat ground, height and camera pitch), falling back to the box height
against a person's height when the foot is not usable; an optional lateral term. Each error goes through
a dead band, a first-order low-pass filter and a PI term; the output is slew-rate limited and finally
passed through `behaviors.safety_limits.apply_limits`, the single place every motion limit is enforced.
Invalid input (bad box, non-finite telemetry or time) gives a zero setpoint and a reset controller.
See docs/control-law.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from behaviors.camera_model import CameraModel
from behaviors.geolocation import foot_point, locate_pixel
from behaviors.geometry import Box
from behaviors.safety_limits import MotionLimits, apply_limits
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry

# Below this height the vehicle is on the ground (or the height is unknown): no foot-point ray, no climb.
_MIN_HEIGHT_FOR_FOOT_M = 0.5
# A foot within this many pixels of the bottom edge is probably cut off: its ray would under-estimate.
_FOOT_EDGE_PX = 2.0


@dataclass(frozen=True)
class ControlGains:
    """Gains and shaping of the law; mirrors the companion's `[control]` section (angles in radians)."""

    yaw_kp: float = 1.2  # rad/s per rad
    yaw_ki: float = 0.05  # rad/s per rad*s
    forward_kp: float = 0.8  # m/s per m
    forward_ki: float = 0.1  # m/s per m*s
    lateral_kp: float = 0.0  # m/s per m of sideways offset
    yaw_dead_band: float = math.radians(1.5)
    distance_dead_band_m: float = 0.5
    filter_time_constant_s: float = 0.15
    max_accel_m_s2: float = 2.0
    max_yaw_accel: float = math.radians(90.0)  # rad/s^2
    altitude_kp: float = 0.5  # m/s per m below the altitude floor
    target_height_m: float = 1.7  # a standing person, for the box-height fallback
    integral_leak_s: float = 1.0  # time constant of the integrals' decay inside the dead bands
    nominal_dt_s: float = 1.0 / 15.0  # first step, before two times are known
    max_dt_s: float = 0.5  # longer gaps count as this, so one late frame cannot kick the integrators


@dataclass(frozen=True)
class ControlState:
    """What the law remembers between steps: filtered errors, integrals and the last (limited) output."""

    time_s: float | None = None
    yaw_error: float = 0.0
    distance_error: float = 0.0
    yaw_integral: float = 0.0
    forward_integral: float = 0.0
    output: Setpoint = Setpoint()


@dataclass(frozen=True)
class FollowGoal:
    """What to achieve: ground distance to the target, a sideways speed (orbit), and whether descent is allowed."""

    standoff_m: float
    lateral_speed_m_s: float = 0.0
    descent_allowed: bool = False


@dataclass(frozen=True)
class DistanceEstimate:
    ground_m: float
    method: str  # "foot" (ray to the foot point) or "box_height" (pinhole size of a person)


def horizontal_angle(camera: CameraModel, box: Box) -> float:
    """Angle of the box centre off the optical axis in the image's horizontal direction; right is positive."""
    return math.atan(camera.normalised(box.cx, box.cy)[0])  # through the lens model, as geolocation


def estimate_distance(
    camera: CameraModel, telemetry: Telemetry, box: Box, target_height_m: float = 1.7
) -> DistanceEstimate | None:
    """Ground distance from the vehicle to the target; None when neither estimate is usable."""
    if not box.is_valid():
        return None
    u, v = foot_point(box)
    if telemetry.height_agl >= _MIN_HEIGHT_FOR_FOOT_M and box.y2 < camera.height - _FOOT_EDGE_PX:
        located = locate_pixel(camera, telemetry, u, v)
        if located is not None:
            return DistanceEstimate(located.ground_range_m, "foot")
    # Fallback: pinhole size of a person gives the slant range; remove the height when it is known.
    slant = camera.fy * target_height_m / box.h
    height = telemetry.height_agl if math.isfinite(telemetry.height_agl) else 0.0
    ground = math.sqrt(max(slant * slant - max(height, 0.0) ** 2, 0.0))
    return DistanceEstimate(ground, "box_height")


def _dead_band(error: float, band: float) -> float:
    if abs(error) <= band:
        return 0.0
    return error - math.copysign(band, error)


def _clamp(value: float, bound: float) -> float:
    return max(-bound, min(bound, value))


def _slew(target: float, previous: float, max_step: float) -> float:
    return previous + _clamp(target - previous, max_step)


def _integrate(
    integral: float, error: float, dt: float, proportional: float, ki: float, limit: float, leak_s: float
) -> float:
    """PI integral with anti-windup: it does not grow while the output is already saturated in the
    error's direction (conditional integration), and on its own it never asks for more than the limit."""
    if ki <= 0:
        return 0.0
    if error == 0.0:
        # Inside the dead band: let the integral leak away, so a target at rest ends in a zero output
        # instead of a creep driven by what was integrated on the way in.
        return integral * math.exp(-dt / leak_s)
    candidate = integral + error * dt
    output = proportional + ki * candidate
    if abs(output) > limit and error * output > 0:
        candidate = integral
    return _clamp(candidate, limit / ki)


def _inputs_valid(camera: CameraModel, telemetry: Telemetry, box: Box, time_s: float) -> bool:
    numbers = (
        time_s,
        telemetry.height_agl,
        telemetry.roll,
        telemetry.pitch,
        telemetry.yaw,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
    )
    return box.is_valid() and all(math.isfinite(x) for x in numbers) and camera.fx > 0 and camera.fy > 0


def follow_step(
    box: Box,
    camera: CameraModel,
    telemetry: Telemetry,
    goal: FollowGoal,
    gains: ControlGains,
    limits: MotionLimits,
    state: ControlState,
    time_s: float,
) -> tuple[Setpoint, ControlState]:
    """One control step for a trusted box at `time_s`: the limited setpoint and the law's next state."""
    if not _inputs_valid(camera, telemetry, box, time_s) or (
        state.time_s is not None and time_s < state.time_s
    ):
        return Setpoint.zero(), ControlState(time_s=time_s if math.isfinite(time_s) else None)

    fresh = state.time_s is None
    dt = gains.nominal_dt_s if fresh or state.time_s is None else min(time_s - state.time_s, gains.max_dt_s)
    alpha = 1.0 if fresh or gains.filter_time_constant_s <= 0 else dt / (gains.filter_time_constant_s + dt)

    angle = horizontal_angle(camera, box)
    yaw_error = _dead_band(angle, gains.yaw_dead_band)
    yaw_filtered = state.yaw_error + alpha * (yaw_error - state.yaw_error)
    yaw_integral = _integrate(
        state.yaw_integral,
        yaw_error,
        dt,
        gains.yaw_kp * yaw_filtered,
        gains.yaw_ki,
        limits.max_yaw_rate,
        gains.integral_leak_s,
    )
    yaw_rate = gains.yaw_kp * yaw_filtered + gains.yaw_ki * yaw_integral

    distance = estimate_distance(camera, telemetry, box, gains.target_height_m)
    forward = right = 0.0
    dist_filtered, forward_integral = 0.0, 0.0
    if distance is not None and math.isfinite(distance.ground_m):
        dist_error = _dead_band(distance.ground_m - goal.standoff_m, gains.distance_dead_band_m)
        dist_filtered = state.distance_error + alpha * (dist_error - state.distance_error)
        forward_integral = _integrate(
            state.forward_integral,
            dist_error,
            dt,
            gains.forward_kp * dist_filtered,
            gains.forward_ki,
            limits.max_speed,
            gains.integral_leak_s,
        )
        # Approach along the view direction only while the target is roughly ahead; turn first.
        forward = (gains.forward_kp * dist_filtered + gains.forward_ki * forward_integral) * max(
            math.cos(angle), 0.0
        )
        # Sideways offset of the target in metres, from the dead-banded angle so the set-point stays at zero.
        right = gains.lateral_kp * distance.ground_m * math.sin(yaw_error)
    right += goal.lateral_speed_m_s

    down = 0.0
    height = telemetry.height_agl
    if _MIN_HEIGHT_FOR_FOOT_M <= height < limits.min_altitude:
        # Climb back into the band, but only when airborne: from the ground this would be a take-off.
        down = -gains.altitude_kp * (limits.min_altitude - height)
    elif height > limits.max_altitude and goal.descent_allowed:
        down = gains.altitude_kp * (height - limits.max_altitude)

    prev = state.output
    step_h = gains.max_accel_m_s2 * dt
    d_f, d_r = forward - prev.forward, right - prev.right
    change = math.hypot(d_f, d_r)
    if change > step_h:  # horizontal acceleration limit on the vector, direction of change kept
        d_f, d_r = d_f * step_h / change, d_r * step_h / change
    wanted = Setpoint(
        prev.forward + d_f,
        prev.right + d_r,
        down,
        _slew(yaw_rate, prev.yaw_rate, gains.max_yaw_accel * dt),
    )
    out = apply_limits(wanted, limits, height, goal.descent_allowed)
    return out, ControlState(time_s, yaw_filtered, dist_filtered, yaw_integral, forward_integral, out)
