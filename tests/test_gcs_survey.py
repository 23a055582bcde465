"""`cloudtrack-gcs survey`: the area from every source, the plan printed, the upload through the mock autopilot
(both personalities), and a one-line error with its exit code for each bad input or refusal."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavwp

from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import DO_CHANGE_SPEED, NAV_WAYPOINT
from cloudtrack.mavlink_connection import MavlinkEndpoint
from cloudtrack.mission_protocol import MissionClient
from gcs import cli as gcs_cli
from gcs.survey_command import InputError, parse_polygon, parse_size, read_area_file
from sitl.autopilot import SimulatedAutopilot
from sitl.autopilot_mission import MissionOptions
from tests.mavlink_harness import autopilot, wait_for

GCS = [str(Path(sys.executable).with_name("cloudtrack-gcs"))]
HOME = (47.397742, 8.545594)
CENTRE = "47.3980,8.5460"
POLYGON = "47.3975,8.5450 47.3975,8.5466 47.3982,8.5466 47.3982,8.5450"  # about 120 m x 78 m


def link_args(sim: SimulatedAutopilot, *rest: str) -> list[str]:
    return ["--connect", f"udpout:127.0.0.1:{sim.link_port('gcs')}", "--timeout", "3", *rest]


def run_survey(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """Exit code, stdout, and the tool's own stderr lines (the mock autopilot's log records, which another
    test's logging set-up may route to this stream, are not the tool's)."""
    code = gcs_cli.main(list(args))
    out, err = capsys.readouterr()
    ours = "".join(line for line in err.splitlines(keepends=True) if line.startswith("error: "))
    return code, out, ours


# ----------------------------------------------------------------------------------- planning only
def test_dry_run_prints_lanes_length_and_time(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    saved = tmp_path / "survey.waypoints"
    defaults = tmp_path / "companion.toml"
    defaults.write_text("")  # the schema's defaults, whatever /etc/cloudtrack holds on this machine
    code, out, err = run_survey(
        capsys, "survey", "--centre", CENTRE, "--size", "120x80", "--altitude", "25", "--speed", "4",
        "--dry-run", "--save", str(saved), "--companion-config", str(defaults),
    )  # fmt: skip
    assert (code, err) == (0, ""), err
    lines = out.splitlines()
    assert lines[0] == "survey (dry run, nothing sent): 4 corners"
    # The defaults' camera: 70 deg across, pitched -45 deg, cut at 50 m: a 63 m swath at 25 m.
    assert lines[1] == "  lanes: 2, 40.0 m apart (camera swath 63.1 m at 25 m), along 90 deg"
    assert lines[2] == "  length: 280 m over 0.96 ha"
    assert lines[3] == "  time to fly: about 1 min 15 s at 4 m/s"
    # The oblique camera looks ahead: what it never sees is behind the lane starts, 2.5 % of the area.
    assert lines[4].startswith("  coverage if flown as planned: 97.5 % of the area (")
    assert lines[5] == "  items: 1 DO_CHANGE_SPEED, 4 NAV_WAYPOINT"
    assert [line.split(":")[0] for line in lines[6:10]] == [f"  waypoint {k}" for k in range(1, 5)]
    assert lines[10] == f"saved 5 items to {saved} (QGC WPL 110)"
    loader = mavwp.MAVWPLoader()
    loader.load(str(saved))  # Mission Planner's and MAVProxy's format reads back: home, then the items
    assert [loader.wp(i).command for i in range(loader.count())] == [16, DO_CHANGE_SPEED] + [NAV_WAYPOINT] * 4


def test_the_companions_config_sizes_the_lanes_and_bounds_the_altitude(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    config = tmp_path / "companion.toml"
    config.write_text("[camera]\nmount_pitch_deg = -90.0\n\n[safety]\nmax_altitude_m = 100.0\n")
    code, out, _ = run_survey(
        capsys, "survey", "--centre", CENTRE, "--size", "120x80", "--altitude", "80", "--dry-run",
        "--companion-config", str(config),
    )  # fmt: skip
    assert code == 0
    assert "  lanes: 1, 80.0 m apart (camera swath 100.0 m at 80 m), along 90 deg" in out.splitlines()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--polygon", "47.3975,8.5450 47.3982,8.5466 47.3975,8.5466 47.3982,8.5450"],
            "error: the search area's edges 1-2 and 3-4 cross: the polygon intersects itself (list the corners in "
            "order around it)",
        ),  # fmt: skip
        (["--polygon", ""], "error: the search area is empty: give at least 3 corners (lat,lon)"),
        (
            ["--polygon", "47.3975,8.5450 47.3982"],
            "error: --polygon: '47.3982' is not lat,lon (e.g. 47.3977,8.5456)",
        ),
        (
            ["--polygon", POLYGON, "--altitude", "80"],
            "error: altitude 80 m is outside the safety band 5-60 m ([safety] min_altitude_m, max_altitude_m)",
        ),  # fmt: skip
        (
            ["--centre", CENTRE, "--size", "120x"],
            "error: --size: '120x' is not WIDTHxHEIGHT in metres (e.g. 100x60)",
        ),
        (["--centre", CENTRE], "error: --centre needs --size WIDTHxHEIGHT (metres)"),
        (
            ["--centre", CENTRE, "--size", "0x60"],
            "error: a survey size must be two positive lengths in metres, got 0x60",
        ),
        ([], "error: give the area one way: --polygon, --area-file, or --centre with --size"),
        (
            ["--polygon", POLYGON, "--centre", CENTRE],
            "error: give the area one way: --polygon, --area-file, or --centre with --size",
        ),
        (
            ["--polygon", POLYGON, "--overlap", "1.5"],
            "error: overlap 1.5 must be between 0 and 0.9 (a fraction of the swath)",
        ),
        (["--polygon", POLYGON, "--speed", "50"], "error: speed 50 m/s must be between 0.5 and 30 m/s"),
        (
            ["--area-file", "/nonexistent/area.geojson"],
            "error: /nonexistent/area.geojson: No such file or directory",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    full = ["survey", "--altitude", "25", *args] if "--altitude" not in args else ["survey", *args]
    code, out, err = run_survey(capsys, *full, "--dry-run")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(message), err


def test_a_bad_companion_config_is_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    config = tmp_path / "companion.toml"
    config.write_text("[safety]\nmin_altitude_m = 70.0\n")
    code, _, err = run_survey(
        capsys,
        "survey",
        "--polygon",
        POLYGON,
        "--altitude",
        "25",
        "--dry-run",
        "--companion-config",
        str(config),
    )
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: invalid configuration: ")
    assert "min_altitude_m (70.0) must be below max_altitude_m (60.0)" in err


# -------------------------------------------------------------------------------------- area files
def _geojson(coords: list[list[list[float]]], kind: str = "Polygon") -> dict[str, object]:
    return {"type": kind, "coordinates": coords}


RING = [[8.5450, 47.3975], [8.5466, 47.3975], [8.5466, 47.3982], [8.5450, 47.3982], [8.5450, 47.3975]]
CORNERS = [(47.3975, 8.5450), (47.3975, 8.5466), (47.3982, 8.5466), (47.3982, 8.5450), (47.3975, 8.5450)]
QGC_PLAN = {
    "fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
    "mission": {"version": 2, "items": [
        {"type": "SimpleItem", "command": 22, "params": [0, 0, 0, None, 0, 0, 25]},
        {"type": "ComplexItem", "complexItemType": "survey", "version": 5,
         "polygon": [list(c) for c in CORNERS[:4]], "TransectStyleComplexItem": {}},
    ]},
}  # fmt: skip


@pytest.mark.parametrize(
    "content",
    [
        _geojson([RING]),
        {"type": "Feature", "properties": {"name": "search"}, "geometry": _geojson([RING])},
        {
            "type": "FeatureCollection",
            "features": [
                {"type": "Feature", "geometry": {"type": "Point", "coordinates": [8.5, 47.3]}},
                {"type": "Feature", "geometry": _geojson([RING])},
            ],
        },  # fmt: skip
        _geojson([[RING]], "MultiPolygon"),
    ],
)
def test_geojson_areas(tmp_path: Path, content: dict[str, object]) -> None:
    path = tmp_path / "area.geojson"
    path.write_text(json.dumps(content))
    assert read_area_file(path) == CORNERS  # GeoJSON's [lon, lat] turned round


def test_a_qgroundcontrol_plan_gives_its_survey_polygon(tmp_path: Path) -> None:
    path = tmp_path / "mission.plan"
    path.write_text(json.dumps(QGC_PLAN))
    assert read_area_file(path) == CORNERS[:4]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("not json", "not JSON"),
        (json.dumps(_geojson([RING, RING])), "the polygon has 1 hole(s); a search area cannot have holes"),
        (json.dumps(_geojson([[RING], [RING]], "MultiPolygon")), "a MultiPolygon of 2 polygons"),
        (json.dumps({"type": "FeatureCollection", "features": []}), "a FeatureCollection with 0 polygons"),
        (
            json.dumps({"type": "Point", "coordinates": [8.5, 47.3]}),
            "neither a GeoJSON Polygon nor a QGroundControl .plan",
        ),
        (
            json.dumps(_geojson([[[8.5, "x"], [8.6, 47.3], [8.6, 47.4]]])),
            "position [8.5, 'x'] is not a pair of numbers",
        ),
        (
            json.dumps({"fileType": "Plan", "mission": {"items": []}}),
            "a QGroundControl plan without a survey",
        ),
    ],
)
def test_bad_area_files(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "area.json"
    path.write_text(content)
    with pytest.raises(InputError, match=r"^" + str(path).replace(".", r"\.") + ": ") as err:
        read_area_file(path)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_huge_area_file_is_refused_before_it_is_read(tmp_path: Path) -> None:
    path = tmp_path / "huge.geojson"
    path.write_text(" " * 1_000_001)
    with pytest.raises(InputError, match=r"1000001 bytes; an area file may have at most 1000000"):
        read_area_file(path)


def test_parsers() -> None:
    assert parse_polygon("47.1,8.2;47.2,8.3  47.3,8.4") == [(47.1, 8.2), (47.2, 8.3), (47.3, 8.4)]
    assert parse_size("100X60") == (100.0, 60.0)


# ------------------------------------------------------------------------------------------ upload
@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_upload_to_the_autopilot(capsys: pytest.CaptureFixture[str], personality: str) -> None:
    with autopilot(personality) as sim:
        code, out, err = run_survey(
            capsys,
            *link_args(
                sim, "survey", "--centre", CENTRE, "--size", "120x80", "--altitude", "25", "--speed", "4"
            ),
        )
        assert (code, err) == (0, "")
        name, mode = ("ArduPilot", "AUTO") if personality == "ardupilot" else ("PX4", "MISSION")
        first = 1 if personality == "ardupilot" else 0
        assert out.splitlines()[0] == f"survey for system 1 ({name}, mode {'GUIDED' if first else 'POSCTL'}):"
        assert out.splitlines()[-1] == (
            f"uploaded 5 items, read back and checked; current item {first}: switch to {mode} to fly the survey"
        )
        items = sim.mission.items[first:]
        assert [i.command for i in items] == [DO_CHANGE_SPEED] + [NAV_WAYPOINT] * 4
        # The survey begins at the lane end nearest the vehicle (at home, south-west of the area).
        north, east = latlon_to_offset(*HOME, items[1].lat_deg, items[1].lon_deg)
        assert north < 40 and east < 0
        assert sim.set_mode(mode)
        assert wait_for(lambda: sim.mission.reached[-1:] == [first + 1], 30.0)  # flies it


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_more_items_than_the_autopilot_accepts(capsys: pytest.CaptureFixture[str], personality: str) -> None:
    with autopilot(personality, mission=MissionOptions(max_items=3)) as sim:
        code, out, err = run_survey(
            capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "25")
        )
        assert code == 1
        assert err == (
            "error: mission upload refused by the autopilot: NO_SPACE (more items than the autopilot can store) "
            "(4 items sent); the previous mission is unchanged\n"
        )
        assert not sim.mission.has_mission


def test_a_mission_ack_error_is_one_line_and_leaves_the_previous_mission(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Another ground station is uploading: the autopilot answers DENIED."""
    with autopilot("ardupilot") as sim:
        assert run_survey(capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "25"))[0] == 0
        before = list(sim.mission.items)
        other = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('gcs')}", 254, 190)
        try:
            other.send(lambda m: m.mission_count_send(1, 1, 3, 0))
            assert wait_for(lambda: sim.mission._upload is not None, 3.0)
            code, _, err = run_survey(
                capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "30")
            )
        finally:
            other.close()
        assert code == 1
        assert err == (
            "error: mission upload refused by the autopilot: DENIED (the autopilot refuses mission changes from us "
            "(another ground station is uploading?)) (4 items sent); the previous mission is unchanged\n"
        )
        assert all(
            i.z == 25.0 for i in sim.mission.items[1:] if i.has_position
        )  # nothing of ours was written
        assert len(before) == 5  # home and the four waypoints


def test_a_mission_in_flight_is_not_replaced(capsys: pytest.CaptureFixture[str]) -> None:
    with autopilot("ardupilot") as sim:
        assert run_survey(capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "25"))[0] == 0
        assert sim.set_mode("AUTO")
        code, _, err = run_survey(capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "30"))
        assert code == 1
        assert err == (
            "error: the vehicle is flying its mission (AUTO): switch it to another mode (e.g. LOITER) before "
            "replacing the mission\n"
        )
        assert all(i.z == 25.0 for i in sim.mission.items[1:])


def test_no_autopilot_is_a_one_line_timeout(capsys: pytest.CaptureFixture[str]) -> None:
    with autopilot("ardupilot") as sim:
        sim.set_link_down("gcs", True)
        code, _, err = run_survey(capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--altitude", "25"))
    assert (
        code == 3 and err.count("\n") == 1 and err.startswith("error: no HEARTBEAT from system 1 on udpout:")
    )


def test_a_qgc_planned_mission_reads_back_as_a_survey() -> None:
    """Nothing on the flight side depends on this tool: a mission uploaded by anyone (here: the protocol
    client with QGC's own items, takeoff and a speed first) downloads to the same waypoints."""
    with autopilot("ardupilot") as sim:
        endpoint = MavlinkEndpoint.open(f"udpout:127.0.0.1:{sim.link_port('gcs')}", 255, 190)
        try:
            endpoint.send(lambda m: m.heartbeat_send(6, 8, 0, 0, 0))
            client = MissionClient(endpoint, "ardupilot", source=(255, 190))
            from behaviors.mission_items import MissionItem, waypoint_positions

            lanes = [offset_to_latlon(*HOME, n, e) for n, e in ((10, 0), (10, 60), (30, 60), (30, 0))]
            qgc = [MissionItem.takeoff(25), MissionItem.change_speed(5),
                   *(MissionItem.waypoint(lat, lon, 25) for lat, lon in lanes)]  # fmt: skip
            client.upload(qgc)
            got = waypoint_positions(client.download().items)
            assert [v for p in got for v in p] == pytest.approx([v for p in lanes for v in p], abs=1e-7)
        finally:
            endpoint.close()


def test_the_console_script_runs(tmp_path: Path) -> None:
    result = subprocess.run(
        [*GCS, "survey", "--centre", CENTRE, "--size", "100x60", "--altitude", "20", "--dry-run"],
        capture_output=True, text=True, timeout=60, env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "lanes: " in result.stdout and "time to fly: about " in result.stdout
