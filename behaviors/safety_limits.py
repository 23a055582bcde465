"""The one place every motion limit is enforced. Every setpoint bound for the autopilot passes through here.

Limits: horizontal speed (vector magnitude, direction kept), vertical speed, yaw rate, and the altitude
band: no descent below the floor or towards a target the supervisor has not confirmed, no climb above
the ceiling, and no vertical motion at all while the height is unknown. Non-finite input gives zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from behaviors.setpoint import Setpoint


@dataclass(frozen=True)
class MotionLimits:
    max_speed: float  # m/s, horizontal
    max_vertical_speed: float  # m/s
    max_yaw_rate: float  # rad/s
    min_altitude: float  # m above ground
    max_altitude: float  # m above ground

    @classmethod
    def from_degrees(
        cls,
        max_speed: float,
        max_vertical_speed: float,
        max_yaw_rate_deg_s: float,
        min_altitude: float,
        max_altitude: float,
    ) -> MotionLimits:
        return cls(
            max_speed, max_vertical_speed, math.radians(max_yaw_rate_deg_s), min_altitude, max_altitude
        )


def _clamp(value: float, bound: float) -> float:
    return max(-bound, min(bound, value))


def apply_limits(
    setpoint: Setpoint,
    limits: MotionLimits,
    height_agl: float | None,
    descent_allowed: bool = False,
) -> Setpoint:
    """The setpoint with every limit applied; `descent_allowed` only once the target is confirmed."""
    if not setpoint.is_finite():
        return Setpoint.zero()
    forward, right = setpoint.forward, setpoint.right
    speed = math.hypot(forward, right)
    if speed > limits.max_speed > 0:
        scale = limits.max_speed / speed
        forward, right = forward * scale, right * scale
    elif limits.max_speed <= 0:
        forward = right = 0.0

    down = _clamp(setpoint.down, limits.max_vertical_speed)
    if height_agl is None or not math.isfinite(height_agl):
        down = 0.0
    else:
        if down > 0 and (not descent_allowed or height_agl <= limits.min_altitude):
            down = 0.0  # never descend below the floor or towards an unconfirmed target
        if down < 0 and height_agl >= limits.max_altitude:
            down = 0.0  # never climb above the ceiling

    return Setpoint(forward, right, down, _clamp(setpoint.yaw_rate, limits.max_yaw_rate))
