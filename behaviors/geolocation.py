"""Where on the ground a box's foot point is: flat-ground ray casting from the camera, with an error estimate.

A pixel becomes a ray through the camera's lens model (`CameraModel.normalised`: OpenCV's distortion
inverted when the camera is calibrated, the pinhole of the field of view otherwise).

Frames: NED world, FRD body, attitude as ZYX Euler angles (yaw, pitch, roll). The camera looks along the
body's forward axis pitched by the mount; a stabilised gimbal cancels the vehicle's roll and pitch. A
pixel's ray is intersected with the ground plane `height_agl` below the camera.

A box against the image's left, right or bottom edge (`clipped_by_frame`) does not show where the person
meets the ground: part of them is outside the view, so the box's bottom centre is shifted off their feet (or,
at the bottom edge, above them), and a tracker whose target has just crossed the edge may hold such a box on
the background it left (a real-ArduCopter fleet run: NanoTrack's box stayed against the left edge, 10 px wide,
trusted for 3.9 s after the person had left the view, its estimates sliding 4-15 m on with the drone). Its
estimate is marked `clipped`; `behaviors.target_fix` lets it stand only where the track has no other. The top
edge is no such edge: a person cut off there still shows their feet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from behaviors.camera_model import CameraModel
from behaviors.geometry import Box
from behaviors.telemetry import Telemetry

# WGS-84: local radii of curvature turn metres north/east into degrees without a projection library.
_A = 6378137.0
_E2 = 6.69437999014e-3
# A ray must dip at least this much (sine of the angle below the horizon) to meet the ground.
_MIN_DIP = 1e-3

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class GeoSigmas:
    """One-sigma input errors the uncertainty estimate propagates (height, attitude, pixel)."""

    height_m: float = 0.5
    angle_rad: float = math.radians(1.0)
    pixel: float = 2.0


@dataclass(frozen=True)
class GeoEstimate:
    """A ground point: absolute position, offset from the vehicle, ranges and a one-sigma error radius."""

    lat_deg: float
    lon_deg: float
    north_m: float
    east_m: float
    ground_range_m: float
    slant_range_m: float
    sigma_m: float
    # Located from a box against the image's left, right or bottom edge: its foot point is not the person's
    # feet, and the box may hold only the background a person who left the view was last seen on.
    clipped: bool = False


def _rot_x(a: float, v: Vec3) -> Vec3:
    c, s = math.cos(a), math.sin(a)
    return (v[0], c * v[1] - s * v[2], s * v[1] + c * v[2])


def _rot_y(a: float, v: Vec3) -> Vec3:
    c, s = math.cos(a), math.sin(a)
    return (c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2])


def _rot_z(a: float, v: Vec3) -> Vec3:
    c, s = math.cos(a), math.sin(a)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


def pixel_ray_ned(camera: CameraModel, u: float, v: float, roll: float, pitch: float, yaw: float) -> Vec3:
    """The (unnormalised) NED direction of pixel (u, v) for a vehicle at the given attitude."""
    x, y = camera.normalised(u, v)  # through the lens model: wide lenses bend the edges most
    return camera_ray_ned(camera, x, y, roll, pitch, yaw)


def camera_ray_ned(camera: CameraModel, x: float, y: float, roll: float, pitch: float, yaw: float) -> Vec3:
    """The NED direction of the ray (1, x, y) in the camera's forward-right-down axes (undistorted
    normalised coordinates); linear in (x, y)."""
    ray: Vec3 = (1.0, x, y)  # FRD of the camera
    ray = _rot_y(camera.mount_pitch, ray)
    if not camera.stabilised:
        ray = _rot_y(pitch, _rot_x(roll, ray))
    return _rot_z(yaw, ray)


def _ground_offset(
    camera: CameraModel, u: float, v: float, height: float, roll: float, pitch: float, yaw: float
) -> tuple[float, float, float] | None:
    """(north, east, slant range) of the ground point under pixel (u, v); None when the ray misses."""
    n, e, d = pixel_ray_ned(camera, u, v, roll, pitch, yaw)
    norm = math.sqrt(n * n + e * e + d * d)
    if height <= 0 or d / norm < _MIN_DIP:
        return None
    t = height / d
    return (n * t, e * t, norm * t)


def offset_to_latlon(lat_deg: float, lon_deg: float, north_m: float, east_m: float) -> tuple[float, float]:
    lat = math.radians(lat_deg)
    w = math.sqrt(1.0 - _E2 * math.sin(lat) ** 2)
    meridian = _A * (1.0 - _E2) / w**3
    normal = _A / w
    return (
        lat_deg + math.degrees(north_m / meridian),
        lon_deg + math.degrees(east_m / (normal * max(math.cos(lat), 1e-9))),
    )


def latlon_to_offset(lat0_deg: float, lon0_deg: float, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(north, east) metres of a nearby point from a reference point (inverse of `offset_to_latlon`)."""
    lat = math.radians(lat0_deg)
    w = math.sqrt(1.0 - _E2 * math.sin(lat) ** 2)
    meridian = _A * (1.0 - _E2) / w**3
    normal = _A / w
    return (
        math.radians(lat_deg - lat0_deg) * meridian,
        math.radians(lon_deg - lon0_deg) * normal * max(math.cos(lat), 1e-9),
    )


def clipped_by_frame(box: Box, width: float, height: float, margin_px: float) -> bool:
    """Whether `box` reaches to within `margin_px` of the left, right or bottom edge of a `width` x `height`
    image (or past it): the person may go on beyond it, so the box's bottom centre need not be their feet.
    The top edge does not count: a standing person cut off there still shows where they stand."""
    return box.x <= margin_px or box.x2 >= width - margin_px or box.y2 >= height - margin_px


def foot_point(box: Box) -> tuple[float, float]:
    """Where a standing person meets the ground in the image: bottom centre of the box."""
    return (box.cx, box.y2)


def locate_pixel(
    camera: CameraModel, telemetry: Telemetry, u: float, v: float, sigmas: GeoSigmas = GeoSigmas()
) -> GeoEstimate | None:
    """The ground position under pixel (u, v); None for invalid input or a ray at or above the horizon."""
    t = telemetry
    values = (u, v, t.height_agl, t.roll, t.pitch, t.yaw, t.lat_deg, t.lon_deg)
    if not all(math.isfinite(x) for x in values):
        return None
    base = _ground_offset(camera, u, v, t.height_agl, t.roll, t.pitch, t.yaw)
    if base is None:
        return None
    north, east, slant = base
    # First-order propagation: move each input by plus and minus its sigma, take the larger ground
    # displacement, and add the inputs in quadrature. A perturbed ray that misses the ground (near the
    # horizon) makes the error unbounded.
    a, dh, dp = sigmas.angle_rad, sigmas.height_m, sigmas.pixel
    # (height, roll, yaw, u, v, camera pitch): the mount pitch stands for gimbal or airframe pitch error.
    deltas = (
        (dh, 0, 0, 0, 0, 0),
        (0, a, 0, 0, 0, 0),
        (0, 0, a, 0, 0, 0),
        (0, 0, 0, dp, 0, 0),
        (0, 0, 0, 0, dp, 0),
        (0, 0, 0, 0, 0, a),
    )
    variance = 0.0
    for d_h, d_roll, d_yaw, d_u, d_v, d_mount in deltas:
        worst = 0.0
        for k in (1.0, -1.0):
            cam = replace(camera, mount_pitch=camera.mount_pitch + k * d_mount) if d_mount else camera
            moved = _ground_offset(
                cam,
                u + k * d_u,
                v + k * d_v,
                t.height_agl + k * d_h,
                t.roll + k * d_roll,
                t.pitch,
                t.yaw + k * d_yaw,
            )
            if moved is None:
                worst = math.inf
                break
            worst = max(worst, (moved[0] - north) ** 2 + (moved[1] - east) ** 2)
        variance += worst
    lat, lon = offset_to_latlon(t.lat_deg, t.lon_deg, north, east)
    return GeoEstimate(lat, lon, north, east, math.hypot(north, east), slant, math.sqrt(variance))


def locate_box(
    camera: CameraModel, telemetry: Telemetry, box: Box, sigmas: GeoSigmas = GeoSigmas()
) -> GeoEstimate | None:
    """The ground position of a box's foot point (see `locate_pixel`); None for an invalid box. A box within
    a pixel sigma of the image's left, right or bottom edge (it cannot be told from one cut off there) gives
    an estimate marked `clipped`."""
    if not box.is_valid():
        return None
    u, v = foot_point(box)
    estimate = locate_pixel(camera, telemetry, u, v, sigmas)
    if estimate is not None and clipped_by_frame(box, camera.width, camera.height, sigmas.pixel):
        return replace(estimate, clipped=True)
    return estimate
