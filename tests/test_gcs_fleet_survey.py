"""`cloudtrack-gcs survey --vehicle ... / --fleet FILE`: the area split over a fleet, a line per vehicle and the
whole area's time, each part uploaded to its own (mock) autopilot, and a one-line error for each bad fleet."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from behaviors.geolocation import latlon_to_offset
from behaviors.mission_items import DO_CHANGE_SPEED, NAV_WAYPOINT
from gcs import cli as gcs_cli
from gcs.fleet_survey import parse_vehicle, read_fleet_file
from gcs.survey_command import InputError
from tests.mavlink_harness import autopilot

HOME = (47.397742, 8.545594)  # the mock autopilot's
CENTRE = "47.3990,8.5470"  # 300 x 200 m north-east of home: 5 lanes at 25 m with the default camera
LINE = re.compile(
    r"  vehicle (?P<id>\S+): lanes? (?P<first>\d+)(-(?P<last>\d+))? of (?P<of>\d+), (?P<length>\d+) m over "
    r"(?P<ha>[\d.]+) ha, transit (?P<transit>\d+) m, about (?P<min>\d+) min (?P<s>\d\d) s at (?P<speed>[\d.]+) m/s, "
    r"(?P<items>\d+) items"
)


def run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = gcs_cli.main(list(args))
    out, err = capsys.readouterr()
    return code, out, "".join(line for line in err.splitlines(keepends=True) if line.startswith("error: "))


@pytest.fixture
def defaults(tmp_path: Path) -> str:
    config = tmp_path / "companion.toml"
    config.write_text("")  # the schema's defaults, whatever /etc/cloudtrack holds on this machine
    return str(config)


def test_a_dry_run_prints_a_line_per_vehicle_and_the_whole_areas_time(
    capsys: pytest.CaptureFixture[str], defaults: str, tmp_path: Path
) -> None:
    saved = tmp_path / "survey.waypoints"
    code, out, err = run(
        capsys, "survey", "--centre", "47.3977,8.5456", "--size", "600x400", "--altitude", "25", "--dry-run",
        "--companion-config", defaults, "--save", str(saved),
        "--vehicle", "a,udpin:0.0.0.0:14551,5,47.3960,8.5440", "--vehicle", "b,/dev/ttyUSB0,57600,8,47.3960,8.5470",
    )  # fmt: skip
    assert (code, err) == (0, ""), err
    lines = out.splitlines()
    assert lines[0] == "fleet survey (dry run, nothing sent): 4 corners, 2 vehicles"
    assert lines[1] == (
        "  the area as one plan: 8 lanes 50.0 m apart (camera swath 63.1 m at 25 m), along 90 deg, 5150 m over "
        "24.00 ha"
    )
    parts = [m.groupdict() for m in map(LINE.fullmatch, lines[2:4]) if m]
    assert [p["id"] for p in parts] == ["a", "b"], out
    # Contiguous runs of the one plan's lanes: the faster vehicle (8 m/s) takes more of them.
    assert (parts[0]["first"], parts[0]["last"], parts[1]["first"], parts[1]["last"]) == ("1", "3", "4", "8")
    assert float(parts[0]["ha"]) + float(parts[1]["ha"]) == pytest.approx(24.0, abs=0.02)
    assert [p["speed"] for p in parts] == ["5", "8"]
    times = [60 * int(p["min"]) + int(p["s"]) for p in parts]
    assert abs(times[0] - times[1]) <= 0.1 * max(times)
    whole = re.fullmatch(
        r"  whole area: about (\d+) min (\d\d) s \(vehicle . finishes last\); one vehicle alone: about (\d+) min "
        r"(\d\d) s \(b, the quickest alone\)",
        lines[4],
    )
    assert whole, lines[4]
    assert 60 * int(whole[1]) + int(whole[2]) == max(times)
    assert 60 * int(whole[3]) + int(whole[4]) > max(times)
    assert lines[5:] == [
        f"saved vehicle a's 7 items to {saved.with_name('survey-a.waypoints')} (QGC WPL 110)",
        f"saved vehicle b's 11 items to {saved.with_name('survey-b.waypoints')} (QGC WPL 110)",
    ]


def test_a_fleet_file_json_or_toml(tmp_path: Path) -> None:
    as_json = tmp_path / "fleet.json"
    as_json.write_text(
        json.dumps({"vehicles": [
            {"id": "a", "connect": "udpin:0.0.0.0:14551", "speed": 5, "lat": 47.396, "lon": 8.544},
            {"id": "b", "connect": "tcp:10.0.0.2:5760", "speed": 8.5, "lat": 47.396, "lon": 8.547, "system": 2},
        ]})
    )  # fmt: skip
    as_toml = tmp_path / "fleet.toml"
    as_toml.write_text(
        '[[vehicles]]\nid = "a"\nconnect = "udpin:0.0.0.0:14551"\nspeed = 5\nlat = 47.396\nlon = 8.544\n\n'
        '[[vehicles]]\nid = "b"\nconnect = "tcp:10.0.0.2:5760"\nspeed = 8.5\nlat = 47.396\nlon = 8.547\nsystem = 2\n'
    )
    for path in (as_json, as_toml):
        members = read_fleet_file(path, 1)
        assert [
            (m.vehicle.id, m.connect, m.vehicle.speed_m_s, m.vehicle.start, m.system) for m in members
        ] == [
            ("a", "udpin:0.0.0.0:14551", 5.0, (47.396, 8.544), 1),
            ("b", "tcp:10.0.0.2:5760", 8.5, (47.396, 8.547), 2),
        ]
    assert parse_vehicle("c,/dev/ttyUSB0,57600,4,47.1,8.2", 3).connect == "/dev/ttyUSB0,57600"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{", "neither JSON nor TOML"),
        ("{}", 'no vehicles: give a list "vehicles" of tables'),
        ('{"vehicles": [1]}', "vehicle 1 is not a table"),
        ('{"vehicles": [{"id": "a"}]}', "vehicle 1: no connect"),
        ('{"vehicles": [{"id": "a", "connect": "x", "speed": 5, "lat": 1, "lon": 2, "colour": 1}]}',
         "vehicle 1: unknown key 'colour'"),
        ('{"vehicles": [{"id": "a", "connect": "x", "speed": "5", "lat": 1, "lon": 2}]}',
         "speed, lat and lon must be numbers"),
        ('{"vehicles": [{"id": "a", "connect": "a b", "speed": 5, "lat": 1, "lon": 2}]}',
         "the link 'a b' must be a MAVLink address"),
        ('{"vehicles": [{"id": "a", "connect": "x", "speed": 5, "lat": 1, "lon": 2, "system": 300}]}',
         "system id 300 must be 1-255"),
        ("[" * 100_000, "more than 64000 bytes"),
        ("directory", "not a regular file; give the fleet as a JSON or TOML file"),
    ],
)  # fmt: skip
def test_bad_fleet_files_are_one_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "fleet.json"
    path.write_text(content)
    if content == "directory":
        path.unlink()
        path.mkdir()
    with pytest.raises(InputError) as caught:
        read_fleet_file(path, 1)
    assert message in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("fleet", "message"),
    [
        (["--vehicle", "a,udpin:0.0.0.0:1,5,47.39"], "error: --vehicle 'a,udpin:0.0.0.0:1,5,47.39' is not ID,CONNECT"),
        (["--vehicle", "a,udpin:0.0.0.0:1,5,47.3960,8.5440", "--vehicle", "b,udpin:0.0.0.0:1,5,47.3960,8.5440"],
         "error: vehicles a and b share the link udpin:0.0.0.0:1: give each its own"),
        (["--vehicle", "a,u:1,5,47.39,8.54", "--vehicle", "a,u:2,5,47.39,8.54"], "error: vehicle id 'a' is given twice"),
        (["--vehicle", "a,u:1,50,47.39,8.54"], "error: vehicle a: speed 50 m/s must be between 0.5 and 30 m/s"),
        (["--vehicle", "a,u:1,5,8.54,47.39"], "error: the search area is 5660 km from vehicle a's start"),
        (["--vehicle", "a,u:1,5,47.39,8.54", "--speed", "4"], "error: --speed goes with one vehicle"),
        (["--vehicle", "a,u:1,5,47.39,8.54", "--from", "47.39,8.54"], "error: --from goes with one vehicle"),
        (["--vehicle", "a,u:1,5,47.39,8.54", "--fleet", "x.json"], "error: give the fleet one way"),
    ],
)  # fmt: skip
def test_bad_fleets_are_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], defaults: str, fleet: list[str], message: str
) -> None:
    code, out, err = run(
        capsys, "survey", "--centre", CENTRE, "--size", "300x200", "--altitude", "25", "--dry-run",
        "--companion-config", defaults, *fleet,
    )  # fmt: skip
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(message), err


def test_each_part_is_uploaded_to_its_own_autopilot(
    capsys: pytest.CaptureFixture[str], defaults: str, tmp_path: Path
) -> None:
    with autopilot("ardupilot") as ardupilot, autopilot("px4", system_id=2) as px4:
        fleet = tmp_path / "fleet.json"
        fleet.write_text(
            json.dumps({"vehicles": [
                {"id": "a", "connect": f"udpout:127.0.0.1:{ardupilot.link_port('gcs')}", "speed": 4,
                 "lat": HOME[0], "lon": HOME[1]},
                {"id": "b", "connect": f"udpout:127.0.0.1:{px4.link_port('gcs')}", "speed": 8,
                 "lat": HOME[0], "lon": HOME[1], "system": 2},
            ]})
        )  # fmt: skip
        code, out, err = run(
            capsys, "--timeout", "3", "survey", "--centre", CENTRE, "--size", "300x200", "--altitude", "25",
            "--companion-config", defaults, "--fleet", str(fleet),
        )  # fmt: skip
        assert (code, err) == (0, ""), err
        lines = out.splitlines()
        assert lines[0] == "fleet survey (to upload): 4 corners, 2 vehicles"
        parts = {m["id"]: m.groupdict() for m in map(LINE.fullmatch, lines) if m}
        assert set(parts) == {"a", "b"}
        assert "vehicle a: system 1 (ArduPilot, mode GUIDED), position checked" in lines
        assert "vehicle b: system 2 (PX4, mode POSCTL), position checked" in lines
        assert lines[-1] == "fleet: 2 of 2 vehicles hold their part"
        for sim, first, vid, speed in ((ardupilot, 1, "a", 4.0), (px4, 0, "b", 8.0)):
            items = sim.mission.items[first:]
            assert items[0].command == DO_CHANGE_SPEED and items[0].param2 == speed
            assert [i.command for i in items[1:]] == [NAV_WAYPOINT] * (len(items) - 1)
            assert len(items) == int(parts[vid]["items"])
        rows = [
            {
                round(latlon_to_offset(*HOME, i.lat_deg, i.lon_deg)[0], 1)
                for i in sim.mission.items[first:][1:]
            }
            for sim, first in ((ardupilot, 1), (px4, 0))
        ]
        assert not rows[0] & rows[1]  # no lane flown twice
        assert len(rows[0]) + len(rows[1]) == int(parts["a"]["of"])  # none left out


def test_nothing_is_uploaded_unless_every_vehicle_is_ready(
    capsys: pytest.CaptureFixture[str], defaults: str
) -> None:
    with autopilot("ardupilot") as ready, autopilot("ardupilot") as flying:
        earlier = ["--connect", f"udpout:127.0.0.1:{flying.link_port('gcs')}", "--timeout", "3", "survey"]
        assert run(capsys, *earlier, "--centre", CENTRE, "--size", "300x200", "--altitude", "30")[0] == 0
        assert flying.set_mode("AUTO")
        code, _, err = run(
            capsys, "--timeout", "3", "survey", "--centre", CENTRE, "--size", "300x200", "--altitude", "25",
            "--companion-config", defaults,
            "--vehicle", f"a,udpout:127.0.0.1:{ready.link_port('gcs')},5,{HOME[0]},{HOME[1]}",
            "--vehicle", f"b,udpout:127.0.0.1:{flying.link_port('gcs')},5,{HOME[0]},{HOME[1]}",
        )  # fmt: skip
        assert code == 1
        assert err.splitlines() == [
            "error: vehicle b: the vehicle is flying its mission (AUTO): switch it to another mode (e.g. LOITER) "
            "before replacing the mission",
            "error: nothing uploaded: vehicle b is not ready",
        ]
        assert not ready.mission.has_mission
        assert all(i.z == 30.0 for i in flying.mission.items[1:])  # the mission it flies is untouched


def test_a_fleet_plan_for_a_pod_flies_the_pod_plans_lanes_at_most_at_its_speed(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from tests.test_gcs_survey import curve_config

    code, out, err = run(
        capsys, "survey", "--centre", CENTRE, "--size", "240x150", "--pod", "0.8", "--target", "person",
        "--dry-run", "--companion-config", str(curve_config(tmp_path)),
        "--vehicle", f"slow,u:1,2,{HOME[0]},{HOME[1]}", "--vehicle", f"fast,u:2,30,{HOME[0]},{HOME[1]}",
    )  # fmt: skip
    assert (code, err) == (0, ""), err
    lines = out.splitlines()
    chosen = re.fullmatch(
        r"  planned for POD 0\.8 \(person, standing, 1\.7 m\): altitude (?P<altitude>[\d.]+) m, lanes "
        r"(?P<spacing>[\d.]+) m apart, at most (?P<speed>[\d.]+) m/s",
        lines[1],
    )
    assert chosen, out
    assert f" {chosen['spacing']} m apart (camera swath " in lines[2]
    assert f" at {chosen['altitude']} m), " in lines[2]
    parts = {m["id"]: m for m in map(LINE.fullmatch, lines) if m}
    assert parts["slow"]["speed"] == "2" and parts["fast"]["speed"] == chosen["speed"]  # faster loses POD
    pods = [
        re.fullmatch(r"  vehicle (\S+): expected POD mean ([\d.]+) over its part \(person, .*\)", line)
        for line in lines
    ]
    assert sorted(m[1] for m in pods if m) == ["fast", "slow"]
