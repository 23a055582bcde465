"""The expected POD of a survey plan (cloudtrack/survey_pod.py): its keyframes laid on the companion's own map
(`cloudtrack.pod_map.PodMap`), the planner's fast model held to that map, and a plan for a POD confirmed on
it. Curves are made up here (never the shipped one)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from behaviors.apparent_size import TargetShape
from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.pod_planner import Keyframing, PodSearch, PodTarget
from behaviors.survey_planner import SurveySettings, check_polygon, plan_survey
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import PodSettings
from cloudtrack.survey_pod import PodOutOfReach, expected_coverage, expected_pod, keyframe_poses, plan_for_pod
from tests.test_pod_planner import step_curve

ORIGIN = (47.397742, 8.545594)
NADIR = CameraModel.from_hfov(640, 480, 70.0, -90.0)
OBLIQUE = CameraModel.from_hfov(640, 480, 70.0, -45.0)
STANDING = TargetShape.person("standing")


def at(north: float, east: float) -> tuple[float, float]:
    return offset_to_latlon(*ORIGIN, north, east)


def box(width: float, height: float) -> list[tuple[float, float]]:
    return [at(0, 0), at(0, width), at(height, width), at(height, 0)]


def settings(camera: CameraModel, altitude: float, **more: object) -> SurveySettings:
    return replace(
        SurveySettings(
            altitude_m=altitude, overlap=0.0, camera=camera, search_range_m=50.0, min_altitude_m=5.0,
            max_altitude_m=60.0,
        ),
        **more,
    )  # fmt: skip


def test_keyframes_fall_every_speed_times_interval_along_the_path_facing_along_each_leg() -> None:
    path = [at(0, 0), at(0, 20), at(10, 20)]  # 20 m east, then 10 m north
    poses = keyframe_poses(path, 4.0, 0.5, LocalFrame(*ORIGIN))
    assert len(poses) == 16  # 0, 2, ... 30 m along
    assert [t for *_, t in poses] == [k * 0.5 for k in range(16)]
    offsets = [latlon_to_offset(*ORIGIN, lat, lon) for lat, lon, _, _ in poses]
    assert [round(e, 6) for _, e in offsets[:11]] == [2.0 * k for k in range(11)]
    assert [round(n, 6) for n, _ in offsets[11:]] == [2.0, 4.0, 6.0, 8.0, 10.0]
    assert [yaw for _, _, yaw, _ in poses] == pytest.approx([math.pi / 2] * 11 + [0.0] * 5)


STRIP = box(100.0, 8.0)  # 100 m east-west, 8 m north-south: a nadir camera at 20 m sees it whole
HALF = PodTarget(step_curve(0.0, 0.5), STANDING)  # any look at the person finds them with 0.5


def test_one_lane_over_a_strip_is_one_pass_everywhere() -> None:
    s = settings(NADIR, 20.0, speed_m_s=5.0)
    plan = plan_survey(STRIP, s)
    assert plan.lanes == 1
    pod_map = expected_pod(plan, STRIP, s, HALF, PodSettings(), 0.5)
    assert pod_map.mean() == pytest.approx(0.5) and pod_map.share_at_least(0.5) == 1.0
    assert pod_map.looks == math.floor(100 / 2.5) + 1
    assert expected_coverage(plan, STRIP, s, 0.5) == (pytest.approx(1.0), pod_map.looks)


def test_flying_back_is_a_second_pass_where_it_comes_after_the_pass_gap() -> None:
    s = settings(NADIR, 20.0, speed_m_s=5.0)
    plan = plan_survey(STRIP, s)
    there_and_back = replace(plan, waypoints=(*plan.waypoints, plan.waypoints[0]))
    pod_map = expected_pod(there_and_back, STRIP, s, HALF, PodSettings(pass_gap_s=10.0), 0.5)
    west, east = plan.waypoints if plan.waypoints[0][1] < plan.waypoints[1][1] else plan.waypoints[::-1]
    turn = plan.waypoints[1]
    far = west if turn == east else east
    # Next to the turn the way back looks again within seconds: the same pass. At the far end, 20 s later.
    assert pod_map.pod_at(at(4.0, 2.0 if turn == west else 98.0)[0], turn[1]) == pytest.approx(0.5, abs=0.01)
    assert pod_map.pod_at(at(4.0, 0.0)[0], far[1]) == pytest.approx(0.75, abs=0.01)


AREA = box(240.0, 150.0)
TARGET = PodTarget(step_curve(16.0, 0.7), STANDING)


@pytest.mark.parametrize(
    ("altitude", "overlap", "speed"),
    [(20.0, 0.2, 5.0), (12.0, 0.5, 8.0), (30.0, 0.0, 10.0), (15.0, 0.6, 3.0)],
)
def test_the_planners_model_holds_to_the_map(altitude: float, overlap: float, speed: float) -> None:
    s = settings(OBLIQUE, altitude, overlap=overlap, speed_m_s=speed)
    plan = plan_survey(AREA, s)
    pod_map = expected_pod(plan, AREA, s, TARGET, PodSettings(), 0.5)
    model = PodSearch(check_polygon(AREA), s, TARGET, Keyframing()).pod(altitude, plan.lanes, speed)
    assert model == pytest.approx(pod_map.mean(), abs=0.04)


def test_a_plan_for_a_pod_reaches_it_on_the_map() -> None:
    found = plan_for_pod(AREA, settings(OBLIQUE, 60.0), TARGET, Keyframing(), PodSettings(), 0.8)
    assert found.map.mean() >= 0.8
    assert found.plan.waypoints and found.plan.speed_m_s == found.choice.speed_m_s
    assert found.map.looks > 0


def test_a_pod_out_of_reach_names_the_closest_plan_as_the_map_shows_it() -> None:
    weak = PodTarget(step_curve(16.0, 0.3), STANDING)
    with pytest.raises(PodOutOfReach) as err:
        plan_for_pod(
            box(120.0, 60.0),
            settings(OBLIQUE, 40.0, min_altitude_m=30.0),
            weak,
            Keyframing(),
            PodSettings(),
            0.99,
        )
    best = err.value.best
    assert 0 < best.map.mean() < 0.99
    assert str(err.value) == f"POD 0.99 cannot be reached; the best is {best.map.mean():.2f}"
