"""Planning a survey for a probability of detection (POD): the altitude, lane spacing and speed that bring an
area's expected POD to a target in the least flight time.

What a plan's POD is: what the companion's map (`cloudtrack/pod_map.py`) would show after flying it. Each
analysed keyframe adds, for every place in view, the detection curve's probability at the size the target
would have there (`behaviors/apparent_size.py`); a pass over a place counts its best look, passes combine as
independent looks, 1 - prod(1 - p). The area's POD is the mean over its places: the chance that the search
finds a target equally likely to be anywhere in it, as a SAR team reads a segment's POD.

The search uses a fast model of that map; the ground tool lays the chosen plan's keyframes on the full map
and prints what it shows (`cloudtrack/survey_pod.py`):
- One lane, straight and level at altitude h, the camera facing along it (level, so it sees the same on
  either side). For a place x metres across the lane and a metres ahead of the vehicle, the target's size
  gives the curve's probability of one look: the lane profile p(x, a).
- Keyframes every `interval_s` at speed v fall every v * interval_s metres along the lane, at a phase the
  place does not choose: one pass's POD at x is the best of p(x, a0 + k v interval_s) over k, averaged over
  the phase a0.
- The survey's N lanes run through bands of equal width across the area, as `behaviors/survey_planner.py`
  lays them: a place is passed by every lane in reach, each pass independent, except near the lane ends,
  where a lane that begins there has not looked at the ground yet (the camera looks ahead) and a lane and
  the one it turns into look at a place within `pass_gap_s` of each other, one pass on the map
  (`merged_share`, `area_pod`). The area's POD is the mean over places across the bands. The turns
  themselves and the shape of a polygon are left to the full map; the model holds to it within about 0.05
  (tests/test_survey_pod.py).

Speed is bounded (`SpeedBounds`) by:
- the keyframes: the ground under the lane is in at least one keyframe (consecutive footprints meet along
  it): v <= the footprint's depth along the lane / interval_s;
- motion blur: during the exposure, no point of a target in view moves more than `max_blur_px` keyframe
  pixels (the curve was measured on sharp keyframes): v <= max_blur_px / (exposure_s * the fastest image
  motion per metre flown);
- the autopilot: the survey speed it is asked to fly (DO_CHANGE_SPEED), `max_speed_m_s`.

The search: a survey's time depends on its lane count and speed, not on its altitude. For each altitude on a
grid over the safety band, the lane counts from the fewest the swath allows up, and, for each, the fastest
speed on a grid below that altitude's bound that still reaches the POD (bisection: the POD falls with the
speed), the least time wins; ties go to the higher POD. A lane count whose time at the altitude's top speed
cannot beat the best so far ends the altitude.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from behaviors.apparent_size import TargetShape, apparent_size_px, camera_frame
from behaviors.camera_footprint import ground_footprint, polygon_area, swath_width_m
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import DetectionCurve
from behaviors.geolocation import latlon_to_offset
from behaviors.survey_planner import (
    MAX_LANES,
    LatLon,
    SurveyError,
    SurveySettings,
    lane_axes,
    leg_time_s,
    plan_checked,
)

MAX_BLUR_PX = 1.0  # keyframe pixels of motion blur the curve still describes
MIN_SPEED_M_S = 1.0
SPEED_STEP_M_S = 0.5
ALTITUDE_STEPS = (
    11  # altitudes tried across the safety band (at least 1 m apart), then halves around the best
)
MAX_OVERLAP = 0.9  # lanes no closer than a tenth of the swath (survey_planner's bound on the overlap)
SAMPLES_PER_BAND = 8  # places across each band the area's mean is taken over
MAX_PHASES = 16  # keyframe phases a pass's best look is averaged over
TIE_S = 1.0  # plans this close in time are told apart by their POD
# Out of reach, the plan named is the fastest this close to the highest POD: the last hundredths cost the most
CLOSE = 0.02


class PodUnreachable(SurveyError):
    """No plan reaches the POD; `best` is the plan that comes closest."""

    def __init__(self, pod: float, best: PodChoice) -> None:
        super().__init__(f"POD {pod:g} cannot be reached; the best is {best.pod:.2f}")
        self.pod = pod
        self.best = best


@dataclass(frozen=True)
class PodTarget:
    """What is searched for and how a look at it is judged: the curve is in keyframe pixels."""

    curve: DetectionCurve
    shape: TargetShape
    accept_uncertain: bool = False
    keyframe_width: int = 640
    pass_gap_s: float = 10.0  # a place unseen this long: the next look is a new pass ([search] pass_gap_s)


@dataclass(frozen=True)
class Keyframing:
    """How the companion takes keyframes while searching, and what bounds the survey's speed."""

    interval_s: float = 0.5  # [backend] search_interval_s
    exposure_s: float = 0.002  # [camera] exposure_s
    max_blur_px: float = MAX_BLUR_PX
    max_speed_m_s: float = 10.0  # what the autopilot may be asked to fly
    min_speed_m_s: float = MIN_SPEED_M_S


@dataclass(frozen=True)
class SpeedBounds:
    """The fastest a survey at one altitude may fly, by each bound (m/s)."""

    keyframes_m_s: float
    blur_m_s: float
    autopilot_m_s: float

    @property
    def limit_m_s(self) -> float:
        return min(self.keyframes_m_s, self.blur_m_s, self.autopilot_m_s)


@dataclass(frozen=True)
class PodChoice:
    """A plan the search weighed: its altitude, lanes, speed, the model's POD and the time to fly it."""

    altitude_m: float
    lanes: int
    spacing_m: float
    speed_m_s: float
    pod: float  # the model's mean over the area
    time_s: float
    bounds: SpeedBounds

    def settings(self, base: SurveySettings) -> SurveySettings:
        """`base` (camera, band, lane angle, start) flying this plan."""
        return replace(base, altitude_m=self.altitude_m, spacing_m=self.spacing_m, speed_m_s=self.speed_m_s)


# ------------------------------------------------------------------------------------- speed bounds
def _image_motion_px_per_m(
    camera: CameraModel, altitude_m: float, north: float, east: float, up: float, scale: float
) -> float:
    """Keyframe pixels a point `up` metres above the ground at (north, east) moves per metre flown north."""
    step = 0.01
    uv = []
    for ahead in (north, north - step):
        f, r, d = camera_frame(camera, ahead, east, altitude_m - up, 0.0, 0.0, 0.0)
        if f <= 1e-6:
            return 0.0
        uv.append((camera.fx * r / f, camera.fy * d / f))
    return scale * math.dist(*uv) / step


def ground_under_lane_m(camera: CameraModel, altitude_m: float, search_range_m: float) -> tuple[float, float]:
    """Where the footprint crosses the ground under the lane: its nearest and farthest distance ahead of the
    vehicle (negative: behind it); (0, 0) when it does not."""
    outline = ground_footprint(camera, altitude_m, search_range_m)
    norths = []
    for (n0, e0), (n1, e1) in zip(outline, [*outline[1:], *outline[:1]], strict=True):
        if (e0 <= 0.0 <= e1 or e1 <= 0.0 <= e0) and e0 != e1:
            norths.append(n0 + (n1 - n0) * (0.0 - e0) / (e1 - e0))
        elif e0 == e1 == 0.0:
            norths.extend((n0, n1))
    return (min(norths), max(norths)) if norths else (0.0, 0.0)


def speed_bounds(
    camera: CameraModel, search_range_m: float, altitude_m: float, target: PodTarget, keyframing: Keyframing
) -> SpeedBounds:
    """The speed bounds of a survey at `altitude_m` (see the module doc)."""
    scale = min(1.0, target.keyframe_width / camera.width)
    fastest = 0.0
    for north, east in ground_footprint(camera, altitude_m, search_range_m):
        for up in (0.0, target.shape.height_m):
            fastest = max(fastest, _image_motion_px_per_m(camera, altitude_m, north, east, up, scale))
    # The footprint's corners hold the fastest image motion but the range cut's arc may not; sample it too.
    for k in range(0, 181, 5):
        bearing = math.radians(k - 90)
        for reach in (0.25, 0.5, 0.75, 1.0):
            north = reach * search_range_m * math.cos(bearing)
            east = reach * search_range_m * math.sin(bearing)
            if apparent_size_px(camera, altitude_m, north, east, target.shape) > 0:
                for up in (0.0, target.shape.height_m):
                    fastest = max(fastest, _image_motion_px_per_m(camera, altitude_m, north, east, up, scale))
    blur = math.inf if fastest <= 0 else keyframing.max_blur_px / (keyframing.exposure_s * fastest)
    near, far = ground_under_lane_m(camera, altitude_m, search_range_m)
    return SpeedBounds((far - near) / keyframing.interval_s, blur, keyframing.max_speed_m_s)


# -------------------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class LaneProfile:
    """p(x, a): one look's POD at a place x metres across a lane (rows: 0, dx, 2 dx, ...) and a metres along
    it from the vehicle (columns: a0, a0 + da, ...); rows end where the camera reaches no farther across."""

    altitude_m: float
    dx_m: float
    da_m: float
    a0_m: float
    rows: tuple[tuple[float, ...], ...]

    @property
    def reach_m(self) -> float:
        return len(self.rows) * self.dx_m


def lane_profile(
    camera: CameraModel, search_range_m: float, altitude_m: float, target: PodTarget
) -> LaneProfile:
    """The lane profile at `altitude_m` (a place counts within `search_range_m` of the vehicle, as on the
    map)."""
    r = search_range_m
    # 2 m across, 1 m along (keyframes fall metres apart): within about 0.05 of the map, in a tenth of a second
    dx, da = max(2.0, r / 25.0), max(1.0, r / 50.0)
    columns = int(2 * r / da) + 1
    rows: list[tuple[float, ...]] = []
    for i in range(int(r / dx) + 1):
        x = i * dx
        row = []
        for j in range(columns):
            a = -r + j * da
            size = 0.0
            if math.hypot(a, x) <= r:
                size = apparent_size_px(
                    camera, altitude_m, a, x, target.shape, 0.0, 0.0, 0.0, target.keyframe_width
                )
            row.append(target.curve.probability(size, target.accept_uncertain) if size > 0 else 0.0)
        rows.append(tuple(row))
    while rows and not any(rows[-1]):
        rows.pop()
    return LaneProfile(altitude_m, dx, da, -r, tuple(rows))


def pass_pod(profile: LaneProfile, step_m: float) -> tuple[float, ...]:
    """One pass's POD at each row's distance across the lane: the best look of keyframes `step_m` apart,
    averaged over where they fall."""
    step = step_m / profile.da_m
    out = []
    for row in profile.rows:
        seen = [j for j, p in enumerate(row) if p > 0]
        if not seen:
            out.append(0.0)
            continue
        first, last = seen[0], seen[-1]
        phases = max(1, min(MAX_PHASES, math.ceil(step)))
        total = 0.0
        for m in range(phases):
            position = first + (m + 0.5) * step / phases
            best = 0.0
            while position <= last + 0.5:
                best = max(best, row[min(last, round(position))])
                position += step
            total += best
        out.append(total / phases)
    return tuple(out)


def merged_share(lane_m: float, band_m: float, depth_m: float, speed_m_s: float, pass_gap_s: float) -> float:
    """The share of a lane's length where the map counts it and its neighbour as one pass: near the end they
    share, the neighbour's first look at a place follows the lane's last one within `pass_gap_s` (the
    vehicle turns there: (2 y + band - depth) / speed for a place y from the end, the camera seeing `depth_m`
    along the lane)."""
    near_end = max(0.0, (pass_gap_s * speed_m_s - band_m + depth_m) / 2)
    return min(1.0, 2 * near_end / lane_m) if lane_m > 0 else 1.0


def area_pod(
    passes: Sequence[float], dx_m: float, lanes: int, band_m: float, merged: float = 0.0, start: float = 0.0
) -> float:
    """The mean POD across `lanes` bands `band_m` wide, a lane through the middle of each, from one pass's
    POD by distance across (`passes`, every `dx_m`). Along the lanes:
    - on a `start` share of their length, next to either end, the lanes that begin there have not seen
      the ground yet (a camera looking ahead): only the lanes that end there count;
    - on a further `merged` share (counted from the ends, so including `start`), each lane and the one it
      turns into there count as one pass, its better look (lanes 0-1, 2-3, ... at one end, 1-2, 3-4, ... at
      the other);
    - elsewhere every lane in reach is an independent pass."""
    reach = len(passes) * dx_m
    start = min(1.0, start)
    merged = max(0.0, min(1.0, merged) - start)

    def place(u: float) -> float:
        low = max(0, math.ceil((u - reach) / band_m - 0.5))
        high = min(lanes - 1, math.floor((u + reach) / band_m - 0.5))
        seen: dict[int, float] = {}
        for k in range(low, high + 1):
            i = round(abs(u - (k + 0.5) * band_m) / dx_m)
            if i < len(passes):
                seen[k] = passes[i]
        pod = (1.0 - start - merged) * (1.0 - math.prod(1.0 - p for p in seen.values()))
        for first in (0, 1):  # the end where lanes `first`, `first` + 2, ... turn into the next one
            arriving = [seen.get(k, 0.0) for k in range(low - 1, high + 1) if k % 2 == first]
            pairs = [
                max(seen.get(k, 0.0), seen.get(k + 1, 0.0))
                for k in range(low - 1, high + 1)
                if k % 2 == first
            ]
            pod += start / 2 * (1.0 - math.prod(1.0 - p for p in arriving))
            pod += merged / 2 * (1.0 - math.prod(1.0 - p for p in pairs))
        return pod

    def band_mean(j: int) -> float:
        return (
            sum(place((j + (m + 0.5) / SAMPLES_PER_BAND) * band_m) for m in range(SAMPLES_PER_BAND))
            / SAMPLES_PER_BAND
        )

    edge = (
        math.ceil(reach / band_m) + 1
    )  # bands this close to a side see fewer lanes; those between are alike
    if lanes <= 2 * edge + 2:
        return sum(band_mean(j) for j in range(lanes)) / lanes
    sides = sum(band_mean(j) for j in range(edge))
    inner = (band_mean(edge) + band_mean(edge + 1)) / 2  # two, for the pairs' parity
    return (2 * sides + (lanes - 2 * edge) * inner) / lanes


# ------------------------------------------------------------------------------------------ search
def _altitudes(low: float, high: float) -> list[float]:
    """The altitudes tried first: `ALTITUDE_STEPS` intervals across the band (at least 1 m apart), to 0.1 m."""
    count = max(1, min(ALTITUDE_STEPS, math.floor(high - low)))
    return sorted({min(high, max(low, round(low + (high - low) * k / count, 1))) for k in range(count + 1)})


def _speeds(low: float, high: float) -> list[float]:
    """The speeds tried, slowest first: `high` (to 0.1 m/s) and every `SPEED_STEP_M_S` below it to `low`."""
    top = math.floor(high * 10 + 1e-9) / 10
    if top < low:
        return []
    count = math.floor((top - low) / SPEED_STEP_M_S + 1e-9)
    return sorted({round(top - k * SPEED_STEP_M_S, 1) for k in range(count + 1)})


def _better(a: PodChoice, b: PodChoice | None) -> bool:
    if b is None:
        return True
    if abs(a.time_s - b.time_s) > TIE_S:
        return a.time_s < b.time_s
    return a.pod > b.pod


class PodSearch:
    """The search for one area (corners checked by `survey_planner.check_polygon`) and settings (camera,
    altitude band, lane angle, start); `altitude_m` / `speed_m_s` hold those fixed. Every figure of the
    model is computed once, so asking again for more costs little."""

    def __init__(
        self,
        corners: tuple[LatLon, ...],
        settings: SurveySettings,
        target: PodTarget,
        keyframing: Keyframing,
        altitude_m: float | None = None,
        speed_m_s: float | None = None,
    ) -> None:
        self.corners = corners
        self.angle, self.extent = lane_axes(corners, settings.angle_deg)
        self.settings = replace(settings, angle_deg=self.angle)
        self.target = target
        self.keyframing = keyframing
        self.speed_m_s = speed_m_s
        local = [latlon_to_offset(*corners[0], lat, lon) for lat, lon in corners]
        self.lane_m = polygon_area(local) / self.extent  # a lane's mean length
        self.altitudes = (
            [altitude_m]
            if altitude_m is not None
            else _altitudes(settings.min_altitude_m, settings.max_altitude_m)
        )
        self._profiles: dict[float, LaneProfile] = {}
        self._bounds: dict[float, SpeedBounds] = {}
        self._under: dict[float, tuple[float, float]] = {}
        self._passes: dict[tuple[float, float], tuple[float, ...]] = {}
        self._legs: dict[int, list[float]] = {}

    # The model's figures
    def profile(self, altitude: float) -> LaneProfile:
        if altitude not in self._profiles:
            s = self.settings
            self._profiles[altitude] = lane_profile(s.camera, s.search_range_m, altitude, self.target)
        return self._profiles[altitude]

    def bounds(self, altitude: float) -> SpeedBounds:
        if altitude not in self._bounds:
            s = self.settings
            self._bounds[altitude] = speed_bounds(
                s.camera, s.search_range_m, altitude, self.target, self.keyframing
            )
        return self._bounds[altitude]

    def pod(self, altitude: float, lanes: int, speed: float) -> float:
        profile = self.profile(altitude)
        if (altitude, speed) not in self._passes:
            self._passes[altitude, speed] = pass_pod(profile, speed * self.keyframing.interval_s)
        band = self.extent / lanes
        near, far = self.under_lane(altitude)
        merged = merged_share(self.lane_m, band, far - near, speed, self.target.pass_gap_s)
        start = 2 * max(0.0, near) / self.lane_m
        return area_pod(self._passes[altitude, speed], profile.dx_m, lanes, band, merged, start)

    def under_lane(self, altitude: float) -> tuple[float, float]:
        if altitude not in self._under:
            s = self.settings
            self._under[altitude] = ground_under_lane_m(s.camera, altitude, s.search_range_m)
        return self._under[altitude]

    def time_s(self, altitude: float, lanes: int, speed: float) -> float:
        if lanes not in self._legs:
            spacing = self.extent / lanes
            plan = plan_checked(self.corners, replace(self.settings, altitude_m=altitude, spacing_m=spacing))
            points = [latlon_to_offset(*plan.waypoints[0], lat, lon) for lat, lon in plan.waypoints]
            self._legs[lanes] = [math.dist(a, b) for a, b in zip(points, points[1:], strict=False)]
        return sum(leg_time_s(leg, speed) for leg in self._legs[lanes])

    def lane_counts(self, altitude: float) -> range:
        """From the fewest lanes the swath allows to the most (`MAX_OVERLAP`)."""
        swath = swath_width_m(self.settings.camera, altitude, self.settings.search_range_m)
        if swath < 1.0:
            return range(0)
        fewest = max(1, math.ceil(self.extent / swath - 1e-9))
        most = min(MAX_LANES, max(fewest, math.floor(self.extent / (swath * (1 - MAX_OVERLAP)) + 1e-9)))
        return range(fewest, most + 1)

    def speeds(self, altitude: float) -> list[float]:
        if self.speed_m_s is not None:
            return [self.speed_m_s]
        return _speeds(self.keyframing.min_speed_m_s, self.bounds(altitude).limit_m_s)

    def choice(self, altitude: float, lanes: int, speed: float) -> PodChoice:
        return PodChoice(
            altitude_m=altitude,
            lanes=lanes,
            spacing_m=self.extent / lanes,
            speed_m_s=speed,
            pod=self.pod(altitude, lanes, speed),
            time_s=self.time_s(altitude, lanes, speed),
            bounds=self.bounds(altitude),
        )

    # The search
    def choose(self, pod: float, required: float | None = None) -> PodChoice:
        """The plan that reaches `pod` in the model (or `required`, when the full map asks for a margin) in
        the least time; PodUnreachable with the plan that comes closest when none does."""
        if not 0.0 < pod < 1.0:
            raise SurveyError(f"a POD to plan for is between 0 and 1 (e.g. 0.8), got {pod:g}")
        goal = pod if required is None else required
        best = self._fastest(self.altitudes, goal)
        if best is not None and len(self.altitudes) > 1:
            # Between the grid's altitudes: halfway, then a quarter of the way, to either side of the best.
            step = self.altitudes[1] - self.altitudes[0]
            low, high = self.settings.min_altitude_m, self.settings.max_altitude_m
            for fraction in (0.5, 0.25):
                around = {round(best.altitude_m + sign * fraction * step, 1) for sign in (-1, 1)}
                found = self._fastest(sorted(a for a in around if low <= a <= high), goal)
                if found is not None and _better(found, best):
                    best = found
        if best is not None:
            return best
        closest = self._closest()
        if closest is None:
            raise SurveyError(
                "the camera sees no ground within [camera] search_range_m from any altitude of the [safety] band"
            )
        raise PodUnreachable(pod, closest)

    def _fastest(self, altitudes: Sequence[float], goal: float) -> PodChoice | None:
        best: PodChoice | None = None
        for altitude in altitudes:
            speeds = self.speeds(altitude)
            if not speeds:
                continue
            for lanes in self.lane_counts(altitude):
                if best is not None and self.time_s(altitude, lanes, speeds[-1]) > best.time_s + TIE_S:
                    break  # more lanes only take longer
                if self.pod(altitude, lanes, speeds[0]) < goal:
                    continue
                # The fastest speed that still reaches the goal (the POD falls as the speed grows).
                low, high = 0, len(speeds) - 1
                while low < high:
                    mid = (low + high + 1) // 2
                    if self.pod(altitude, lanes, speeds[mid]) >= goal:
                        low = mid
                    else:
                        high = mid - 1
                candidate = self.choice(altitude, lanes, speeds[low])
                if _better(candidate, best):
                    best = candidate
        return best

    def _closest(self) -> PodChoice | None:
        """The fastest plan within `CLOSE` of the highest POD the model gives (most lanes, slowest speed)."""
        top: float | None = None
        for altitude in self.altitudes:
            speeds, counts = self.speeds(altitude), self.lane_counts(altitude)
            if speeds and counts:
                top = max(top or 0.0, self.pod(altitude, counts[-1], speeds[0]))
        return None if top is None else self._fastest(self.altitudes, max(0.0, top - CLOSE))
