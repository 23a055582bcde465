"""The pinhole camera on the vehicle: intrinsics and how it is mounted."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics in pixels and the mount's pitch (radians, negative looks down).

    Image axes: u to the right, v down. The camera looks along the body's forward axis, pitched by
    `mount_pitch`; with `stabilised` the gimbal holds that pitch against the vehicle's own pitch/roll.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    mount_pitch: float = math.radians(-45.0)
    stabilised: bool = True

    @classmethod
    def from_hfov(
        cls, width: int, height: int, hfov_deg: float, mount_pitch_deg: float = -45.0, stabilised: bool = True
    ) -> CameraModel:
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0, math.radians(mount_pitch_deg), stabilised)
