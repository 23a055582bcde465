"""Target geolocation against synthetic geometry with known answers (exact inputs: error < 1 % of range)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from behaviors.camera_model import CameraModel
from behaviors.geolocation import (
    GeoSigmas,
    clipped_by_frame,
    foot_point,
    latlon_to_offset,
    locate_box,
    locate_pixel,
    offset_to_latlon,
)
from behaviors.geometry import Box
from behaviors.telemetry import Telemetry

CAM = CameraModel.from_hfov(640, 480, 70.0, -45.0)
LAT, LON = 47.3769, 8.5417


def haversine_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    r = 6371008.8
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * r * math.asin(math.sqrt(a))


def project(
    cam: CameraModel, roll: float, pitch: float, yaw: float, height: float, north: float, east: float
) -> tuple[float, float, float]:
    """Independent pinhole projection of a ground point (rotation matrices, not the library's ray code)."""

    def rx(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    body = rz(yaw) if cam.stabilised else rz(yaw) @ ry(pitch) @ rx(roll)
    r = body @ ry(cam.mount_pitch)  # columns: camera forward, right, down in NED
    p = np.array([north, east, height])  # from the camera down to the ground point
    z, x, y = p @ r[:, 0], p @ r[:, 1], p @ r[:, 2]
    return cam.cx + cam.fx * x / z, cam.cy + cam.fy * y / z, float(z)


def test_known_answers_for_the_optical_axis() -> None:
    h = 30.0
    for yaw, north, east in (
        (0.0, h, 0.0),
        (math.pi / 2, 0.0, h),
        (math.pi, -h, 0.0),
        (-math.pi / 2, 0.0, -h),
    ):
        est = locate_pixel(CAM, Telemetry(0, LAT, LON, h, yaw=yaw), CAM.cx, CAM.cy)
        assert est is not None
        assert math.isclose(est.north_m, north, abs_tol=1e-9) and math.isclose(est.east_m, east, abs_tol=1e-9)
        assert math.isclose(est.ground_range_m, h) and math.isclose(est.slant_range_m, h * math.sqrt(2))
    nadir = replace(CAM, mount_pitch=-math.pi / 2)
    est = locate_pixel(nadir, Telemetry(0, LAT, LON, 25.0), CAM.cx, CAM.cy)
    assert est is not None and est.ground_range_m < 1e-9 and math.isclose(est.slant_range_m, 25.0)
    assert math.isclose(est.lat_deg, LAT) and math.isclose(est.lon_deg, LON)


def test_pixel_right_of_centre_lies_to_the_right_of_the_heading() -> None:
    est = locate_pixel(CAM, Telemetry(0, LAT, LON, 20.0), CAM.cx + 100, CAM.cy)
    assert est is not None and est.east_m > 0 and est.north_m > 0
    west = locate_pixel(CAM, Telemetry(0, LAT, LON, 20.0, yaw=math.pi), CAM.cx + 100, CAM.cy)
    assert west is not None and west.east_m < 0 and west.north_m < 0


def test_stabilised_camera_ignores_vehicle_tilt_and_fixed_mount_does_not() -> None:
    tilted = Telemetry(0, LAT, LON, 20.0, roll=0.1, pitch=-math.radians(10))
    level = locate_pixel(CAM, Telemetry(0, LAT, LON, 20.0), CAM.cx, CAM.cy)
    assert level is not None and locate_pixel(CAM, tilted, CAM.cx, CAM.cy) == level
    fixed = replace(CAM, mount_pitch=math.radians(-35), stabilised=False)
    nose_down = locate_pixel(fixed, Telemetry(0, LAT, LON, 20.0, pitch=-math.radians(10)), CAM.cx, CAM.cy)
    assert nose_down is not None and math.isclose(nose_down.north_m, 20.0) and abs(nose_down.east_m) < 1e-9


@settings(max_examples=200, deadline=None)
@given(
    height=st.floats(3.0, 120.0),
    yaw=st.floats(-math.pi, math.pi),
    roll=st.floats(-0.3, 0.3),
    pitch=st.floats(-0.3, 0.3),
    mount_deg=st.floats(-90.0, -10.0),
    stabilised=st.booleans(),
    bearing=st.floats(-math.pi, math.pi),
    ground=st.floats(0.0, 300.0),
    lat=st.floats(-70.0, 70.0),
)
def test_synthetic_ground_points_are_recovered(
    height: float,
    yaw: float,
    roll: float,
    pitch: float,
    mount_deg: float,
    stabilised: bool,
    bearing: float,
    ground: float,
    lat: float,
) -> None:
    cam = replace(CAM, mount_pitch=math.radians(mount_deg), stabilised=stabilised)
    north, east = ground * math.cos(bearing), ground * math.sin(bearing)
    u, v, depth = project(cam, roll, pitch, yaw, height, north, east)
    assume(depth > 0.1 and 0 <= u < cam.width and 0 <= v < cam.height)
    est = locate_pixel(cam, Telemetry(0, lat, 10.0, height, roll=roll, pitch=pitch, yaw=yaw), u, v)
    slant = math.sqrt(ground**2 + height**2)
    assert est is not None
    assert math.hypot(est.north_m - north, est.east_m - east) < 0.01 * slant
    assert abs(est.slant_range_m - slant) < 0.01 * slant
    # Latitude/longitude: the great-circle distance and the offsets agree within 1 % of the range.
    assert abs(haversine_m(lat, 10.0, est.lat_deg, est.lon_deg) - ground) < 0.01 * slant
    back_n, back_e = latlon_to_offset(lat, 10.0, est.lat_deg, est.lon_deg)
    assert math.hypot(back_n - north, back_e - east) < 0.01 * slant


def test_box_foot_point_is_what_gets_located() -> None:
    box = Box(300, 250, 40, 100)
    assert foot_point(box) == (320, 350)
    tel = Telemetry(0, LAT, LON, 20.0, yaw=0.3)
    assert locate_box(CAM, tel, box) == locate_pixel(CAM, tel, 320, 350)
    assert locate_box(CAM, tel, Box(0, 0, 0, 10)) is None


@pytest.mark.parametrize(
    ("box", "clipped", "why"),
    [
        (Box(300, 250, 40, 100), False, "inside the frame"),
        (Box(27.0, 0.0, 16.4, 24.2), False, "cut off at the top: the feet are still seen"),
        (Box(3, 9, 15, 26), False, "3 px from the left edge: more than the pixel sigma"),
        (Box(2, 6, 11, 21), True, "2 px from the left edge: within the pixel sigma"),
        (Box(1, 7, 10, 19), True, "against the left edge (a tracker left on the background there)"),
        (Box(-6, 20, 12, 26), True, "past the left edge"),
        (Box(600, 100, 38, 60), True, "against the right edge (x2 638)"),
        (Box(600, 100, 37, 60), False, "3 px from the right edge"),
        (Box(300, 400, 20, 78.5), True, "against the bottom edge: the feet may be below the frame"),
        (Box(300, 400, 20, 77), False, "3 px above the bottom edge"),
    ],
)
def test_a_box_against_the_side_or_bottom_edge_is_clipped(box: Box, clipped: bool, why: str) -> None:
    assert clipped_by_frame(box, 640, 480, GeoSigmas().pixel) is clipped, why
    est = locate_box(CAM, Telemetry(0, LAT, LON, 10.0, yaw=0.3), box)
    assert est is not None
    assert est.clipped is clipped, why
    # Marked, not moved: the position and sigma are the foot point's all the same.
    u, v = foot_point(box)
    unmarked = locate_pixel(CAM, Telemetry(0, LAT, LON, 10.0, yaw=0.3), u, v)
    assert unmarked is not None and replace(est, clipped=False) == unmarked


def test_rays_at_or_above_the_horizon_and_bad_inputs_give_none() -> None:
    tel = Telemetry(0, LAT, LON, 20.0)
    horizon_v = CAM.cy - CAM.fy * math.tan(math.radians(45))  # the horizon row for a 45 degree mount
    assert locate_pixel(CAM, tel, CAM.cx, horizon_v) is None
    assert locate_pixel(CAM, tel, CAM.cx, horizon_v - 50) is None
    assert locate_pixel(CAM, replace(tel, height_agl=0.0), CAM.cx, CAM.cy) is None
    assert locate_pixel(CAM, replace(tel, height_agl=math.nan), CAM.cx, CAM.cy) is None
    assert locate_pixel(CAM, replace(tel, yaw=math.inf), CAM.cx, CAM.cy) is None
    assert locate_pixel(CAM, tel, math.nan, CAM.cy) is None


def test_uncertainty_grows_with_range_and_vanishes_with_exact_inputs() -> None:
    tel = Telemetry(0, LAT, LON, 20.0)
    near = locate_pixel(CAM, tel, CAM.cx, CAM.cy + 150)
    far = locate_pixel(CAM, tel, CAM.cx, CAM.cy - 150)
    assert near is not None and far is not None and far.ground_range_m > near.ground_range_m
    assert 0 < near.sigma_m < far.sigma_m
    # One degree of attitude error at ~20 m ground range moves the point by roughly 0.5 m or more.
    axis = locate_pixel(CAM, tel, CAM.cx, CAM.cy)
    assert axis is not None and 0.5 < axis.sigma_m < 3.0
    exact = locate_pixel(CAM, tel, CAM.cx, CAM.cy, GeoSigmas(0.0, 0.0, 0.0))
    assert exact is not None and exact.sigma_m == 0.0
    # Close to the horizon the perturbed rays miss the ground: an unbounded error, said honestly.
    grazing = locate_pixel(CAM, tel, CAM.cx, CAM.cy - CAM.fy * math.tan(math.radians(44.9)))
    assert grazing is not None and grazing.sigma_m == math.inf


def test_offset_round_trip() -> None:
    lat, lon = offset_to_latlon(LAT, LON, 1234.5, -987.6)
    n, e = latlon_to_offset(LAT, LON, lat, lon)
    assert math.isclose(n, 1234.5, rel_tol=1e-9) and math.isclose(e, -987.6, rel_tol=1e-9)
