"""`cloudtrack-gcs survey --vehicle ... / --fleet FILE`: one search area split over several vehicles, each part
uploaded to its own autopilot.

The area, the altitude, the overlap and a `--pod` are given as for one vehicle (`gcs/survey_command.py`);
the area is planned once as for one vehicle (for a POD: the altitude, lane spacing and speed the POD planner
chooses) and its lanes are shared out in contiguous runs, one per vehicle, so that the vehicles' times
(transit from their start position, then their lanes, at their own speeds) are close
(`behaviors/fleet_split.py`). Each vehicle flies its part at its own speed (with `--pod`: at most the POD
plan's, faster would lower the POD).

The fleet: `--vehicle ID,CONNECT,SPEED,LAT,LON` once per vehicle (CONNECT may itself hold commas, e.g.
`/dev/ttyUSB0,57600`), or `--fleet FILE`, JSON or TOML:

    {"vehicles": [{"id": "a", "connect": "udpin:0.0.0.0:14551", "speed": 5, "lat": 47.397, "lon": 8.545},
                  {"id": "b", "connect": "tcp:10.0.0.2:5760", "speed": 8, "lat": 47.398, "lon": 8.546,
                   "system": 2}]}

    [[vehicles]]
    id = "a"
    connect = "udpin:0.0.0.0:14551"
    ...

`system` (the autopilot's MAVLink system id) defaults to `--system`. LAT,LON is where the vehicle begins
(its position, or home): a start farther than [safety] max_survey_distance_m from the area is refused.

It prints the single plan, a line per vehicle (its lanes, length, area, transit, time, items) and the time
to finish the whole area (the slowest vehicle's) beside the time the quickest vehicle would need alone.
Without `--dry-run` it first hears every vehicle (its HEARTBEAT, mode and position: an autopilot flying its
mission, or one farther than [safety] max_survey_distance_m from its part, is refused) and uploads nothing
unless all are ready; then it uploads each part to its own autopilot as for one vehicle (read back,
checked, first item current). A failed upload is one line naming the vehicle; the others still go, and
the last line says which vehicles hold their part. Exit codes as for one vehicle: the worst.
"""

from __future__ import annotations

import argparse
import json
import os
import stat
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from behaviors.fleet_split import FleetSplit, FleetVehicle, split_area
from behaviors.survey_planner import LatLon, SurveyError
from cloudtrack.autopilot_modes import AutopilotKind
from cloudtrack.config_files import ConfigError
from cloudtrack.mission_protocol import MissionError
from cloudtrack.survey_pod import PodOutOfReach, expected_pod
from cloudtrack.vehicle_config import load_vehicle_sections
from gcs.survey_command import (
    CRUISE_SPEED,
    EXIT_INPUT,
    EXIT_REFUSED,
    EXIT_TIMEOUT,
    InputError,
    PodContext,
    Vehicle,
    _one_line,
    area_from_args,
    check_distance,
    out_of_reach,
    plan_for,
    pod_context,
    refused_in_mission,
    save_waypoints,
    send_mission,
    settings_from,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

MAX_FLEET_FILE_BYTES = 64_000
MAX_CONNECT_CHARS = 200
FLEET_KEYS = {"id", "connect", "speed", "lat", "lon", "system"}


@dataclass(frozen=True)
class FleetMember:
    vehicle: FleetVehicle
    connect: str  # its MAVLink link
    system: int  # its autopilot's system id


def _minutes(seconds: float) -> str:
    minutes, secs = divmod(round(seconds), 60)
    return f"{minutes} min {secs:02d} s"


# --------------------------------------------------------------------------------------- the fleet
def _member(
    name: str, connect: str, speed: float, lat: float, lon: float, system: int, where: str
) -> FleetMember:
    if (
        not connect
        or len(connect) > MAX_CONNECT_CHARS
        or any(c.isspace() or not c.isprintable() for c in connect)
    ):
        raise InputError(
            f"{where}: the link {connect[:40]!r} must be a MAVLink address of at most {MAX_CONNECT_CHARS} characters "
            "without spaces (e.g. udpin:0.0.0.0:14551)"
        )
    if not 1 <= system <= 255:
        raise InputError(f"{where}: system id {system} must be 1-255")
    return FleetMember(FleetVehicle(name, speed, (lat, lon)), connect, system)


def parse_vehicle(text: str, system: int) -> FleetMember:
    """ "ID,CONNECT,SPEED,LAT,LON" (CONNECT may hold commas: a serial port and its baud rate)."""
    parts = text.split(",")
    usage = f"--vehicle {text[:80]!r} is not ID,CONNECT,SPEED,LAT,LON (e.g. a,udpin:0.0.0.0:14551,5,47.3977,8.5456)"
    if len(parts) < 5:
        raise InputError(usage)
    try:
        speed, lat, lon = (float(v) for v in parts[-3:])
    except ValueError:
        raise InputError(usage) from None
    return _member(parts[0], ",".join(parts[1:-3]), speed, lat, lon, system, f"--vehicle {parts[0][:32]}")


def read_fleet_file(path: Path, system: int) -> list[FleetMember]:
    """The vehicles of a JSON or TOML fleet file (`vehicles`: a list of tables); only a regular file is read,
    and at most `MAX_FLEET_FILE_BYTES` of it; whatever is wrong is one InputError naming the file."""
    raw = _read_bounded(path)
    try:
        text = raw.decode("utf-8")
        data: Any = json.loads(text) if text.lstrip().startswith("{") else tomllib.loads(text)
    except (ValueError, RecursionError) as exc:  # JSON's, TOML's and UTF-8's own errors
        raise InputError(f"{path}: neither JSON nor TOML ({_one_line(exc)[:120]})") from None
    entries = data.get("vehicles") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(
            f'{path}: no vehicles: give a list "vehicles" of tables (id, connect, speed, lat, lon)'
        )
    members = []
    for k, entry in enumerate(entries):
        where = f"{path}: vehicle {k + 1}"
        if not isinstance(entry, dict):
            raise InputError(f"{where} is not a table (id, connect, speed, lat, lon)")
        unknown = sorted(set(entry) - FLEET_KEYS)
        if unknown:
            raise InputError(
                f"{where}: unknown key {unknown[0][:32]!r} (known: {', '.join(sorted(FLEET_KEYS))})"
            )
        missing = sorted({"id", "connect", "speed", "lat", "lon"} - set(entry))
        if missing:
            raise InputError(f"{where}: no {missing[0]}")
        name, connect, own_system = entry["id"], entry["connect"], entry.get("system", system)
        numbers = [entry["speed"], entry["lat"], entry["lon"]]
        if not isinstance(name, str) or not isinstance(connect, str):
            raise InputError(f"{where}: id and connect must be strings")
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
            raise InputError(f"{where}: speed, lat and lon must be numbers")
        if not isinstance(own_system, int) or isinstance(own_system, bool):
            raise InputError(f"{where}: system must be a whole number")
        speed, lat, lon = (float(v) for v in numbers)
        members.append(_member(name, connect, speed, lat, lon, own_system, f"{where} ({name[:32]})"))
    return members


def _read_bounded(path: Path) -> bytes:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO would otherwise wait for a writer
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(f"{path}: not a regular file; give the fleet as a JSON or TOML file")
        with os.fdopen(fd, "rb", closefd=False) as file:
            raw = file.read(MAX_FLEET_FILE_BYTES + 1)
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(raw) > MAX_FLEET_FILE_BYTES:
        raise InputError(
            f"{path}: more than {MAX_FLEET_FILE_BYTES} bytes; a fleet file may have at most that"
        )
    return raw


def fleet_from_args(args: argparse.Namespace) -> list[FleetMember]:
    if args.fleet is not None and args.vehicle:
        raise InputError("give the fleet one way: --vehicle (once per vehicle) or --fleet FILE")
    members = (
        read_fleet_file(Path(args.fleet), args.system)
        if args.fleet is not None
        else [parse_vehicle(text, args.system) for text in args.vehicle]
    )
    links: dict[str, str] = {}
    for m in members:
        if m.connect in links and links[m.connect] != m.vehicle.id:
            raise InputError(
                f"vehicles {links[m.connect]} and {m.vehicle.id} share the link {m.connect}: give each its own "
                "(a MAVLink router gives each vehicle its own port)"
            )
        links.setdefault(m.connect, m.vehicle.id)
    return members


# ------------------------------------------------------------------------------------------- the plan
def describe_fleet(split: FleetSplit, altitude_m: float) -> list[str]:
    whole = split.whole
    lines = [
        f"the area as one plan: {whole.lanes} lanes {whole.spacing_m:.1f} m apart (camera swath {whole.swath_m:.1f} m "
        f"at {altitude_m:g} m), along {whole.angle_deg:g} deg, {whole.length_m:.0f} m over "
        f"{whole.area_m2 / 1e4:.2f} ha"
    ]
    for part in split.parts:
        plan = part.plan
        lanes = f"lane {part.first_lane}" if plan.lanes == 1 else f"lanes {part.first_lane}-{part.last_lane}"
        lines.append(
            f"vehicle {part.vehicle.id}: {lanes} of {whole.lanes}, {plan.length_m:.0f} m over "
            f"{plan.area_m2 / 1e4:.2f} ha, transit {part.transit_m:.0f} m, about {_minutes(part.time_s)} at "
            f"{plan.speed_m_s:g} m/s, {len(plan.items)} items"
        )
    last = max(split.parts, key=lambda p: p.time_s)
    lines.append(
        f"whole area: about {_minutes(split.finish_s)} (vehicle {last.vehicle.id} finishes last); one vehicle alone: "
        f"about {_minutes(split.alone_s)} ({split.alone_id}, the quickest alone)"
    )
    return lines


def _pod_lines(split: FleetSplit, settings: Any, pod: PodContext) -> list[str]:
    if pod.target is None:
        return []
    lines = []
    for part in split.parts:
        pod_map = expected_pod(
            part.plan, part.corners, settings, pod.target, pod.map_settings, pod.keyframing.interval_s
        )
        lines.append(
            f"vehicle {part.vehicle.id}: expected POD mean {pod_map.mean():.2f} over its part ({pod.label})"
        )
    return lines


def _save_parts(args: argparse.Namespace, split: FleetSplit) -> int:
    if not args.save:
        return 0
    base = Path(args.save)
    for part in split.parts:
        path = base.with_name(f"{base.stem}-{part.vehicle.id}{base.suffix}")
        try:
            save_waypoints(path, part.plan.items)
        except OSError as exc:
            print(f"error: cannot write {path}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_INPUT
        print(
            f"saved vehicle {part.vehicle.id}'s {len(part.plan.items)} items to {path} (QGC WPL 110)",
            flush=True,
        )
    return 0


# --------------------------------------------------------------------------------------------- run
def run_fleet(args: argparse.Namespace) -> int:
    """The fleet survey: everything checked and planned before any link opens (`--dry-run` opens none)."""
    try:
        if args.from_position is not None:
            raise InputError(
                "--from goes with one vehicle: a fleet's vehicles each give their start (LAT,LON)"
            )
        if args.speed is not None:
            raise InputError("--speed goes with one vehicle: a fleet's vehicles each give their speed")
        area = area_from_args(args)
        members = fleet_from_args(args)
        config = load_vehicle_sections(Path(args.companion_config) if args.companion_config else None)
        for m in members:
            check_distance(
                area, m.vehicle.start, config.safety.max_survey_distance_m, f"vehicle {m.vehicle.id}'s start"
            )
        pod = pod_context(args, config)
        settings = settings_from(args, config, CRUISE_SPEED[AutopilotKind.PX4])
        _, chosen = plan_for(args, area, settings, pod)
        vehicles = [m.vehicle for m in members]
        if chosen is not None:
            settings = chosen.choice.settings(settings)
            top = chosen.choice.speed_m_s
            vehicles = [replace(v, speed_m_s=min(v.speed_m_s, top)) for v in vehicles]
        split = split_area(area, settings, vehicles)
    except (InputError, SurveyError, ConfigError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except PodOutOfReach as exc:
        print(f"error: {out_of_reach(exc, args, settings, pod)}", file=sys.stderr)
        return EXIT_INPUT
    mode = "dry run, nothing sent" if args.dry_run else "to upload"
    print(f"fleet survey ({mode}): {len(area)} corners, {len(members)} vehicles", flush=True)
    if chosen is not None:
        c = chosen.choice
        print(
            f"  planned for POD {pod.map_settings.target_pod:g} ({pod.label}): altitude {c.altitude_m:g} m, lanes "
            f"{chosen.plan.spacing_m:.1f} m apart, at most {c.speed_m_s:g} m/s",
            flush=True,
        )
    lines = describe_fleet(split, settings.altitude_m)
    if chosen is not None:
        lines += _pod_lines(split, settings, pod)
    for line in lines:
        print(f"  {line}", flush=True)
    if args.dry_run:
        return _save_parts(args, split)
    by_id = {m.vehicle.id: m for m in members}
    return _upload_fleet(args, split, by_id, config.safety.max_survey_distance_m) or _save_parts(args, split)


def _upload_fleet(
    args: argparse.Namespace, split: FleetSplit, members: dict[str, FleetMember], max_distance_m: float
) -> int:
    from gcs.cli import GcsError, GcsSession  # the ground tool's link and its errors (cli imports us)

    sessions: list[tuple[Any, Vehicle, Any]] = []  # (session, vehicle, part)
    try:
        for part in split.parts:  # every vehicle heard and ready before anything is sent
            member = members[part.vehicle.id]
            who = f"vehicle {member.vehicle.id}: "
            link = argparse.Namespace(**{**vars(args), "connect": member.connect, "system": member.system})
            try:
                session = GcsSession(link)
            except OSError as exc:
                print(f"error: {who}cannot open {member.connect}: {exc}", file=sys.stderr)
                return EXIT_TIMEOUT
            vehicle = Vehicle(session, member.system)
            sessions.append((session, vehicle, part))
            code = _ready(args, session, vehicle, part.corners, max_distance_m, who, GcsError)
            if code:
                print(f"error: nothing uploaded: vehicle {member.vehicle.id} is not ready", file=sys.stderr)
                return code
        worst, done = 0, []
        for session, vehicle, part in sessions:
            code = send_mission(args, session, vehicle, part.plan, f"vehicle {part.vehicle.id}: ")
            worst = max(worst, code)
            if not code:
                done.append(part.vehicle.id)
        missing = [p.vehicle.id for p in split.parts if p.vehicle.id not in done]
        print(
            f"fleet: {len(done)} of {len(split.parts)} vehicles hold their part"
            + (f"; not uploaded: {', '.join(missing)}" if missing else ""),
            flush=True,
        )
        return worst
    finally:
        for session, _, _ in sessions:
            session.close()


def _ready(
    args: argparse.Namespace,
    session: Any,
    vehicle: Vehicle,
    part: Sequence[LatLon],
    max_distance_m: float,
    who: str,
    gcs_error: type[Exception],
) -> int:
    """The vehicle heard (HEARTBEAT, mode, position), near its part and not flying a mission: 0, else the exit
    code after one line on stderr."""
    try:
        session.connect()
        vehicle.wait(args.timeout)
        assert vehicle.kind is not None
        if vehicle.position is not None:
            check_distance(part, vehicle.position, max_distance_m, "the vehicle")
    except gcs_error as exc:
        print(f"error: {who}{exc}", file=sys.stderr)
        return int(getattr(exc, "code", EXIT_TIMEOUT))
    except InputError as exc:
        print(f"error: {who}{_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except MissionError as exc:
        print(f"error: {who}{exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    name = "ArduPilot" if vehicle.kind is AutopilotKind.ARDUPILOT else "PX4"
    where = "no position reported" if vehicle.position is None else "position checked"
    print(f"{who}system {vehicle.system} ({name}, mode {vehicle.mode}), {where}", flush=True)
    return EXIT_REFUSED if refused_in_mission(vehicle, who) else 0
