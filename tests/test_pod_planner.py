"""Planning a survey for a POD (behaviors/pod_planner.py): the speed bounds, the lane model's pieces, and the
search's choice, as tables. The curves here are made up for the tests (never the shipped one)."""

from __future__ import annotations

import math

import pytest

from behaviors.apparent_size import TargetShape
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import SIZE_EDGES_PX, CurveBin, DetectionCurve
from behaviors.geolocation import offset_to_latlon
from behaviors.pod_planner import (
    TIE_S,
    Keyframing,
    LaneProfile,
    PodSearch,
    PodTarget,
    PodUnreachable,
    SpeedBounds,
    area_pod,
    merged_share,
    pass_pod,
    speed_bounds,
)
from behaviors.survey_planner import SurveyError, SurveySettings, check_polygon, plan_checked

ORIGIN = (47.397742, 8.545594)
NADIR = CameraModel.from_hfov(640, 480, 70.0, -90.0)
OBLIQUE = CameraModel.from_hfov(640, 480, 70.0, -45.0)


def step_curve(from_px: float, p: float) -> DetectionCurve:
    """A curve that finds a target of `from_px` or more with probability `p`, a smaller one never."""
    bins = tuple(
        CurveBin(lo, hi, 100, round(100 * p), round(100 * p)) if lo >= from_px else CurveBin(lo, hi, 100)
        for lo, hi in zip(SIZE_EDGES_PX, SIZE_EDGES_PX[1:], strict=False)
    )
    return DetectionCurve("person", bins)


STANDING = TargetShape.person("standing")
TARGET = PodTarget(step_curve(16.0, 0.7), STANDING)


def rectangle(width: float, height: float) -> tuple[tuple[float, float], ...]:
    return check_polygon(
        [offset_to_latlon(*ORIGIN, n, e) for n, e in ((0, 0), (0, width), (height, width), (height, 0))]
    )


def settings(camera: CameraModel = OBLIQUE, low: float = 5.0, high: float = 60.0) -> SurveySettings:
    return SurveySettings(
        altitude_m=high,
        overlap=0.0,
        camera=camera,
        search_range_m=50.0,
        min_altitude_m=low,
        max_altitude_m=high,
    )


# ------------------------------------------------------------------------------------- speed bounds
@pytest.mark.parametrize("altitude", [10.0, 20.0, 40.0])
def test_a_nadir_cameras_speed_bounds_are_the_textbook_ones(altitude: float) -> None:
    keyframing = Keyframing(interval_s=0.5, exposure_s=0.002, max_blur_px=1.0, max_speed_m_s=12.0)
    bounds = speed_bounds(NADIR, 50.0, altitude, TARGET, keyframing)
    # Everything moves fx / depth pixels per metre flown; the target's top, 1.7 m up, is the nearest.
    assert bounds.blur_m_s == pytest.approx((altitude - 1.7) / (0.002 * NADIR.fx), rel=1e-3)
    # The footprint's length along the lane is 2 h tan(vfov / 2) = 2 h (240 / fy), one per keyframe.
    assert bounds.keyframes_m_s == pytest.approx(2 * altitude * 240 / NADIR.fy / 0.5, rel=1e-6)
    assert bounds.autopilot_m_s == 12.0
    assert bounds.limit_m_s == min(bounds.blur_m_s, bounds.keyframes_m_s, 12.0)


def test_a_longer_exposure_or_a_smaller_keyframe_moves_the_blur_bound() -> None:
    base = speed_bounds(OBLIQUE, 50.0, 15.0, TARGET, Keyframing())
    longer = speed_bounds(OBLIQUE, 50.0, 15.0, TARGET, Keyframing(exposure_s=0.004))
    half = speed_bounds(
        OBLIQUE, 50.0, 15.0, PodTarget(TARGET.curve, STANDING, keyframe_width=320), Keyframing()
    )
    assert longer.blur_m_s == pytest.approx(base.blur_m_s / 2)
    assert half.blur_m_s == pytest.approx(base.blur_m_s * 2)  # blur is counted in keyframe pixels
    assert SpeedBounds(80.0, 9.0, 10.0).limit_m_s == 9.0


# ---------------------------------------------------------------------------------- the lane model
def profile(*rows: tuple[float, ...]) -> LaneProfile:
    return LaneProfile(altitude_m=20.0, dx_m=1.0, da_m=1.0, a0_m=0.0, rows=rows)


SPOT = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # one metre of ground along the lane where a look finds it
STRIP = (0.0,) * 5 + (0.6,) * 20 + (0.0,) * 5  # 20 m where a look finds it with 0.6


@pytest.mark.parametrize(
    ("row", "step_m", "expected"),
    [
        (SPOT, 0.5, 1.0),  # keyframes closer than the spot is long: always one on it
        (SPOT, 1.0, 1.0),
        (SPOT, 2.0, 0.5),  # one keyframe in two places lands on it
        (SPOT, 4.0, 0.25),
        (STRIP, 5.0, 0.6),  # a pass's best look: many looks at 0.6 are one look at 0.6
        (STRIP, 20.0, 0.6),
        (STRIP, 40.0, 0.3),  # keyframes 40 m apart: half the places are in none
        ((0.0,) * 8, 1.0, 0.0),
    ],
)
def test_one_pass_counts_its_best_look_wherever_the_keyframes_fall(
    row: tuple[float, ...], step_m: float, expected: float
) -> None:
    assert pass_pod(profile(row), step_m) == (pytest.approx(expected, abs=0.03),)


@pytest.mark.parametrize(
    ("lanes", "merged", "expected"),
    [
        (1, 0.0, 0.5),
        (3, 0.0, 1 - 0.5**3),  # every lane in reach: three independent passes
        (3, 1.0, 1 - 0.5**2),  # near the ends two neighbours are one pass: two passes at either end
        (3, 0.5, 0.5 * (1 - 0.5**3) + 0.5 * (1 - 0.5**2)),
    ],
)
def test_lanes_in_reach_are_independent_passes_except_where_they_turn(
    lanes: int, merged: float, expected: float
) -> None:
    passes = (0.5,) * 100  # one pass finds it with 0.5 anywhere within 100 m across
    assert area_pod(passes, 1.0, lanes, 10.0, merged) == pytest.approx(expected)


def test_a_place_out_of_every_lanes_reach_has_no_pod() -> None:
    passes = (0.8,) * 5  # a lane reaches 5 m to either side: half of each 20 m band is never seen
    assert area_pod(passes, 1.0, 4, 20.0) == pytest.approx(0.8 * 0.5)
    # Many lanes (the bands between the sides are alike, and counted once) give the same share.
    assert area_pod(passes, 1.0, 40, 20.0) == pytest.approx(0.8 * 0.5)


@pytest.mark.parametrize(
    ("speed", "gap_s", "expected"),
    [
        (10.0, 10.0, 2 * (100 - 30 + 40) / 2 / 300),  # (2 y + band - depth) / speed < gap for y < 55 m
        (1.0, 10.0, 2 * (10 - 30 + 40) / 2 / 300),
        (1.0, 1.0, 2 * (1 - 30 + 40) / 2 / 300),
        (10.0, 100.0, 1.0),  # the whole lane is one pass with its neighbours
    ],
)
def test_the_share_of_a_lane_where_the_map_joins_it_to_its_neighbour(
    speed: float, gap_s: float, expected: float
) -> None:
    assert merged_share(300.0, 30.0, 40.0, speed, gap_s) == pytest.approx(expected)


# ------------------------------------------------------------------------------------------ search
AREA = rectangle(200.0, 120.0)


def test_the_chosen_plan_reaches_the_pod_within_its_bounds() -> None:
    search = PodSearch(AREA, settings(), TARGET, Keyframing())
    choice = search.choose(0.8)
    assert choice.pod >= 0.8
    assert 5.0 <= choice.altitude_m <= 60.0
    assert Keyframing().min_speed_m_s <= choice.speed_m_s <= choice.bounds.limit_m_s
    plan = plan_checked(AREA, choice.settings(search.settings))
    assert plan.lanes == choice.lanes and plan.spacing_m == pytest.approx(choice.spacing_m)
    assert plan.speed_m_s == choice.speed_m_s and plan.time_s == pytest.approx(choice.time_s, rel=1e-5)
    assert plan.spacing_m <= plan.swath_m  # no gaps between the lanes


def test_no_plan_the_search_weighs_is_faster_and_reaches_the_pod() -> None:
    search = PodSearch(AREA, settings(low=10.0, high=40.0), TARGET, Keyframing())
    choice = search.choose(0.75)
    for altitude in search.altitudes:
        for lanes in search.lane_counts(altitude):
            for speed in search.speeds(altitude):
                if search.time_s(altitude, lanes, speed) < choice.time_s - TIE_S:
                    assert search.pod(altitude, lanes, speed) < 0.75, (altitude, lanes, speed)


def test_a_higher_pod_takes_no_less_time() -> None:
    search = PodSearch(AREA, settings(), TARGET, Keyframing())
    times = [search.choose(pod).time_s for pod in (0.5, 0.7, 0.85, 0.9)]
    assert times == sorted(times)


def test_held_altitude_and_speed_are_kept() -> None:
    search = PodSearch(AREA, settings(), TARGET, Keyframing(), altitude_m=20.0, speed_m_s=3.0)
    choice = search.choose(0.7)
    assert (choice.altitude_m, choice.speed_m_s) == (20.0, 3.0)


def test_a_slower_autopilot_or_a_longer_exposure_slows_the_plan() -> None:
    fast = PodSearch(AREA, settings(), TARGET, Keyframing(max_speed_m_s=12.0)).choose(0.8)
    slow = PodSearch(AREA, settings(), TARGET, Keyframing(max_speed_m_s=3.0)).choose(0.8)
    assert slow.speed_m_s <= 3.0 < fast.speed_m_s
    assert slow.time_s > fast.time_s
    dusk = PodSearch(AREA, settings(), TARGET, Keyframing(exposure_s=0.02)).choose(0.8)
    assert dusk.speed_m_s <= dusk.bounds.blur_m_s < fast.bounds.blur_m_s


def test_an_unreachable_pod_names_the_closest_plan() -> None:
    weak = PodTarget(step_curve(16.0, 0.3), STANDING)
    search = PodSearch(AREA, settings(low=30.0, high=40.0), weak, Keyframing())
    with pytest.raises(PodUnreachable) as err:
        search.choose(0.99)
    best = err.value.best
    assert 0 < best.pod < 0.99 and err.value.pod == 0.99
    assert search.choose(round(best.pod - 0.02, 2)).time_s <= best.time_s  # a little less is reachable


def test_a_target_never_found_is_unreachable() -> None:
    blind = PodTarget(step_curve(math.inf, 0.0), STANDING)
    with pytest.raises(PodUnreachable) as err:
        PodSearch(AREA, settings(), blind, Keyframing()).choose(0.5)
    assert err.value.best.pod < 0.05  # 0 of 100 frames at every size: the fit's half a frame, no more


@pytest.mark.parametrize("pod", [0.0, 1.0, 1.5, -0.2])
def test_a_pod_outside_0_1_is_refused(pod: float) -> None:
    with pytest.raises(SurveyError, match=r"^a POD to plan for is between 0 and 1"):
        PodSearch(AREA, settings(), TARGET, Keyframing()).choose(pod)
