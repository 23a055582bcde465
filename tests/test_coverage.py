"""The coverage library (cloudtrack/coverage.py) on geometry with known answers."""

from __future__ import annotations

import math

import pytest
from shapely.geometry import MultiPolygon, Polygon

from behaviors.camera_footprint import swath_width_m
from behaviors.camera_model import CameraModel
from behaviors.geolocation import offset_to_latlon
from behaviors.survey_planner import SurveySettings, plan_survey, rectangle
from cloudtrack.coverage import (
    CoverageMap,
    LocalFrame,
    area_from_waypoints,
    bounded_rings,
    fly_path,
    footprint_polygon,
    geometry_from_rings,
)

ORIGIN = (47.397742, 8.545594)
NADIR = CameraModel.from_hfov(640, 480, 90.0, -90.0)  # 90 deg: at 10 m the footprint is 20 m x 15 m


def at(north: float, east: float) -> tuple[float, float]:
    return offset_to_latlon(*ORIGIN, north, east)


def square(size: float, north: float = 0.0, east: float = 0.0) -> list[tuple[float, float]]:
    return [at(north, east), at(north, east + size), at(north + size, east + size), at(north + size, east)]


def test_local_frame_round_trip() -> None:
    frame = LocalFrame(*ORIGIN)
    x, y = frame.xy(*at(30.0, -40.0))
    assert (x, y) == pytest.approx((-40.0, 30.0), abs=1e-6)
    assert frame.latlon(x, y) == pytest.approx(at(30.0, -40.0), abs=1e-12)


def test_a_nadir_footprint_is_its_rectangle_on_the_map() -> None:
    frame = LocalFrame(*ORIGIN)
    view = footprint_polygon(NADIR, frame, *at(50.0, 20.0), 10.0, 0.0, 1000.0)
    assert view.area == pytest.approx(20.0 * 15.0)
    assert view.bounds == pytest.approx((10.0, 42.5, 30.0, 57.5))  # x east 20 +- 10, y north 50 +- 7.5


@pytest.mark.parametrize(
    ("views", "share"),
    [
        ([], 0.0),
        ([(10.0, 10.0)], 20.0 * 15.0 / 400.0),  # one footprint wholly inside a 20 m square: 300 of 400 m^2
        ([(7.5, 10.0), (12.5, 10.0)], 1.0),  # two overlapping ones cover it all
        ([(-100.0, -100.0)], 0.0),  # seen elsewhere
        ([(0.0, 0.0)], 10.0 * 7.5 / 400.0),  # centred on a corner: a quarter of the footprint is inside
    ],
)
def test_coverage_share_of_a_square(views: list[tuple[float, float]], share: float) -> None:
    cover = CoverageMap(square(20.0), NADIR, 1000.0)
    for north, east in views:
        assert cover.add_view(*at(north, east), 10.0, 0.0)
    assert cover.coverage() == pytest.approx(share, abs=1e-6)


def test_a_straight_track_covers_a_swath_and_thin_views_are_skipped() -> None:
    """Flying 100 m north at 10 m over a 100 m x 100 m square with a 20 m wide footprint: 20 % of it."""
    cover = CoverageMap(square(100.0), NADIR, 1000.0)
    added = sum(cover.add_view(*at(y / 10.0, 50.0), 10.0, 0.0) for y in range(0, 1001))  # a view every 0.1 m
    assert 46 <= added <= 51  # about one per 2 m: the rest would add nothing
    assert cover.coverage() == pytest.approx(0.2, abs=1e-6)
    assert not cover.add_view(*at(100.05, 50.0), 10.0, 0.0)
    assert cover.add_view(*at(100.05, 50.0), 10.0, math.radians(10.0))  # turned: a new view
    assert not cover.add_view(math.nan, 0.0, 10.0, 0.0)


def test_covered_rings_are_bounded_and_keep_holes() -> None:
    """A ring-shaped seen area (a hole in the middle) comes back as an outer ring and a hole, oriented as
    GeoJSON orders them, and rebuilds the same geometry."""
    cover = CoverageMap(square(60.0), NADIR, 1000.0)
    for k in range(0, 61, 2):  # a hollow square track 7.5 m in from the sides: footprint 20 x 15 (turning)
        for north, east in ((7.5, k), (52.5, k), (k, 7.5), (k, 52.5)):
            cover.add_view(*at(north, east), 10.0, 0.0)
    rings = cover.covered_rings()
    assert len(rings) == 2
    rebuilt = geometry_from_rings(rings)
    assert isinstance(rebuilt, Polygon) and len(rebuilt.interiors) == 1
    frame = cover.frame
    metres = Polygon([frame.xy(lat, lon) for lon, lat in rebuilt.exterior.coords])
    assert metres.area == pytest.approx(
        60.0 * 60.0, rel=1e-3
    )  # clipped to the area: all of it outside the hole
    assert all(isinstance(v, float) for ring in rings for point in ring for v in point)


def test_covered_rings_beyond_the_area_keep_what_was_seen_of_a_neighbours_part() -> None:
    """A lane along a 20 m part's east edge sees 10 m into the next part: clipped to the part, the rings hold
    none of it (the share is unchanged); `beyond_m` keeps it, up to that distance, for the merged map."""
    cover = CoverageMap(square(20.0), NADIR, 1000.0)
    for north in range(0, 21, 2):
        cover.add_view(*at(float(north), 20.0), 10.0, 0.0)  # footprint east 10..30
    frame = cover.frame

    def east_extent(rings: list[list[list[float]]]) -> tuple[float, float]:
        xs = [frame.xy(lat, lon)[0] for ring in rings for lat, lon in ring]
        return min(xs), max(xs)

    assert east_extent(cover.covered_rings()) == pytest.approx((10.0, 20.0), abs=0.01)
    assert east_extent(cover.covered_rings(beyond_m=5.0)) == pytest.approx((10.0, 25.0), abs=0.01)
    assert east_extent(cover.covered_rings(beyond_m=50.0)) == pytest.approx((10.0, 30.0), abs=0.01)
    assert cover.coverage() == pytest.approx(0.5, abs=1e-6)


def test_many_patches_are_cut_to_twenty_rings_and_five_hundred_vertices() -> None:
    frame = LocalFrame(*ORIGIN)
    circles = [Polygon([(100 * i + 30 * math.cos(a / 50 * math.tau), 30 * math.sin(a / 50 * math.tau))
                        for a in range(50)]).buffer(0) for i in range(40)]  # fmt: skip
    circles[3] = circles[3].difference(Polygon([(290, -5), (310, -5), (310, 5), (290, 5)]))  # one with a hole
    rings = bounded_rings(MultiPolygon(circles), frame)
    assert len(rings) == 20
    assert sum(len(r) for r in rings) <= 500
    rebuilt = geometry_from_rings(rings)
    assert isinstance(rebuilt, MultiPolygon)
    assert (
        len(rebuilt.geoms) == 20 and sum(len(p.interiors) for p in rebuilt.geoms) == 0
    )  # the hole lost its slot
    rings = bounded_rings(MultiPolygon(circles[:5]), frame, max_vertices=60)
    assert len(rings) == 6 and sum(len(r) for r in rings) <= 60  # five circles and the hole, simplified


def test_the_area_a_survey_sweeps_from_its_waypoints_alone() -> None:
    """A mission planned elsewhere has only waypoints: the area recovered from them is the planned polygon to
    within half a lane spacing on each side."""
    area = rectangle(ORIGIN, 120.0, 80.0)
    plan = plan_survey(
        area,
        SurveySettings(20.0, 0.2, CameraModel.from_hfov(640, 480, 70.0, -90.0), 50.0, 5.0, 60.0),
    )
    recovered = area_from_waypoints(plan.waypoints)
    frame = LocalFrame(*ORIGIN)
    truth = frame.polygon(area)
    got = frame.polygon(recovered)
    assert got.symmetric_difference(truth).area / truth.area < 0.05
    assert Polygon([frame.xy(*p) for p in recovered]).exterior.is_ccw
    assert area_from_waypoints(plan.waypoints[:1]) == []
    assert area_from_waypoints([at(0, 0), at(0, 50)]) == []  # a line sweeps no area without a margin
    line = area_from_waypoints([at(0, 0), at(0, 50)], margin_m=10.0)  # a line, widened 10 m each side
    assert LocalFrame(*ORIGIN).polygon(line).bounds == pytest.approx((0.0, -10.0, 50.0, 10.0), abs=1e-6)


def test_a_search_area_must_have_an_area() -> None:
    with pytest.raises(ValueError):
        CoverageMap([at(0, 0), at(0, 10)], NADIR, 50.0)
    with pytest.raises(ValueError):
        CoverageMap([at(0, 0), at(0, 10), at(0, 20)], NADIR, 50.0)


def test_a_planned_survey_flown_as_planned_covers_its_area() -> None:
    """The planner's lane spacing is the camera's swath less the overlap: flown exactly, a nadir survey sees
    the whole area (the lane ends reach the polygon's edges, the swath the bands' edges)."""
    camera = CameraModel.from_hfov(640, 480, 70.0, -90.0)
    area = rectangle(ORIGIN, 120.0, 80.0)
    plan = plan_survey(area, SurveySettings(20.0, 0.2, camera, 50.0, 5.0, 60.0))
    cover = fly_path(CoverageMap(area, camera, 50.0), plan.waypoints, 20.0)
    assert cover.coverage() == pytest.approx(1.0, abs=1e-6)
    sparse = plan_survey(area, SurveySettings(20.0, 0.2, camera, 50.0, 5.0, 60.0, angle_deg=0.0))
    one_lane = fly_path(CoverageMap(area, camera, 50.0), sparse.waypoints[:2], 20.0)
    # The first of six 20 m bands: its lane 10 m in from the west edge, half its 28 m swath beyond the edge.
    seen = 10.0 + swath_width_m(camera, 20.0, 50.0) / 2
    assert one_lane.coverage() == pytest.approx(seen * 80.0 / (120.0 * 80.0), rel=1e-3)
