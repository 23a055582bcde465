"""`cloudtrack-gcs survey`: the area from every source, the plan printed, the upload through the mock autopilot
(both personalities), and a one-line error with its exit code for each bad input or refusal."""

from __future__ import annotations

import json
import math
import os
import re
import resource
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavwp

from behaviors.detection_curve import curves_document
from behaviors.geolocation import latlon_to_offset, offset_to_latlon
from behaviors.mission_items import DO_CHANGE_SPEED, NAV_WAYPOINT
from cloudtrack.mavlink_connection import MavlinkEndpoint
from cloudtrack.mission_protocol import MissionClient
from gcs import cli as gcs_cli
from gcs.survey_command import InputError, parse_polygon, parse_size, read_area_file
from sitl.autopilot import SimulatedAutopilot
from sitl.autopilot_mission import MissionOptions
from tests.mavlink_harness import autopilot, wait_for
from tests.test_pod_planner import step_curve

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
    assert lines[1] == "  distance to the vehicle not checked: give --from LAT,LON (the vehicle or home)"
    # The defaults' camera: 70 deg across, pitched -45 deg, cut at 50 m: a 63 m swath at 25 m.
    assert lines[2] == "  lanes: 2, 40.0 m apart (camera swath 63.1 m at 25 m), along 90 deg"
    assert lines[3] == "  length: 280 m over 0.96 ha"
    assert lines[4] == "  time to fly: about 1 min 15 s at 4 m/s"
    # The oblique camera looks ahead: what it never sees is behind the lane starts, 2.5 % of the area.
    assert lines[5].startswith(
        "  coverage if flown as planned: 97.5 % of the area (141 keyframes, one every 0.5 s; "
    )
    # The shipped curve's figures are not this test's to hold (tests/test_survey_pod.py holds the map's).
    assert re.fullmatch(
        r"  expected POD: mean 0\.\d\d, \d+ % of the area at 0\.8 or more \(person, standing, 1\.7 m; the shipped "
        r"curve.*\)",
        lines[6],
    )
    assert lines[7] == "  search rate: 0.46 km2/h (0.96 ha in 1 min 15 s)"
    assert lines[8] == "  items: 1 DO_CHANGE_SPEED, 4 NAV_WAYPOINT"
    assert [line.split(":")[0] for line in lines[9:13]] == [f"  waypoint {k}" for k in range(1, 5)]
    assert lines[13] == f"saved 5 items to {saved} (QGC WPL 110)"
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


# ------------------------------------------------------------------------------ planning for a POD
def curve_config(tmp_path: Path, p: float = 0.7, more: str = "") -> Path:
    """A companion configuration whose [search] curve is made up for the test (a person of 16 px or more is
    found with `p`): the shipped curve's figures are not the tests' to hold."""
    curve = tmp_path / "curve.json"
    curve.write_text(json.dumps(curves_document({"person": step_curve(16.0, p)})))
    config = tmp_path / "companion.toml"
    config.write_text(f'[search]\ncurve_file = "{curve}"\n{more}')
    return config


PLANNED = re.compile(
    r"  planned for POD 0\.8 \(person, standing, 1\.7 m\): altitude (?P<altitude>[\d.]+) m, lanes "
    r"(?P<spacing>[\d.]+) m apart, (?P<speed>[\d.]+) m/s: the least time the model found"
)
EXPECTED = re.compile(
    r"  expected POD: mean (?P<mean>[\d.]+), (?P<share>\d+) % of the area at (?P<target>[\d.]+) or more "
    r"\(person, standing, 1\.7 m; the curve of .*curve\.json\)"
)


def test_a_plan_for_a_pod_prints_its_choice_its_bounds_and_what_the_map_would_show(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    saved = tmp_path / "survey.waypoints"
    code, out, err = run_survey(
        capsys, "survey", "--centre", CENTRE, "--size", "240x150", "--pod", "0.8", "--target", "person",
        "--dry-run", "--save", str(saved), "--companion-config", str(curve_config(tmp_path)),
    )  # fmt: skip
    assert (code, err) == (0, ""), err
    lines = out.splitlines()
    chosen = PLANNED.fullmatch(lines[2])
    assert chosen, lines[2]
    altitude, speed = float(chosen["altitude"]), float(chosen["speed"])
    assert 5 <= altitude <= 60 and 1 <= speed <= 10
    bounds = re.fullmatch(
        rf"  speed bounds at {chosen['altitude']} m: the autopilot's 10 m/s \(--max-speed\), motion blur "
        r"(?P<blur>[\d.]+) m/s \(1 px in a 0\.002 s exposure, \[camera\] exposure_s\), keyframes [\d.]+ m/s "
        r"\(one every 0\.5 s, \[backend\] search_interval_s\)",
        lines[3],
    )
    assert bounds and speed <= float(bounds["blur"])
    assert lines[4].startswith("  lanes: ") and f"{chosen['spacing']} m apart" in lines[4]
    expected = EXPECTED.fullmatch(lines[8])
    assert expected, lines[8]
    assert float(expected["mean"]) >= 0.8 and float(expected["target"]) == 0.8  # reached on the map
    minutes, seconds = map(int, re.findall(r"about (\d+) min (\d+) s", lines[6])[0])
    rate = re.fullmatch(r"  search rate: ([\d.]+) km2/h \(3\.60 ha in .*\)", lines[9])
    assert rate and float(rate[1]) == pytest.approx(0.036 / ((60 * minutes + seconds) / 3600), abs=0.006)
    # The autopilot is told the chosen speed, and flies the chosen altitude.
    loader = mavwp.MAVWPLoader()
    loader.load(str(saved))
    assert loader.wp(1).command == DO_CHANGE_SPEED and loader.wp(1).param2 == pytest.approx(speed, rel=1e-6)
    assert [loader.wp(i).z for i in range(2, loader.count())] == pytest.approx(
        [altitude] * (loader.count() - 2)
    )


def test_any_plan_prints_its_expected_pod(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    config = curve_config(tmp_path, more="target_pod = 0.5\n")
    code, out, _ = run_survey(
        capsys, "survey", "--centre", CENTRE, "--size", "240x150", "--altitude", "20", "--overlap", "0.3",
        "--speed", "5", "--dry-run", "--companion-config", str(config),
    )  # fmt: skip
    assert code == 0
    expected = [m for m in map(EXPECTED.fullmatch, out.splitlines()) if m]
    assert len(expected) == 1 and expected[0]["target"] == "0.5"  # [search] target_pod
    assert 0 < float(expected[0]["mean"]) < 1 and 0 <= int(expected[0]["share"]) <= 100


def test_an_unreachable_pod_is_one_line_naming_the_best_plan(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    config = curve_config(tmp_path, p=0.3, more="\n[safety]\nmin_altitude_m = 30.0\nmax_altitude_m = 40.0\n")
    code, out, err = run_survey(
        capsys, "survey", "--centre", CENTRE, "--size", "120x60", "--pod", "0.95", "--dry-run",
        "--companion-config", str(config),
    )  # fmt: skip
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert re.fullmatch(
        r"error: POD 0\.95 is out of reach over this area within the \[safety\] altitude band 30-40 m at up to "
        r"10 m/s: the best is 0\.\d\d \(altitude [\d.]+ m, \d+ lanes [\d.]+ m apart, [\d.]+ m/s, \d+ min \d\d s\); "
        r"lower --pod, or fly the area again \(two flights at POD P give 1 - \(1 - P\)\^2\)\n",
        err,
    ), err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--pod", "0.8", "--overlap", "0.3"], "error: --pod chooses the lane spacing: drop --overlap"),
        ([], "error: give --altitude M, or --pod P to have the altitude chosen for a POD"),
        (["--pod", "1.5"], "error: a POD to plan for is between 0 and 1 (e.g. 0.8), got 1.5"),
        (["--pod", "0.8", "--max-speed", "0.5"], "error: --max-speed 0.5 must be between 1 and 30 m/s"),
        (["--pod", "0.8", "--target", "car"], "error: --pod: no detection curve for 'car' in "),
    ],
)
def test_bad_pod_input_is_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: list[str], message: str
) -> None:
    code, out, err = run_survey(
        capsys, "survey", "--polygon", POLYGON, *args, "--dry-run", "--companion-config", str(curve_config(tmp_path))
    )  # fmt: skip
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(message), err


# ------------------------------------------------------------------------------- distance to the area
LON_FIRST = "8.5450,47.3975 8.5466,47.3975 8.5466,47.3982 8.5450,47.3982"  # POLYGON typed the GeoJSON way


def test_a_polygon_given_longitude_first_is_refused_naming_the_swap(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, err = run_survey(
        capsys, "survey", "--polygon", LON_FIRST, "--altitude", "25", "--dry-run", "--from", f"{HOME[0]},{HOME[1]}"
    )  # fmt: skip
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err == (
        "error: the search area is 5660 km from the --from position (47.397742,8.545594); at most 3000 m is "
        "accepted ([safety] max_survey_distance_m): latitude and longitude may be swapped (swapped, the --from "
        "position is inside it; GeoJSON lists longitude first, --polygon and --centre take lat,lon)\n"
    )


def test_an_area_too_far_is_refused_without_a_swap_to_blame(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    config = tmp_path / "companion.toml"
    config.write_text("[safety]\nmax_survey_distance_m = 100.0\n")
    far = offset_to_latlon(*HOME, 500.0, 0.0)
    code, _, err = run_survey(
        capsys, "survey", "--centre", f"{far[0]},{far[1]}", "--size", "100x100", "--altitude", "25", "--dry-run",
        "--from", f"{HOME[0]},{HOME[1]}", "--companion-config", str(config),
    )  # fmt: skip
    assert code == 2
    assert err == (
        "error: the search area is 450 m from the --from position (47.397742,8.545594); at most 100 m is "
        "accepted ([safety] max_survey_distance_m)\n"
    )
    code, out, _ = run_survey(
        capsys, "survey", "--centre", f"{far[0]},{far[1]}", "--size", "100x100", "--altitude", "25", "--dry-run",
        "--from", f"{far[0]},{far[1] + 0.01}",
    )  # fmt: skip
    assert code == 0 and "distance to the vehicle not checked" not in out  # 700 m: within the default 3 km


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


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ("/dev/zero", "/dev/zero: a character device, not a file; give the area as a GeoJSON or QGroundControl "
                      ".plan file"),
        ("/dev/urandom", "/dev/urandom: a character device, not a file; give the area as a GeoJSON or "
                         "QGroundControl .plan file"),
        ("FIFO", "area.fifo: a FIFO, not a file; give the area as a GeoJSON or QGroundControl .plan file"),
        ("DIRECTORY", ": a directory, not a file; give the area as a GeoJSON or QGroundControl .plan file"),
    ],
)  # fmt: skip
def test_an_area_file_that_is_not_a_file_is_refused_before_any_byte_is_read(
    tmp_path: Path, path: str, message: str
) -> None:
    """In a process of its own, with a memory limit and a timeout: reading /dev/zero whole would take the
    machine's memory, and opening a FIFO with no writer would wait for ever."""
    if path == "FIFO":
        os.mkfifo(tmp_path / "area.fifo")
        path = str(tmp_path / "area.fifo")
    elif path == "DIRECTORY":
        path = str(tmp_path)
    result = subprocess.run(
        [*GCS, "survey", "--area-file", path, "--altitude", "25", "--dry-run"],
        capture_output=True, text=True, timeout=60, env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30)),
    )  # fmt: skip
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ") and message in result.stderr


def _ring(corners: int) -> list[list[float]]:
    ring = [
        [round(8.5456 + 0.001 * math.cos(2 * math.pi * k / corners), 6),
         round(47.3977 + 0.0007 * math.sin(2 * math.pi * k / corners), 6)]
        for k in range(corners)
    ]  # fmt: skip
    return [*ring, ring[0]]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("[" * 100_000, "not a search area (nested too deeply)"),
        ('{"features": 5}', "neither a GeoJSON Polygon nor a QGroundControl .plan"),
        ('{"type": "FeatureCollection", "features": 5}', "a FeatureCollection whose features are not a list"),
        ('{"fileType": "Plan", "mission": {"items": 5}}', "a QGroundControl plan without a survey"),
        (json.dumps(_geojson([_ring(30_000)])), "the polygon has 30000 corners; at most 200 are accepted"),
        (
            json.dumps(_geojson([[[8.5, 47.3], [8.6, 47.3], [True, False]]])),
            "position [True, False] is not a pair",
        ),
        (
            json.dumps(_geojson([[[[[[[[[[8.5]]]]]]]]]])),
            "position [[[[[[[...]]]]]]] is not a pair of numbers",
        ),
        ("\xff\xfe{", "not JSON ("),
        ('{"type": "Polygon", "coordinates": [[[1e999, 47.3], [8.6, 47.3], [8.6, 47.4]]]}', "not a latitude"),
    ],
)
def test_hostile_area_files_are_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, content: str, message: str
) -> None:
    path = tmp_path / "area.geojson"
    path.write_bytes(content.encode("latin-1") if content.startswith("\xff") else content.encode())
    code, out, err = run_survey(capsys, "survey", "--area-file", str(path), "--altitude", "25", "--dry-run")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("error: ") and message in err, err


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


def test_a_plan_for_a_pod_is_uploaded_with_its_speed_and_altitude(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    config = curve_config(tmp_path)
    with autopilot("ardupilot") as sim:
        code, out, err = run_survey(
            capsys, *link_args(sim, "survey", "--polygon", POLYGON, "--pod", "0.8", "--companion-config", str(config))
        )  # fmt: skip
        assert (code, err) == (0, ""), err
        chosen = PLANNED.fullmatch(out.splitlines()[1])
        assert chosen, out
        expected = [m for m in map(EXPECTED.fullmatch, out.splitlines()) if m]
        assert len(expected) == 1 and float(expected[0]["mean"]) >= 0.8  # the uploaded plan's own map
        items = sim.mission.items[1:]
        assert items[0].command == DO_CHANGE_SPEED  # MAVLink carries float32
        assert items[0].param2 == pytest.approx(float(chosen["speed"]), rel=1e-6)
        assert [i.z for i in items[1:]] == pytest.approx(
            [float(chosen["altitude"])] * (len(items) - 1), rel=1e-6
        )


def test_an_area_far_from_the_vehicle_is_not_uploaded(capsys: pytest.CaptureFixture[str]) -> None:
    with autopilot("ardupilot") as sim:
        code, out, err = run_survey(
            capsys, *link_args(sim, "survey", "--polygon", LON_FIRST, "--altitude", "25")
        )
        assert code == 2 and out == ""
        assert err.startswith("error: the search area is 5660 km from the vehicle (47.39774")
        assert "latitude and longitude may be swapped (swapped, the vehicle is inside it;" in err
        assert not sim.mission.has_mission  # nothing uploaded


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
