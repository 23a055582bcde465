"""Where a candidate seen in a keyframe stands in the camera's view now.

A tracker starts on the candidate's keyframe and catches up through the frames since; a surveying drone flies
on meanwhile, and a person who has left the image by then leaves the tracker on the background (a seeded
search: the described person proposed from a keyframe where they were at the image's bottom edge, the tracker
on grass when the supervisor looked, rejected). Where the candidate stands, seen from the vehicle's pose now,
tells the two apart before a tracker is started: the keyframe's box moved to the pixel its foot point
projects to now (its size as in the keyframe: the range changes little in the second or two it takes).
"""

from __future__ import annotations

import math

from behaviors.apparent_size import camera_frame
from behaviors.camera_model import CameraModel
from behaviors.geolocation import GeoEstimate, foot_point, latlon_to_offset
from behaviors.geometry import Box
from behaviors.telemetry import Telemetry


def box_now(camera: CameraModel, box: Box, seen: GeoEstimate, now: Telemetry) -> Box | None:
    """`box` (the candidate's in its keyframe, standing at `seen`) where the camera sees it from `now`; None
    when its foot point is behind the camera or the pose is not finite."""
    values = (now.lat_deg, now.lon_deg, now.height_agl, now.roll, now.pitch, now.yaw)
    if not all(math.isfinite(v) for v in values):
        return None
    north, east = latlon_to_offset(now.lat_deg, now.lon_deg, seen.lat_deg, seen.lon_deg)
    forward, right, down = camera_frame(camera, north, east, now.height_agl, now.roll, now.pitch, now.yaw)
    if forward <= 1e-6:
        return None
    u, v = camera.pixel(right / forward, down / forward)
    fu, fv = foot_point(box)
    return Box(box.x + u - fu, box.y + v - fv, box.w, box.h)


def in_view_now(camera: CameraModel, box: Box, seen: GeoEstimate, now: Telemetry) -> bool:
    """Whether the whole of `box` (see `box_now`) is inside the image from `now`: a tracker started on it
    would still have the person in its first live frame."""
    moved = box_now(camera, box, seen, now)
    return (
        moved is not None
        and moved.x >= 0
        and moved.y >= 0
        and moved.x2 <= camera.width
        and moved.y2 <= camera.height
    )
