"""Multicopter kinematics for the autopilot simulator: velocity tracking under acceleration and yaw limits.

Pure functions over frozen dataclasses; the simulator's clock calls `step`. Not a flight-dynamics model:
the vehicle's velocity follows the commanded velocity as fast as `max_accel` allows, its yaw rate follows
the commanded yaw rate within `max_yaw_accel`, and a steady wind pushes it by the fraction its position
controller does not reject. Roll and pitch are the tilt that produces the current acceleration, so the
camera sees the vehicle lean as a real one does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

GRAVITY = 9.80665


@dataclass(frozen=True)
class VehicleLimits:
    max_accel: float = 3.0  # m/s^2, horizontal
    max_vertical_accel: float = 2.0  # m/s^2
    max_speed: float = 12.0  # m/s, horizontal
    max_vertical_speed: float = 3.0  # m/s
    max_yaw_rate: float = math.radians(90.0)  # rad/s
    max_yaw_accel: float = math.radians(180.0)  # rad/s^2


@dataclass(frozen=True)
class Wind:
    north: float = 0.0  # m/s, the air mass moves towards north
    east: float = 0.0
    rejection: float = 0.8  # fraction of the wind the position/velocity controller cancels


@dataclass(frozen=True)
class VehicleState:
    """NED position (m) from home, NED velocity (m/s), yaw (rad, 0 = north, clockwise) and yaw rate."""

    north: float = 0.0
    east: float = 0.0
    down: float = -20.0
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    yaw: float = 0.0
    yaw_rate: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0

    @property
    def height(self) -> float:
        return -self.down


@dataclass(frozen=True)
class VelocityCommand:
    """What the flight mode asks for: NED velocity and yaw rate (rad/s)."""

    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    yaw_rate: float = 0.0


def body_to_ned(forward: float, right: float, yaw: float) -> tuple[float, float]:
    """A body-frame horizontal vector (forward, right) rotated into (north, east) by the heading."""
    c, s = math.cos(yaw), math.sin(yaw)
    return forward * c - right * s, forward * s + right * c


def ned_to_body(north: float, east: float, yaw: float) -> tuple[float, float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return north * c + east * s, -north * s + east * c


def _toward(current: float, target: float, max_step: float) -> float:
    return current + max(-max_step, min(max_step, target - current))


def wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def step(
    state: VehicleState,
    command: VelocityCommand,
    dt: float,
    limits: VehicleLimits = VehicleLimits(),
    wind: Wind = Wind(),
    ground_down: float = 0.0,
) -> VehicleState:
    """The state `dt` seconds later. The vehicle never goes below the ground (down <= ground_down)."""
    if dt <= 0:
        return state
    # Command saturation, the way an autopilot clamps its own velocity targets.
    cn, ce = command.vn, command.ve
    speed = math.hypot(cn, ce)
    if speed > limits.max_speed:
        cn, ce = cn * limits.max_speed / speed, ce * limits.max_speed / speed
    cd = max(-limits.max_vertical_speed, min(limits.max_vertical_speed, command.vd))
    cyr = max(-limits.max_yaw_rate, min(limits.max_yaw_rate, command.yaw_rate))

    # Horizontal acceleration limited as a vector so the direction of the change is kept.
    dn, de = cn - state.vn, ce - state.ve
    dv = math.hypot(dn, de)
    max_dv = limits.max_accel * dt
    if dv > max_dv:
        dn, de = dn * max_dv / dv, de * max_dv / dv
    vn, ve = state.vn + dn, state.ve + de
    vd = _toward(state.vd, cd, limits.max_vertical_accel * dt)
    yaw_rate = _toward(state.yaw_rate, cyr, limits.max_yaw_accel * dt)

    drift = 1.0 - wind.rejection
    north = state.north + (vn + wind.north * drift) * dt
    east = state.east + (ve + wind.east * drift) * dt
    down = state.down + vd * dt
    if down > ground_down:
        down, vd = ground_down, 0.0
    yaw = wrap_pi(state.yaw + yaw_rate * dt)

    # Tilt that produces the acceleration just applied (forward acceleration pitches the nose down).
    a_fwd, a_right = ned_to_body(dn / dt, de / dt, yaw)
    pitch = -math.atan2(a_fwd, GRAVITY)
    roll = math.atan2(a_right, GRAVITY)
    return replace(
        state,
        north=north,
        east=east,
        down=down,
        vn=vn,
        ve=ve,
        vd=vd,
        yaw=yaw,
        yaw_rate=yaw_rate,
        roll=roll,
        pitch=pitch,
    )
