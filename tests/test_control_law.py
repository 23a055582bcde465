"""Control-law properties (hypothesis): bounded by the limits, sign-correct, zero at the set-point."""

from __future__ import annotations

import math
from dataclasses import replace

from hypothesis import assume, given, settings
from hypothesis import strategies as st

from behaviors.camera_model import CameraModel
from behaviors.control_law import (
    ControlGains,
    ControlState,
    FollowGoal,
    estimate_distance,
    follow_step,
    horizontal_angle,
)
from behaviors.geometry import Box
from behaviors.safety_limits import MotionLimits
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry

CAM = CameraModel.from_hfov(640, 480, 70.0, -45.0)
LIMITS = MotionLimits.from_degrees(3.0, 1.0, 45.0, 5.0, 60.0)
GAINS = ControlGains()

any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
gains_st = st.builds(
    ControlGains,
    yaw_kp=st.floats(0.1, 10.0),
    yaw_ki=st.floats(0.0, 2.0),
    forward_kp=st.floats(0.05, 5.0),
    forward_ki=st.floats(0.0, 1.0),
    lateral_kp=st.floats(0.0, 1.0),
    filter_time_constant_s=st.floats(0.0, 2.0),
    max_accel_m_s2=st.floats(0.1, 20.0),
    max_yaw_accel=st.floats(0.1, 20.0),
)
limits_st = st.builds(
    MotionLimits,
    max_speed=st.floats(0.1, 15.0),
    max_vertical_speed=st.floats(0.0, 5.0),
    max_yaw_rate=st.floats(0.05, 3.0),
    min_altitude=st.floats(1.0, 20.0),
    max_altitude=st.floats(25.0, 200.0),
)


def foot_v(distance_m: float, height_m: float, cam: CameraModel = CAM) -> float:
    return cam.cy + cam.fy * math.tan(math.atan2(height_m, distance_m) + cam.mount_pitch)


def box_with_foot(u: float, v: float, h_px: float = 40.0) -> Box:
    return Box(u - 8.0, v - h_px, 16.0, h_px)


def run(
    box: Box, telemetry: Telemetry, goal: FollowGoal, gains: ControlGains, limits: MotionLimits, steps: int
) -> list[Setpoint]:
    state, out = ControlState(), []
    for i in range(steps):
        sp, state = follow_step(
            box, CAM, replace(telemetry, time_s=i * 0.05), goal, gains, limits, state, i * 0.05
        )
        out.append(sp)
    return out


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.tuples(any_float, any_float, any_float, any_float, any_float), min_size=1, max_size=12),
    st.one_of(st.floats(-10.0, 300.0), st.just(math.nan)),
    st.booleans(),
    gains_st,
    limits_st,
    st.floats(0.0, 5.0),
)
def test_output_always_within_limits(
    boxes: list[tuple[float, float, float, float, float]],
    height: float,
    descent: bool,
    gains: ControlGains,
    limits: MotionLimits,
    lateral: float,
) -> None:
    state = ControlState()
    goal = FollowGoal(12.0, lateral, descent)
    t = 0.0
    for x, y, w, h, dt in boxes:
        t += dt if math.isfinite(dt) else 0.05
        sp, state = follow_step(
            Box(x, y, w, h), CAM, Telemetry(t, height_agl=height), goal, gains, limits, state, t
        )
        assert sp.is_finite()
        assert sp.horizontal_speed <= limits.max_speed + 1e-9
        assert abs(sp.yaw_rate) <= limits.max_yaw_rate + 1e-9
        assert abs(sp.down) <= limits.max_vertical_speed + 1e-9
        if not descent or not math.isfinite(height) or height <= limits.min_altitude:
            assert sp.down <= 0.0  # never descends towards an unconfirmed target or below the floor
        if not math.isfinite(height) or height >= limits.max_altitude:
            assert sp.down >= 0.0


@settings(max_examples=150, deadline=None)
@given(st.floats(4.0, 300.0), st.floats(8.0, 40.0), st.integers(1, 20), gains_st, st.booleans())
def test_target_right_of_centre_gives_positive_yaw_rate(
    offset_px: float, height: float, steps: int, gains: ControlGains, left: bool
) -> None:
    assume(math.atan2(offset_px, CAM.fx) > gains.yaw_dead_band * 1.01)
    u = CAM.cx - offset_px if left else CAM.cx + offset_px
    box = box_with_foot(u, foot_v(15.0, height))
    yaw = run(box, Telemetry(0.0, height_agl=height), FollowGoal(12.0), gains, LIMITS, steps)[-1].yaw_rate
    assert (yaw < 0) if left else (yaw > 0)


@settings(max_examples=150, deadline=None)
@given(st.floats(8.0, 40.0), st.floats(0.0, 1.0), st.floats(-60.0, 60.0), st.integers(1, 20), gains_st)
def test_target_far_gives_forward_motion_and_near_gives_backward(
    height: float, extra: float, u_offset: float, steps: int, gains: ControlGains
) -> None:
    standoff = 12.0
    far_d = standoff + gains.distance_dead_band_m + 1.0 + extra * 30.0
    near_d = max(standoff - gains.distance_dead_band_m - 1.0 - extra * 5.0, 1.0)
    telemetry = Telemetry(0.0, height_agl=height)
    for d, sign in ((far_d, 1.0), (near_d, -1.0)):
        v = foot_v(d, height)
        assume(0.0 < v < CAM.height - 5.0)
        box = box_with_foot(CAM.cx + u_offset, v)
        est = estimate_distance(CAM, telemetry, box)
        assert est is not None and est.method == "foot"
        # Off-centre the same image row is a little further away; the law must see it beyond the dead band.
        assert est.ground_m >= d - 1e-9
        assume((est.ground_m - standoff) * sign > gains.distance_dead_band_m + 0.5)
        centred = estimate_distance(CAM, telemetry, box_with_foot(CAM.cx, v))
        assert centred is not None and math.isclose(centred.ground_m, d, rel_tol=1e-9)
        forward = run(box, telemetry, FollowGoal(standoff), gains, LIMITS, steps)[-1].forward
        assert forward * sign > 0


@settings(max_examples=100, deadline=None)
@given(st.floats(6.0, 50.0), st.floats(-0.9, 0.9), st.floats(-0.9, 0.9), st.integers(1, 30), gains_st)
def test_zero_at_the_set_point(
    height: float, u_frac: float, d_frac: float, steps: int, gains: ControlGains
) -> None:
    standoff = 12.0
    # Anywhere inside both dead bands counts as the set-point.
    u = CAM.cx + CAM.fx * math.tan(u_frac * gains.yaw_dead_band)
    d = standoff + d_frac * gains.distance_dead_band_m
    v = foot_v(d, height)
    assume(0.0 < v < CAM.height - 5.0)
    for sp in run(
        box_with_foot(u, v), Telemetry(0.0, height_agl=height), FollowGoal(standoff), gains, LIMITS, steps
    ):
        assert sp == Setpoint.zero()


@given(
    st.sampled_from(
        [
            Box(math.nan, 100, 10, 10),
            Box(100, 100, 0, 10),
            Box(100, 100, -5, 10),
            Box(100, math.inf, 10, 10),
        ]
    ),
    st.floats(0.1, 5.0),
)
def test_invalid_box_gives_zero_and_resets(box: Box, prior_speed: float) -> None:
    warm = ControlState(
        time_s=1.0, yaw_integral=0.5, forward_integral=3.0, output=Setpoint(prior_speed, 0, 0, 0.3)
    )
    sp, state = follow_step(
        box, CAM, Telemetry(1.1, height_agl=20.0), FollowGoal(12.0), GAINS, LIMITS, warm, 1.1
    )
    assert sp == Setpoint.zero()
    assert state.yaw_integral == 0.0 and state.forward_integral == 0.0 and state.output == Setpoint.zero()


def test_invalid_telemetry_or_time_gives_zero() -> None:
    box = box_with_foot(CAM.cx + 100, foot_v(30.0, 20.0))
    goal = FollowGoal(12.0)
    for telemetry, t in (
        (Telemetry(1.0, height_agl=math.nan), 1.0),
        (Telemetry(1.0, height_agl=20.0, yaw=math.inf), 1.0),
        (Telemetry(1.0, height_agl=20.0), math.nan),
    ):
        assert follow_step(box, CAM, telemetry, goal, GAINS, LIMITS, ControlState(), t)[0] == Setpoint.zero()
    # Time going backwards is a broken input too.
    _, state = follow_step(
        box, CAM, Telemetry(2.0, height_agl=20.0), goal, GAINS, LIMITS, ControlState(), 2.0
    )
    assert (
        follow_step(box, CAM, Telemetry(1.0, height_agl=20.0), goal, GAINS, LIMITS, state, 1.0)[0]
        == Setpoint.zero()
    )


@settings(max_examples=100, deadline=None)
@given(gains_st, st.lists(st.floats(-300, 300), min_size=2, max_size=15))
def test_slew_rate_limits_change_per_step(gains: ControlGains, offsets: list[float]) -> None:
    state, prev, dt = ControlState(), Setpoint.zero(), 0.05
    for i, off in enumerate(offsets):
        t = i * dt
        box = box_with_foot(CAM.cx + off, foot_v(12.0 + off / 10.0, 20.0))
        sp, state = follow_step(
            box, CAM, Telemetry(t, height_agl=20.0), FollowGoal(12.0), gains, LIMITS, state, t
        )
        step_dt = gains.nominal_dt_s if i == 0 else dt
        assert (
            math.hypot(sp.forward - prev.forward, sp.right - prev.right)
            <= gains.max_accel_m_s2 * step_dt + 1e-9
        )
        assert abs(sp.yaw_rate - prev.yaw_rate) <= gains.max_yaw_accel * step_dt + 1e-9
        prev = sp


def test_converges_to_the_limit_for_a_far_target_and_holds_it() -> None:
    box = box_with_foot(CAM.cx, foot_v(45.0, 20.0))
    out = run(box, Telemetry(0.0, height_agl=20.0), FollowGoal(12.0), GAINS, LIMITS, 60)
    assert math.isclose(out[-1].forward, LIMITS.max_speed)
    assert all(b.forward >= a.forward for a, b in zip(out, out[1:], strict=False))


def test_box_height_fallback_when_the_foot_is_cut_off() -> None:
    telemetry = Telemetry(0.0, height_agl=10.0)
    near_big = Box(300, 200, 60, CAM.height - 200)  # reaches the bottom edge: foot not visible
    est = estimate_distance(CAM, telemetry, near_big)
    assert est is not None and est.method == "box_height"
    slant = CAM.fy * 1.7 / near_big.h
    assert math.isclose(est.ground_m, math.sqrt(max(slant**2 - 100.0, 0.0)))
    # Unknown height: the pinhole size alone, and it still drives the sign of the forward term.
    small = Box(300, 150, 10, 20)
    for unknown in (0.0, math.nan):  # on the ground or not reported
        est = estimate_distance(CAM, Telemetry(0.0, height_agl=unknown), small)
        assert est is not None and est.method == "box_height" and est.ground_m > 12.0
    sp = run(small, Telemetry(0.0, height_agl=0.0), FollowGoal(12.0), GAINS, LIMITS, 5)[-1]
    assert sp.forward > 0 and sp.down == 0.0  # no climb from the ground: that would be a take-off


def test_climbs_back_into_the_altitude_band_but_never_descends_unconfirmed() -> None:
    box = box_with_foot(CAM.cx, 300.0)
    low = run(box, Telemetry(0.0, height_agl=3.0), FollowGoal(12.0), GAINS, LIMITS, 3)[-1]
    assert low.down < 0
    high = Telemetry(0.0, height_agl=70.0)
    assert run(box, high, FollowGoal(12.0), GAINS, LIMITS, 3)[-1].down == 0.0
    assert run(box, high, FollowGoal(12.0, descent_allowed=True), GAINS, LIMITS, 3)[-1].down > 0


def test_orbit_adds_sideways_speed_and_lateral_term_moves_towards_the_target() -> None:
    box = box_with_foot(CAM.cx, foot_v(12.0, 20.0))
    orbit = run(
        box, Telemetry(0.0, height_agl=20.0), FollowGoal(12.0, lateral_speed_m_s=1.0), GAINS, LIMITS, 40
    )[-1]
    assert math.isclose(orbit.right, 1.0) and orbit.forward == 0.0
    right_box = box_with_foot(CAM.cx + 150, foot_v(12.0, 20.0))
    lateral = replace(GAINS, lateral_kp=0.3)
    assert (
        run(right_box, Telemetry(0.0, height_agl=20.0), FollowGoal(12.0), lateral, LIMITS, 20)[-1].right > 0
    )


def test_horizontal_angle_uses_the_intrinsics() -> None:
    box = Box.from_center(CAM.cx + CAM.fx, 200, 10, 10)
    assert math.isclose(horizontal_angle(CAM, box), math.pi / 4)


def _image_box(
    cam: CameraModel, x: float, y: float, yaw: float, height: float, person: tuple[float, float]
) -> Box | None:
    """Pinhole image of a 1.7 m, 0.5 m wide person standing at `person` (north, east), stabilised camera."""
    pts = []
    for up, side in ((0.0, -0.25), (0.0, 0.25), (1.7, -0.25), (1.7, 0.25)):
        dn, de = person[0] - x, person[1] - y
        fwd = dn * math.cos(yaw) + de * math.sin(yaw)
        right = -dn * math.sin(yaw) + de * math.cos(yaw) + side
        down = height - up
        c, s = math.cos(cam.mount_pitch), math.sin(cam.mount_pitch)
        z = c * fwd - s * down  # camera axis: body forward pitched by the mount
        yc = s * fwd + c * down
        if z <= 0.1:
            return None
        pts.append((cam.cx + cam.fx * right / z, cam.cy + cam.fy * yc / z))
    us, vs = [p[0] for p in pts], [p[1] for p in pts]
    return Box.from_xyxy(min(us), min(vs), max(us), max(vs))


def test_closed_loop_settles_centred_at_the_standoff() -> None:
    """Kinematic vehicle obeying the setpoints exactly: it turns to the person and stops at the standoff."""
    person = (30.0, 12.0)
    x = y = yaw = 0.0
    height, dt, standoff = 20.0, 1.0 / 15.0, 12.0
    state = ControlState()
    for i in range(int(40 / dt)):
        t = i * dt
        box = _image_box(CAM, x, y, yaw, height, person)
        assert box is not None and 0 <= box.cx < CAM.width, f"target left the image at t={t:.1f}"
        sp, state = follow_step(
            box, CAM, Telemetry(t, height_agl=height, yaw=yaw), FollowGoal(standoff), GAINS, LIMITS, state, t
        )
        x += (sp.forward * math.cos(yaw) - sp.right * math.sin(yaw)) * dt
        y += (sp.forward * math.sin(yaw) + sp.right * math.cos(yaw)) * dt
        yaw += sp.yaw_rate * dt
    ground = math.hypot(person[0] - x, person[1] - y)
    assert abs(ground - standoff) < GAINS.distance_dead_band_m + 0.3
    final = _image_box(CAM, x, y, yaw, height, person)
    assert final is not None and abs(horizontal_angle(CAM, final)) < GAINS.yaw_dead_band + math.radians(0.2)
    # At rest inside both dead bands the integrals have leaked away: the vehicle stops.
    assert sp.horizontal_speed < 0.01 and abs(sp.yaw_rate) < 0.005


def test_closed_loop_keeps_a_walking_person_in_view_near_the_standoff() -> None:
    x = y = yaw = 0.0
    height, dt, standoff = 20.0, 1.0 / 15.0, 12.0
    state, late = ControlState(), []
    for i in range(int(60 / dt)):
        t = i * dt
        person = (25.0 + 0.8 * t, 5.0 + 1.0 * t)  # 1.3 m/s, across the initial view
        box = _image_box(CAM, x, y, yaw, height, person)
        assert box is not None and 0 <= box.cx < CAM.width, f"target left the image at t={t:.1f}"
        sp, state = follow_step(
            box, CAM, Telemetry(t, height_agl=height, yaw=yaw), FollowGoal(standoff), GAINS, LIMITS, state, t
        )
        x += (sp.forward * math.cos(yaw) - sp.right * math.sin(yaw)) * dt
        y += (sp.forward * math.sin(yaw) + sp.right * math.cos(yaw)) * dt
        yaw += sp.yaw_rate * dt
        if t > 40:
            late.append(math.hypot(person[0] - x, person[1] - y))
    # The integral term removes most of the lag a P-only law would keep (1.3 m/s / 0.8 = 1.6 m).
    assert max(abs(d - standoff) for d in late) < 1.5


def test_product_defaults_reach_a_person_walking_at_1_5_m_s() -> None:
    """The shipped `[control]` gains catch up with a walker soon enough for the supervisor to be asked.

    The vehicle's velocity follows the setpoint with a 0.5 s lag (a multirotor is not kinematic). The old
    defaults (0.4 / 0.02) needed 21 s here and never arrived in SITL.
    """
    from behaviors.mission_config import MissionConfig
    from companion.config import CompanionConfig

    cfg = CompanionConfig()
    mission = MissionConfig.from_sections(
        behavior=cfg.behavior.model_dump(),
        control=cfg.control.model_dump(),
        safety=cfg.safety.model_dump(),
        camera=cfg.camera.model_dump(),
        backend=cfg.backend.model_dump(),
    )
    assert mission.gains == GAINS  # the behaviour's own defaults are the product's
    x = y = yaw = vn = ve = 0.0
    height, dt, tau = 20.0, 1.0 / 15.0, 0.5
    state, arrived = ControlState(), None
    for i in range(int(15 / dt)):
        t = i * dt
        person = (25.0 + 0.9 * t, 5.0 + 1.2 * t)  # 1.5 m/s
        box = _image_box(mission.camera, x, y, yaw, height, person)
        assert box is not None and 0 <= box.cx < mission.camera.width, f"target left the image at t={t:.1f}"
        sp, state = follow_step(
            box,
            mission.camera,
            Telemetry(t, height_agl=height, yaw=yaw),
            FollowGoal(mission.standoff_m),
            mission.gains,
            mission.limits,
            state,
            t,
        )
        alpha = dt / (tau + dt)
        vn += alpha * (sp.forward * math.cos(yaw) - sp.right * math.sin(yaw) - vn)
        ve += alpha * (sp.forward * math.sin(yaw) + sp.right * math.cos(yaw) - ve)
        x, y, yaw = x + vn * dt, y + ve * dt, yaw + sp.yaw_rate * dt
        if (
            t > 1.0
            and abs(math.hypot(person[0] - x, person[1] - y) - mission.standoff_m)
            < mission.arrive_tolerance_m
        ):
            arrived = t
            break
    assert arrived is not None, "never came within arrive_tolerance_m of the standoff in 15 s"
