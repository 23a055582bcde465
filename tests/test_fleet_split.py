"""behaviors/fleet_split.py: one area shared out over a fleet, parts contiguous and disjoint, their lanes the
single plan's own, and times close whatever the speeds and start positions."""

from __future__ import annotations

import math

import pytest

from behaviors.camera_footprint import polygon_area
from behaviors.camera_model import CameraModel
from behaviors.fleet_split import FleetSplit, FleetVehicle, split_area
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import DO_CHANGE_SPEED, NAV_TAKEOFF, NAV_WAYPOINT
from behaviors.survey_planner import SurveyError, SurveySettings, plan_survey

ORIGIN = (47.397742, 8.545594)
NADIR = CameraModel.from_hfov(640, 480, 70.0, -90.0)
SETTINGS = SurveySettings(altitude_m=20.0, overlap=0.2, camera=NADIR, search_range_m=50.0,
                          min_altitude_m=5.0, max_altitude_m=60.0)  # fmt: skip


def at(north: float, east: float) -> tuple[float, float]:
    return offset_to_latlon(*ORIGIN, north, east)


def local(p: tuple[float, float]) -> tuple[float, float]:
    return latlon_to_offset(*ORIGIN, *p)


# 600 m east-west x 400 m north-south: 18 lanes of 22.2 m running east-west
AREA = [at(0, 0), at(0, 600), at(400, 600), at(400, 0)]
MIDDLE = at(200, 300)


def fleet(*specs: tuple[str, float, tuple[float, float]]) -> list[FleetVehicle]:
    return [FleetVehicle(name, speed, start) for name, speed, start in specs]


def lanes_of(split: FleetSplit) -> dict[str, int]:
    return {part.vehicle.id: part.plan.lanes for part in split.parts}


def spread(split: FleetSplit) -> float:
    times = [part.time_s for part in split.parts]
    return (max(times) - min(times)) / max(times)


@pytest.mark.parametrize(
    ("vehicles", "expected"),
    [
        # Equal speeds from the same place: equal parts.
        (fleet(("a", 5.0, MIDDLE), ("b", 5.0, MIDDLE)), {"a": 9, "b": 9}),
        (fleet(("a", 5.0, MIDDLE), ("b", 5.0, MIDDLE), ("c", 5.0, MIDDLE)), {"a": 6, "b": 6, "c": 6}),
        # A vehicle twice as fast takes about twice the lanes.
        (fleet(("slow", 4.0, MIDDLE), ("fast", 8.0, MIDDLE)), {"slow": 6, "fast": 12}),
        # A vehicle starting 1.5 km away spends its first minutes getting there: it takes fewer.
        (fleet(("near", 5.0, MIDDLE), ("far", 5.0, at(-1500, 300))), {"near": 10, "far": 8}),
    ],
)
def test_the_split_balances_speeds_and_start_positions(
    vehicles: list[FleetVehicle], expected: dict[str, int]
) -> None:
    split = split_area(AREA, SETTINGS, vehicles)
    assert lanes_of(split) == expected
    assert spread(split) < 0.12
    assert split.finish_s == max(part.time_s for part in split.parts)


@pytest.mark.parametrize(
    "vehicles",
    [
        fleet(("a", 5.0, MIDDLE), ("b", 5.0, MIDDLE)),
        fleet(("a", 3.0, at(-100, 0)), ("b", 9.0, at(500, 700)), ("c", 5.0, MIDDLE)),
        fleet(("a", 5.0, at(-300, -300)), ("b", 5.0, at(-300, -300)), ("c", 6.0, at(900, 900)), ("d", 4.0, MIDDLE)),
    ],
)  # fmt: skip
def test_parts_are_contiguous_disjoint_and_make_up_the_area(vehicles: list[FleetVehicle]) -> None:
    split = split_area(AREA, SETTINGS, vehicles)
    whole = plan_survey(AREA, SETTINGS)
    assert split.whole.lanes == whole.lanes and split.whole.spacing_m == whole.spacing_m
    # Every lane of the single plan is flown by exactly one vehicle, in runs one after another across the area.
    assert [p.first_lane for p in split.parts] == [1] + [p.last_lane + 1 for p in split.parts[:-1]]
    assert split.parts[-1].last_lane == whole.lanes
    assert sum(p.plan.lanes for p in split.parts) == whole.lanes

    def lane_rows(waypoints: tuple[tuple[float, float], ...]) -> list[float]:
        return sorted({round(local(p)[0], 3) for p in waypoints})

    assert sorted(row for p in split.parts for row in lane_rows(p.plan.waypoints)) == lane_rows(
        whole.waypoints
    )
    # The parts are bands across the lanes, edge to edge: their areas add up to the area, none overlap.
    assert sum(p.plan.area_m2 for p in split.parts) == pytest.approx(whole.area_m2, rel=1e-6)
    bands = sorted((min(rows), max(rows)) for p in split.parts for rows in [[local(c)[0] for c in p.corners]])
    assert bands[0][0] == pytest.approx(0.0, abs=1e-6) and bands[-1][1] == pytest.approx(400.0)
    assert all(a[1] == pytest.approx(b[0]) for a, b in zip(bands, bands[1:], strict=False))
    for part in split.parts:
        assert polygon_area([local(c) for c in part.corners]) == pytest.approx(part.plan.area_m2, rel=1e-6)
        # The estimate the split balanced is the part's own plan: transit, then its lanes and turns.
        first = local(part.plan.waypoints[0])
        start = local(part.vehicle.start)
        assert part.transit_m == pytest.approx(math.dist(first, start), rel=1e-6)
        assert part.plan.speed_m_s == part.vehicle.speed_m_s
    # Together they finish sooner than the quickest of them alone.
    assert split.finish_s < split.alone_s


def test_each_part_is_a_mission_at_its_vehicles_speed_beginning_nearest_it() -> None:
    split = split_area(
        AREA, SETTINGS.__class__(**{**SETTINGS.__dict__, "takeoff": True}),
        fleet(("west", 4.0, at(100, -50)), ("east", 6.0, at(300, 650))),
    )  # fmt: skip
    for part in split.parts:
        commands = [item.command for item in part.plan.items]
        assert commands == [NAV_TAKEOFF, DO_CHANGE_SPEED] + [NAV_WAYPOINT] * (2 * part.plan.lanes)
        assert part.plan.items[1].param2 == part.vehicle.speed_m_s
        # Of the four ways to fly its lanes (either outer lane, either end), the one beginning nearest it.
        w = part.plan.waypoints
        ways = (w[0], w[1], w[-2], w[-1])
        start = local(part.vehicle.start)
        assert math.dist(local(w[0]), start) == pytest.approx(min(math.dist(local(p), start) for p in ways))


def test_a_single_vehicle_flies_the_single_plan() -> None:
    split = split_area(AREA, SETTINGS, fleet(("solo", 5.0, at(0, 0))))
    (part,) = split.parts
    assert part.plan.waypoints == plan_survey(AREA, SETTINGS.__class__(**{**SETTINGS.__dict__, "start": at(0, 0), "speed_m_s": 5.0})).waypoints  # fmt: skip
    assert split.finish_s == pytest.approx(split.alone_s)


@pytest.mark.parametrize(
    ("vehicles", "message"),
    [
        ([], "the fleet is empty: name at least one vehicle"),
        (fleet(*[(f"v{k}", 5.0, MIDDLE) for k in range(17)]), "the fleet has 17 vehicles; at most 16 are accepted"),
        (fleet(("a", 5.0, MIDDLE), ("a", 5.0, MIDDLE)), "vehicle id 'a' is given twice"),
        (fleet(("a b", 5.0, MIDDLE)), "vehicle id 'a b' must be 1-32 letters, digits"),
        (fleet(("", 5.0, MIDDLE)), "vehicle id '' must be"),
        (fleet(("a", 0.1, MIDDLE)), "vehicle a: speed 0.1 m/s must be between 0.5 and 30 m/s"),
        (fleet(("a", math.nan, MIDDLE)), "vehicle a: speed nan m/s"),
        (fleet(("a", 5.0, (91.0, 8.0))), "vehicle a: start 91.0,8.0 is not a latitude,longitude"),
        (fleet(("a", 5.0, (8.5, 47.4))), "vehicle a: start 8.500000,47.400000 is more than 50 km from the area"),
    ],
)  # fmt: skip
def test_bad_fleets_are_refused_in_one_line(vehicles: list[FleetVehicle], message: str) -> None:
    with pytest.raises(SurveyError) as caught:
        split_area(AREA, SETTINGS, vehicles)
    assert str(caught.value).startswith(message) and "\n" not in str(caught.value)


def test_more_vehicles_than_lanes_is_refused() -> None:
    narrow = [at(0, 0), at(0, 300), at(30, 300), at(30, 0)]  # 2 lanes
    with pytest.raises(
        SurveyError, match=r"^the area has 2 lanes for 3 vehicles: fly it with fewer vehicles"
    ):
        split_area(narrow, SETTINGS, fleet(("a", 5.0, MIDDLE), ("b", 5.0, MIDDLE), ("c", 5.0, MIDDLE)))


def test_a_bad_area_is_refused_as_for_one_vehicle() -> None:
    with pytest.raises(SurveyError, match="at least 3 distinct corners"):
        split_area(AREA[:2], SETTINGS, fleet(("a", 5.0, MIDDLE)))


def test_a_concave_area_splits_into_lanes_of_the_single_plan() -> None:
    ell = [at(0, 0), at(0, 400), at(100, 400), at(100, 100), at(300, 100), at(300, 0)]
    split = split_area(ell, SETTINGS, fleet(("a", 5.0, at(0, 0)), ("b", 5.0, at(300, 0))))
    whole = plan_survey(ell, SETTINGS)
    assert sum(p.plan.lanes for p in split.parts) == whole.lanes
    assert sum(p.plan.area_m2 for p in split.parts) == pytest.approx(whole.area_m2, rel=1e-6)
    assert spread(split) < 0.25


def test_the_estimate_the_split_balances_is_each_parts_own_plan() -> None:
    """The split times every run of lanes in O(1) (prefix sums over the turns); each part's mission, built
    as plan_checked builds one, takes exactly that."""
    from behaviors.fleet_split import _Times
    from behaviors.survey_planner import _lanes, _rotate, _to_local

    for vehicles in (
        fleet(("a", 3.0, at(-100, 0)), ("b", 9.0, at(500, 700)), ("c", 5.0, MIDDLE)),
        fleet(("a", 5.0, at(50, -300)), ("b", 7.0, at(390, 610)), ("c", 5.0, at(410, 0)), ("d", 4.0, MIDDLE)),
    ):
        split = split_area(AREA, SETTINGS, vehicles)
        corners = tuple(AREA)
        lanes, _ = _lanes(_to_local(corners[0], corners), split.whole.angle_deg, split.whole.swath_m * 0.8)
        for part in split.parts:
            start = _rotate([latlon_to_offset(*corners[0], *part.vehicle.start)], split.whole.angle_deg)[0]
            times = _Times(lanes, start, part.vehicle.speed_m_s)
            assert times.time(part.first_lane - 1, part.last_lane - 1) == pytest.approx(part.time_s, rel=1e-9)


@pytest.mark.parametrize(
    "vehicles",
    [
        fleet(("a", 3.0, at(-100, 0)), ("b", 9.0, at(500, 700))),
        fleet(("a", 5.0, at(50, -300)), ("b", 7.0, at(390, 610)), ("c", 5.0, at(410, 0))),
    ],
)
def test_no_other_cut_or_order_finishes_sooner(vehicles: list[FleetVehicle]) -> None:
    """Every way to deal the lanes out in contiguous runs, in every order: none beats the split's finish."""
    import itertools

    from behaviors.fleet_split import _Times
    from behaviors.survey_planner import _lanes, _rotate, _to_local

    split = split_area(AREA, SETTINGS, vehicles)
    corners = tuple(AREA)
    lanes, _ = _lanes(_to_local(corners[0], corners), split.whole.angle_deg, split.whole.swath_m * 0.8)
    n = len(lanes)
    times = {
        v.id: _Times(
            lanes, _rotate([latlon_to_offset(*corners[0], *v.start)], split.whole.angle_deg)[0], v.speed_m_s
        )
        for v in vehicles
    }
    best = math.inf
    for order in itertools.permutations(vehicles):
        for cuts in itertools.combinations(range(1, n), len(vehicles) - 1):
            bounds = [0, *cuts, n]
            finish = max(times[v.id].time(bounds[k], bounds[k + 1] - 1) for k, v in enumerate(order))
            best = min(best, finish)
    assert split.finish_s == pytest.approx(best, abs=1e-5)
