"""Where a keyframe's candidate stands in the view now (`behaviors.live_view`), table-driven: the vehicle flown
on, turned or tilted since the keyframe, from the candidate's place as the keyframe's pose located it."""

from __future__ import annotations

import math

import pytest

from behaviors.camera_model import CameraModel
from behaviors.geolocation import locate_box, offset_to_latlon
from behaviors.geometry import Box
from behaviors.live_view import box_now, in_view_now
from behaviors.telemetry import Telemetry

CAM = CameraModel.from_hfov(640, 480, 90.0, mount_pitch_deg=-45.0)
HEIGHT = 10.0
MIDDLE = Box.from_center(320.0, 220.0, 16.0, 40.0)
BOTTOM = Box.from_center(320.0, 450.0, 16.0, 40.0)  # its foot 10 px above the image's edge


def pose(
    north_m: float = 0.0, east_m: float = 0.0, yaw_deg: float = 0.0, height_m: float = HEIGHT
) -> Telemetry:
    lat, lon = offset_to_latlon(47.0, 8.0, north_m, east_m)
    return Telemetry(1.0, lat, lon, height_m, yaw=math.radians(yaw_deg))


@pytest.mark.parametrize(
    ("box", "now", "in_view", "foot_v"),
    [
        (MIDDLE, pose(), True, MIDDLE.y2),  # not moved: where it was
        (BOTTOM, pose(), True, BOTTOM.y2),
        (BOTTOM, pose(north_m=0.1), True, None),  # 10 cm on: 5 px lower, still whole
        (BOTTOM, pose(north_m=3.0), False, None),  # flown on: below the image's bottom edge
        (MIDDLE, pose(north_m=3.0), True, None),  # from the middle: lower, still in view
        (MIDDLE, pose(north_m=30.0), False, None),  # flown past: behind the camera
        (MIDDLE, pose(east_m=8.0), True, None),  # 8 m aside: left of the middle
        (MIDDLE, pose(east_m=15.0), False, None),  # the next lane: off the image's left edge
        (MIDDLE, pose(yaw_deg=90.0), False, None),  # turned away
        (MIDDLE, pose(height_m=math.nan), False, None),  # no height: nothing to project
    ],
)
def test_where_a_keyframes_candidate_is_now(
    box: Box, now: Telemetry, in_view: bool, foot_v: float | None
) -> None:
    seen = locate_box(CAM, pose(), box)
    assert seen is not None
    assert in_view_now(CAM, box, seen, now) is in_view
    moved = box_now(CAM, box, seen, now)
    if foot_v is not None:
        assert moved is not None and moved.y2 == pytest.approx(foot_v, abs=1e-6)
        assert (moved.w, moved.h) == (box.w, box.h) and moved.cx == pytest.approx(box.cx, abs=1e-6)


def test_flying_on_moves_the_candidate_down_the_image() -> None:
    """Forward flight with a forward-pitched camera: each metre flown moves the foot point down, faster near."""
    seen = locate_box(CAM, pose(), MIDDLE)
    assert seen is not None
    feet = [box_now(CAM, MIDDLE, seen, pose(north_m=n)) for n in (0.0, 1.0, 2.0, 3.0)]
    assert all(b is not None for b in feet)
    ys = [b.y2 for b in feet if b is not None]
    steps = [b - a for a, b in zip(ys, ys[1:], strict=False)]
    assert all(s > 0 for s in steps) and steps == sorted(steps)
