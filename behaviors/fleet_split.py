"""A fleet survey: one search area split into a contiguous part per vehicle, sized so their flight times are
close.

Pure planning, no I/O: `split_area(area, settings, vehicles)` gives each vehicle its part of the area and the
survey over it (`SurveyPlan`, as `behaviors/survey_planner.py` plans one), the time the whole area takes (the
slowest vehicle's) and the time one vehicle alone would need on the same plan. Every input it refuses raises
`SurveyError` with a one-line reason.

The area is planned once, as for one vehicle (`plan_checked`: the lane direction, the spacing from the
camera's swath or given outright, e.g. the POD planner's); its lanes, in order across the area, are then
dealt out in contiguous runs, one run per vehicle. A part is the area between two cuts across the lane
direction, each cut on the boundary between two lanes' bands, so neighbouring parts meet edge to edge, their
lanes are the single plan's own (none doubled, none dropped) and the parts together are the area.

A vehicle's time is what the planner estimates for one vehicle (after its `busy_s`, the time it flies before
its part begins: in a re-plan, its own lanes left): its transit from its start position to its
part's first waypoint, then the lanes and the turns between them, each leg flown from rest to rest at the
vehicle's speed (`leg_time_s`); its lanes are flown in the order that begins nearest its start, as
`plan_checked` flies them. The climb from the ground is not counted (all vehicles climb alike). The split
minimises the slowest vehicle's time (exactly, over every run of lanes: dynamic programming on the cuts),
then the spread of the others; which vehicle takes which side is every order where few enough vehicles make
that cheap, else their order across the lanes by start position.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace

from behaviors.camera_footprint import Point, polygon_area
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.survey_planner import (
    LatLon,
    SurveyError,
    SurveyPlan,
    SurveySettings,
    _band,
    _lanes,
    _order,
    _rotate,
    _to_local,
    _unrotate,
    check_polygon,
    leg_time_s,
    mission_items,
    plan_checked,
)

MAX_VEHICLES = 16  # a search team flies two to six; more is surely a typo
MIN_SPEED_M_S = 0.5  # survey_planner's bounds on a survey speed
MAX_SPEED_M_S = 30.0
MAX_START_M = 50_000.0  # a start position farther from the area is a typo (the ground tool checks closer)
MAX_BUSY_S = 86_400.0  # a day's flying before its part begins is surely a typo
MAX_ORDER_WORK = 200_000  # every order of the vehicles is tried while orders x lanes^2 stays under this
VEHICLE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,31}")


@dataclass(frozen=True)
class FleetVehicle:
    id: str  # how the operator names it: letters, digits, _ . -, at most 32
    speed_m_s: float  # the survey speed it flies (DO_CHANGE_SPEED)
    start: LatLon  # where it begins: its position, or home (a re-plan: where its own lanes left end)
    busy_s: float = 0.0  # how long it flies before it begins its part (a re-plan: its own lanes left)


@dataclass(frozen=True)
class FleetPart:
    vehicle: FleetVehicle
    plan: SurveyPlan  # the survey over the part, at the vehicle's speed, beginning nearest its start
    corners: tuple[LatLon, ...]  # the part of the area
    first_lane: int  # the single plan's lanes it flies, 1-based, inclusive
    last_lane: int
    transit_m: float  # from the start to the first waypoint
    transit_s: float

    @property
    def time_s(self) -> float:
        """Its busy time first, then the transit and its part."""
        return self.vehicle.busy_s + self.transit_s + self.plan.time_s


@dataclass(frozen=True)
class FleetSplit:
    whole: SurveyPlan  # the area as one vehicle's plan: the lanes the parts share out
    parts: tuple[FleetPart, ...]  # across the area in lane order
    alone_s: float  # the least time one vehicle of the fleet alone needs for the whole plan
    alone_id: str  # which vehicle that is

    @property
    def finish_s(self) -> float:
        """The whole area's: the slowest vehicle's."""
        return max(part.time_s for part in self.parts)


def check_vehicles(vehicles: Sequence[FleetVehicle]) -> tuple[FleetVehicle, ...]:
    """The fleet, checked; SurveyError says what is wrong with it."""
    if not vehicles:
        raise SurveyError("the fleet is empty: name at least one vehicle")
    if len(vehicles) > MAX_VEHICLES:
        raise SurveyError(f"the fleet has {len(vehicles)} vehicles; at most {MAX_VEHICLES} are accepted")
    seen: set[str] = set()
    for v in vehicles:
        if not VEHICLE_ID.fullmatch(v.id):
            raise SurveyError(
                f"vehicle id {v.id[:40]!r} must be 1-32 letters, digits, '_', '.' or '-' (beginning with a letter "
                "or digit)"
            )
        if v.id in seen:
            raise SurveyError(f"vehicle id {v.id!r} is given twice")
        seen.add(v.id)
        if not (math.isfinite(v.speed_m_s) and MIN_SPEED_M_S <= v.speed_m_s <= MAX_SPEED_M_S):
            raise SurveyError(
                f"vehicle {v.id}: speed {v.speed_m_s:g} m/s must be between {MIN_SPEED_M_S:g} and "
                f"{MAX_SPEED_M_S:g} m/s"
            )
        if not (math.isfinite(v.busy_s) and 0 <= v.busy_s <= MAX_BUSY_S):
            raise SurveyError(
                f"vehicle {v.id}: busy time {v.busy_s:g} s must be between 0 and {MAX_BUSY_S:g} s"
            )
        lat, lon = v.start
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
            raise SurveyError(f"vehicle {v.id}: start {lat},{lon} is not a latitude,longitude")
    return tuple(vehicles)


# ----------------------------------------------------------------------------------- the estimate
class _Times:
    """One vehicle's time for any run of the lanes, in O(1): the lanes' and the turns' leg times as prefix
    sums (a turn's side, the lanes' far or near ends, alternates with the lane's parity)."""

    def __init__(
        self, lanes: Sequence[tuple[Point, Point]], start: Point, speed: float, busy_s: float = 0.0
    ) -> None:
        self.lanes = lanes
        self.start = start
        self.speed = speed
        self.busy_s = busy_s
        n = len(lanes)
        self.lane = [0.0]
        for a, b in lanes:
            self.lane.append(self.lane[-1] + leg_time_s(math.dist(a, b), speed))
        # near[par][x]: the turns m < x with m % 2 == par between the lanes' near ends (a), far: their far ends
        self.near = [[0.0] * (n + 1), [0.0] * (n + 1)]
        self.far = [[0.0] * (n + 1), [0.0] * (n + 1)]
        for m in range(n):
            for par in (0, 1):
                turn = m % 2 == par and m + 1 < n
                self.near[par][m + 1] = self.near[par][m] + (
                    leg_time_s(math.dist(lanes[m][0], lanes[m + 1][0]), speed) if turn else 0.0
                )
                self.far[par][m + 1] = self.far[par][m] + (
                    leg_time_s(math.dist(lanes[m][1], lanes[m + 1][1]), speed) if turn else 0.0
                )

    def _turns(self, i: int, j: int, far_par: int) -> float:
        """The turns between lanes i..j (inclusive): at the far ends after lanes m % 2 == far_par, else near."""
        return (
            self.far[far_par][j]
            - self.far[far_par][i]
            + self.near[1 - far_par][j]
            - self.near[1 - far_par][i]
        )

    def time(self, i: int, j: int) -> float:
        """Transit and survey for lanes i..j, flown in `_order`'s order (the one beginning nearest the start)."""
        a_i, b_i = self.lanes[i]
        a_j, b_j = self.lanes[j]
        # _order's four ways, in its order: lanes i..j, first forwards (turns at the far ends after lanes of
        # i's parity) or backwards; lanes j..i, first forwards (far ends after lanes of j's other parity,
        # turn m following lane m + 1) or backwards.
        ways = (
            (a_i, i % 2),
            (b_i, 1 - i % 2),
            (a_j, 1 - j % 2),
            (b_j, j % 2),
        )
        best = ways[0]
        for way in ways[1:]:
            if math.dist(way[0], self.start) < math.dist(best[0], self.start) - 1e-9:
                best = way
        first, far_par = best
        return (
            self.busy_s
            + leg_time_s(math.dist(first, self.start), self.speed)
            + self.lane[j + 1]
            - self.lane[i]
            + self._turns(i, j, far_par)
        )


def _best_split(times: Sequence[_Times], n: int) -> tuple[tuple[float, float], list[int]]:
    """Where each vehicle's run of lanes begins (0 first), minimising (slowest, sum of squares)
    for vehicles in this order, each taking at least one lane."""
    k = len(times)
    inf = (math.inf, math.inf)
    # best[v][j]: vehicles 0..v-1 over lanes 0..j-1
    best = [[inf] * (n + 1) for _ in range(k + 1)]
    cut = [[0] * (n + 1) for _ in range(k + 1)]
    best[0][0] = (0.0, 0.0)
    for v in range(1, k + 1):
        t = times[v - 1]
        for j in range(v, n - (k - v) + 1):
            for i in range(v - 1, j):
                prev = best[v - 1][i]
                if prev[0] == math.inf:
                    continue
                own = t.time(i, j - 1)
                value = (round(max(prev[0], own), 6), prev[1] + own * own)
                if value < best[v][j]:
                    best[v][j], cut[v][j] = value, i
    cuts = [n]
    for v in range(k, 0, -1):
        cuts.append(cut[v][cuts[-1]])
    return best[k][n], cuts[::-1][:-1]


# -------------------------------------------------------------------------------------------- split
def split_area(
    area: Sequence[LatLon], settings: SurveySettings, vehicles: Sequence[FleetVehicle]
) -> FleetSplit:
    """The area shared out over the fleet; SurveyError with a one-line reason when it cannot be."""
    corners = check_polygon(area)
    fleet = check_vehicles(vehicles)
    whole = plan_checked(corners, replace(settings, start=None))
    origin = corners[0]
    local = _to_local(origin, corners)
    spacing = settings.spacing_m if settings.spacing_m is not None else whole.swath_m * (1 - settings.overlap)
    lanes, band = _lanes(local, whole.angle_deg, spacing)
    if len(lanes) < len(fleet):
        raise SurveyError(
            f"the area has {len(lanes)} lane{'s' if len(lanes) != 1 else ''} for {len(fleet)} vehicles: fly it "
            "with fewer vehicles, or lower the altitude for narrower lanes"
        )
    starts: dict[str, Point] = {}
    for v in fleet:
        ne = latlon_to_offset(origin[0], origin[1], *v.start)
        if math.hypot(*ne) > MAX_START_M:
            raise SurveyError(
                f"vehicle {v.id}: start {v.start[0]:.6f},{v.start[1]:.6f} is more than {MAX_START_M / 1000:g} km "
                "from the area (check lat,lon)"
            )
        starts[v.id] = _rotate([ne], whole.angle_deg)[0]
    times = {v.id: _Times(lanes, starts[v.id], v.speed_m_s, v.busy_s) for v in fleet}
    n = len(lanes)
    across = sorted(fleet, key=lambda v: (starts[v.id][1], v.id))
    orders: list[Sequence[FleetVehicle]] = [across]
    if math.factorial(len(fleet)) * n * n <= MAX_ORDER_WORK:
        orders = [list(p) for p in itertools.permutations(across)]
    best: tuple[tuple[float, float], list[int], Sequence[FleetVehicle]] | None = None
    for order in orders:
        value, cuts = _best_split([times[v.id] for v in order], n)
        if best is None or value < best[0]:
            best = (value, cuts, order)
    assert best is not None
    _, cuts, order = best
    rotated = _rotate(local, whole.angle_deg)
    low = min(p[1] for p in rotated)
    high = max(p[1] for p in rotated)
    parts = []
    for k, vehicle in enumerate(order):
        first, last = cuts[k], (cuts[k + 1] if k + 1 < len(cuts) else n) - 1
        lo = low if k == 0 else _cut(lanes, first, band)
        hi = high if k == len(order) - 1 else _cut(lanes, last + 1, band)
        piece = _band(rotated, lo, hi)
        part_local = [_unrotate(p, whole.angle_deg) for p in piece]
        plan = _plan(lanes[first : last + 1], starts[vehicle.id], vehicle.speed_m_s, settings, whole, origin)
        plan = replace(plan, area_m2=polygon_area(part_local))
        transit = math.dist(_order(lanes[first : last + 1], starts[vehicle.id])[0], starts[vehicle.id])
        parts.append(
            FleetPart(
                vehicle=vehicle,
                plan=plan,
                corners=tuple(offset_to_latlon(origin[0], origin[1], *p) for p in part_local),
                first_lane=first + 1,
                last_lane=last + 1,
                transit_m=transit,
                transit_s=leg_time_s(transit, vehicle.speed_m_s),
            )
        )
    alone = min((times[v.id].time(0, n - 1), v.id) for v in fleet)
    return FleetSplit(whole=whole, parts=tuple(parts), alone_s=alone[0], alone_id=alone[1])


def _cut(lanes: Sequence[tuple[Point, Point]], k: int, band: float) -> float:
    """The boundary between lane k - 1's band and lane k's (lanes run through their bands' middles)."""
    return (lanes[k - 1][0][1] + lanes[k][0][1]) / 2 if k > 0 else lanes[0][0][1] - band / 2


def _plan(
    lanes: Sequence[tuple[Point, Point]],
    start: Point,
    speed: float,
    settings: SurveySettings,
    whole: SurveyPlan,
    origin: LatLon,
) -> SurveyPlan:
    """A part's survey: its lanes flown as `plan_checked` flies them, at the vehicle's speed."""
    path = _order(list(lanes), start)
    waypoints = tuple(offset_to_latlon(origin[0], origin[1], *_unrotate(p, whole.angle_deg)) for p in path)
    legs = [math.dist(a, b) for a, b in zip(path, path[1:], strict=False)]
    return replace(
        whole,
        items=mission_items(settings, speed, waypoints),
        waypoints=waypoints,
        lanes=len(lanes),
        length_m=sum(legs),
        time_s=sum(leg_time_s(leg, speed) for leg in legs),
        speed_m_s=speed,
    )
