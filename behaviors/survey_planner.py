"""A search survey: a lawnmower pattern over a polygon, with lanes sized by the camera's ground footprint.

Pure planning, no I/O: `plan_survey(area, settings)` gives the mission items a ground station uploads
(`cloudtrack/mission_protocol.py`) and the figures an operator checks first (lanes, length, time to fly).
Every input it refuses raises `SurveyError` with a one-line reason.

Geometry: the polygon is laid on a local flat frame (metres north/east of its first corner, WGS-84 radii:
`behaviors/geolocation.py`), good to centimetres over the few kilometres a multicopter survey spans. The
lanes run along `angle_deg` (clockwise from north; by default the direction that needs the fewest lanes).
Across them the area is cut into equal bands no wider than the lane spacing, the camera's swath
(`behaviors/camera_footprint.py`: the footprint at the survey altitude, cut at the search range) less the
overlap (or a spacing given outright: the POD planner's, `behaviors/pod_planner.py`); each band's lane runs
through its middle, from where the band enters the polygon to where it leaves it, so the swath covers the
band edge to edge. The lanes alternate direction and start at the end
nearest `start` (the vehicle, or the polygon's first corner). A concave polygon's lane is flown straight
across a notch.

Items, as QGroundControl plans them: NAV_TAKEOFF only when asked, DO_CHANGE_SPEED when a speed is given,
then a NAV_WAYPOINT at each lane end, all at the survey altitude above home (MAV_FRAME_GLOBAL_RELATIVE_ALT).

`distance_to_area_m` says how far a point (the vehicle) is from an area: the ground tool refuses one that
is too far to be meant (a typo, or latitude and longitude swapped).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from behaviors.camera_footprint import Point, clip_polygon, polygon_area, swath_width_m
from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import MissionItem

LatLon = tuple[float, float]

MAX_VERTICES = 200  # a search area's polygon (also the bound the status report carries)
MAX_EXTENT_M = 10_000.0  # wider than a multicopter can survey in one flight: surely a typo
MIN_AREA_M2 = 1.0
MAX_LANES = 500
MAX_LATITUDE = 85.0  # the flat local frame does not hold near the poles
EARTH_RADIUS_M = 6_371_008.8  # mean radius: great-circle distances to an area far away
NEAR_M = 50_000.0  # within this, distances are measured on the flat local frame (edges, not just corners)
WAYPOINT_ACCEL_M_S2 = 2.5  # ArduCopter WPNAV_ACCEL's default: the time estimate's slow-down at each corner


class SurveyError(ValueError):
    """A survey that cannot be planned; the message is one line saying why and what to change."""


@dataclass(frozen=True)
class SurveySettings:
    altitude_m: float  # above home
    overlap: float  # side overlap between neighbouring lanes' swaths, 0 .. 0.9
    camera: CameraModel
    search_range_m: float  # the footprint's far edge (`[camera] search_range_m`)
    min_altitude_m: float  # the `[safety]` altitude band
    max_altitude_m: float
    speed_m_s: float | None = None  # DO_CHANGE_SPEED when given
    cruise_speed_m_s: float = 5.0  # the time estimate's speed when none is given (the autopilot's own)
    angle_deg: float | None = None  # lane direction, clockwise from north; None: fewest lanes
    takeoff: bool = False
    start: LatLon | None = None  # begin at the lane end nearest this point (the vehicle)
    spacing_m: float | None = None  # between lanes, at most the swath; None: the swath less the overlap


@dataclass(frozen=True)
class SurveyPlan:
    items: tuple[MissionItem, ...]
    waypoints: tuple[LatLon, ...]
    lanes: int
    length_m: float  # from the first waypoint to the last
    time_s: float  # at the speed flown, with a slow-down at every corner
    speed_m_s: float  # the speed the time is estimated at
    spacing_m: float  # between neighbouring lanes
    swath_m: float  # the camera's ground swath at the survey altitude
    angle_deg: float
    area_m2: float

    def summary(self) -> str:
        minutes, seconds = divmod(round(self.time_s), 60)
        return (
            f"{self.lanes} lanes {self.spacing_m:.1f} m apart (swath {self.swath_m:.1f} m) at "
            f"{self.angle_deg:.0f} deg, {self.length_m:.0f} m, about {minutes} min {seconds:02d} s at "
            f"{self.speed_m_s:g} m/s, {len(self.items)} mission items, area {self.area_m2 / 1e4:.2f} ha"
        )


# ------------------------------------------------------------------------------------------- polygons
def _segments_cross(p1: Point, p2: Point, q1: Point, q2: Point) -> bool:
    """Whether two closed segments share a point (touching and collinear overlap included)."""

    def orient(a: Point, b: Point, c: Point) -> float:
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    def on_segment(a: Point, b: Point, c: Point) -> bool:
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])

    scale = max(math.dist(p1, p2), math.dist(q1, q2), 1.0)
    eps = 1e-9 * scale * scale
    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    if ((d1 > eps and d2 < -eps) or (d1 < -eps and d2 > eps)) and (
        (d3 > eps and d4 < -eps) or (d3 < -eps and d4 > eps)
    ):
        return True
    return (
        (abs(d1) <= eps and on_segment(q1, q2, p1))
        or (abs(d2) <= eps and on_segment(q1, q2, p2))
        or (abs(d3) <= eps and on_segment(p1, p2, q1))
        or (abs(d4) <= eps and on_segment(p1, p2, q2))
    )


def _self_intersection(points: Sequence[Point]) -> tuple[int, int] | None:
    """The first pair of non-neighbouring edges (by index) that meet, or None for a simple polygon."""
    n = len(points)
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbours share a corner
            if _segments_cross(points[i], points[(i + 1) % n], points[j], points[(j + 1) % n]):
                return i, j
    return None


def check_polygon(corners: Sequence[LatLon]) -> tuple[LatLon, ...]:
    """The polygon's corners, checked (a repeated closing corner dropped); SurveyError says what is wrong."""
    if not corners:
        raise SurveyError("the search area is empty: give at least 3 corners (lat,lon)")
    pts = [(float(lat), float(lon)) for lat, lon in corners]
    for lat, lon in pts:
        if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
            raise SurveyError(f"corner {lat},{lon} is not a latitude,longitude")
        if abs(lat) > MAX_LATITUDE:
            raise SurveyError(f"corner {lat},{lon} is within {90 - MAX_LATITUDE:g} deg of a pole")
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts.pop()  # GeoJSON and QGC repeat the first corner at the end
    distinct = list(dict.fromkeys(pts))
    if len(distinct) < 3:
        raise SurveyError(f"the search area needs at least 3 distinct corners, got {len(distinct)}")
    if len(pts) > MAX_VERTICES:
        raise SurveyError(f"the search area has {len(pts)} corners; at most {MAX_VERTICES} are accepted")
    local = _to_local(pts[0], pts)
    if any(math.dist(a, b) < 1e-6 for a, b in zip(local, local[1:] + local[:1], strict=True)):
        raise SurveyError("the search area repeats a corner: remove the duplicate")
    extent = max(math.dist(a, b) for a in local for b in local)
    if extent > MAX_EXTENT_M:
        raise SurveyError(
            f"the search area spans {extent / 1000:.1f} km; at most {MAX_EXTENT_M / 1000:g} km is accepted "
            "(check the corners' order: lat,lon)"
        )
    crossing = _self_intersection(local)
    if crossing is not None:
        i, j = crossing
        raise SurveyError(
            f"the search area's edges {i + 1}-{(i + 1) % len(pts) + 1} and {j + 1}-{(j + 1) % len(pts) + 1} "
            "cross: the polygon intersects itself (list the corners in order around it)"
        )
    if polygon_area(local) < MIN_AREA_M2:
        raise SurveyError("the search area has no area: its corners lie on one line")
    return tuple(pts)


def rectangle(
    centre: LatLon, width_m: float, height_m: float, heading_deg: float = 0.0
) -> tuple[LatLon, ...]:
    """The corners of a `width_m` (east-west) x `height_m` (north-south) rectangle around `centre`, turned
    clockwise by `heading_deg`."""
    if not (math.isfinite(width_m) and math.isfinite(height_m)) or width_m <= 0 or height_m <= 0:
        raise SurveyError(
            f"a survey size must be two positive lengths in metres, got {width_m:g}x{height_m:g}"
        )
    c, s = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))
    corners = []
    for east, north in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        e, n = east * width_m / 2, north * height_m / 2
        corners.append(offset_to_latlon(centre[0], centre[1], n * c - e * s, e * c + n * s))
    return tuple(corners)


def _to_local(origin: LatLon, pts: Sequence[LatLon]) -> list[Point]:
    return [latlon_to_offset(origin[0], origin[1], lat, lon) for lat, lon in pts]


# -------------------------------------------------------------------------------------------- lanes
def _rotate(points: Sequence[Point], angle_deg: float) -> list[Point]:
    """(north, east) into lane axes (along, across): `along` points along the lanes' direction."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return [(n * c + e * s, -n * s + e * c) for n, e in points]


def _unrotate(p: Point, angle_deg: float) -> Point:
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    along, across = p
    return (along * c - across * s, along * s + across * c)


def _band(points: Sequence[Point], low: float, high: float) -> list[Point]:
    """The part of a polygon (lane axes) with `across` in [low, high]."""
    return clip_polygon(clip_polygon(points, lambda p: p[1] - low), lambda p: high - p[1])


def _lanes(
    local: Sequence[Point], angle_deg: float, spacing: float
) -> tuple[list[tuple[Point, Point]], float]:
    """Each band's lane as (start, end) in lane axes, bands in order across, all running `along`+, and the
    bands' width."""
    rotated = _rotate(local, angle_deg)
    low = min(p[1] for p in rotated)
    high = max(p[1] for p in rotated)
    count = max(1, math.ceil((high - low) / spacing - 1e-9))
    width = (high - low) / count
    lanes = []
    for k in range(count):
        band = _band(rotated, low + k * width, low + (k + 1) * width)
        if len(band) < 3:
            continue
        across = low + (k + 0.5) * width
        lanes.append(((min(p[0] for p in band), across), (max(p[0] for p in band), across)))
    return lanes, width


def _fewest_lanes_angle(local: Sequence[Point]) -> float:
    """The lane direction (whole degrees, 0-179) across which the polygon is narrowest."""

    def width(angle: float) -> float:
        across = [p[1] for p in _rotate(local, angle)]
        return max(across) - min(across)

    return min(range(180), key=lambda a: (round(width(a), 6), a))


def _order(lanes: list[tuple[Point, Point]], start: Point) -> list[Point]:
    """Boustrophedon: lanes alternate direction; of the four ways to fly them, the one that begins nearest
    `start` (lane axes)."""
    best: list[Point] = []
    for reverse_lanes in (False, True):
        seq = lanes[::-1] if reverse_lanes else lanes
        for first_backwards in (False, True):
            path: list[Point] = []
            for k, (a, b) in enumerate(seq):
                backwards = (k % 2 == 1) != first_backwards
                path.extend((b, a) if backwards else (a, b))
            if not best or math.dist(path[0], start) < math.dist(best[0], start) - 1e-9:
                best = path
    return best


def leg_time_s(length_m: float, speed_m_s: float, accel_m_s2: float = WAYPOINT_ACCEL_M_S2) -> float:
    """A leg flown from rest to rest: accelerate, cruise, brake (a triangle profile on a short leg)."""
    if length_m <= 0:
        return 0.0
    if length_m >= speed_m_s * speed_m_s / accel_m_s2:
        return length_m / speed_m_s + speed_m_s / accel_m_s2
    return 2.0 * math.sqrt(length_m / accel_m_s2)


def lane_axes(corners: Sequence[LatLon], angle_deg: float | None = None) -> tuple[float, float]:
    """The lanes' direction (`angle_deg`, or the one that needs the fewest lanes) and the polygon's width
    across them in metres; `corners` as `check_polygon` returns them."""
    local = _to_local(corners[0], corners)
    angle = _fewest_lanes_angle(local) if angle_deg is None else angle_deg % 180.0
    across = [p[1] for p in _rotate(local, angle)]
    return angle, max(across) - min(across)


def plan_survey(area: Sequence[LatLon], settings: SurveySettings) -> SurveyPlan:
    """The survey over `area` (corners as lat, lon); SurveyError with a one-line reason when it cannot be."""
    return plan_checked(check_polygon(area), settings)


def plan_checked(corners: tuple[LatLon, ...], settings: SurveySettings) -> SurveyPlan:
    """`plan_survey` over corners `check_polygon` has checked (a planner trying many plans checks once)."""
    s = settings
    if not math.isfinite(s.altitude_m) or not s.min_altitude_m <= s.altitude_m <= s.max_altitude_m:
        raise SurveyError(
            f"altitude {s.altitude_m:g} m is outside the safety band {s.min_altitude_m:g}-{s.max_altitude_m:g} m "
            "([safety] min_altitude_m, max_altitude_m)"
        )
    if not (math.isfinite(s.overlap) and 0.0 <= s.overlap <= 0.9):
        raise SurveyError(f"overlap {s.overlap:g} must be between 0 and 0.9 (a fraction of the swath)")
    if s.speed_m_s is not None and not (math.isfinite(s.speed_m_s) and 0.5 <= s.speed_m_s <= 30.0):
        raise SurveyError(f"speed {s.speed_m_s:g} m/s must be between 0.5 and 30 m/s")
    if s.angle_deg is not None and not math.isfinite(s.angle_deg):
        raise SurveyError("the lane angle must be a number of degrees")
    swath = swath_width_m(s.camera, s.altitude_m, s.search_range_m)
    if swath < 1.0:
        raise SurveyError(
            f"the camera sees no ground within {s.search_range_m:g} m from {s.altitude_m:g} m "
            "([camera] mount_pitch_deg looks at or above the horizon?)"
        )
    spacing = swath * (1.0 - s.overlap)
    if s.spacing_m is not None:
        if not (math.isfinite(s.spacing_m) and 0.0 < s.spacing_m <= swath * (1.0 + 1e-9)):
            raise SurveyError(
                f"lanes {s.spacing_m:g} m apart leave gaps: the camera's swath is {swath:.1f} m at "
                f"{s.altitude_m:g} m"
            )
        spacing = s.spacing_m
    origin = corners[0]
    local = _to_local(origin, corners)
    angle = _fewest_lanes_angle(local) if s.angle_deg is None else s.angle_deg % 180.0
    rotated = _rotate(local, angle)
    across = [p[1] for p in rotated]
    if (max(across) - min(across)) / spacing > MAX_LANES:
        raise SurveyError(
            f"the survey would need more than {MAX_LANES} lanes {spacing:.1f} m apart: raise the altitude, "
            "lower the overlap or split the area"
        )
    lanes, band_width = _lanes(local, angle, spacing)
    start_ne = latlon_to_offset(origin[0], origin[1], *s.start) if s.start is not None else local[0]
    path = _order(lanes, _rotate([start_ne], angle)[0])
    waypoints = tuple(offset_to_latlon(origin[0], origin[1], *_unrotate(p, angle)) for p in path)
    speed = s.speed_m_s if s.speed_m_s is not None else s.cruise_speed_m_s
    legs = [math.dist(a, b) for a, b in zip(path, path[1:], strict=False)]
    return SurveyPlan(
        items=mission_items(s, s.speed_m_s, waypoints),
        waypoints=waypoints,
        lanes=len(lanes),
        length_m=sum(legs),
        time_s=sum(leg_time_s(leg, speed) for leg in legs),
        speed_m_s=speed,
        spacing_m=band_width,
        swath_m=swath,
        angle_deg=angle,
        area_m2=polygon_area(local),
    )


def mission_items(
    s: SurveySettings, speed_m_s: float | None, waypoints: Sequence[LatLon]
) -> tuple[MissionItem, ...]:
    """The mission for a path: a takeoff where asked, the speed where one is set, the waypoints."""
    items: list[MissionItem] = []
    if s.takeoff:
        items.append(MissionItem.takeoff(s.altitude_m))
    if speed_m_s is not None:
        items.append(MissionItem.change_speed(speed_m_s))
    items.extend(MissionItem.waypoint(lat, lon, s.altitude_m) for lat, lon in waypoints)
    return tuple(items)


# ------------------------------------------------------------------------------------------ distance
def _great_circle_m(a: LatLon, b: LatLon) -> float:
    lat1, lon1, lat2, lon2 = (math.radians(v) for v in (*a, *b))
    h = math.sin((lat2 - lat1) / 2) ** 2 + math.cos(lat1) * math.cos(lat2) * math.sin((lon2 - lon1) / 2) ** 2
    return 2 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))


def _to_segment_m(p: Point, a: Point, b: Point) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return math.dist(p, (a[0] + t * dx, a[1] + t * dy))


def _inside(p: Point, polygon: Sequence[Point]) -> bool:
    inside = False
    for a, b in zip(polygon, [*polygon[1:], polygon[0]], strict=True):
        if (a[1] > p[1]) != (b[1] > p[1]) and p[0] < a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1]):
            inside = not inside
    return inside


def distance_to_area_m(point: LatLon, corners: Sequence[LatLon]) -> float:
    """How far `point` is from the area (0 inside it): to its nearest edge on the flat local frame around
    `point` within `NEAR_M`, else the great-circle distance to its nearest corner."""
    nearest = min(_great_circle_m(point, corner) for corner in corners)
    if nearest > NEAR_M:
        return nearest
    local = _to_local(point, corners)
    if _inside((0.0, 0.0), local):
        return 0.0
    return min(_to_segment_m((0.0, 0.0), a, b) for a, b in zip(local, [*local[1:], local[0]], strict=True))


def swapped(corners: Sequence[LatLon]) -> tuple[LatLon, ...] | None:
    """The corners with latitude and longitude exchanged, when they still make latitudes (|lon| <= 90)."""
    if any(abs(lon) > 90 for _, lon in corners):
        return None
    return tuple((lon, lat) for lat, lon in corners)


def too_far(
    corners: Sequence[LatLon], reference: LatLon, max_m: float, what: str, swap_note: str = ""
) -> str | None:
    """Why an area farther than `max_m` from `reference` (`what`: "the vehicle") is refused, saying that
    latitude and longitude may be swapped (and `swap_note`) when swapping them brings it near; None when it
    is near enough."""
    distance = distance_to_area_m(reference, corners)
    if distance <= max_m:
        return None
    message = (
        f"the search area is {_distance_words(distance)} from {what} ({reference[0]:.6f},{reference[1]:.6f}); "
        f"at most {max_m:g} m is accepted ([safety] max_survey_distance_m)"
    )
    turned = swapped(corners)
    if turned is not None and (near := distance_to_area_m(reference, turned)) <= max_m:
        where = f"{what} is inside it" if near == 0 else f"it is {_distance_words(near)} from {what}"
        message += f": latitude and longitude may be swapped (swapped, {where}{swap_note})"
    return message


def _distance_words(metres: float) -> str:
    if metres >= 10_000:
        return f"{metres / 1000:.0f} km"
    return f"{metres / 1000:.1f} km" if metres >= 1000 else f"{metres:.0f} m"
