"""How big a target would look in a keyframe: a box of the target's size, standing on flat ground at a place,
projected into the camera from the vehicle's pose.

The size is the one the detection curve is measured in (`behaviors/detection_curve.py`): sqrt(w * h) of
the target's bounding box in keyframe pixels (camera pixels times the keyframe's downscale). The target is
an upright box (`TargetShape`: a standing person is 1.7 x 0.5 x 0.3 m) or a flat one (a person lying down,
0.3 m tall and 1.7 m long); its heading is unknown, so the size is the mean of the box turned along the
line of sight and across it. The lens is the pinhole of the camera's intrinsics (distortion changes a
target's size by a few per cent at the edges, well inside the curve's bins).

Offsets are metres north and east of the point under the vehicle; attitude in radians as in
`behaviors/geolocation.py` (yaw 0 = north, clockwise; a stabilised camera ignores roll and pitch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from behaviors.camera_model import CameraModel

Posture = Literal["standing", "lying"]


@dataclass(frozen=True)
class TargetShape:
    """The box a target fills: `height_m` up from the ground, `length_m` x `width_m` on it."""

    height_m: float
    length_m: float
    width_m: float

    @classmethod
    def person(cls, posture: Posture = "standing", height_m: float = 1.7) -> TargetShape:
        """A person of `height_m`: upright, or lying at full length."""
        if posture == "lying":
            return cls(0.3, height_m, 0.5)
        return cls(height_m, 0.5, 0.3)

    @classmethod
    def for_class(
        cls, target_class: str, posture: Posture = "standing", height_m: float = 1.7
    ) -> TargetShape:
        """The box of a superset class: a person as `person`, else a typical one of the class (a person's
        box for a class not listed, the smallest target a search looks for)."""
        if target_class == "person":
            return cls.person(posture, height_m)
        return CLASS_SHAPES.get(target_class, cls.person(posture, height_m))


CLASS_SHAPES: dict[str, TargetShape] = {
    "car": TargetShape(1.5, 4.5, 1.8),
    "truck": TargetShape(3.0, 8.0, 2.5),
    "bus": TargetShape(3.0, 12.0, 2.5),
    "motorcycle": TargetShape(1.2, 2.0, 0.8),
    "bicycle": TargetShape(1.1, 1.8, 0.6),
    "boat": TargetShape(1.5, 6.0, 2.5),
}


def camera_frame(
    camera: CameraModel, north: float, east: float, down: float, roll: float, pitch: float, yaw: float
) -> tuple[float, float, float]:
    """A NED offset from the camera in the camera's forward-right-down axes (the inverse of
    `behaviors.geolocation.camera_ray_ned`)."""
    c, s = math.cos(-yaw), math.sin(-yaw)
    v = (c * north - s * east, s * north + c * east, down)
    if not camera.stabilised:
        c, s = math.cos(-pitch), math.sin(-pitch)
        v = (c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2])
        c, s = math.cos(-roll), math.sin(-roll)
        v = (v[0], c * v[1] - s * v[2], s * v[1] + c * v[2])
    c, s = math.cos(-camera.mount_pitch), math.sin(-camera.mount_pitch)
    return (c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2])


def _box_px(
    camera: CameraModel,
    height_m: float,
    attitude: tuple[float, float, float],
    north: float,
    east: float,
    shape: TargetShape,
    along: bool,
) -> tuple[float, float, float, float] | None:
    """The image box (u0, v0, u1, v1) of the target's box at (north, east), its length along the line of
    sight (`along`) or across it; None when any corner is behind the camera."""
    bearing = math.atan2(east, north)
    half_l, half_w = shape.length_m / 2, shape.width_m / 2
    if not along:
        half_l, half_w = half_w, half_l
    cb, sb = math.cos(bearing), math.sin(bearing)
    us, vs = [], []
    for dl in (-half_l, half_l):
        for dw in (-half_w, half_w):
            n = north + dl * cb - dw * sb
            e = east + dl * sb + dw * cb
            for up in (0.0, shape.height_m):
                f, r, d = camera_frame(camera, n, e, height_m - up, *attitude)
                if f <= 1e-6:
                    return None
                us.append(camera.cx + camera.fx * r / f)
                vs.append(camera.cy + camera.fy * d / f)
    return min(us), min(vs), max(us), max(vs)


def apparent_size_px(
    camera: CameraModel,
    height_m: float,
    north: float,
    east: float,
    shape: TargetShape,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
    keyframe_width: int = 640,
) -> float:
    """The target's size in keyframe pixels at (north, east) from the point under the vehicle, `height_m`
    below the camera; 0 when any of it is outside the image (either way round) or behind the camera."""
    if not all(math.isfinite(v) for v in (height_m, north, east, roll, pitch, yaw)) or height_m <= 0:
        return 0.0
    sizes = []
    for along in (True, False):
        box = _box_px(camera, height_m, (roll, pitch, yaw), north, east, shape, along)
        if box is None:
            return 0.0
        u0, v0, u1, v1 = box
        if not (u0 >= 0 and u1 < camera.width and v0 >= 0 and v1 < camera.height):
            return 0.0  # cut by the image's edge: the curve was not measured on such views
        sizes.append(math.sqrt((u1 - u0) * (v1 - v0)))
    return min(1.0, keyframe_width / camera.width) * (sizes[0] + sizes[1]) / 2
