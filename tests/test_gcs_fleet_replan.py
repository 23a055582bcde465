"""`cloudtrack-gcs replan` (issue 43 item 3): what a dropped vehicle left unflown, read from a real back-end on
loopback (uvicorn), re-split over two mock autopilots (ArduPilot and PX4, over real UDP) still flying their
missions; each gets its share appended without leaving AUTO / Mission, and goes on from where it is. The
supervisor token comes from a file and is never printed; every refusal is one line and a non-zero exit."""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import requests

from backend.app import create_app
from behaviors.camera_model import CameraModel
from behaviors.fleet_split import FleetVehicle, split_area
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import NAV_WAYPOINT, MissionItem
from behaviors.survey_planner import SurveySettings, check_polygon
from cloudtrack.mavlink_connection import MavlinkEndpoint
from cloudtrack.mission_protocol import MissionClient, positions_match
from gcs import cli as gcs_cli
from gcs import fleet_replan as replan_module
from gcs.fleet_replan import replan_area, split_over
from tests.backend_fixtures import SUPERVISOR, TOKENS, backend_config
from tests.live_backend import serve
from tests.mavlink_harness import autopilot, wait_for

HOME = (47.397742, 8.545594)  # the mock autopilot's
DROPPED_TOKEN = "drone-3-token-three"
VEHICLE_TOKENS = {**TOKENS, "drone-3": DROPPED_TOKEN}
LINE = re.compile(
    r"  vehicle (?P<id>\S+): (?P<first>.*?) lanes? (?P<lanes>[\d-]+) of (?P<of>\d+), (?P<length>\d+) m over "
    r"(?P<ha>[\d.]+) ha, transit (?P<transit>\d+) m, at (?P<speed>[\d.]+) m/s; done in about (?P<min>\d+) min "
    r"(?P<s>\d\d) s, (?P<items>\d+) items added"
)


def _at(north_m: float, east_m: float) -> list[float]:
    return [round(v, 8) for v in offset_to_latlon(HOME[0], HOME[1], north_m, east_m)]


def _rect(west: float, south: float, east: float, north: float) -> list[list[float]]:
    """Counter-clockwise [lat, lon] corners, in metres east and north of HOME."""
    return [_at(south, west), _at(south, east), _at(north, east), _at(north, west)]


def _waypoint(north_m: float) -> MissionItem:
    lat, lon = _at(north_m, 0)
    return MissionItem.waypoint(lat, lon, 20.0)


# A log record from the mock autopilots in this process, on stderr where another test left a handler.
LOG_RECORD = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} +[A-Z]+ +[\w.]+: ")


def run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = gcs_cli.main(list(args))
    out, err = capsys.readouterr()
    err = "".join(line for line in err.splitlines(keepends=True) if not LOG_RECORD.match(line))
    return code, out, err


@pytest.fixture
def defaults(tmp_path: Path) -> str:
    config = tmp_path / "companion.toml"
    config.write_text("")  # the schema's defaults, whatever /etc/cloudtrack holds on this machine
    return str(config)


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    path = tmp_path / "supervisor-token"
    path.write_text(SUPERVISOR + "\n")
    path.chmod(0o600)
    return path


@pytest.fixture(scope="module")
def backend(models_dir: Path) -> Iterator[str]:
    """A back-end where drone-3 went home (RTL) with the west 40 m of its 200 x 200 m part covered, and
    drone-1 and drone-2 search their parts in AUTO / Mission."""
    # Reported once for the module: silence must not drop drone-1 and drone-2 however long the tests take
    # on a busy machine (the silent drop-out is tested in test_fleet_dropout.py).
    app = create_app(
        backend_config(models_dir, f"auth.tokens={json.dumps(VEHICLE_TOKENS)}", "fleet.dropout_s=3600")
    )
    with serve(app) as url:
        _report_three(url)
        yield url


def _report(url: str, vehicle: str, search: dict[str, Any]) -> None:
    answer = requests.post(
        f"{url}/v1/vehicles/{vehicle}/status",
        json={"mission_id": "m-43", "state": "SEARCHING", "search": search},
        headers={"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"},
        timeout=10,
    )
    assert answer.status_code == 200, answer.text[:300]


def _report_three(url: str) -> None:
    """drone-1 and drone-2 searching their parts, drone-3 gone home (RTL) with its west 40 m covered."""
    _report(url, "drone-1", {"area": _rect(-200, 0, -100, 200), "mode": "AUTO"})
    _report(url, "drone-2", {"area": _rect(-100, 0, 100, 200), "mode": "MISSION"})
    _report(
        url, "drone-3", {"area": _rect(100, 0, 300, 200), "covered": [_rect(100, 0, 140, 200)], "mode": "RTL"}
    )


def _fleet(tmp_path: Path, ardupilot_port: int, px4_port: int) -> Path:
    fleet = tmp_path / "fleet.json"
    fleet.write_text(
        json.dumps({"vehicles": [
            {"id": "drone-1", "connect": f"udpout:127.0.0.1:{ardupilot_port}", "speed": 5, "lat": HOME[0],
             "lon": HOME[1]},
            {"id": "drone-2", "connect": f"udpout:127.0.0.1:{px4_port}", "speed": 8, "lat": HOME[0],
             "lon": HOME[1], "system": 2},
            {"id": "drone-3", "connect": "udpout:127.0.0.1:9", "speed": 5, "lat": HOME[0], "lon": HOME[1],
             "system": 3},
        ]})
    )  # fmt: skip
    return fleet


def _upload(port: int, system: int, personality: str, items: list[MissionItem]) -> None:
    """The vehicle's own mission, through the mission protocol over its GCS link."""
    endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{port}", 255, 190, system)
    try:
        MissionClient(endpoint, personality, target=(system, 1), source=(255, 190)).upload(items)
    finally:
        endpoint.close()


def _east_of_lanes(items: list[Any]) -> set[float]:
    return {
        round(latlon_to_offset(*HOME, i.lat_deg, i.lon_deg)[1], 0) for i in items if i.command == NAV_WAYPOINT
    }


def test_the_dropped_area_is_appended_and_the_vehicles_go_on_in_their_mission(
    capsys: pytest.CaptureFixture[str], backend: str, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    with autopilot("ardupilot") as ardupilot, autopilot("px4", system_id=2) as px4:
        # drone-1 (ArduPilot) flies a long leg north; drone-2 (PX4) has flown its short mission to the end.
        north = [MissionItem.change_speed(3.0), *(_waypoint(n) for n in (150, 300))]
        _upload(ardupilot.link_port("gcs"), 1, "ardupilot", north)
        _upload(px4.link_port("gcs"), 2, "px4", [_waypoint(3)])
        assert ardupilot.set_mode("AUTO") and px4.set_mode("MISSION")
        assert wait_for(lambda: px4.mission.complete, 15.0), "the PX4 never finished its one-waypoint mission"
        assert wait_for(lambda: ardupilot.mission.current == 2, 5.0)  # its first waypoint, after the speed
        fleet = _fleet(tmp_path, ardupilot.link_port("gcs"), px4.link_port("gcs"))
        code, out, err = run(
            capsys, "--timeout", "3", "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25",
            "--backend", backend, "--supervisor-token-file", str(token_file), "--companion-config", defaults,
        )  # fmt: skip
        assert (code, err) == (0, ""), err
        assert SUPERVISOR not in out
        lines = out.splitlines()
        assert (
            lines[0]
            == "replan of mission m-43 (to upload): 1 vehicle left the search, 2 of the fleet still searching"
        )
        assert lines[1] == "  vehicle drone-3 left the search (mode RTL): 3.20 ha unflown"
        assert lines[2].startswith("  the unflown area as one plan: 4 lanes "), out
        parts = {m["id"]: m.groupdict() for m in map(LINE.fullmatch, lines) if m}
        assert set(parts) == {"drone-1", "drone-2"}, out
        assert parts["drone-1"]["first"].startswith("its own 2 waypoints left first (about ")
        assert parts["drone-2"]["first"] == "its own mission flown, then"
        assert re.fullmatch(
            r"  time to finish: about \d+ min \d\d s \(vehicle drone-. finishes last\)", lines[5]
        )
        assert lines[-3:] == [
            f"vehicle drone-1: uploaded {3 + int(parts['drone-1']['items'])} items (its 3, then "
            f"{parts['drone-1']['items']} for the dropped area), read back and checked; current item 2, mode AUTO: "
            "it goes on",
            f"vehicle drone-2: uploaded {1 + int(parts['drone-2']['items'])} items (its 1, then "
            f"{parts['drone-2']['items']} for the dropped area), read back and checked; current item 1, mode "
            "MISSION: it goes on",
            "replan: 2 of 2 vehicles hold their share",
        ]
        # drone-1's own lanes stand as they were, its share after them; it still flies to the same waypoint.
        items_1 = ardupilot.mission.items[1:]
        assert positions_match(items_1[:3], north) and len(items_1) == 3 + int(parts["drone-1"]["items"])
        assert ardupilot.mode == "AUTO" and ardupilot.mission.running and ardupilot.mission.current == 2
        north_now = ardupilot.snapshot().north
        assert wait_for(lambda: ardupilot.snapshot().north > north_now + 3.0, 10.0), "drone-1 stopped"
        # drone-2 had finished: it now flies its share, from its first item, still in Mission mode.
        items_2 = px4.mission.items
        assert px4.mode == "MISSION" and px4.mission.running and not px4.mission.complete
        assert px4.mission.current >= 1
        target = next(i for i in items_2[1:] if i.command == NAV_WAYPOINT)
        goal = latlon_to_offset(*HOME, target.lat_deg, target.lon_deg)

        def gap() -> float:
            s = px4.snapshot()
            return float(((s.north - goal[0]) ** 2 + (s.east - goal[1]) ** 2) ** 0.5)

        before = gap()
        assert wait_for(lambda: gap() < before - 5.0, 10.0), "drone-2 does not fly towards its share"
        # The shares are the dropped area's lanes, none doubled, none left out, all east of the covered 40 m.
        lanes = [_east_of_lanes(items_1[3:]), _east_of_lanes(items_2[1:])]
        assert lanes[0] and lanes[1] and not lanes[0] & lanes[1]
        assert len(lanes[0]) + len(lanes[1]) == 4 * 1  # each lane: one east offset (lanes run north-south)
        assert min(min(x) for x in lanes) > 140 and max(max(x) for x in lanes) < 300
        # Run again, it would append the same share again: refused, nothing sent.
        code, out, err = run(
            capsys, "--timeout", "3", "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25",
            "--backend", backend, "--supervisor-token-file", str(token_file), "--companion-config", defaults,
        )  # fmt: skip
        assert code == 1 and err.count("\n") == 1, err
        assert re.fullmatch(
            r"error: vehicle drone-.: its waypoints left already fly into the dropped area \(re-planned before\?\); "
            r"--again appends its share all the same; nothing uploaded\n",
            err,
        ), err
        assert len(ardupilot.mission.items[1:]) == len(items_1)
        assert len(px4.mission.items) == len(items_2)


def test_a_finished_ardupilot_is_resumed_on_its_share_and_a_px4_keeps_its_item(
    capsys: pytest.CaptureFixture[str], backend: str, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    with autopilot("ardupilot") as ardupilot, autopilot("px4", system_id=2) as px4:
        north = [MissionItem.change_speed(3.0), *(_waypoint(n) for n in (150, 300))]
        _upload(ardupilot.link_port("gcs"), 1, "ardupilot", [_waypoint(3)])
        _upload(px4.link_port("gcs"), 2, "px4", north)
        assert ardupilot.set_mode("AUTO") and px4.set_mode("MISSION")
        assert wait_for(lambda: ardupilot.mission.complete, 15.0), "the ArduPilot never finished its mission"
        assert wait_for(lambda: px4.mission.current == 1, 5.0)
        fleet = _fleet(tmp_path, ardupilot.link_port("gcs"), px4.link_port("gcs"))
        code, out, err = run(
            capsys, "--timeout", "3", "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25",
            "--backend", backend, "--supervisor-token-file", str(token_file), "--companion-config", defaults,
        )  # fmt: skip
        assert (code, err) == (0, ""), err
        lines = out.splitlines()
        assert re.fullmatch(
            r"vehicle drone-1: uploaded \d+ items \(its 1, then \d+ for the dropped area\), read back and checked; "
            r"current item 2, mode AUTO: it goes on",
            lines[-3],
        ), out
        assert re.fullmatch(
            r"vehicle drone-2: uploaded \d+ items \(its 3, then \d+ for the dropped area\), read back and checked; "
            r"current item 1, mode MISSION: it goes on",
            lines[-2],
        ), out
        # MISSION_SET_CURRENT alone would leave ArduCopter's finished mission stopped (held): MISSION_START ran.
        assert ardupilot.mode == "AUTO" and not ardupilot.mission.held and ardupilot.mission.current >= 2
        assert positions_match(px4.mission.items[:3], north) and px4.mission.current == 1
        assert px4.mode == "MISSION" and px4.mission.running
        target = ardupilot.mission.items[2:]
        goal = next(
            latlon_to_offset(*HOME, i.lat_deg, i.lon_deg) for i in target if i.command == NAV_WAYPOINT
        )

        def gap() -> float:
            s = ardupilot.snapshot()
            return float(((s.north - goal[0]) ** 2 + (s.east - goal[1]) ** 2) ** 0.5)

        before, north_now = gap(), px4.snapshot().north
        assert wait_for(lambda: gap() < before - 5.0, 10.0), "drone-1 does not fly towards its share"
        assert wait_for(lambda: px4.snapshot().north > north_now + 3.0, 10.0), "drone-2 stopped"


def test_the_mock_arducopter_holds_a_finished_mission_set_current_until_mission_start() -> None:
    with autopilot("ardupilot") as sim:
        _upload(sim.link_port("gcs"), 1, "ardupilot", [_waypoint(3), _waypoint(40)])
        assert sim.set_mode("AUTO")
        assert wait_for(lambda: sim.mission.complete, 30.0)
        endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('gcs')}", 255, 190, 1)
        try:
            client = MissionClient(endpoint, "ardupilot", target=(1, 1), source=(255, 190))
            assert client.set_current(1).seq == 1
            assert sim.mission.held and client.read_current().state == 2  # NOT_STARTED: AP's MISSION_STOPPED
            here = sim.snapshot().north
            assert not wait_for(lambda: abs(sim.snapshot().north - here) > 3.0, 2.0)  # it holds in AUTO
            endpoint.send(lambda m: m.command_long_send(1, 1, 300, 0, 0, 0, 0, 0, 0, 0, 0))
            assert wait_for(lambda: not sim.mission.held, 5.0) and sim.mode == "AUTO"
            assert wait_for(lambda: sim.snapshot().north < here - 3.0, 10.0)  # back to item 1, 3 m north
        finally:
            endpoint.close()


def test_a_remaining_vehicle_going_home_is_refused_and_nothing_is_sent(
    capsys: pytest.CaptureFixture[str], backend: str, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    with autopilot("ardupilot") as ardupilot, autopilot("px4", system_id=2) as px4:
        assert ardupilot.set_mode("RTL")  # the back-end has not heard of it yet: the link has
        fleet = _fleet(tmp_path, ardupilot.link_port("gcs"), px4.link_port("gcs"))
        code, out, err = run(
            capsys, "--timeout", "3", "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25",
            "--backend", backend, "--supervisor-token-file", str(token_file), "--companion-config", defaults,
        )  # fmt: skip
        assert code == 1
        assert err.count("\n") == 1 and re.fullmatch(
            r"error: vehicle drone-1: it is leaving the search \(mode (RTL|LAND)\): leave it out of the fleet "
            r"for the re-plan; nothing uploaded\n",
            err,
        ), err  # RTL right over home lands at once
        assert not px4.mission.has_mission and not ardupilot.mission.has_mission


def test_a_dry_run_prints_the_plan_and_sends_nothing(
    capsys: pytest.CaptureFixture[str], backend: str, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    fleet = _fleet(tmp_path, 11, 12)  # nobody listens: a dry run opens no link
    code, out, err = run(
        capsys, "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25", "--dry-run",
        "--backend", backend, "--supervisor-token-file", str(token_file), "--companion-config", defaults,
    )  # fmt: skip
    assert (code, err) == (0, ""), err
    lines = out.splitlines()
    assert (
        lines[0]
        == "replan of mission m-43 (dry run, nothing sent): 1 vehicle left the search, 2 of the fleet still searching"
    )
    parts = [m.groupdict() for m in map(LINE.fullmatch, lines) if m]
    assert [p["first"] for p in parts] == ["from its start,", "from its start,"]
    assert lines[-1].startswith("  time to finish: about ")


@pytest.mark.parametrize(
    ("extra", "env", "message", "exit_code"),
    [
        (["--supervisor-token", SUPERVISOR], {}, "error: a token on the command line is visible", 2),
        (["--supervisor-token-file", "/nonexistent/token"], {}, "error: cannot read the supervisor token file", 2),
        ([], {}, "error: replan needs the back-end's supervisor token", 2),
        ([], {"CLOUDTRACK_GCS_SUPERVISOR_TOKEN": "wrong-token-wrong-token"},
         "error: back-end http://127.0.0.1:", 1),
    ],
)  # fmt: skip
def test_refusals_are_one_line(
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    backend: str,
    defaults: str,
    tmp_path: Path,
    extra: list[str],
    env: dict[str, str],
    message: str,
    exit_code: int,
) -> None:
    monkeypatch.delenv("CLOUDTRACK_GCS_SUPERVISOR_TOKEN", raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    fleet = _fleet(tmp_path, 11, 12)
    code, out, err = run(
        capsys, "replan", "--mission", "m-43", "--fleet", str(fleet), "--altitude", "25", "--dry-run",
        "--backend", backend, "--companion-config", defaults, *extra,
    )  # fmt: skip
    assert code == exit_code and out == ""
    assert err.count("\n") == 1 and err.startswith(message), err
    assert SUPERVISOR not in err


def test_an_unknown_mission_and_nothing_left_unflown(
    capsys: pytest.CaptureFixture[str], backend: str, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    fleet = _fleet(tmp_path, 11, 12)
    common = ["--fleet", str(fleet), "--altitude", "25", "--dry-run", "--backend", backend,
              "--supervisor-token-file", str(token_file), "--companion-config", defaults]  # fmt: skip
    code, out, err = run(capsys, "replan", "--mission", "m-9", *common)
    assert code == 1 and out == "" and "(HTTP 404): no vehicle has reported a map of mission 'm-9'" in err
    code, out, err = run(capsys, "replan", "--mission", "a/b", *common)
    assert code == 2 and err.startswith("error: --mission 'a/b' must be")


SETTINGS = SurveySettings(
    altitude_m=25.0,
    overlap=0.2,
    camera=CameraModel.from_hfov(1280, 720, 90.0, -90.0, True),
    search_range_m=150.0,
    min_altitude_m=10.0,
    max_altitude_m=120.0,
)


def test_a_busy_vehicle_takes_fewer_lanes() -> None:
    settings = SETTINGS
    area = [(p[0], p[1]) for p in _rect(0, 0, 400, 200)]
    free = [FleetVehicle("a", 5.0, HOME), FleetVehicle("b", 5.0, HOME)]
    even = split_area(area, settings, free)
    busy = split_area(area, settings, [free[0], FleetVehicle("b", 5.0, HOME, busy_s=120.0)])
    lanes = {p.vehicle.id: p.last_lane - p.first_lane + 1 for p in busy.parts}
    assert lanes["b"] < lanes["a"]
    assert busy.finish_s >= even.finish_s
    b = next(p for p in busy.parts if p.vehicle.id == "b")
    assert b.time_s == pytest.approx(120.0 + b.transit_s + b.plan.time_s)


def test_fewer_lanes_than_vehicles_go_to_those_that_finish_them_soonest() -> None:
    strip = [(p[0], p[1]) for p in _rect(0, 0, 30, 200)]  # one lane: what a drone leaves near its part's end
    near = FleetVehicle("near", 5.0, tuple(_at(0, -50)))  # type: ignore[arg-type]
    far = FleetVehicle("far", 5.0, tuple(_at(0, -900)))  # type: ignore[arg-type]
    busy = FleetVehicle("busy", 5.0, tuple(_at(0, -50)), busy_s=600.0)  # type: ignore[arg-type]
    split, idle = split_over(strip, SETTINGS, [far, busy, near])
    assert [p.vehicle.id for p in split.parts] == ["near"] and [v.id for v in idle] == ["far", "busy"]
    wide = [(p[0], p[1]) for p in _rect(0, 0, 400, 200)]
    split, idle = split_over(wide, SETTINGS, [far, near])
    assert sorted(p.vehicle.id for p in split.parts) == ["far", "near"] and idle == []


def test_a_px4_begins_a_new_mission_at_the_item_sent_as_current() -> None:
    with autopilot("px4") as sim:
        items = [_waypoint(n) for n in (10, 20, 30)]
        endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('gcs')}", 255, 190, 1)
        try:
            client = MissionClient(endpoint, "px4", target=(1, 1), source=(255, 190))
            client.upload(items, current=2)
            assert sim.mission.current == 2 and client.read_current().seq == 2
            client.upload(items)
            assert sim.mission.current == 0  # none flagged: from the start
        finally:
            endpoint.close()


def test_watch_replans_each_vehicle_as_it_leaves_once_and_ends_on_sigterm(
    models_dir: Path, token_file: Path, defaults: str, tmp_path: Path
) -> None:
    """`replan --watch`: the re-plan done without the operator. drone-3's drop-out is re-planned onto
    drone-1 and drone-2, and not again in later rounds; when drone-2 then goes home, its unflown part goes
    to drone-1 alone; SIGTERM ends the watch between rounds."""
    app = create_app(
        backend_config(models_dir, f"auth.tokens={json.dumps(VEHICLE_TOKENS)}", "fleet.dropout_s=3600")
    )
    with (
        serve(app) as url,
        autopilot("ardupilot") as ardupilot,
        autopilot("px4", system_id=2) as px4,
    ):
        _report_three(url)
        north = [MissionItem.change_speed(3.0), *(_waypoint(n) for n in (150, 300))]
        _upload(ardupilot.link_port("gcs"), 1, "ardupilot", north)
        _upload(px4.link_port("gcs"), 2, "px4", [_waypoint(150)])
        assert ardupilot.set_mode("AUTO") and px4.set_mode("MISSION")
        fleet = _fleet(tmp_path, ardupilot.link_port("gcs"), px4.link_port("gcs"))
        errors = tmp_path / "watch.err"
        watch = subprocess.Popen(
            [sys.executable, "-m", "gcs.cli", "--timeout", "3", "replan", "--mission", "m-43", "--fleet",
             str(fleet), "--altitude", "25", "--backend", url, "--supervisor-token-file", str(token_file),
             "--companion-config", defaults, "--watch", "--watch-period", "0.5"],
            stdout=subprocess.PIPE, stderr=errors.open("w"), text=True,
        )  # fmt: skip
        lines: queue.Queue[str] = queue.Queue()

        def read() -> None:
            for line in watch.stdout or ():
                lines.put(line)

        threading.Thread(target=read, daemon=True).start()
        seen: list[str] = []

        def printed(text: str, timeout_s: float = 60.0) -> None:
            end = time.monotonic() + timeout_s
            while not any(text in x for x in seen):
                assert watch.poll() is None, f"the watch ended ({watch.returncode}): {''.join(seen)}"
                try:
                    seen.append(lines.get(timeout=max(0.0, end - time.monotonic())))
                except queue.Empty:
                    raise AssertionError(f"never printed {text!r}: {''.join(seen)}") from None

        try:
            printed("AUTO REPLAN: done for drone-3")
            shares = (len(ardupilot.mission.items) - 4, len(px4.mission.items) - 1)  # after their own 3 and 1
            assert shares[0] > 0 and shares[1] > 0, seen
            assert ardupilot.mode == "AUTO" and px4.mode == "MISSION"
            # drone-2 goes home with its east half unflown: re-planned onto drone-1 alone.
            _report(url, "drone-2", {"area": _rect(-100, 0, 100, 200), "covered": [_rect(-100, 0, 0, 200)],
                                     "mode": "RTL"})  # fmt: skip
            printed("AUTO REPLAN: done for drone-2")
            assert len(px4.mission.items) - 1 == shares[1]  # drone-2 took nothing more
            assert len(ardupilot.mission.items) - 4 > shares[0]
            watch.send_signal(signal.SIGTERM)
            try:
                code = watch.wait(30)
            # As once in CI (the handler's deadlock, cloudtrack/stop_signals.py): say what the watch did.
            except subprocess.TimeoutExpired:
                watch.kill()
                watch.wait()
                code = None
            assert code == 0, (code, "".join(seen) + "".join(lines.queue), errors.read_text())
        finally:
            if watch.poll() is None:
                watch.kill()
                watch.wait()
        out = "".join(seen) + "".join(lines.queue)
        err = errors.read_text()
        assert out.count("AUTO REPLAN: drone-3 left the search") == 1, out  # once, however many rounds
        assert out.count("AUTO REPLAN: drone-2 left the search") == 1, out
        assert out.rstrip().endswith("replan --watch: stopped"), out
        assert SUPERVISOR not in out + err
        assert "error" not in err, err


def test_the_unflown_area_never_repeats_a_corner_after_rounding() -> None:
    """Two corners of the back-end's outline a few millimetres apart are one at the plan's 1 cm: the area is
    still planned (the survey refuses a repeated corner: a real ArduCopter fleet run exited 2 on it)."""
    ring = [_at(0, 0), _at(0, 30), _at(0.003, 30.002), _at(80, 30), _at(80, 0)]
    dropout = replan_module._Dropout(
        vehicle_id="drone-3", kind="mode", reason="mode RTL", since=1.0, unflown=[ring]
    )
    area, note = replan_area([dropout])
    assert note == "" and len(area) == 4 and len(set(area)) == 4
    assert all(a != b for a, b in zip(area, area[1:] + area[:1], strict=True))
    assert check_polygon(area)
    sliver = [_at(0, 0), _at(0, 0.004), _at(0.004, 0.004)]  # 4 mm: nothing to plan
    assert replan_area([dropout.model_copy(update={"unflown": [sliver]})]) == ([], "")
