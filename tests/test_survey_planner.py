"""The survey planner (behaviors/survey_planner.py): lanes, items, figures and every refusal, as tables."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from behaviors.camera_footprint import swath_width_m
from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import DO_CHANGE_SPEED, NAV_TAKEOFF, NAV_WAYPOINT
from behaviors.survey_planner import (
    MAX_VERTICES,
    SurveyError,
    SurveySettings,
    check_polygon,
    distance_to_area_m,
    lane_axes,
    leg_time_s,
    plan_survey,
    rectangle,
    swapped,
)

ORIGIN = (47.397742, 8.545594)
NADIR = CameraModel.from_hfov(640, 480, 70.0, -90.0)
# Nadir, 70 deg across, at 20 m: a 28.0 m swath; 20 % overlap spaces lanes at most 22.4 m apart.
SETTINGS = SurveySettings(altitude_m=20.0, overlap=0.2, camera=NADIR, search_range_m=50.0,
                          min_altitude_m=5.0, max_altitude_m=60.0)  # fmt: skip


def at(north: float, east: float) -> tuple[float, float]:
    return offset_to_latlon(*ORIGIN, north, east)


def local(p: tuple[float, float]) -> tuple[float, float]:
    return latlon_to_offset(*ORIGIN, *p)


RECT = [at(0, 0), at(0, 120), at(80, 120), at(80, 0)]  # 120 m east-west, 80 m north-south


def test_swath_of_the_default_test_camera() -> None:
    assert swath_width_m(NADIR, 20.0, 50.0) == pytest.approx(2 * 20 * math.tan(math.radians(35)))


def test_a_rectangle_is_mown_along_its_long_side() -> None:
    plan = plan_survey(RECT, SETTINGS)
    # Across the 80 m side: ceil(80 / 22.4) = 4 bands of 20 m, lanes at 10, 30, 50, 70 m north.
    assert (plan.lanes, plan.spacing_m, plan.angle_deg) == (4, pytest.approx(20.0), 90.0)
    assert plan.swath_m == pytest.approx(28.008, abs=1e-3)
    points = [local(p) for p in plan.waypoints]
    assert [round(n, 6) for n, _ in points] == [10, 10, 30, 30, 50, 50, 70, 70]
    assert [round(e, 6) for _, e in points] == [0, 120, 120, 0, 0, 120, 120, 0]  # alternating, edge to edge
    assert plan.length_m == pytest.approx(4 * 120 + 3 * 20)
    assert plan.area_m2 == pytest.approx(120 * 80, rel=1e-6)
    assert all(item.command == NAV_WAYPOINT and item.z == 20.0 for item in plan.items)
    assert len(plan.items) == 8


def test_figures_the_operator_checks() -> None:
    plan = plan_survey(RECT, replace(SETTINGS, speed_m_s=5.0))
    # 7 legs from rest to rest at 5 m/s, 2.5 m/s^2: each takes length / 5 + 2 s.
    assert plan.time_s == pytest.approx((4 * 120 + 3 * 20) / 5.0 + 7 * 2.0)
    assert plan.summary() == (
        "4 lanes 20.0 m apart (swath 28.0 m) at 90 deg, 540 m, about 2 min 02 s at 5 m/s, 9 mission items, "
        "area 0.96 ha"
    )


@pytest.mark.parametrize(
    ("length", "speed", "expected"),
    [(100.0, 5.0, 22.0), (10.0, 5.0, 2.0 * math.sqrt(10.0 / 2.5)), (0.0, 5.0, 0.0), (10.0, 5.0, 4.0)],
)
def test_leg_time(length: float, speed: float, expected: float) -> None:
    assert leg_time_s(length, speed) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("settings", "commands"),
    [
        (SETTINGS, [NAV_WAYPOINT] * 8),
        (replace(SETTINGS, speed_m_s=4.0), [DO_CHANGE_SPEED] + [NAV_WAYPOINT] * 8),
        (replace(SETTINGS, takeoff=True), [NAV_TAKEOFF] + [NAV_WAYPOINT] * 8),
        (replace(SETTINGS, takeoff=True, speed_m_s=4.0), [NAV_TAKEOFF, DO_CHANGE_SPEED] + [NAV_WAYPOINT] * 8),
    ],
)
def test_items_as_qgroundcontrol_plans_them(settings: SurveySettings, commands: list[int]) -> None:
    plan = plan_survey(RECT, settings)
    assert [item.command for item in plan.items] == commands
    for item in plan.items:
        if item.command == DO_CHANGE_SPEED:
            assert (item.frame, item.param1, item.param2, item.param3) == (2, 1.0, 4.0, -1.0)
        else:
            assert (item.frame, item.z) == (3, 20.0)  # MAV_FRAME_GLOBAL_RELATIVE_ALT at the survey altitude
            assert math.isnan(item.param4)  # heading left to the autopilot (faces the next waypoint)


@pytest.mark.parametrize(
    ("start", "first"),
    [(at(0, 0), (10, 0)), (at(0, 130), (10, 120)), (at(90, 130), (70, 120)), (at(90, -10), (70, 0))],
)
def test_the_survey_begins_at_the_lane_end_nearest_the_vehicle(
    start: tuple[float, float], first: tuple[float, float]
) -> None:
    plan = plan_survey(RECT, replace(SETTINGS, start=start))
    assert tuple(round(v, 6) for v in local(plan.waypoints[0])) == first
    assert plan.length_m == pytest.approx(540.0)


@pytest.mark.parametrize(("angle", "lanes"), [(0.0, 6), (90.0, 4), (180.0, 6), (45.0, 7)])
def test_lane_direction_can_be_chosen(angle: float, lanes: int) -> None:
    plan = plan_survey(RECT, replace(SETTINGS, angle_deg=angle))
    assert plan.lanes == lanes
    assert plan.angle_deg == angle % 180


@pytest.mark.parametrize(("overlap", "lanes"), [(0.0, 3), (0.2, 4), (0.5, 6), (0.9, 29)])
def test_overlap_sets_the_lane_count(overlap: float, lanes: int) -> None:
    plan = plan_survey(RECT, replace(SETTINGS, overlap=overlap))
    assert plan.lanes == lanes
    assert plan.spacing_m <= plan.swath_m * (1 - overlap) + 1e-9


def test_an_oblique_camera_sees_a_wider_swath_cut_at_the_search_range() -> None:
    oblique = replace(SETTINGS, camera=CameraModel.from_hfov(640, 480, 70.0, -45.0))
    plan = plan_survey(RECT, oblique)
    assert plan.swath_m == pytest.approx(swath_width_m(oblique.camera, 20.0, 50.0))
    assert plan.swath_m > 55.0 and plan.lanes == 2


def test_lanes_stay_inside_a_concave_polygon() -> None:
    """An L: every lane runs from where its band enters the polygon to where it leaves it."""
    ell = [at(0, 0), at(0, 100), at(30, 100), at(30, 30), at(100, 30), at(100, 0)]
    plan = plan_survey(ell, replace(SETTINGS, angle_deg=90.0))
    points = [local(p) for p in plan.waypoints]
    for n, e in points:
        assert -1e-6 <= e <= 100 + 1e-6 and -1e-6 <= n <= 100 + 1e-6
        assert not (n > 30 + 1e-6 and e > 30 + 1e-6), (n, e)  # never in the notch
    assert plan.lanes == math.ceil(100 / 22.4)


def test_centre_and_size_make_a_rectangle() -> None:
    corners = rectangle(at(40, 60), 120.0, 80.0)
    assert [tuple(round(v, 2) for v in local(c)) for c in corners] == [(0, 0), (0, 120), (80, 120), (80, 0)]
    turned = rectangle(at(40, 60), 120.0, 80.0, heading_deg=90.0)
    assert {tuple(round(v, 2) for v in local(c)) for c in turned} == {
        (100, 20),
        (-20, 20),
        (-20, 100),
        (100, 100),
    }


@pytest.mark.parametrize(
    ("corners", "message"),
    [
        ([], "the search area is empty: give at least 3 corners (lat,lon)"),
        ([at(0, 0), at(0, 10)], "the search area needs at least 3 distinct corners, got 2"),
        ([at(0, 0), at(0, 10), at(0, 0)], "the search area needs at least 3 distinct corners, got 2"),
        (
            [at(0, 0), at(0, 10), at(0, 10), at(10, 10)],
            "the search area repeats a corner: remove the duplicate",
        ),
        ([at(0, 0), at(0, 10), at(0, 20)], "the search area has no area: its corners lie on one line"),
        (
            [at(0, 0), at(10, 10), at(10, 0), at(0, 10)],
            "the search area's edges 1-2 and 3-4 cross: the polygon intersects itself (list the corners in order "
            "around it)",
        ),
        (
            [at(0, 0), at(0, 10), at(10, 10), at(10, 0), at(5, 5), at(-5, 5)],
            "the search area's edges 1-2 and 5-6 cross: the polygon intersects itself (list the corners in order "
            "around it)",
        ),
        (
            [(47.0, 8.0), (47.0, 8.1), (47.2, 8.1)],
            "the search area spans 23.5 km; at most 10 km is accepted (check the corners' order: lat,lon)",
        ),  # fmt: skip
        ([(91.0, 8.0), (47.0, 8.1), (47.2, 8.1)], "corner 91.0,8.0 is not a latitude,longitude"),
        ([(math.nan, 8.0), (47.0, 8.1), (47.2, 8.1)], "corner nan,8.0 is not a latitude,longitude"),
        ([(89.0, 8.0), (89.0, 8.1), (88.9, 8.1)], "corner 89.0,8.0 is within 5 deg of a pole"),
        (
            [at(0, k) for k in range(MAX_VERTICES)] + [at(10, 0)],
            "the search area has 201 corners; at most 200 are accepted",
        ),
    ],
)
def test_bad_polygons_get_one_line_errors(corners: list[tuple[float, float]], message: str) -> None:
    with pytest.raises(SurveyError) as err:
        plan_survey(corners, SETTINGS)
    assert str(err.value) == message
    assert "\n" not in message


def test_a_closed_ring_is_accepted() -> None:
    assert check_polygon([*RECT, RECT[0]]) == tuple(RECT)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"altitude_m": 80.0},
            "altitude 80 m is outside the safety band 5-60 m ([safety] min_altitude_m, max_altitude_m)",
        ),
        (
            {"altitude_m": 4.0},
            "altitude 4 m is outside the safety band 5-60 m ([safety] min_altitude_m, max_altitude_m)",
        ),
        (
            {"altitude_m": math.nan},
            "altitude nan m is outside the safety band 5-60 m ([safety] min_altitude_m, max_altitude_m)",
        ),
        ({"overlap": 0.95}, "overlap 0.95 must be between 0 and 0.9 (a fraction of the swath)"),
        ({"overlap": -0.1}, "overlap -0.1 must be between 0 and 0.9 (a fraction of the swath)"),
        ({"speed_m_s": 0.0}, "speed 0 m/s must be between 0.5 and 30 m/s"),
        ({"speed_m_s": 45.0}, "speed 45 m/s must be between 0.5 and 30 m/s"),
        ({"angle_deg": math.inf}, "the lane angle must be a number of degrees"),
        (
            {"camera": CameraModel.from_hfov(640, 480, 70.0, 10.0), "search_range_m": 20.0},
            "the camera sees no ground within 20 m from 20 m ([camera] mount_pitch_deg looks at or above the horizon?)",
        ),
    ],
)
def test_bad_settings_get_one_line_errors(change: dict[str, object], message: str) -> None:
    with pytest.raises(SurveyError) as err:
        plan_survey(RECT, replace(SETTINGS, **change))  # type: ignore[arg-type]
    assert str(err.value) == message


def test_too_many_lanes_is_refused() -> None:
    tiny = replace(SETTINGS, altitude_m=5.0, overlap=0.9)  # a 0.7 m lane spacing
    with pytest.raises(SurveyError, match=r"^the survey would need more than 500 lanes 0\.7 m apart: raise"):
        plan_survey(rectangle(ORIGIN, 1000.0, 1000.0), tiny)


@pytest.mark.parametrize(("width", "height"), [(0.0, 10.0), (10.0, -1.0), (math.nan, 10.0)])
def test_bad_sizes_get_one_line_errors(width: float, height: float) -> None:
    with pytest.raises(SurveyError, match=r"^a survey size must be two positive lengths in metres, got "):
        rectangle(ORIGIN, width, height)


# ------------------------------------------------------------------------------ spacing and distance
def test_a_spacing_given_outright_lays_the_lanes() -> None:
    plan = plan_survey(RECT, replace(SETTINGS, spacing_m=80 / 5))
    assert (plan.lanes, plan.spacing_m) == (5, pytest.approx(16.0))
    assert lane_axes(check_polygon(RECT)) == (90.0, pytest.approx(80.0))  # narrowest across north-south
    assert lane_axes(check_polygon(RECT), 0.0) == (0.0, pytest.approx(120.0))


@pytest.mark.parametrize("spacing", [28.1, 0.0, -3.0, math.nan])
def test_a_spacing_that_leaves_gaps_is_refused(spacing: float) -> None:
    with pytest.raises(SurveyError, match=r"leave gaps: the camera's swath is 28\.0 m at 20 m$"):
        plan_survey(RECT, replace(SETTINGS, spacing_m=spacing))


@pytest.mark.parametrize(
    ("point", "expected_m"),
    [
        ((40.0, 60.0), 0.0),  # inside
        ((40.0, 160.0), 40.0),  # east of the east edge
        ((-30.0, -40.0), 50.0),  # off the south-west corner
        ((120.0, 60.0), 40.0),
    ],
)
def test_distance_to_an_area(point: tuple[float, float], expected_m: float) -> None:
    assert distance_to_area_m(at(*point), RECT) == pytest.approx(expected_m, abs=0.01)


def test_distance_to_an_area_far_away_is_the_great_circle_one() -> None:
    zurich, swapped_area = (47.397742, 8.545594), [(8.5450, 47.3975), (8.5466, 47.3975), (8.5466, 47.3982)]
    assert distance_to_area_m(zurich, swapped_area) == pytest.approx(5_660_000, rel=0.005)
    assert swapped(swapped_area) == ((47.3975, 8.5450), (47.3975, 8.5466), (47.3982, 8.5466))
    assert distance_to_area_m(zurich, swapped(swapped_area) or ()) < 100
    assert swapped([(10.0, 120.0), (11.0, 120.0), (10.0, 121.0)]) is None  # 120 is no latitude
