"""The camera's ground footprint against geometry with known answers."""

from __future__ import annotations

import math

import pytest

from behaviors.camera_footprint import clip_polygon, ground_footprint, polygon_area, swath_width_m
from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, locate_pixel
from behaviors.telemetry import Telemetry

HFOV = 70.0
VFOV = 2 * math.degrees(math.atan(math.tan(math.radians(HFOV / 2)) * 480 / 640))  # 55.4 deg at 4:3


def cam(pitch: float, stabilised: bool = True) -> CameraModel:
    return CameraModel.from_hfov(640, 480, HFOV, pitch, stabilised)


def ground(height: float, depression_deg: float) -> float:
    """How far ahead a ray this many degrees below the horizon meets the ground."""
    return height / math.tan(math.radians(depression_deg))


def extent(points: tuple[tuple[float, float], ...]) -> tuple[float, float, float, float]:
    """(min north, max north, min east, max east)."""
    ns, es = [p[0] for p in points], [p[1] for p in points]
    return min(ns), max(ns), min(es), max(es)


def test_nadir_footprint_is_the_image_rectangle() -> None:
    h = 30.0
    fp = ground_footprint(cam(-90.0), h, 1000.0)
    half_w = h * math.tan(math.radians(HFOV / 2))  # across the image: east when facing north
    half_h = h * math.tan(math.radians(VFOV / 2))
    n0, n1, e0, e1 = extent(fp)
    assert (n0, n1, e0, e1) == pytest.approx((-half_h, half_h, -half_w, half_w), abs=1e-6)
    assert polygon_area(fp) == pytest.approx(4 * half_w * half_h, rel=1e-9)
    assert swath_width_m(cam(-90.0), h, 1000.0) == pytest.approx(2 * half_w)


@pytest.mark.parametrize(
    ("pitch", "height", "search_range", "near", "far"),
    [
        # Oblique: the near edge is where the image's bottom ray meets the ground; the far edge is the top ray's,
        # or the range cut when that lies beyond it.
        (-45.0, 30.0, 1000.0, ground(30, 45 + VFOV / 2), ground(30, 45 - VFOV / 2)),
        (-45.0, 30.0, 50.0, ground(30, 45 + VFOV / 2), 50.0),
        (-60.0, 20.0, 1000.0, ground(20, 60 + VFOV / 2), ground(20, 60 - VFOV / 2)),
        # Looking at the horizon: the upper half of the image sees sky; the ground is cut at the range.
        (-20.0, 30.0, 80.0, ground(30, 20 + VFOV / 2), 80.0),
    ],
)
def test_oblique_footprint_near_and_far_edges(
    pitch: float, height: float, search_range: float, near: float, far: float
) -> None:
    fp = ground_footprint(cam(pitch), height, search_range)
    n0, n1, e0, e1 = extent(fp)
    assert n0 == pytest.approx(near, rel=1e-6)
    assert n1 == pytest.approx(far, rel=3e-3)  # the range cut is a 48-gon inscribed in the circle
    assert e0 == pytest.approx(-e1, abs=1e-6)  # symmetric about the heading
    assert all(math.hypot(n, e) <= search_range + 1e-6 for n, e in fp)


@pytest.mark.parametrize(
    ("pitch", "height", "search_range"),
    [(0.0, 30.0, 50.0), (30.0, 30.0, 1000.0), (-45.0, 0.0, 50.0), (-45.0, -5.0, 50.0), (-45.0, 30.0, 0.0)],
)
def test_no_ground_seen_gives_an_empty_footprint(pitch: float, height: float, search_range: float) -> None:
    assert ground_footprint(cam(pitch), height, search_range) == ()
    assert swath_width_m(cam(pitch), height, search_range) == 0.0


def test_level_camera_sees_ground_only_beyond_the_lower_image_edge() -> None:
    fp = ground_footprint(cam(0.0), 30.0, 1000.0)
    assert extent(fp)[0] == pytest.approx(30 / math.tan(math.radians(VFOV / 2)), rel=1e-6)
    assert extent(fp)[1] == pytest.approx(1000.0, rel=3e-3)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_input_gives_an_empty_footprint(value: float) -> None:
    assert ground_footprint(cam(-45.0), value, 50.0) == ()
    assert ground_footprint(cam(-45.0), 30.0, 50.0, yaw=value) == ()


def test_yaw_turns_the_footprint_about_the_vehicle() -> None:
    north = ground_footprint(cam(-45.0), 30.0, 1000.0)  # no range cut: the cut's polygon does not turn
    east = ground_footprint(cam(-45.0), 30.0, 1000.0, yaw=math.pi / 2)
    turned = sorted((round(e, 6), round(-n, 6)) for n, e in east)  # east's points turned back by 90 deg
    assert turned == sorted((round(n, 6), round(e, 6)) for n, e in north)


def test_an_unstabilised_camera_rolls_with_the_vehicle_and_a_gimbal_does_not() -> None:
    roll = math.radians(10)
    level = extent(ground_footprint(cam(-90.0, stabilised=False), 30.0, 1000.0))
    rolled = extent(ground_footprint(cam(-90.0, stabilised=False), 30.0, 1000.0, roll=roll))
    gimbal = extent(ground_footprint(cam(-90.0), 30.0, 1000.0, roll=roll))
    # Rolling right (right side down) swings a body-fixed camera's view to the left: west, facing north.
    assert rolled[3] < level[3] - 5 and rolled[2] < level[2] - 5
    assert gimbal == pytest.approx(level)


def test_every_border_pixel_geolocates_inside_the_footprint() -> None:
    """The footprint and `locate_pixel` are the same geometry: the ground point under any pixel lies inside."""
    camera = CameraModel(
        640, 480, 420.0, 420.0, 330.0, 250.0, math.radians(-50), True, (-0.25, 0.08, 0, 0, 0)
    )
    lat, lon, height = 47.0, 8.0, 25.0
    fp = ground_footprint(camera, height, 1000.0, yaw=0.3)
    telemetry = Telemetry(0.0, lat, lon, height, 0.0, 0.0, 0.3)
    for u, v in ((0, 479), (320, 479), (639, 479), (320, 240), (0, 300), (639, 300)):
        geo = locate_pixel(camera, telemetry, u, v)
        assert geo is not None
        n, e = latlon_to_offset(lat, lon, geo.lat_deg, geo.lon_deg)
        assert _inside(fp, (n, e), tolerance=0.05 * math.hypot(n, e)), (u, v)


def _inside(polygon: tuple[tuple[float, float], ...], p: tuple[float, float], tolerance: float) -> bool:
    """Ray casting, with the point also accepted within `tolerance` of the outline (sampled border)."""
    inside = False
    n = len(polygon)
    for i in range(n):
        (ax, ay), (bx, by) = polygon[i], polygon[(i + 1) % n]
        if (ay > p[1]) != (by > p[1]) and p[0] < ax + (p[1] - ay) * (bx - ax) / (by - ay):
            inside = not inside
        length = math.dist((ax, ay), (bx, by))
        if length > 0:
            t = max(0.0, min(1.0, ((p[0] - ax) * (bx - ax) + (p[1] - ay) * (by - ay)) / length**2))
            if math.dist(p, (ax + t * (bx - ax), ay + t * (by - ay))) <= tolerance:
                return True
    return inside


def test_clip_polygon_keeps_the_part_on_the_positive_side() -> None:
    square = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)]
    assert polygon_area(clip_polygon(square, lambda p: 1.0 - p[0])) == pytest.approx(2.0)
    assert clip_polygon(square, lambda p: -1.0) == []
    assert polygon_area(clip_polygon(square, lambda p: p[0] + p[1] - 2.0)) == pytest.approx(2.0)
