"""`cloudtrack-gcs survey`: plan a search survey over an area and upload it to the autopilot as its mission.

The area comes from the command line (`--polygon "lat,lon lat,lon ..."`), a file (`--area-file`: a GeoJSON
Polygon / Feature / FeatureCollection, or a QGroundControl .plan with a survey), or a centre and a size
(`--centre lat,lon --size 100x60`). The lanes are sized from the camera's ground footprint at the survey
altitude and the altitude is held to the safety band, both read from the companion's configuration
([camera], [safety]: `cloudtrack/vehicle_config.py`), so the plan matches what the companion will see and
allow. `behaviors/survey_planner.py` plans; `cloudtrack/mission_protocol.py` uploads. The mission the
autopilot receives is plain MAVLink (NAV_WAYPOINT, DO_CHANGE_SPEED), as QGroundControl would send it: the
companion flies a QGC-planned survey the same way.

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
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from pymavlink import mavwp

from behaviors.camera_model import CameraModel
from behaviors.mission_items import MissionItem
from behaviors.survey_planner import LatLon, SurveyError, SurveyPlan, SurveySettings, plan_survey, rectangle
from cloudtrack.autopilot_modes import AutopilotKind, detect_autopilot, mission_mode, mode_name
from cloudtrack.config_files import ConfigError
from cloudtrack.coverage import CoverageMap, fly_path
from cloudtrack.mavlink_connection import mavlink
from cloudtrack.mission_protocol import MissionClient, MissionError, MissionTimeouts, positions_match
from cloudtrack.vehicle_config import VehicleSections, load_vehicle_sections

EXIT_REFUSED, EXIT_INPUT, EXIT_TIMEOUT = 1, 2, 3
MAX_AREA_FILE_BYTES = 1_000_000
AUTOPILOT_COMPONENT = 1
CRUISE_SPEED = {AutopilotKind.ARDUPILOT: 10.0, AutopilotKind.PX4: 5.0}  # WPNAV_SPEED, MPC_XY_CRUISE defaults
EXAMPLES = """\
examples:
  cloudtrack-gcs survey --centre 47.3977,8.5456 --size 120x80 --altitude 25 --dry-run
  cloudtrack-gcs survey --polygon "47.3975,8.5450 47.3975,8.5466 47.3982,8.5466 47.3982,8.5450" --altitude 25 --speed 4
  cloudtrack-gcs survey --area-file search-area.geojson --altitude 30 --overlap 0.3
  cloudtrack-gcs survey --area-file mission.plan --altitude 25 --save survey.waypoints   # QGC's survey polygon
  cloudtrack-gcs --connect tcp:192.168.1.10:5760 survey --centre 47.3977,8.5456 --size 200x100 --altitude 30

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
    polygon; [lon, lat] order) or of a QGroundControl .plan's first survey ([lat, lon])."""
    try:
        size = path.stat().st_size
        if size > MAX_AREA_FILE_BYTES:
            raise InputError(f"{path}: {size} bytes; an area file may have at most {MAX_AREA_FILE_BYTES}")
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None
    if isinstance(data, dict) and data.get("fileType") == "Plan":
        return _plan_polygon(path, data)
    return _geojson_polygon(path, data)


def _plan_polygon(path: Path, data: dict[str, Any]) -> list[LatLon]:
    items = data.get("mission", {}).get("items", []) if isinstance(data.get("mission"), dict) else []
    for item in items if isinstance(items, list) else []:
        if isinstance(item, dict) and item.get("complexItemType") == "survey":
            return _corners(path, item.get("polygon"), lon_first=False)
    raise InputError(
        f"{path}: a QGroundControl plan without a survey (add a Survey pattern in QGC's Plan view)"
    )


def _geojson_polygon(path: Path, data: Any) -> list[LatLon]:
    geometry = data
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        polygons = [
            f.get("geometry")
            for f in data.get("features", [])
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
    corners = []
    for position in ring[:1000]:
        if not (
            isinstance(position, list)
            and len(position) >= 2
            and all(isinstance(v, (int, float)) for v in position[:2])
        ):
            raise InputError(f"{path}: position {position!r} is not a pair of numbers")
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
        altitude_m=args.altitude,
        overlap=args.overlap,
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


def describe(
    plan: SurveyPlan, area: list[LatLon], settings: SurveySettings, speed_note: str = ""
) -> list[str]:
    minutes, seconds = divmod(round(plan.time_s), 60)
    counts = Counter(item.name for item in plan.items)
    speed = f"{plan.speed_m_s:g} m/s" + (f" ({speed_note})" if speed_note else "")
    started = time.perf_counter()
    cover = fly_path(
        CoverageMap(area, settings.camera, settings.search_range_m), plan.waypoints, settings.altitude_m
    )
    share, took = cover.coverage(), time.perf_counter() - started
    return [
        f"lanes: {plan.lanes}, {plan.spacing_m:.1f} m apart (camera swath {plan.swath_m:.1f} m at "
        f"{settings.altitude_m:g} m), along {plan.angle_deg:g} deg",
        f"length: {plan.length_m:.0f} m over {plan.area_m2 / 1e4:.2f} ha",
        f"time to fly: about {minutes} min {seconds:02d} s at {speed}",
        f"coverage if flown as planned: {100 * share:.1f} % of the area ({cover.views} camera views, {took:.2f} s)",
        "items: " + ", ".join(f"{n} {name}" for name, n in counts.items()),
    ]


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

    try:
        area = area_from_args(args)
        vehicle_config = load_vehicle_sections(Path(args.companion_config) if args.companion_config else None)
        settings = settings_from(args, vehicle_config, CRUISE_SPEED[AutopilotKind.PX4])
        plan = plan_survey(area, settings)
    except (InputError, SurveyError, ConfigError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    if args.dry_run:
        print(f"survey (dry run, nothing sent): {len(area)} corners", flush=True)
        note = "" if args.speed is not None else "assumed: the autopilot's own unless --speed"
        for line in describe(plan, area, settings, note):
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
        return _upload(args, session, area, vehicle_config)
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
    args: argparse.Namespace, session: Any, area: list[LatLon], vehicle_config: VehicleSections
) -> int:
    vehicle = Vehicle(session, args.system)
    try:
        vehicle.wait(args.timeout)
        assert vehicle.kind is not None
        settings = settings_from(args, vehicle_config, CRUISE_SPEED[vehicle.kind])
        plan = plan_survey(area, replace(settings, start=vehicle.position))
    except SurveyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    name = "ArduPilot" if vehicle.kind is AutopilotKind.ARDUPILOT else "PX4"
    print(f"survey for system {args.system} ({name}, mode {vehicle.mode}):", flush=True)
    note = "" if args.speed is not None else f"the {name} default; --speed sets one"
    for line in describe(plan, area, settings, note):
        print(f"  {line}", flush=True)
    if vehicle.mode == mission_mode(vehicle.kind):
        print(
            f"error: the vehicle is flying its mission ({vehicle.mode}): switch it to another mode (e.g. "
            f"{'LOITER' if vehicle.kind is AutopilotKind.ARDUPILOT else 'HOLD'}) before replacing the mission",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    client = MissionClient(
        session.endpoint,
        vehicle.kind.value,
        target=(args.system, AUTOPILOT_COMPONENT),
        source=(args.gcs_system, args.gcs_component),
        timeouts=MissionTimeouts(step_s=args.step_timeout, retries=5),
    )
    try:
        client.upload(plan.items)
        current = client.set_current(client.first_seq)
        stored = client.download().items
    except MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT if exc.result is None and "no answer" in str(exc) else EXIT_REFUSED
    if not positions_match(stored, plan.items):
        print(
            f"error: the autopilot holds {len(stored)} items that differ from the {len(plan.items)} uploaded: "
            "check the mission in the ground station before AUTO",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    print(
        f"uploaded {len(plan.items)} items, read back and checked; current item {current.seq}: switch to "
        f"{mission_mode(vehicle.kind)} to fly the survey",
        flush=True,
    )
    return _save(args, plan)


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
    p.add_argument("--altitude", type=float, required=True, metavar="M", help="above home, within [safety]")
    p.add_argument(
        "--overlap",
        type=float,
        default=0.2,
        help="side overlap of neighbouring lanes' swaths, 0-0.9 (default 0.2)",
    )
    p.add_argument(
        "--speed", type=float, metavar="M/S", help="ground speed (DO_CHANGE_SPEED; default: the autopilot's)"
    )
    p.add_argument(
        "--angle",
        type=float,
        metavar="DEG",
        help="lane direction clockwise from north (default: fewest lanes)",
    )
    p.add_argument("--takeoff", action="store_true", help="begin with NAV_TAKEOFF to the survey altitude")
    p.add_argument(
        "--companion-config", metavar="FILE",
        help="the companion's configuration, for [camera] and [safety] (default: /etc/cloudtrack/companion.toml "
        "and ~/.config/cloudtrack/companion.toml where they exist, else the defaults)",
    )  # fmt: skip
    p.add_argument("--dry-run", action="store_true", help="plan and print; send nothing")
    p.add_argument("--save", metavar="FILE", help="also write the mission as a QGC WPL 110 waypoint file")
    p.add_argument(
        "--step-timeout", type=float, default=1.5, metavar="S",
        help="mission protocol: wait this long for each answer, 5 retries (default 1.5)",
    )  # fmt: skip
    p.set_defaults(func=run, opens_own_link=True)
