"""Coverage of a search area: what the camera has seen along the flown track, as shapely geometry.

The companion adds a view per pose (`CoverageMap.add_view`: where the vehicle is, its height and
attitude); each view is the camera's ground footprint (`behaviors/camera_footprint.py`: the image outline on
flat ground, cut at the search range), laid on a local flat frame of metres (x east, y north) around the
search area's first corner. `coverage()` is the share of the search area inside the union of the views;
`covered_rings()` is that union, clipped to the area (the companion reports it clipped to the area grown by
its search range: in a fleet a vehicle's camera sees into its neighbours' parts, and the mission's merged map
must count that; clipped to its own part, a strip the neighbour's lane saw of a part whose vehicle went home
stayed "unseen" on the merged map) and simplified to what a status report carries
(CONTRACT: at most 20 rings and 500 vertices in all), as [lat, lon] rings: outer boundaries
counter-clockwise, holes (unseen patches inside) clockwise, as GeoJSON orders them (x = longitude), each
listed once without repeating its first corner. `geometry_from_rings` turns such rings back into a
shapely geometry (the back-end's GeoJSON/KML of the covered area).

A mission planned elsewhere (QGroundControl, Mission Planner) carries no polygon, only waypoints:
`area_from_waypoints` gives the search area they sweep.

Views are thinned (a new one only after the vehicle moved, turned or climbed noticeably) and merged into
the union in batches, so a long flight stays cheap.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass

import shapely
from shapely.geometry import LinearRing, MultiPolygon, Point, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

from behaviors.camera_footprint import ground_footprint
from behaviors.camera_model import CameraModel
from behaviors.geolocation import latlon_to_offset, offset_to_latlon

LatLon = tuple[float, float]
MAX_RINGS = 20
MAX_VERTICES = 500
BATCH = 32  # views merged into the union at a time


@dataclass(frozen=True)
class LocalFrame:
    """Metres east (x) and north (y) of an origin; WGS-84 radii at the origin (good over a few km)."""

    lat: float
    lon: float

    def xy(self, lat: float, lon: float) -> tuple[float, float]:
        north, east = latlon_to_offset(self.lat, self.lon, lat, lon)
        return east, north

    def latlon(self, x: float, y: float) -> LatLon:
        return offset_to_latlon(self.lat, self.lon, y, x)

    def polygon(self, corners: Sequence[LatLon]) -> Polygon:
        return Polygon([self.xy(lat, lon) for lat, lon in corners])


def footprint_polygon(
    camera: CameraModel,
    frame: LocalFrame,
    lat: float,
    lon: float,
    height_m: float,
    yaw: float,
    search_range_m: float,
    roll: float = 0.0,
    pitch: float = 0.0,
) -> Polygon:
    """The ground the camera sees from a pose, in `frame`'s metres (empty when it sees none)."""
    outline = ground_footprint(camera, height_m, search_range_m, roll, pitch, yaw)
    if not outline:
        return Polygon()
    x0, y0 = frame.xy(lat, lon)
    return Polygon([(x0 + east, y0 + north) for north, east in outline])


class CoverageMap:
    """The seen part of one search area, grown view by view. Not thread-safe (one owner: the main loop)."""

    def __init__(
        self,
        area: Sequence[LatLon],
        camera: CameraModel,
        search_range_m: float,
        min_step_m: float = 2.0,
        min_turn_deg: float = 5.0,
        min_climb_m: float = 1.0,
    ) -> None:
        if len(area) < 3:
            raise ValueError("a search area needs at least 3 corners")
        self.frame = LocalFrame(area[0][0], area[0][1])
        self.area = shapely.make_valid(self.frame.polygon(area))
        if self.area.area <= 0:
            raise ValueError("the search area has no area")
        self.area_corners = tuple((float(lat), float(lon)) for lat, lon in area)
        self.camera = camera
        self.search_range_m = search_range_m
        self.min_step_m = min_step_m
        self.min_turn = math.radians(min_turn_deg)
        self.min_climb_m = min_climb_m
        self.views = 0  # views merged (after thinning)
        self._covered: BaseGeometry = Polygon()
        self._pending: list[Polygon] = []
        self._last: tuple[float, float, float, float] | None = None  # x, y, height, yaw of the last view

    def add_view(
        self, lat: float, lon: float, height_m: float, yaw: float, roll: float = 0.0, pitch: float = 0.0
    ) -> bool:
        """Add what the camera sees from this pose; False when it is too close to the last view to matter
        (or sees no ground)."""
        if not all(math.isfinite(v) for v in (lat, lon, height_m, yaw, roll, pitch)):
            return False
        x, y = self.frame.xy(lat, lon)
        if self._last is not None:
            lx, ly, lh, lyaw = self._last
            turned = abs(math.remainder(yaw - lyaw, math.tau))
            if (
                math.hypot(x - lx, y - ly) < self.min_step_m
                and turned < self.min_turn
                and abs(height_m - lh) < self.min_climb_m
            ):
                return False
        view = footprint_polygon(
            self.camera, self.frame, lat, lon, height_m, yaw, self.search_range_m, roll, pitch
        )
        if view.is_empty:
            return False
        self._last = (x, y, height_m, yaw)
        self._pending.append(view)
        self.views += 1
        if len(self._pending) >= BATCH:
            self._merge()
        return True

    def _merge(self) -> None:
        if self._pending:
            self._covered = shapely.union_all([self._covered, *self._pending])
            self._pending.clear()

    @property
    def covered(self) -> BaseGeometry:
        """Everything seen so far (metres in `frame`), inside the search area or not."""
        self._merge()
        return self._covered

    def coverage(self) -> float:
        """The share of the search area seen so far, 0..1."""
        return float(min(1.0, self.covered.intersection(self.area).area / self.area.area))

    def covered_rings(
        self, max_rings: int = MAX_RINGS, max_vertices: int = MAX_VERTICES, beyond_m: float = 0.0
    ) -> list[list[list[float]]]:
        """The seen part of the search area for a status report: [lat, lon] rings (see the module doc).
        `beyond_m` > 0: the seen ground within that distance of the area too (a fleet's vehicle sees into
        its neighbours' parts, and the mission's merged map counts it there)."""
        within = self.area.buffer(beyond_m, join_style="mitre") if beyond_m > 0 else self.area
        return bounded_rings(self.covered.intersection(within), self.frame, max_rings, max_vertices)


def fly_path(cover: CoverageMap, path: Sequence[LatLon], height_m: float, step_m: float = 2.0) -> CoverageMap:
    """Add the views along straight legs between `path`'s points at `height_m`, facing along each leg (as the
    autopilot flies a survey), one every `step_m`: what a flight exactly on the plan would see."""
    frame = cover.frame
    points = [frame.xy(lat, lon) for lat, lon in path]
    for (x0, y0), (x1, y1) in zip(points, points[1:], strict=False):
        length = math.hypot(x1 - x0, y1 - y0)
        if length <= 0:
            continue
        yaw = math.atan2(x1 - x0, y1 - y0)  # clockwise from north: atan2(east, north)
        for k in range(math.ceil(length / step_m) + 1):
            t = min(1.0, k * step_m / length)
            cover.add_view(*frame.latlon(x0 + t * (x1 - x0), y0 + t * (y1 - y0)), height_m, yaw)
    return cover


def _polygons(geometry: BaseGeometry) -> list[Polygon]:
    if isinstance(geometry, Polygon):
        return [] if geometry.is_empty else [geometry]
    return [p for g in getattr(geometry, "geoms", ()) for p in _polygons(g)]


def _vertices(polygons: Sequence[Polygon]) -> int:
    return sum(len(p.exterior.coords) - 1 + sum(len(r.coords) - 1 for r in p.interiors) for p in polygons)


def bounded_rings(
    geometry: BaseGeometry, frame: LocalFrame, max_rings: int = MAX_RINGS, max_vertices: int = MAX_VERTICES
) -> list[list[list[float]]]:
    """`geometry` (metres in `frame`) as at most `max_rings` rings of at most `max_vertices` vertices in all:
    the largest patches first, then their largest holes; simplified (Douglas-Peucker, topology kept) with a
    growing tolerance until the vertices fit."""
    if max_rings < 1 or max_vertices < 3 * max_rings:
        raise ValueError("need at least one ring and three vertices per ring")
    parts = sorted(_polygons(geometry), key=lambda p: -p.area)[:max_rings]
    holes = sorted(
        ((Polygon(ring).area, i, ring) for i, p in enumerate(parts) for ring in p.interiors),
        key=lambda h: -h[0],
    )[: max_rings - len(parts)]
    kept = [Polygon(p.exterior, [ring for _, j, ring in holes if j == i]) for i, p in enumerate(parts)]
    tolerance = 0.25
    while _vertices(kept) > max_vertices and tolerance < 1e5:
        kept = [p for p in (q.simplify(tolerance, preserve_topology=True) for q in kept) if not p.is_empty]
        kept = [p for g in kept for p in _polygons(g)]
        tolerance *= 2
    rings: list[list[list[float]]] = []
    for polygon in kept:
        polygon = orient(polygon, 1.0)  # exterior counter-clockwise, holes clockwise (x east, y north)
        for ring in (polygon.exterior, *polygon.interiors):
            coords = list(ring.coords)[:-1]
            rings.append([[round(v, 7) for v in frame.latlon(x, y)] for x, y in coords])
    return rings[:max_rings]


def geometry_from_rings(rings: Sequence[Sequence[Sequence[float]]]) -> BaseGeometry:
    """Rings as `covered_rings` writes them ([lat, lon], outer counter-clockwise, holes clockwise) back to a
    shapely (Multi)Polygon in longitude/latitude (x, y), as GeoJSON and KML want it."""
    shells: list[Polygon] = []
    holes: list[LinearRing] = []
    for ring in rings:
        if len(ring) < 3:
            continue
        lr = LinearRing([(float(lon), float(lat)) for lat, lon in ring])
        if lr.is_ccw:
            shells.append(Polygon(lr))
        else:
            holes.append(lr)
    polygons = []
    for shell in shells:
        inside = [h for h in holes if shell.contains(Point(h.coords[0]))]
        polygons.append(Polygon(shell.exterior, inside))
    if not polygons:
        return Polygon()
    return polygons[0] if len(polygons) == 1 else MultiPolygon(polygons)


def area_from_waypoints(waypoints: Sequence[LatLon], margin_m: float | None = None) -> list[LatLon]:
    """The area a lawnmower mission sweeps, from its waypoints alone (a mission planned in QGroundControl
    carries no polygon): their convex hull, widened across the lanes (the direction of the longest leg) by
    `margin_m` on each side. Without a margin, half the lane spacing, estimated as the median of the shorter
    half of the legs (the hops between lanes). Corners as (lat, lon), counter-clockwise; empty when the
    waypoints span no area."""
    if len(waypoints) < 2:
        return []
    frame = LocalFrame(waypoints[0][0], waypoints[0][1])
    points = [frame.xy(lat, lon) for lat, lon in waypoints]
    legs = [(math.dist(a, b), a, b) for a, b in zip(points, points[1:], strict=False)]
    if margin_m is None:
        short = sorted(length for length, _, _ in legs)[: max(1, len(legs) // 2)]
        short = [length for length in short if length > 0]
        margin_m = statistics.median(short) / 2 if short and len(legs) >= 3 else 0.0
    length, a, b = max(legs)
    if length <= 0:
        return []
    across = (-(b[1] - a[1]) / length * margin_m, (b[0] - a[0]) / length * margin_m)
    widened = [(x + k * across[0], y + k * across[1]) for x, y in points for k in (-1.0, 1.0)]
    hull = shapely.MultiPoint(widened).convex_hull
    if not isinstance(hull, Polygon) or hull.area <= 0:
        return []
    return [frame.latlon(x, y) for x, y in list(orient(hull, 1.0).exterior.coords)[:-1]]
