"""The expected probability of detection (POD) of a survey plan: what the companion's map would show had it
flown exactly that plan, and the plan for a POD confirmed on that map. Its footprint coverage too, laid from
the same keyframes (`expected_coverage`), as the companion lays it from the keyframes analysed.

`expected_pod` lays the plan's keyframes on a `cloudtrack.pod_map.PodMap` of the area, as the companion lays
the analysed ones in flight: one every `interval_s` ([backend] search_interval_s) along the waypoints at the
plan's speed, at the survey altitude, the camera facing along each leg (as `cloudtrack.coverage.fly_path`
flies it), every keyframe analysed. Speed changes at the corners are left out (the autopilot slows there, so
a real flight takes a few more keyframes near the lane ends, never fewer).

`plan_for_pod` searches with the fast model of `behaviors/pod_planner.py` and confirms its choice here:
where the map falls short of the POD (lane ends, turns, a polygon that is not a rectangle), it asks the
model for that much more and tries again, a few times at most; what it returns was reached on the map.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import shapely
from shapely.geometry import Polygon

from behaviors.camera_footprint import ground_footprint
from behaviors.pod_planner import Keyframing, PodChoice, PodSearch, PodTarget, PodUnreachable
from behaviors.survey_planner import LatLon, SurveyPlan, SurveySettings, check_polygon, plan_checked
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import PodMap, PodSettings

MAX_TRIES = 4  # the model asked for more this many times before the plan is said out of reach
MARGIN = (
    0.01  # asked of the model beyond the POD (and beyond a shortfall on the map): its error is about that
)


@dataclass(frozen=True)
class PodPlan:
    """A plan for a POD, as confirmed: the model's choice, the plan, its map."""

    choice: PodChoice
    plan: SurveyPlan
    map: PodMap


class PodOutOfReach(ValueError):
    """No plan reaches the POD on the map; `best` is the one that comes closest (confirmed on the map)."""

    def __init__(self, pod: float, best: PodPlan) -> None:
        super().__init__(f"POD {pod:g} cannot be reached; the best is {best.map.mean():.2f}")
        self.pod = pod
        self.best = best


def keyframe_poses(
    waypoints: Sequence[LatLon], speed_m_s: float, interval_s: float, frame: LocalFrame
) -> list[tuple[float, float, float, float]]:
    """(lat, lon, yaw, time) of each keyframe along the waypoints, `speed_m_s * interval_s` apart, the first
    at the first waypoint; yaw along the leg it is on (radians clockwise from north); `frame` near them."""
    points = [frame.xy(lat, lon) for lat, lon in waypoints]
    step = speed_m_s * interval_s
    poses = []
    travelled = 0.0  # along the path to the start of this leg
    k = 0
    for (x0, y0), (x1, y1) in zip(points, points[1:], strict=False):
        length = math.hypot(x1 - x0, y1 - y0)
        if length <= 0:
            continue
        yaw = math.atan2(x1 - x0, y1 - y0)
        while k * step <= travelled + length + 1e-9:
            t = (k * step - travelled) / length
            lat, lon = frame.latlon(x0 + t * (x1 - x0), y0 + t * (y1 - y0))
            poses.append((lat, lon, yaw, k * interval_s))
            k += 1
        travelled += length
    return poses


def expected_coverage(
    plan: SurveyPlan, area: Sequence[LatLon], settings: SurveySettings, interval_s: float
) -> tuple[float, int]:
    """The share of `area` the camera would see flying `plan`, from the same keyframes (as the companion
    lays its coverage from the keyframes analysed), and their number."""
    frame = LocalFrame(area[0][0], area[0][1])
    region = shapely.make_valid(frame.polygon(area))
    outlines: dict[float, tuple[tuple[float, float], ...]] = {}  # a leg's keyframes differ only by place
    views = []
    for lat, lon, yaw, _ in keyframe_poses(plan.waypoints, plan.speed_m_s, interval_s, frame):
        if yaw not in outlines:
            outlines[yaw] = ground_footprint(
                settings.camera, settings.altitude_m, settings.search_range_m, yaw=yaw
            )
        x, y = frame.xy(lat, lon)
        if outlines[yaw]:
            views.append(Polygon([(x + east, y + north) for north, east in outlines[yaw]]))
    seen = shapely.union_all(views) if views else Polygon()
    return float(min(1.0, seen.intersection(region).area / region.area)), len(views)


def expected_pod(
    plan: SurveyPlan,
    area: Sequence[LatLon],
    settings: SurveySettings,
    target: PodTarget,
    map_settings: PodSettings,
    interval_s: float,
) -> PodMap:
    """The map after flying `plan` over `area` (see the module doc)."""
    pod_map = PodMap(area, settings.camera, settings.search_range_m, target.curve, map_settings)
    for lat, lon, yaw, time_s in keyframe_poses(plan.waypoints, plan.speed_m_s, interval_s, pod_map.frame):
        pod_map.add_look(lat, lon, settings.altitude_m, yaw, time_s)
    return pod_map


def plan_for_pod(
    area: Sequence[LatLon],
    settings: SurveySettings,
    target: PodTarget,
    keyframing: Keyframing,
    map_settings: PodSettings,
    pod: float,
    altitude_m: float | None = None,
    speed_m_s: float | None = None,
) -> PodPlan:
    """The plan that reaches `pod` (the map's mean) in the least time the model finds; PodOutOfReach with the
    closest plan when none does. `altitude_m` / `speed_m_s` hold those fixed."""
    corners = check_polygon(area)
    search = PodSearch(corners, settings, target, keyframing, altitude_m, speed_m_s)

    def confirmed(choice: PodChoice) -> PodPlan:
        chosen = choice.settings(search.settings)
        plan = plan_checked(corners, chosen)
        return PodPlan(
            choice, plan, expected_pod(plan, area, chosen, target, map_settings, keyframing.interval_s)
        )

    required = min(0.999, pod + MARGIN)
    closest: PodPlan | None = None
    for _ in range(MAX_TRIES):
        try:
            choice = search.choose(pod, required)
        except PodUnreachable as exc:
            best = confirmed(exc.best)
            if best.map.mean() >= pod:
                return best
            if closest is None or best.map.mean() > closest.map.mean():
                closest = best
            raise PodOutOfReach(pod, closest) from None
        found = confirmed(choice)
        if found.map.mean() >= pod:
            return found
        if closest is None or found.map.mean() > closest.map.mean():
            closest = found
        required = min(0.999, required + (pod - found.map.mean()) + MARGIN)
    assert closest is not None
    raise PodOutOfReach(pod, closest)
