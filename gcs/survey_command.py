"""`cloudtrack-gcs survey`: plan a search survey over an area and upload it to the autopilot as its mission.

The area comes from the command line (`--polygon "lat,lon lat,lon ..."`), a file (`--area-file`: a GeoJSON
Polygon / Feature / FeatureCollection, or a QGroundControl .plan with a survey), or a centre and a size
(`--centre lat,lon --size 100x60`). The lanes are sized from the camera's ground footprint at the survey
altitude and the altitude is held to the safety band, both read from the companion's configuration
([camera], [safety], [search]: `cloudtrack/vehicle_config.py`), so the plan matches what the companion will see and
allow. `behaviors/survey_planner.py` plans; `cloudtrack/mission_protocol.py` uploads. The mission the
autopilot receives is plain MAVLink (NAV_WAYPOINT, DO_CHANGE_SPEED), as QGroundControl would send it: the
companion flies a QGC-planned survey the same way.

Every plan prints its expected probability of detection (POD): what the companion's map would show had it
flown exactly that plan, for the target of [search] (`cloudtrack/survey_pod.py`). With `--pod P` the
altitude, lane spacing and speed are chosen to bring the area's mean POD to P in the least flight time
(`behaviors/pod_planner.py`, confirmed on the map); a P out of reach is one line naming the best plan.

An area farther than [safety] max_survey_distance_m from the vehicle (or from `--from` on a dry run) is
refused, saying when latitude and longitude look swapped. An area file is read only if it is a regular file,
and only so far, before it is parsed.

Before uploading it waits for the autopilot's HEARTBEAT (its family and mode) and asks for its position (the
survey begins at the lane end nearest the vehicle). It refuses to replace a mission the vehicle is flying
(AUTO / Mission). After the upload it makes the survey's first item the current one (so AUTO starts the
survey, not an index left from an older mission) and reads the mission back to check it. Every failure is
one line on stderr; a failed upload leaves no partial mission (see `cloudtrack/mission_protocol.py`).
Exit codes: 0 done, 1 refused by the autopilot, 2 bad input, 3 no answer.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import reprlib
import stat
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pymavlink import mavwp

from behaviors.apparent_size import TargetShape
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import CurveError
from behaviors.mission_items import MissionItem
from behaviors.pod_planner import MIN_SPEED_M_S, Keyframing, PodTarget, SpeedBounds, speed_bounds
from behaviors.survey_planner import (
    MAX_VERTICES,
    LatLon,
    SurveyError,
    SurveyPlan,
    SurveySettings,
    plan_survey,
    rectangle,
    too_far,
)
from cloudtrack.autopilot_modes import AutopilotKind, detect_autopilot, mission_mode, mode_name
from cloudtrack.config_files import ConfigError
from cloudtrack.detection_curves import curve_for
from cloudtrack.mavlink_connection import mavlink
from cloudtrack.mission_protocol import MissionClient, MissionError, MissionTimeouts, positions_match
from cloudtrack.pod_map import PodSettings
from cloudtrack.survey_pod import PodOutOfReach, PodPlan, expected_coverage, expected_pod, plan_for_pod
from cloudtrack.vehicle_config import VehicleSections, load_vehicle_sections

EXIT_REFUSED, EXIT_INPUT, EXIT_TIMEOUT = 1, 2, 3
MAX_AREA_FILE_BYTES = 1_000_000
_REPR = reprlib.Repr()  # an offending value in a message: short, however deep or long
AUTOPILOT_COMPONENT = 1
DEFAULT_OVERLAP = 0.2
MAX_SPEED_M_S = 30.0  # survey_planner's bound on --speed
DEFAULT_MAX_SPEED = (
    10.0  # m/s: ArduCopter's WPNAV_SPEED default; PX4 flies DO_CHANGE_SPEED to MPC_XY_VEL_MAX (12)
)
CRUISE_SPEED = {AutopilotKind.ARDUPILOT: 10.0, AutopilotKind.PX4: 5.0}  # WPNAV_SPEED, MPC_XY_CRUISE defaults
EXAMPLES = """\
examples:
  cloudtrack-gcs survey --centre 47.3977,8.5456 --size 120x80 --altitude 25 --dry-run
  cloudtrack-gcs survey --centre 47.3977,8.5456 --size 300x200 --pod 0.8 --target person --dry-run --from 47.3970,8.5450
  cloudtrack-gcs survey --polygon "47.3975,8.5450 47.3975,8.5466 47.3982,8.5466 47.3982,8.5450" --altitude 25 --speed 4
  cloudtrack-gcs survey --area-file search-area.geojson --altitude 30 --overlap 0.3
  cloudtrack-gcs survey --area-file mission.plan --altitude 25 --save survey.waypoints   # QGC's survey polygon
  cloudtrack-gcs --connect tcp:192.168.1.10:5760 survey --centre 47.3977,8.5456 --size 200x100 --altitude 30
  cloudtrack-gcs survey --centre 47.3977,8.5456 --size 600x400 --altitude 25 --dry-run \\
      --vehicle a,udpin:0.0.0.0:14551,5,47.3960,8.5440 --vehicle b,udpin:0.0.0.0:14552,8,47.3960,8.5470
  cloudtrack-gcs survey --area-file search-area.geojson --pod 0.8 --fleet fleet.toml   # each part uploaded

Then switch the vehicle to AUTO (ArduPilot) / Mission (PX4) and start the search:
  cloudtrack-gcs start --prompt "injured man in a gray shirt" --allow-engage
"""


class InputError(ValueError):
    """A bad argument or file: one line."""


# ------------------------------------------------------------------------------------------- the area
def _latlon(text: str, what: str) -> LatLon:
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        lat, lon = float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"{what}: {text!r} is not lat,lon (e.g. 47.3977,8.5456)") from None
    return lat, lon


def parse_polygon(text: str) -> list[LatLon]:
    """ "lat,lon lat,lon ..." (spaces or semicolons between corners)."""
    return [_latlon(corner, "--polygon") for corner in text.replace(";", " ").split()]


def parse_size(text: str) -> tuple[float, float]:
    """ "WIDTHxHEIGHT" in metres: east-west x north-south."""
    try:
        width, height = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size: {text!r} is not WIDTHxHEIGHT in metres (e.g. 100x60)") from None
    return width, height


def read_area_file(path: Path) -> list[LatLon]:
    """The polygon of a GeoJSON file (Polygon, MultiPolygon of one, Feature, FeatureCollection of one
    polygon; [lon, lat] order) or of a QGroundControl .plan's first survey ([lat, lon]).

    Only a regular file is read, and at most `MAX_AREA_FILE_BYTES` of it, before anything is parsed (a
    device never ends, a FIFO waits for a writer); whatever the file holds, what goes wrong reading it is
    one InputError naming the file."""
    raw = _read_bounded(path)
    try:
        data = json.loads(raw)
        if isinstance(data, dict) and data.get("fileType") == "Plan":
            return _plan_polygon(path, data)
        return _geojson_polygon(path, data)
    except InputError:
        raise
    except RecursionError:
        raise InputError(f"{path}: not a search area (nested too deeply)") from None
    except ValueError as exc:  # JSON's and UTF-8's own errors
        raise InputError(f"{path}: not JSON ({_one_line(exc)[:120]})") from None
    except Exception as exc:  # a shape the checks above did not foresee: still one line, never a traceback
        raise InputError(f"{path}: not a search area ({type(exc).__name__})") from None


_FILE_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _read_bounded(path: Path) -> bytes:
    try:
        # Non-blocking: opening a FIFO would otherwise wait for a writer before the check below can refuse it.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = next((name for test, name in _FILE_KINDS if test(info.st_mode)), "not a regular file")
            raise InputError(
                f"{path}: {kind}, not a file; give the area as a GeoJSON or QGroundControl .plan file"
            )
        if info.st_size > MAX_AREA_FILE_BYTES:
            raise InputError(
                f"{path}: {info.st_size} bytes; an area file may have at most {MAX_AREA_FILE_BYTES}"
            )
        with os.fdopen(fd, "rb", closefd=False) as file:
            raw = file.read(MAX_AREA_FILE_BYTES + 1)  # a file that grows meanwhile is still read no further
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(raw) > MAX_AREA_FILE_BYTES:
        raise InputError(f"{path}: more than {MAX_AREA_FILE_BYTES} bytes; an area file may have at most that")
    return raw


def _plan_polygon(path: Path, data: dict[str, Any]) -> list[LatLon]:
    mission = data.get("mission")
    items = mission.get("items") if isinstance(mission, dict) else None
    for item in items if isinstance(items, list) else []:
        if isinstance(item, dict) and item.get("complexItemType") == "survey":
            return _corners(path, item.get("polygon"), lon_first=False)
    raise InputError(
        f"{path}: a QGroundControl plan without a survey (add a Survey pattern in QGC's Plan view)"
    )


def _geojson_polygon(path: Path, data: Any) -> list[LatLon]:
    geometry = data
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        features = data.get("features")
        if not isinstance(features, list):
            raise InputError(f"{path}: a FeatureCollection whose features are not a list")
        polygons = [
            f.get("geometry")
            for f in features
            if isinstance(f, dict)
            and isinstance(f.get("geometry"), dict)
            and f["geometry"].get("type") in ("Polygon", "MultiPolygon")
        ]
        if len(polygons) != 1:
            raise InputError(f"{path}: a FeatureCollection with {len(polygons)} polygons; give exactly one")
        geometry = polygons[0]
    elif isinstance(data, dict) and data.get("type") == "Feature":
        geometry = data.get("geometry")
    if not isinstance(geometry, dict) or geometry.get("type") not in ("Polygon", "MultiPolygon"):
        raise InputError(f"{path}: neither a GeoJSON Polygon nor a QGroundControl .plan")
    rings = geometry.get("coordinates")
    if geometry["type"] == "MultiPolygon":
        if not isinstance(rings, list) or len(rings) != 1:
            raise InputError(
                f"{path}: a MultiPolygon of {len(rings) if isinstance(rings, list) else 0} polygons"
            )
        rings = rings[0]
    if not isinstance(rings, list) or not rings:
        raise InputError(f"{path}: the Polygon has no coordinates")
    if len(rings) > 1:
        raise InputError(f"{path}: the polygon has {len(rings) - 1} hole(s); a search area cannot have holes")
    return _corners(path, rings[0], lon_first=True)


def _corners(path: Path, ring: Any, lon_first: bool) -> list[LatLon]:
    if not isinstance(ring, list):
        raise InputError(f"{path}: the polygon is not a list of positions")
    count = len(ring) - (1 if len(ring) > 1 and ring[0] == ring[-1] else 0)  # GeoJSON closes its rings
    if count > MAX_VERTICES:
        raise InputError(
            f"{path}: the polygon has {count} corners; at most {MAX_VERTICES} are accepted (simplify it, e.g. "
            "QGIS's Simplify, or draw the search area with fewer)"
        )
    corners = []
    for position in ring:
        if not (
            isinstance(position, list)
            and len(position) >= 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in position[:2])
        ):
            raise InputError(f"{path}: position {_REPR.repr(position)} is not a pair of numbers")
        a, b = float(position[0]), float(position[1])
        corners.append((b, a) if lon_first else (a, b))
    return corners


def area_from_args(args: argparse.Namespace) -> list[LatLon]:
    given = [name for name in ("polygon", "area_file", "centre") if getattr(args, name) is not None]
    if len(given) != 1:
        raise InputError("give the area one way: --polygon, --area-file, or --centre with --size")
    if args.centre is not None:
        if not args.size:
            raise InputError("--centre needs --size WIDTHxHEIGHT (metres)")
        return list(rectangle(_latlon(args.centre, "--centre"), *parse_size(args.size), args.heading))
    if args.size:
        raise InputError("--size goes with --centre")
    return parse_polygon(args.polygon) if args.polygon is not None else read_area_file(Path(args.area_file))


def settings_from(args: argparse.Namespace, vehicle: VehicleSections, cruise: float) -> SurveySettings:
    cam = vehicle.camera
    return SurveySettings(
        # A plan for a POD chooses its own altitude: the band's top stands in until it has.
        altitude_m=args.altitude if args.altitude is not None else vehicle.safety.max_altitude_m,
        overlap=args.overlap if args.overlap is not None else DEFAULT_OVERLAP,
        camera=CameraModel.from_hfov(
            cam.width, cam.height, cam.hfov_deg, cam.mount_pitch_deg, cam.stabilised
        ),
        search_range_m=cam.search_range_m,
        min_altitude_m=vehicle.safety.min_altitude_m,
        max_altitude_m=vehicle.safety.max_altitude_m,
        speed_m_s=args.speed,
        cruise_speed_m_s=cruise,
        angle_deg=args.angle,
        takeoff=args.takeoff,
    )


# ------------------------------------------------------------------------------------------ the POD
@dataclass(frozen=True)
class PodContext:
    """What the expected POD is of: the target, the curve, the keyframes, the map's settings."""

    target: PodTarget | None  # None: no curve for the class (`error` says why)
    keyframing: Keyframing
    map_settings: PodSettings
    label: str  # "person, standing, 1.7 m"
    curve: str  # which curve, in words
    error: str = ""


def pod_context(args: argparse.Namespace, vehicle: VehicleSections) -> PodContext:
    """The target and keyframes the companion's map will be laid for ([search], [backend], [behavior],
    [camera]), `--target` / `--posture` over [search]'s."""
    s = vehicle.search
    target_class = args.target or s.target_class
    posture = args.posture or s.posture
    shape = TargetShape.for_class(target_class, posture, s.target_height_m)
    keyframe_width = vehicle.backend.max_keyframe_width
    map_settings = PodSettings(
        target_class=target_class,
        posture=posture if target_class == "person" else "",
        shape=shape,
        accept_uncertain=vehicle.behavior.accept_uncertain,
        target_pod=args.pod if args.pod is not None else s.target_pod,
        keyframe_width=keyframe_width,
        pass_gap_s=s.pass_gap_s,
    )
    keyframing = Keyframing(
        interval_s=vehicle.backend.search_interval_s,
        exposure_s=vehicle.camera.exposure_s,
        max_speed_m_s=args.max_speed,
    )
    label = (
        f"{target_class}, {posture}, {s.target_height_m:g} m" if target_class == "person" else target_class
    )
    try:
        curve = curve_for(target_class, Path(s.curve_file) if s.curve_file else None)
    except CurveError as exc:
        return PodContext(None, keyframing, map_settings, label, "", _one_line(exc))
    target = PodTarget(curve, shape, vehicle.behavior.accept_uncertain, keyframe_width, s.pass_gap_s)
    if s.curve_file:
        words = f"the curve of {s.curve_file}"
    elif dict(curve.configuration).get("provisional") == "true":
        words = "the shipped curve, provisional: not measured yet"
    else:
        words = "the shipped curve"
    return PodContext(target, keyframing, map_settings, label, words)


def plan_for(
    args: argparse.Namespace, area: list[LatLon], settings: SurveySettings, pod: PodContext
) -> tuple[SurveyPlan, PodPlan | None]:
    """The plan asked for: for a POD (`--pod`, altitude and speed held where given), or as given."""
    if args.pod is None:
        if args.altitude is None:
            raise InputError("give --altitude M, or --pod P to have the altitude chosen for a POD")
        return plan_survey(area, settings), None
    if not MIN_SPEED_M_S <= args.max_speed <= MAX_SPEED_M_S:
        raise InputError(
            f"--max-speed {args.max_speed:g} must be between {MIN_SPEED_M_S:g} and {MAX_SPEED_M_S:g} m/s"
        )
    if pod.target is None:
        raise InputError(f"--pod: {pod.error}")
    if args.overlap is not None:
        raise InputError("--pod chooses the lane spacing: drop --overlap")
    found = plan_for_pod(
        area, settings, pod.target, pod.keyframing, pod.map_settings, args.pod, args.altitude, args.speed
    )
    return found.plan, found


def out_of_reach(
    exc: PodOutOfReach, args: argparse.Namespace, settings: SurveySettings, pod: PodContext
) -> str:
    best = exc.best
    band = (
        f"at {args.altitude:g} m"
        if args.altitude is not None
        else f"within the [safety] altitude band {settings.min_altitude_m:g}-{settings.max_altitude_m:g} m"
    )
    return (
        f"POD {exc.pod:g} is out of reach over this area {band} at up to {pod.keyframing.max_speed_m_s:g} m/s: "
        f"the best is {best.map.mean():.2f} ({_plan_words(best.plan, best.choice.altitude_m)}); "
        f"{'let the altitude be chosen (no --altitude), ' if args.altitude is not None else ''}lower --pod, or "
        "fly the area again (two flights at POD P give 1 - (1 - P)^2)"
    )


def _plan_words(plan: SurveyPlan, altitude: float) -> str:
    minutes, seconds = divmod(round(plan.time_s), 60)
    return (
        f"altitude {altitude:g} m, {plan.lanes} lanes {plan.spacing_m:.1f} m apart, {plan.speed_m_s:g} m/s, "
        f"{minutes} min {seconds:02d} s"
    )


def check_distance(area: Sequence[LatLon], reference: LatLon, max_m: float, what: str) -> None:
    """InputError when the area is farther than `max_m` from `reference` (the vehicle, or --from)."""
    refusal = too_far(
        area, reference, max_m, what, "; GeoJSON lists longitude first, --polygon and --centre take lat,lon"
    )
    if refusal is not None:
        raise InputError(refusal)


def describe(
    plan: SurveyPlan,
    area: list[LatLon],
    settings: SurveySettings,
    pod: PodContext,
    speed_note: str = "",
    chosen: PodPlan | None = None,
) -> list[str]:
    minutes, seconds = divmod(round(plan.time_s), 60)
    counts = Counter(item.name for item in plan.items)
    speed = f"{plan.speed_m_s:g} m/s" + (f" ({speed_note})" if speed_note else "")
    started = time.perf_counter()
    share, views = expected_coverage(plan, area, settings, pod.keyframing.interval_s)
    took = time.perf_counter() - started
    lines = []
    if chosen is not None:
        c = chosen.choice
        lines.append(
            f"planned for POD {pod.map_settings.target_pod:g} ({pod.label}): altitude {c.altitude_m:g} m, lanes "
            f"{plan.spacing_m:.1f} m apart, {c.speed_m_s:g} m/s: the least time the model found"
        )
        lines.append(_bounds_line(c.bounds, c.altitude_m, pod.keyframing))
    lines += [
        f"lanes: {plan.lanes}, {plan.spacing_m:.1f} m apart (camera swath {plan.swath_m:.1f} m at "
        f"{settings.altitude_m:g} m), along {plan.angle_deg:g} deg",
        f"length: {plan.length_m:.0f} m over {plan.area_m2 / 1e4:.2f} ha",
        f"time to fly: about {minutes} min {seconds:02d} s at {speed}",
        f"coverage if flown as planned: {100 * share:.1f} % of the area ({views} keyframes, one every "
        f"{pod.keyframing.interval_s:g} s; {took:.2f} s)",
        _pod_line(plan, area, settings, pod, chosen),
        f"search rate: {plan.area_m2 / 1e6 / (plan.time_s / 3600):.2f} km2/h ({plan.area_m2 / 1e4:.2f} ha in "
        f"{minutes} min {seconds:02d} s)"
        if plan.time_s > 0
        else "search rate: -",
        "items: " + ", ".join(f"{n} {name}" for name, n in counts.items()),
    ]
    return lines


def _bounds_line(bounds: SpeedBounds, altitude: float, keyframing: Keyframing) -> str:
    return (
        f"speed bounds at {altitude:g} m: the autopilot's {bounds.autopilot_m_s:g} m/s (--max-speed), motion "
        f"blur {bounds.blur_m_s:.1f} m/s ({keyframing.max_blur_px:g} px in a {keyframing.exposure_s:g} s exposure, "
        f"[camera] exposure_s), keyframes {bounds.keyframes_m_s:.1f} m/s (one every {keyframing.interval_s:g} s, "
        "[backend] search_interval_s)"
    )


def _pod_line(
    plan: SurveyPlan, area: list[LatLon], settings: SurveySettings, pod: PodContext, chosen: PodPlan | None
) -> str:
    if pod.target is None:
        return f"expected POD: none ({pod.error})"
    pod_map = (
        chosen.map
        if chosen is not None and chosen.plan.waypoints == plan.waypoints
        else expected_pod(plan, area, settings, pod.target, pod.map_settings, pod.keyframing.interval_s)
    )
    target = pod.map_settings.target_pod
    line = (
        f"expected POD: mean {pod_map.mean():.2f}, {100 * pod_map.share_at_least(target):.0f} % of the area at "
        f"{target:g} or more ({pod.label}; {pod.curve})"
    )
    bounds = speed_bounds(
        settings.camera, settings.search_range_m, settings.altitude_m, pod.target, pod.keyframing
    )
    if plan.speed_m_s > min(bounds.blur_m_s, bounds.keyframes_m_s) + 1e-9:
        line += (
            f"; at {plan.speed_m_s:g} m/s the keyframes blur or leave gaps (bounds {bounds.blur_m_s:.1f} m/s "
            f"blur, {bounds.keyframes_m_s:.1f} m/s keyframes): this POD is optimistic"
        )
    return line


def save_waypoints(path: Path, items: Sequence[MissionItem]) -> None:
    """The mission as a QGC WPL 110 waypoint file (Mission Planner, QGroundControl, MAVProxy `wp load`),
    home first as those tools write it."""
    loader = mavwp.MAVWPLoader()
    for seq, item in enumerate([MissionItem(16, 0), *items]):
        loader.add(
            mavlink.MAVLink_mission_item_message(
                0,
                0,
                seq,
                item.frame,
                item.command,
                0,
                int(item.autocontinue),
                item.param1,
                item.param2,
                item.param3,
                0.0 if math.isnan(item.param4) else item.param4,
                item.lat_deg,
                item.lon_deg,
                item.z,
            )  # fmt: skip
        )
    loader.save(str(path))


# ----------------------------------------------------------------------------------------- the vehicle
class Vehicle:
    """What the survey needs from the autopilot before uploading: its family, mode and position."""

    def __init__(self, session: Any, system: int) -> None:
        self.session = session
        self.system = system
        self.kind: AutopilotKind | None = None
        self.mode = ""
        self.position: LatLon | None = None

    def _note(self, msg: Any) -> None:
        if msg.get_srcSystem() != self.system or msg.get_srcComponent() != AUTOPILOT_COMPONENT:
            return
        if msg.get_type() == "HEARTBEAT":
            kind = detect_autopilot(msg.autopilot)
            if kind is not None:
                self.kind = kind
                self.mode = mode_name(kind, msg.custom_mode, msg.type)
        elif msg.get_type() == "GLOBAL_POSITION_INT" and (msg.lat or msg.lon):
            self.position = (msg.lat / 1e7, msg.lon / 1e7)

    def wait(self, timeout: float, position_s: float = 1.5) -> None:
        """The autopilot's HEARTBEAT (required), then its position (asked for; optional)."""
        endpoint = self.session.endpoint
        deadline = time.monotonic() + timeout
        while self.kind is None and time.monotonic() < deadline:
            self._receive(endpoint)
        if self.kind is None:
            raise MissionError(
                f"no autopilot HEARTBEAT from system {self.system} within {timeout:g} s: is the autopilot "
                "sending to this link?"
            )
        endpoint.send(lambda m: m.command_long_send(
            self.system, AUTOPILOT_COMPONENT, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 0, 0, 0, 0, 0, 0))  # fmt: skip
        deadline = time.monotonic() + position_s
        while self.position is None and time.monotonic() < deadline:
            self._receive(endpoint)

    def _receive(self, endpoint: Any) -> None:
        msg = endpoint.receive(timeout=0.2)
        if msg is not None:
            self._note(msg)


# --------------------------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    """The subcommand: the area and the plan are checked before any link opens (`--dry-run` opens none)."""
    from gcs.cli import GcsError, GcsSession  # the ground tool's link and its errors (cli imports us)

    if args.vehicle or args.fleet is not None:
        from gcs.fleet_survey import run_fleet  # the area split over several vehicles (it imports us)

        return run_fleet(args)
    try:
        area = area_from_args(args)
        vehicle_config = load_vehicle_sections(Path(args.companion_config) if args.companion_config else None)
        if args.from_position is not None:
            reference = _latlon(args.from_position, "--from")
            check_distance(
                area, reference, vehicle_config.safety.max_survey_distance_m, "the --from position"
            )
        pod = pod_context(args, vehicle_config)
        settings = settings_from(args, vehicle_config, CRUISE_SPEED[AutopilotKind.PX4])
        if args.dry_run and args.from_position is not None:
            settings = replace(settings, start=reference)
        plan, chosen = plan_for(args, area, settings, pod)
    except (InputError, SurveyError, ConfigError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except PodOutOfReach as exc:
        print(f"error: {out_of_reach(exc, args, settings, pod)}", file=sys.stderr)
        return EXIT_INPUT
    if chosen is not None:
        settings = chosen.choice.settings(settings)
    if args.dry_run:
        print(f"survey (dry run, nothing sent): {len(area)} corners", flush=True)
        if args.from_position is None:
            print(
                "  distance to the vehicle not checked: give --from LAT,LON (the vehicle or home)", flush=True
            )
        note = "" if settings.speed_m_s is not None else "assumed: the autopilot's own unless --speed"
        for line in describe(plan, area, settings, pod, note, chosen):
            print(f"  {line}", flush=True)
        for k, (lat, lon) in enumerate(plan.waypoints):
            print(f"  waypoint {k + 1}: {lat:.7f},{lon:.7f}")
        return _save(args, plan)
    try:
        session = GcsSession(args)
    except OSError as exc:
        print(f"error: cannot open {args.connect}: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    try:
        session.connect()
        return _upload(args, session, area, vehicle_config, settings, pod, chosen)
    except GcsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.code
    finally:
        session.close()


def _save(args: argparse.Namespace, plan: SurveyPlan) -> int:
    if args.save:
        try:
            save_waypoints(Path(args.save), plan.items)
        except OSError as exc:
            print(f"error: cannot write {args.save}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_INPUT
        print(f"saved {len(plan.items)} items to {args.save} (QGC WPL 110)", flush=True)
    return 0


def _upload(
    args: argparse.Namespace,
    session: Any,
    area: list[LatLon],
    vehicle_config: VehicleSections,
    planned: SurveySettings,
    pod: PodContext,
    chosen: PodPlan | None,
) -> int:
    vehicle = Vehicle(session, args.system)
    try:
        vehicle.wait(args.timeout)
        assert vehicle.kind is not None
        if vehicle.position is not None:
            check_distance(area, vehicle.position, vehicle_config.safety.max_survey_distance_m, "the vehicle")
        settings = replace(planned, cruise_speed_m_s=CRUISE_SPEED[vehicle.kind], start=vehicle.position)
        plan = plan_survey(area, settings)
    except (SurveyError, InputError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    name = "ArduPilot" if vehicle.kind is AutopilotKind.ARDUPILOT else "PX4"
    print(f"survey for system {args.system} ({name}, mode {vehicle.mode}):", flush=True)
    if vehicle.position is None:
        print("  distance to the vehicle not checked: it reported no position", flush=True)
    note = "" if settings.speed_m_s is not None else f"the {name} default; --speed sets one"
    for line in describe(plan, area, settings, pod, note, chosen):
        print(f"  {line}", flush=True)
    if refused_in_mission(vehicle):
        return EXIT_REFUSED
    code = send_mission(args, session, vehicle, plan)
    return code if code else _save(args, plan)


def refused_in_mission(vehicle: Vehicle, who: str = "") -> bool:
    """True (and says why) when the vehicle flies its mission: a mission is never replaced under it."""
    if vehicle.kind is None or vehicle.mode != mission_mode(vehicle.kind):
        return False
    print(
        f"error: {who}the vehicle is flying its mission ({vehicle.mode}): switch it to another mode (e.g. "
        f"{'LOITER' if vehicle.kind is AutopilotKind.ARDUPILOT else 'HOLD'}) before replacing the mission",
        file=sys.stderr,
    )
    return True


def send_mission(
    args: argparse.Namespace, session: Any, vehicle: Vehicle, plan: SurveyPlan, who: str = ""
) -> int:
    """Upload `plan` to the vehicle (heard: its family known), make its first item current, read it back and
    check it; 0, or the exit code after one line on stderr. `who` ("vehicle a: ") begins each line."""
    assert vehicle.kind is not None
    client = MissionClient(
        session.endpoint,
        vehicle.kind.value,
        target=(vehicle.system, AUTOPILOT_COMPONENT),
        source=(args.gcs_system, args.gcs_component),
        timeouts=MissionTimeouts(step_s=args.step_timeout, retries=5),
    )
    try:
        client.upload(plan.items)
        current = client.set_current(client.first_seq)
        stored = client.download().items
    except MissionError as exc:
        print(f"error: {who}{exc}", file=sys.stderr)
        return EXIT_TIMEOUT if exc.result is None and "no answer" in str(exc) else EXIT_REFUSED
    if not positions_match(stored, plan.items):
        print(
            f"error: {who}the autopilot holds {len(stored)} items that differ from the {len(plan.items)} "
            "uploaded: check the mission in the ground station before AUTO",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    print(
        f"{who}uploaded {len(plan.items)} items, read back and checked; current item {current.seq}: switch to "
        f"{mission_mode(vehicle.kind)} to fly the survey",
        flush=True,
    )
    return 0


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "survey",
        help="plan a survey over an area and upload it as the autopilot's mission",
        description="Plan a lawnmower survey over an area (lanes sized by the camera's footprint) and upload "
        "it to the autopilot through the MAVLink mission protocol.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    area = p.add_argument_group("the area (one of)")
    area.add_argument("--polygon", metavar='"LAT,LON ..."', help="the corners in order around the area")
    area.add_argument(
        "--area-file", metavar="FILE", help="a GeoJSON polygon, or a QGroundControl .plan with a survey"
    )
    area.add_argument(
        "--centre", "--center", metavar="LAT,LON", help="the centre of a rectangle (with --size)"
    )
    p.add_argument("--size", metavar="WxH", help="the rectangle: W m east-west by H m north-south")
    p.add_argument(
        "--heading", type=float, default=0.0, metavar="DEG", help="turn the rectangle clockwise (default 0)"
    )
    p.add_argument(
        "--altitude",
        type=float,
        metavar="M",
        help="above home, within [safety] (with --pod: held, not chosen)",
    )
    p.add_argument(
        "--overlap",
        type=float,
        help=f"side overlap of neighbouring lanes' swaths, 0-0.9 (default {DEFAULT_OVERLAP:g}; not with --pod)",
    )
    p.add_argument(
        "--speed",
        type=float,
        metavar="M/S",
        help="ground speed (DO_CHANGE_SPEED; default: the autopilot's; with --pod: held, not chosen)",
    )
    pod = p.add_argument_group("planning for a probability of detection (POD)")
    pod.add_argument(
        "--pod",
        type=float,
        metavar="P",
        help="choose the altitude, lane spacing and speed that bring the area's mean POD to P (e.g. 0.8) in the "
        "least flight time",
    )
    pod.add_argument(
        "--target", metavar="CLASS", help="what is searched for (default: [search] target_class, person)"
    )
    pod.add_argument(
        "--posture", choices=("standing", "lying"), help="a person's (default: [search] posture, standing)"
    )
    pod.add_argument(
        "--max-speed",
        type=float,
        default=DEFAULT_MAX_SPEED,
        metavar="M/S",
        help=f"the fastest survey speed the autopilot may be asked to fly (default {DEFAULT_MAX_SPEED:g})",
    )
    p.add_argument(
        "--from",
        dest="from_position",
        metavar="LAT,LON",
        help="the vehicle's (or home) position: refuse an area farther than [safety] max_survey_distance_m "
        "(with a link, the vehicle's own position is used)",
    )
    p.add_argument(
        "--angle",
        type=float,
        metavar="DEG",
        help="lane direction clockwise from north (default: fewest lanes)",
    )
    p.add_argument("--takeoff", action="store_true", help="begin with NAV_TAKEOFF to the survey altitude")
    fleet = p.add_argument_group(
        "several vehicles (the area split so their flight times are close; each part to its own autopilot)"
    )
    fleet.add_argument(
        "--vehicle",
        action="append",
        default=[],
        metavar="ID,CONNECT,SPEED,LAT,LON",
        help="one vehicle of the fleet: its id, MAVLink link, survey speed (m/s) and start position; once per "
        "vehicle (system id: --system)",
    )
    fleet.add_argument(
        "--fleet",
        metavar="FILE",
        help='the fleet as a JSON or TOML file: "vehicles", each with id, connect, speed, lat, lon (and system)',
    )
    p.add_argument(
        "--companion-config", metavar="FILE",
        help="the companion's configuration, for [camera], [safety], [search], [backend] search_interval_s and "
        "max_keyframe_width, [behavior] accept_uncertain (default: /etc/cloudtrack/companion.toml "
        "and ~/.config/cloudtrack/companion.toml where they exist, else the defaults)",
    )  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="plan and print; send nothing")
    p.add_argument("--save", metavar="FILE", help="also write the mission as a QGC WPL 110 waypoint file")
    p.add_argument(
        "--step-timeout", type=float, default=1.5, metavar="S",
        help="mission protocol: wait this long for each answer, 5 retries (default 1.5)",
    )  # fmt: skip
    p.set_defaults(func=run, opens_own_link=True)
