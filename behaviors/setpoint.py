"""A velocity command in the vehicle's body frame, the only thing the companion asks the autopilot to fly."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Setpoint:
    """Body frame (FRD): forward, right, down velocities in m/s and yaw rate in rad/s (positive = clockwise)."""

    forward: float = 0.0
    right: float = 0.0
    down: float = 0.0
    yaw_rate: float = 0.0

    @classmethod
    def zero(cls) -> Setpoint:
        return cls()

    def is_finite(self) -> bool:
        return all(math.isfinite(v) for v in (self.forward, self.right, self.down, self.yaw_rate))

    @property
    def horizontal_speed(self) -> float:
        return math.hypot(self.forward, self.right)
