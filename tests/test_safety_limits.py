from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from behaviors.safety_limits import MotionLimits, apply_limits
from behaviors.setpoint import Setpoint

LIMITS = MotionLimits.from_degrees(3.0, 1.0, 45.0, 5.0, 60.0)
values = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(values, values, values, values, st.one_of(st.none(), st.floats(-10, 200)), st.booleans())
def test_output_always_within_limits(
    f: float, r: float, d: float, y: float, h: float | None, descent: bool
) -> None:
    out = apply_limits(Setpoint(f, r, d, y), LIMITS, h, descent)
    assert out.is_finite()
    assert out.horizontal_speed <= LIMITS.max_speed + 1e-9
    assert abs(out.down) <= LIMITS.max_vertical_speed + 1e-9
    assert abs(out.yaw_rate) <= LIMITS.max_yaw_rate + 1e-9
    if h is None or h <= LIMITS.min_altitude or not descent:
        assert out.down <= 0.0
    if h is None or h >= LIMITS.max_altitude:
        assert out.down >= 0.0


def test_speed_clamp_keeps_direction() -> None:
    out = apply_limits(Setpoint(6.0, 8.0, 0, 0), LIMITS, 20.0)
    assert math.isclose(out.horizontal_speed, 3.0)
    assert math.isclose(out.forward / out.right, 6.0 / 8.0)


def test_non_finite_gives_zero() -> None:
    assert apply_limits(Setpoint(float("nan"), 1, 0, 0.1), LIMITS, 20.0) == Setpoint.zero()


def test_descent_only_when_confirmed_and_above_floor() -> None:
    assert apply_limits(Setpoint(down=0.5), LIMITS, 20.0, descent_allowed=False).down == 0.0
    assert apply_limits(Setpoint(down=0.5), LIMITS, 20.0, descent_allowed=True).down == 0.5
    assert apply_limits(Setpoint(down=0.5), LIMITS, 4.0, descent_allowed=True).down == 0.0
    assert apply_limits(Setpoint(down=-0.5), LIMITS, 61.0).down == 0.0
    assert apply_limits(Setpoint(down=-0.5), LIMITS, None).down == 0.0
