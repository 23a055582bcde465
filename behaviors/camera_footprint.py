"""The patch of flat ground the camera sees: the image's outline cast onto the ground, cut at a sane range.

The image border is sampled (so a calibrated wide lens's curved edges are followed), each sample becomes a
ray through the lens model (`behaviors/geolocation.py`), and the outline is cast onto the ground plane
`height` below the camera. Rays at or above the horizon never meet the ground, and those that meet it
far away see nothing useful, so the footprint is cut twice, exactly: first to the rays that dip below the
horizon (a half-plane in the camera's normalised image plane, where the ray's down component is linear),
then to a disc of `max_range_m` around the vehicle on the ground. Casting rays onto a plane maps straight
lines to straight lines, so the cut outline stays a polygon. Offsets are metres (north, east) from the
point under the vehicle.

Used by the survey planner (the lane spacing) and by the coverage library (`cloudtrack/coverage.py`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from behaviors.camera_model import CameraModel
from behaviors.geolocation import camera_ray_ned

Point = tuple[float, float]  # (north, east) metres, or (x, y) on the normalised image plane

BORDER_SAMPLES = 8  # samples per image edge: a distorted lens's edges are curves
RANGE_DISC_SIDES = 48  # the range cut is a regular polygon inscribed in the disc (within 0.2 % of it)
# The horizon cut keeps rays whose down component (ray (1, x, y) has length >= 1) is at least this: such a
# ray meets the ground within 1000 times the height, far beyond any range cut, so nothing useful is lost.
_MIN_DOWN = 1e-3


def clip_polygon(points: Sequence[Point], inside: Callable[[Point], float]) -> list[Point]:
    """Sutherland-Hodgman: the part of a polygon where the affine function `inside` is >= 0."""
    out: list[Point] = []
    n = len(points)
    for i in range(n):
        a, b = points[i], points[(i + 1) % n]
        fa, fb = inside(a), inside(b)
        if fa >= 0:
            out.append(a)
        if (fa >= 0) != (fb >= 0):
            t = fa / (fa - fb)
            out.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
    return out


def _border(camera: CameraModel) -> list[Point]:
    """The image outline in undistorted normalised coordinates, clockwise from the top-left corner."""
    w, h, k = float(camera.width), float(camera.height), BORDER_SAMPLES
    pixels = (
        [(w * i / k, 0.0) for i in range(k)]
        + [(w, h * i / k) for i in range(k)]
        + [(w - w * i / k, h) for i in range(k)]
        + [(0.0, h - h * i / k) for i in range(k)]
    )
    return [camera.normalised(u, v) for u, v in pixels]


def ground_footprint(
    camera: CameraModel,
    height_m: float,
    max_range_m: float,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
) -> tuple[Point, ...]:
    """The ground the camera sees within `max_range_m` of the point under the vehicle, as (north, east)
    offsets in metres; empty when it sees no ground (looking up, on the ground, or invalid input).

    Attitude in radians (yaw 0 = north, clockwise); a stabilised camera ignores roll and pitch.
    """
    values = (height_m, max_range_m, roll, pitch, yaw)
    if not all(math.isfinite(v) for v in values) or height_m <= 0 or max_range_m <= 0:
        return ()

    def ray(p: Point) -> tuple[float, float, float]:
        return camera_ray_ned(camera, p[0], p[1], roll, pitch, yaw)

    below = clip_polygon(_border(camera), lambda p: ray(p)[2] - _MIN_DOWN)
    if len(below) < 3:
        return ()
    ground: list[Point] = []
    for p in below:
        n, e, d = ray(p)
        ground.append((height_m * n / d, height_m * e / d))
    for i in range(RANGE_DISC_SIDES):
        ground = clip_polygon(ground, _left_of_disc_side(max_range_m, i))
        if len(ground) < 3:
            return ()
    return _without_repeats(ground)


def _left_of_disc_side(radius: float, i: int) -> Callable[[Point], float]:
    """Side i of the range polygon, its corners counter-clockwise in (north, east) axes: >= 0 inside."""
    a, b = 2 * math.pi * i / RANGE_DISC_SIDES, 2 * math.pi * (i + 1) / RANGE_DISC_SIDES
    an, ae = radius * math.cos(a), radius * math.sin(a)
    bn, be = radius * math.cos(b), radius * math.sin(b)
    return lambda p: (bn - an) * (p[1] - ae) - (be - ae) * (p[0] - an)


def _without_repeats(points: list[Point], tolerance: float = 1e-9) -> tuple[Point, ...]:
    out: list[Point] = []
    for p in points:
        if not out or math.dist(p, out[-1]) > tolerance:
            out.append(p)
    while len(out) > 1 and math.dist(out[0], out[-1]) <= tolerance:
        out.pop()
    return tuple(out) if len(out) >= 3 else ()


def swath_width_m(camera: CameraModel, height_m: float, max_range_m: float) -> float:
    """Width across the track of the ground a level camera sweeps while the vehicle flies straight ahead
    (the footprint's widest extent to either side); 0 when it sees no ground."""
    footprint = ground_footprint(camera, height_m, max_range_m)
    if not footprint:
        return 0.0
    easts = [e for _, e in footprint]
    return max(easts) - min(easts)


def polygon_area(points: Sequence[Point]) -> float:
    """Unsigned area of a simple polygon (shoelace formula)."""
    n = len(points)
    twice = sum(
        points[i][0] * points[(i + 1) % n][1] - points[(i + 1) % n][0] * points[i][1] for i in range(n)
    )
    return abs(twice) / 2.0
