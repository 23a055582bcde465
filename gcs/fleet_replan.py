"""`cloudtrack-gcs replan`: the part of the area a vehicle left unflown (it went home, landed, its pilot took
over, or it fell silent) re-split over the vehicles still searching, and uploaded to each of them without
taking it out of its search.

What was left unflown comes from the back-end (`GET /v1/missions/{m}/dropouts`, with the supervisor token,
as `status --all` reads it: from --supervisor-token-file or $CLOUDTRACK_GCS_SUPERVISOR_TOKEN, never from the
command line, never printed): the union of the dropped vehicles' unflown parts is planned as one area (pieces
apart: their convex hull; a covered hole inside is flown over). The vehicles are the fleet `survey` took
(`--vehicle ID,CONNECT,SPEED,LAT,LON` or `--fleet FILE`); of them, those the back-end counts as still
searching the mission take a share, each at its own speed, at the survey's `--altitude` (lanes across the
camera's swath as `survey` plans them).

Each remaining vehicle first finishes its own lanes: the tool hears it (HEARTBEAT, mode, position), downloads
its mission and reads its current item. Its share begins where its own lanes end, and the split
(`behaviors/fleet_split.py`) counts the time those lanes take, so the vehicles finish close together.

The upload leaves the vehicle in its search. Its new mission is its mission as it stands, every item
unchanged and at the same number, with its share appended: ArduPilot writes the items as they arrive while it
flies AUTO (an item it is flying is written with the same content, its current item stays), PX4 switches to
the new mission whole on its last MISSION_ACK and begins it at the item sent flagged current, which is the
item the vehicle was flying to. After the upload the tool reads the current item and, where it went back,
sets it (MISSION_SET_CURRENT: it flies there from where it is); a vehicle that had finished its mission is
set to the first item of its share, and an ArduCopter, which then holds its finished mission stopped at that
item, gets MAV_CMD_MISSION_START (in AUTO: no mode change, the mission resumed there). The mode is never
changed: a vehicle in AUTO / Mission goes on; one in another mode (e.g. GUIDED while its companion follows a
candidate) flies it when it is back in its mission. A vehicle going home or landing is refused, and so is one
whose waypoints left already fly into the dropped area (a re-plan run twice; `--again` overrides). `survey`
refuses a vehicle flying its mission because it replaces that mission; `replan` only adds to it.

`--dry-run` fetches the drop-outs and prints the plan, from each vehicle's start in the fleet (its own lanes
left are not known without its link); nothing is sent. It prints a line per dropped vehicle, the re-planned
area as one plan, a line per remaining vehicle (its own lanes left, its share's lanes, length and time) and
the time for the whole area; each error is one line on stderr and a non-zero exit (2: input, 1: refused,
3: no answer).

`--watch` does the re-plan without the operator (issue 43 item 3, "or, if configured, does"): it asks the
back-end every `--watch-period` seconds and re-plans each drop-out once, by itself, as it happens, until
SIGINT / SIGTERM.
"""

from __future__ import annotations

import argparse
import re
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import shapely
from pydantic import BaseModel, ValidationError
from shapely.geometry import Polygon

from behaviors.fleet_split import FleetPart, FleetSplit, FleetVehicle, split_area
from behaviors.geolocation import latlon_to_offset
from behaviors.mission_items import NAV_TAKEOFF, MissionItem
from behaviors.survey_planner import (
    LatLon,
    SurveyError,
    SurveySettings,
    check_polygon,
    leg_time_s,
    plan_checked,
)
from cloudtrack.api_models import IDENTIFIER
from cloudtrack.autopilot_modes import RETURN_MODES, AutopilotKind, mission_mode
from cloudtrack.config_files import ConfigError, hide_url_secrets
from cloudtrack.coverage import LocalFrame
from cloudtrack.mission_protocol import (
    MissionClient,
    MissionCurrent,
    MissionError,
    MissionTimeouts,
    positions_match,
)
from cloudtrack.plain_text import without_controls
from cloudtrack.stop_signals import set_on_signals
from cloudtrack.vehicle_config import VehicleSections, load_vehicle_sections
from gcs.fleet_status import (
    BACKEND_ENV,
    TOKEN_ENV,
    StatusError,
    backend_url,
    supervisor_get,
    supervisor_token,
)
from gcs.fleet_survey import FleetMember, _minutes, fleet_from_args
from gcs.survey_command import (
    AUTOPILOT_COMPONENT,
    CRUISE_SPEED,
    EXIT_INPUT,
    EXIT_REFUSED,
    EXIT_TIMEOUT,
    InputError,
    Vehicle,
    _one_line,
    check_distance,
    settings_from,
)

TIMEOUT_S = 10.0
MAX_ANSWER_BYTES = 2_000_000
MAX_CORNERS = 200  # the re-planned area's outline is simplified to at most this many corners
INSIDE_MARGIN_M = 2.0  # a waypoint this far inside the dropped area flies into it
MISSION_STATE_COMPLETE = 5  # MISSION_CURRENT.mission_state
MAV_CMD_MISSION_START = 300
MAV_RESULT_ACCEPTED = 0
WATCH_TRIES = 3  # rounds a drop-out is tried while the vehicles to take it do not answer
EXAMPLES = """\
examples:
  cloudtrack-gcs replan --mission m-7 --fleet fleet.toml --altitude 25 --dry-run
  cloudtrack-gcs replan --mission m-7 --fleet fleet.toml --altitude 25 \\
      --backend https://backend.example --supervisor-token-file ~/.config/cloudtrack/supervisor.token
"""


class ReplanError(Exception):
    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


# ------------------------------------------------------------------------------------------ the back-end
class _Dropout(BaseModel):
    vehicle_id: str
    kind: str
    reason: str
    since: float
    unflown: list[list[list[float]]] = []
    area_m2: float = 0.0
    area_known: bool = True  # false: it left before reporting its part: what it left unflown is unknown


class Dropouts(BaseModel):
    mission_id: str
    dropout_s: float
    dropouts: list[_Dropout] = []
    searching: list[str] = []
    server_time: float


def _backend(args: argparse.Namespace) -> tuple[str, str]:
    """The back-end's address and the supervisor token, as `status --all` reads them."""
    try:
        return backend_url(args, "replan"), supervisor_token(args, "replan")
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _text(value: object, limit: int = 120) -> str:
    return " ".join(without_controls(str(value)).split())[:limit]


def fetch_dropouts(url: str, token: str, mission: str, timeout_s: float = TIMEOUT_S) -> Dropouts:
    """The mission's drop-outs from the back-end; ReplanError with one line for a person."""
    shown = hide_url_secrets(url)
    try:
        response = supervisor_get(url, f"/v1/missions/{mission}/dropouts", token, timeout_s)
    except StatusError as exc:
        raise ReplanError(str(exc), exc.code) from None
    if len(response.content) > MAX_ANSWER_BYTES:
        raise ReplanError(f"back-end {shown}: its answer is over {MAX_ANSWER_BYTES} bytes", EXIT_TIMEOUT)
    try:
        return Dropouts.model_validate_json(response.content)
    except ValidationError as exc:
        problem = exc.errors()[0]
        where = ".".join(map(str, problem["loc"]))
        raise ReplanError(
            f"back-end {shown}: its answer is not the mission's drop-outs ({where}: {problem['msg']}); is this "
            "the CloudTrack back-end, and of the same version?",
            EXIT_TIMEOUT,
        ) from None


# ------------------------------------------------------------------------------------------ the area
def replan_area(dropouts: Sequence[_Dropout]) -> tuple[list[LatLon], str]:
    """The dropped vehicles' unflown parts as one polygon to plan ([(lat, lon)], at most MAX_CORNERS corners)
    and a note on how it was made ("" when they are one piece without holes); [] when nothing is unflown."""
    rings = [ring for d in dropouts for ring in d.unflown if len(ring) >= 3]
    if not rings:
        return [], ""
    frame = LocalFrame(float(rings[0][0][0]), float(rings[0][0][1]))
    shells, holes = [], 0
    for ring in rings:
        polygon = Polygon([frame.xy(float(lat), float(lon)) for lat, lon in ring])
        if polygon.exterior.is_ccw:
            shells.append(shapely.make_valid(polygon))
        else:
            holes += 1
    union = shapely.union_all(shells)
    pieces = [g for g in getattr(union, "geoms", [union]) if isinstance(g, Polygon) and not g.is_empty]
    if not pieces:
        return [], ""
    notes = []
    if len(pieces) > 1:
        outline = shapely.convex_hull(union)
        notes.append(f"{len(pieces)} pieces planned as one (their convex hull)")
    else:
        outline = Polygon(pieces[0].exterior)
    if holes or any(p.interiors for p in pieces):
        notes.append("covered holes inside are flown over")
    tolerance = 0.25
    while len(outline.exterior.coords) - 1 > MAX_CORNERS and tolerance < 1e5:
        outline = outline.simplify(tolerance, preserve_topology=True)
        tolerance *= 2
    latlons = [frame.latlon(x, y) for x, y in list(outline.exterior.coords)[:-1]]
    rounded = [(round(lat, 7), round(lon, 7)) for lat, lon in latlons]
    # Rounding to 1 cm can make two corners of the back-end's outline one (the survey refuses a repeated corner).
    corners = [c for i, c in enumerate(rounded) if c != rounded[i - 1]]
    if len(set(corners)) < 3:
        return [], ""
    return corners, "; ".join(notes)


# ------------------------------------------------------------------------------------------ the vehicles
@dataclass(frozen=True)
class OwnMission:
    """A remaining vehicle as heard: its mission as it stands and how far it has flown it."""

    items: tuple[MissionItem, ...]  # without ArduPilot's home item
    first_seq: int  # the autopilot's number for items[0]
    current: int  # the item it flies to (the autopilot's numbering)
    complete: bool  # it flew the whole of it
    left: tuple[LatLon, ...]  # the waypoints it has yet to reach, in order

    @property
    def next_seq(self) -> int:
        """The number its share's first item gets."""
        return self.first_seq + len(self.items)


def own_mission(items: Sequence[MissionItem], first_seq: int, current: MissionCurrent) -> OwnMission:
    complete = current.state == MISSION_STATE_COMPLETE or not (
        first_seq <= current.seq < first_seq + len(items)
    )
    left = (
        ()
        if complete
        else tuple((i.lat_deg, i.lon_deg) for i in items[current.seq - first_seq :] if i.has_position)
    )
    return OwnMission(tuple(items), first_seq, current.seq, complete, left)


def busy_time_s(position: LatLon | None, left: Sequence[LatLon], speed_m_s: float) -> float:
    """How long the vehicle flies its own waypoints left (from `position`, each leg from rest to rest)."""
    path = ([position] if position is not None else []) + list(left)
    total = 0.0
    for a, b in zip(path, path[1:], strict=False):
        north, east = latlon_to_offset(a[0], a[1], b[0], b[1])
        total += leg_time_s(float((north * north + east * east) ** 0.5), speed_m_s)
    return total


@dataclass
class Remaining:
    member: FleetMember
    session: Any = None
    vehicle: Vehicle | None = None
    own: OwnMission | None = None

    def fleet_vehicle(self) -> FleetVehicle:
        v = self.member.vehicle
        if self.vehicle is None or self.own is None:
            return v  # a dry run: from its start in the fleet
        position = self.vehicle.position
        start = self.own.left[-1] if self.own.left else (position or v.start)
        return replace(v, start=start, busy_s=busy_time_s(position, self.own.left, v.speed_m_s))


def _client(args: argparse.Namespace, session: Any, vehicle: Vehicle) -> MissionClient:
    assert vehicle.kind is not None
    return MissionClient(
        session.endpoint,
        vehicle.kind.value,
        target=(vehicle.system, AUTOPILOT_COMPONENT),
        source=(args.gcs_system, args.gcs_component),
        timeouts=MissionTimeouts(step_s=args.step_timeout, retries=5),
    )


def _hear(args: argparse.Namespace, remaining: Remaining, gcs_error: type[Exception]) -> None:
    """Open the vehicle's link, hear it, refuse one going home, read its mission; ReplanError otherwise."""
    from gcs.cli import GcsSession

    member = remaining.member
    link = argparse.Namespace(**{**vars(args), "connect": member.connect, "system": member.system})
    who = f"vehicle {member.vehicle.id}: "
    try:
        remaining.session = GcsSession(link)
    except OSError as exc:
        raise ReplanError(f"{who}cannot open {member.connect}: {exc}", EXIT_TIMEOUT) from None
    vehicle = Vehicle(remaining.session, member.system)
    remaining.vehicle = vehicle
    try:
        remaining.session.connect()
        vehicle.wait(args.timeout)
        client = _client(args, remaining.session, vehicle)
        downloaded = client.download()
        current = client.read_current()
    except gcs_error as exc:
        raise ReplanError(f"{who}{exc}", int(getattr(exc, "code", EXIT_TIMEOUT))) from None
    except MissionError as exc:
        raise ReplanError(f"{who}{exc}", EXIT_TIMEOUT) from None
    if vehicle.mode.upper() in RETURN_MODES:
        raise ReplanError(
            f"{who}it is leaving the search (mode {vehicle.mode}): leave it out of the fleet for the re-plan",
            EXIT_REFUSED,
        )
    remaining.own = own_mission(downloaded.items, downloaded.first_seq, current)


def _not_replanned_before(remaining: Remaining, area: Sequence[LatLon]) -> None:
    """ReplanError when the path along the vehicle's waypoints left already flies into the area (a re-plan run twice would
    append the same share again)."""
    own = remaining.own
    if own is None or not own.left:
        return
    frame = LocalFrame(*area[0])
    inside = Polygon([frame.xy(lat, lon) for lat, lon in area]).buffer(-INSIDE_MARGIN_M)
    points = [frame.xy(lat, lon) for lat, lon in own.left]
    path = shapely.LineString(points) if len(points) > 1 else shapely.Point(points[0])
    if path.intersects(inside):  # lanes end on the area's edge: their legs, not their ends, lie in it
        raise ReplanError(
            f"vehicle {remaining.member.vehicle.id}: its waypoints left already fly into the dropped area "
            "(re-planned before?); --again appends its share all the same",
            EXIT_REFUSED,
        )


# ------------------------------------------------------------------------------------------ the lines
def split_over(
    area: Sequence[LatLon], settings: SurveySettings, vehicles: Sequence[FleetVehicle]
) -> tuple[FleetSplit, list[FleetVehicle]]:
    """The area split over the vehicles (`split_area`); where it has fewer lanes than vehicles (a vehicle that
    dropped out near the end of its part leaves a lane or two), over those that would fly the whole of it
    soonest alone, one lane or more each. The vehicles left without a share come second."""
    whole = plan_checked(check_polygon(area), replace(settings, start=None))
    if whole.lanes >= len(vehicles):
        return split_area(area, settings, vehicles), []
    soonest = sorted(vehicles, key=lambda v: (split_area(area, settings, [v]).finish_s, v.id))
    taking = {v.id for v in soonest[: whole.lanes]}
    return (
        split_area(area, settings, [v for v in vehicles if v.id in taking]),
        [v for v in vehicles if v.id not in taking],
    )


def describe(split: FleetSplit, remaining: dict[str, Remaining], altitude_m: float) -> list[str]:
    whole = split.whole
    lines = [
        f"the unflown area as one plan: {whole.lanes} lanes {whole.spacing_m:.1f} m apart (camera swath "
        f"{whole.swath_m:.1f} m at {altitude_m:g} m), along {whole.angle_deg:g} deg, {whole.length_m:.0f} m over "
        f"{whole.area_m2 / 1e4:.2f} ha"
    ]
    for part in split.parts:
        plan, own = part.plan, remaining[part.vehicle.id].own
        lanes = f"lane {part.first_lane}" if plan.lanes == 1 else f"lanes {part.first_lane}-{part.last_lane}"
        if own is None:
            first = "from its start,"
        elif own.left:
            first = (
                f"its own {len(own.left)} waypoints left first (about {_minutes(part.vehicle.busy_s)}), then"
            )
        else:
            first = "its own mission flown, then"
        lines.append(
            f"vehicle {part.vehicle.id}: {first} {lanes} of {whole.lanes}, {plan.length_m:.0f} m over "
            f"{plan.area_m2 / 1e4:.2f} ha, transit {part.transit_m:.0f} m, at {plan.speed_m_s:g} m/s; done in about "
            f"{_minutes(part.time_s)}, {len(_share_items(part))} items added"
        )
    last = max(split.parts, key=lambda p: p.time_s)
    lines.append(
        f"time to finish: about {_minutes(split.finish_s)} (vehicle {last.vehicle.id} finishes last)"
    )
    return lines


def _share_items(part: FleetPart) -> list[MissionItem]:
    return [i for i in part.plan.items if i.command != NAV_TAKEOFF]  # it is in the air


# ------------------------------------------------------------------------------------------ the upload
def _mode_now(remaining: Remaining, seconds: float = 2.5) -> str:
    """The mode in the vehicle's next HEARTBEAT (its last known when none comes)."""
    vehicle = remaining.vehicle
    assert vehicle is not None
    known, vehicle.mode = vehicle.mode, ""
    deadline = time.monotonic() + seconds
    while not vehicle.mode and time.monotonic() < deadline:
        vehicle._receive(remaining.session.endpoint)
    if not vehicle.mode:
        vehicle.mode = known
    return vehicle.mode


def _mission_start(args: argparse.Namespace, session: Any, vehicle: Vehicle) -> None:
    """MAV_CMD_MISSION_START to an ArduCopter in AUTO whose mission had finished: MISSION_SET_CURRENT leaves
    such a mission stopped at the item, holding (AP_Mission::set_current_cmd); this resumes it there without
    a mode change (it is in AUTO already). MissionError unless it is accepted."""
    endpoint, target = session.endpoint, (vehicle.system, AUTOPILOT_COMPONENT)
    for _ in range(3):
        endpoint.send(lambda m: m.command_long_send(*target, MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0))
        deadline = time.monotonic() + args.step_timeout
        while time.monotonic() < deadline:
            msg = endpoint.receive(timeout=0.2)
            if (
                msg is None
                or msg.get_type() != "COMMAND_ACK"
                or msg.command != MAV_CMD_MISSION_START
                or msg.get_srcSystem() != vehicle.system
            ):
                continue
            if msg.result != MAV_RESULT_ACCEPTED:
                raise MissionError(
                    f"MAV_CMD_MISSION_START refused (result {msg.result}): switch it out of AUTO and back to fly "
                    "its share"
                )
            return
    raise MissionError("MAV_CMD_MISSION_START: no answer; switch it out of AUTO and back to fly its share")


def send_share(args: argparse.Namespace, remaining: Remaining, part: FleetPart) -> int:
    """Append the vehicle's share to its mission, leave it flying where it was: 0, or the exit code after one
    line on stderr."""
    vehicle, own = remaining.vehicle, remaining.own
    assert vehicle is not None and vehicle.kind is not None and own is not None
    who = f"vehicle {part.vehicle.id}: "
    client = _client(args, remaining.session, vehicle)
    share = _share_items(part)
    items = [*own.items, *share]
    try:
        before = client.read_current()  # it may have moved on since it was heard
        now_own = own_mission(own.items, own.first_seq, before)
        expected = own.next_seq if now_own.complete else now_own.current
        client.upload(items, current=expected)  # where PX4 begins the new mission
        after = client.read_current()
        if after.seq < expected or now_own.complete:
            after = client.set_current(expected)
        stored = client.download().items
        flying = mission_mode(vehicle.kind)
        mode = _mode_now(remaining)
        if now_own.complete and vehicle.kind is AutopilotKind.ARDUPILOT and mode == flying:
            _mission_start(args, remaining.session, vehicle)  # a finished mission is held, not resumed
    except MissionError as exc:
        print(f"error: {who}{exc}", file=sys.stderr)
        return EXIT_TIMEOUT if exc.result is None and "no answer" in str(exc) else EXIT_REFUSED
    if not positions_match(stored, items):
        print(
            f"error: {who}the autopilot holds {len(stored)} items that differ from the {len(items)} uploaded: "
            "check its mission in the ground station",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    goes_on = (
        f"mode {mode}: it goes on" if mode == flying else f"mode {mode}: it flies them when back in {flying}"
    )
    print(
        f"{who}uploaded {len(items)} items (its {len(own.items)}, then {len(share)} for the dropped area), read "
        f"back and checked; current item {after.seq}, {goes_on}",
        flush=True,
    )
    return 0


# ------------------------------------------------------------------------------------------ run
def run(args: argparse.Namespace) -> int:
    from gcs.cli import GcsError

    try:
        url, token = _backend(args)
        if not re.fullmatch(IDENTIFIER, args.mission):
            raise InputError(
                f"--mission {_text(args.mission, 64)!r} must be 1-64 letters, digits, '_', '.' or '-' (as the "
                "vehicles report it)"
            )
        if args.altitude is None:
            raise InputError("give --altitude M: the survey's altitude, which the dropped area is flown at")
        if not 0.5 <= args.watch_period <= 3600:
            raise InputError(f"--watch-period {args.watch_period:g} must be 0.5-3600 s")
        members = fleet_from_args(args)
        config = load_vehicle_sections(Path(args.companion_config) if args.companion_config else None)
        settings = settings_from(args, config, CRUISE_SPEED[AutopilotKind.PX4])
    except (InputError, ConfigError, SurveyError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    if args.watch:
        return _watch(args, url, token, members, config, settings, GcsError)
    try:
        answer = fetch_dropouts(url, token, args.mission, args.timeout)
    except ReplanError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.code
    return _replan(args, answer.dropouts, answer.searching, members, config, settings, GcsError)


def _replan(
    args: argparse.Namespace,
    dropouts: Sequence[_Dropout],
    searching: Sequence[str],
    members: Sequence[FleetMember],
    config: VehicleSections,
    settings: SurveySettings,
    gcs_error: type[Exception],
) -> int:
    """One re-plan of these drop-outs' unflown parts over the fleet's vehicles still searching."""
    dropped = {d.vehicle_id: d for d in dropouts}
    remaining = {m.vehicle.id: Remaining(m) for m in members if m.vehicle.id in searching}
    mode = "dry run, nothing sent" if args.dry_run else "to upload"
    print(
        f"replan of mission {_text(args.mission, 64)} ({mode}): {len(dropped)} vehicle"
        f"{'s' if len(dropped) != 1 else ''} left the search, {len(remaining)} of the fleet still searching",
        flush=True,
    )
    for d in dropouts:
        left = (
            f"{d.area_m2 / 1e4:.2f} ha unflown"
            if d.area_known
            else "its part of the area unknown (it reported none before it left): what it left unflown is not "
            "known, and nothing of it can be re-planned"
        )
        print(f"  vehicle {_text(d.vehicle_id, 32)} left the search ({_text(d.reason)}): {left}", flush=True)
    for m in members:
        if m.vehicle.id not in remaining and m.vehicle.id not in dropped:
            print(
                f"  vehicle {m.vehicle.id}: not searching mission {_text(args.mission, 64)} on the back-end: left out"
            )
    area, note = replan_area(dropouts)
    if not area:
        unknown = [d.vehicle_id for d in dropouts if not d.area_known]
        if unknown:
            print(
                "  nothing to re-plan from what the back-end knows: the part of "
                f"{', '.join(_text(v, 32) for v in unknown)} is unknown (plan it by hand)",
                flush=True,
            )
        else:
            print("  nothing to re-plan: no vehicle left part of its area unflown", flush=True)
        return 0
    if not remaining:
        print(
            "error: no vehicle of the fleet still searches the mission: nothing to re-plan onto",
            file=sys.stderr,
        )
        return EXIT_REFUSED
    if note:
        print(f"  the unflown area: {note}", flush=True)
    try:
        return _plan_and_send(args, area, settings, remaining, config.safety.max_survey_distance_m, gcs_error)
    finally:
        for r in remaining.values():
            if r.session is not None:
                r.session.close()


def _watch(
    args: argparse.Namespace,
    url: str,
    token: str,
    members: Sequence[FleetMember],
    config: VehicleSections,
    settings: SurveySettings,
    gcs_error: type[Exception],
) -> int:
    """`--watch`: the re-plan done as each vehicle drops out, without the operator. Each drop-out (a vehicle
    and the time it left) is re-planned once, by itself; one whose vehicles did not answer is tried again
    next round, up to WATCH_TRIES. A round's error is a line and the watch goes on; SIGINT or SIGTERM ends
    it between rounds (an upload under way is finished, not cut)."""
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        set_on_signals(stop)
    mission = _text(args.mission, 64)
    print(
        f"replan --watch of mission {mission}: asking the back-end every {args.watch_period:g} s, re-planning "
        "each vehicle that leaves the search; Ctrl-C ends",
        flush=True,
    )
    tries: dict[tuple[str, float], int] = {}
    done: set[tuple[str, float]] = set()
    while not stop.is_set():
        try:
            answer = fetch_dropouts(url, token, args.mission, args.timeout)
        except ReplanError as exc:
            print(
                f"replan --watch: {exc}; asking again in {args.watch_period:g} s", file=sys.stderr, flush=True
            )
        else:
            new = [d for d in answer.dropouts if (d.vehicle_id, d.since) not in done]
            if new:
                names = ", ".join(_text(d.vehicle_id, 32) for d in new)
                print(f"AUTO REPLAN: {names} left the search of mission {mission}", flush=True)
                code = _replan(args, new, answer.searching, members, config, settings, gcs_error)
                for d in new:
                    key = (d.vehicle_id, d.since)
                    tries[key] = tries.get(key, 0) + 1
                    if code != EXIT_TIMEOUT or tries[key] >= WATCH_TRIES:
                        done.add(key)
                if code == 0:
                    print(f"AUTO REPLAN: done for {names}", flush=True)
                elif any((d.vehicle_id, d.since) not in done for d in new):
                    print(f"AUTO REPLAN: not done for {names}; trying again next round", flush=True)
                else:
                    print(
                        f"AUTO REPLAN: not done for {names}: re-plan by hand (cloudtrack-gcs replan)",
                        flush=True,
                    )
        stop.wait(args.watch_period)
    print("replan --watch: stopped", flush=True)
    return 0


def _plan_and_send(
    args: argparse.Namespace,
    area: list[LatLon],
    settings: SurveySettings,
    remaining: dict[str, Remaining],
    max_distance_m: float,
    gcs_error: type[Exception],
) -> int:
    try:
        for r in remaining.values():
            check_distance(
                area, r.member.vehicle.start, max_distance_m, f"vehicle {r.member.vehicle.id}'s start"
            )
        if not args.dry_run:
            for r in remaining.values():  # every vehicle heard before anything is sent
                _hear(args, r, gcs_error)
                assert r.vehicle is not None
                where = r.vehicle.position or r.member.vehicle.start
                check_distance(area, where, max_distance_m, f"vehicle {r.member.vehicle.id}")
                if not args.again:
                    _not_replanned_before(r, area)
        split, idle = split_over(area, settings, [r.fleet_vehicle() for r in remaining.values()])
    except ReplanError as exc:
        print(f"error: {exc}; nothing uploaded", file=sys.stderr)
        return exc.code
    except (InputError, SurveyError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    if args.dry_run:
        print(
            "  (dry run: each vehicle's own lanes left are not known without its link; its share is planned "
            "from its start in the fleet)",
            flush=True,
        )
    for line in describe(split, remaining, settings.altitude_m):
        print(f"  {line}", flush=True)
    for vehicle in idle:
        print(
            f"  vehicle {vehicle.id}: no share (the unflown area has {split.whole.lanes} lane"
            f"{'s' if split.whole.lanes != 1 else ''}, taken by the vehicles that finish them soonest)",
            flush=True,
        )
    if args.dry_run:
        return 0
    worst, done = 0, []
    for part in split.parts:
        code = send_share(args, remaining[part.vehicle.id], part)
        worst = max(worst, code)
        if not code:
            done.append(part.vehicle.id)
    missing = [p.vehicle.id for p in split.parts if p.vehicle.id not in done]
    print(
        f"replan: {len(done)} of {len(split.parts)} vehicles hold their share"
        + (f"; not uploaded: {', '.join(missing)} (its share stays unflown)" if missing else ""),
        flush=True,
    )
    return worst


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "replan",
        help="re-split the area a dropped vehicle left unflown over the vehicles still searching, uploaded "
        "without taking them out of their search",
        description=__doc__.split("\n\n")[0].replace("`", "") if __doc__ else None,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--mission", required=True, metavar="ID", help="the mission id the vehicles report to the back-end"
    )
    p.add_argument("--backend", metavar="URL", help=f"the back-end's address (default: ${BACKEND_ENV})")
    p.add_argument(
        "--supervisor-token-file", type=Path, metavar="PATH",
        help=f"file holding the back-end's supervisor token (default: ${TOKEN_ENV})",
    )  # fmt: skip
    p.add_argument("--supervisor-token", help=argparse.SUPPRESS)  # only there to say why not
    fleet = p.add_argument_group(
        "the fleet (as survey takes it; those the back-end counts as searching take a share)"
    )
    fleet.add_argument(
        "--vehicle", action="append", default=[], metavar="ID,CONNECT,SPEED,LAT,LON",
        help="one vehicle: its id (as it reports to the back-end), MAVLink link, survey speed (m/s) and start",
    )  # fmt: skip
    fleet.add_argument(
        "--fleet", metavar="FILE", help="the fleet as a JSON or TOML file (as survey takes it)"
    )
    p.add_argument("--altitude", type=float, metavar="M", help="the survey's altitude above home (required)")
    p.add_argument(
        "--overlap", type=float, help="side overlap of neighbouring lanes' swaths, 0-0.9 (default 0.2)"
    )
    p.add_argument(
        "--angle",
        type=float,
        metavar="DEG",
        help="lane direction clockwise from north (default: fewest lanes)",
    )
    p.add_argument(
        "--companion-config", metavar="FILE",
        help="the companion's configuration, for [camera] and [safety] (default: as survey)",
    )  # fmt: skip
    p.add_argument(
        "--dry-run", action="store_true", help="fetch the drop-outs and print the plan; send nothing"
    )
    p.add_argument(
        "--watch", action="store_true",
        help="keep asking the back-end and re-plan each vehicle that leaves the search as it leaves, until "
        "Ctrl-C (the re-plan done without the operator)",
    )  # fmt: skip
    p.add_argument(
        "--watch-period", type=float, default=5.0, metavar="S",
        help="with --watch: ask the back-end every S seconds (default 5)",
    )  # fmt: skip
    p.add_argument(
        "--again", action="store_true",
        help="append the shares even where a vehicle's waypoints left already fly into the dropped area (by "
        "default that is refused: a re-plan run twice would fly it twice)",
    )  # fmt: skip
    p.add_argument(
        "--step-timeout", type=float, default=1.5, metavar="S",
        help="mission protocol: wait this long for each answer, 5 retries (default 1.5)",
    )  # fmt: skip
    p.set_defaults(func=run, opens_own_link=True, speed=None, takeoff=False)
