"""fleet-search (issue 43) on real autopilots: `cloudtrack-sim run fleet-search --autopilot arducopter` (two real
ArduCopter SITL instances, system ids 1 and 2, each on its own TCP ports) and `--autopilot arducopter,px4-sitl`
(a comma list: drone-1 the real ArduCopter, drone-2 the real PX4 with SIH, in the same mission).

A fleet on real autopilots flies two vehicles, not the mock's three (`sitl.scenarios.for_autopilots`, docs/sitl.md):
one `cloudtrack-gcs survey --fleet` splits the area two ways over the autopilots' second ground links, drone-2
goes home (RTL) a third of the way into its part, the back-end lists it in /dropouts and `cloudtrack-gcs replan`
puts its unflown part onto drone-1 without taking it out of AUTO. The scenario's checks hold the rest (the
look-alike rejected once and proposed by no other vehicle, one find, merged coverage >= 0.95). About 2.5-3 min
each on a 2-core machine, in `make test` (no longer `trial`: since the shared rejections by place, the corner
fix and the clipped estimates they passed 3 of 4 and 4 of 4 runs, docs/sitl.md). The mixed flight starts its
own PX4 (not the `shares_px4` one: tests/conftest.py stops that before a test without the mark).

The fast tests below check how `--autopilot` names one autopilot per vehicle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sitl.cli import build_parser
from sitl.scenarios import REAL_FLEET_VEHICLES, SCENARIOS, autopilot_names, for_autopilots


def _fly_fleet(autopilot: str, models_dir: Path, tmp_path: Path) -> dict[str, Any]:
    from sitl.scenario_runner import RunOptions, run_scenario

    lines: list[str] = []
    results = run_scenario(
        SCENARIOS["fleet-search"],
        RunOptions(
            autopilot=autopilot,
            model_dir=models_dir,
            work_dir=tmp_path,
            tracker="nano",
            json_out=tmp_path / "out.json",
        ),
        progress=lines.append,
    )
    print("\n".join(lines))
    # Every scenario check counts: the look-alike drone-2's candidate had rejected is never proposed again by
    # drone-1 once the re-plan sends it over drone-2's lanes (the fleet's rejections by place), one find, coverage.
    failed = [f for f in results["failures"] if not f.startswith("the runner itself paused")]
    assert not failed, (failed, lines[-20:])
    fleet = results["fleet"]
    survey = fleet["survey"]
    assert set(survey["parts"]) == {"drone-1", "drone-2"}
    assert survey["one_vehicle_alone_s"] > survey["whole_area_s"] > 0
    assert fleet["dropout"]["vehicle"] == "drone-2" and fleet["dropout"]["reason"] == "mode RTL"
    assert fleet["replan"]["exit_code"] == 0 and fleet["replan"]["output"][-1].startswith("replan: 1 of 1")
    assert len(fleet["finds"]) == 1 and fleet["coverage_at_end"] >= 0.95
    assert any(r["person"] == "decoy" for r in fleet["rejections"])
    for vid, m in results["vehicles"].items():
        assert m["companion_exit_code"] == 0, vid
        assert m["companion_commands"] == {"setpoints": 0, "mode_commands": 0}, vid
    print(
        "fleet-search", autopilot, ": parts", {v: p["lanes"] for v, p in survey["parts"].items()}, "whole area",
        survey["whole_area_s"], "s, one alone", survey["one_vehicle_alone_s"], "s, covered",
        fleet["time_to_cover_s"], "s, coverage", fleet["coverage_at_end"], ", run", results["duration_s"], "s",
    )  # fmt: skip
    return results


@pytest.mark.slow
def test_fleet_search_arducopter(models_dir: Path, tmp_path: Path) -> None:
    """Two real ArduCopter SITL instances, system ids 1 and 2, one mission."""
    results = _fly_fleet("arducopter", models_dir, tmp_path)
    assert results["autopilot"] == "arducopter"
    assert [m["autopilot"] for m in results["vehicles"].values()] == ["arducopter", "arducopter"]
    members = (tmp_path / "fleet.json").read_text()
    assert '"system": 1' in members and '"system": 2' in members
    for vid in ("drone-1", "drone-2"):
        assert (tmp_path / f"{vid}-arducopter" / "eeprom.bin").is_file()  # each SITL in its own directory


@pytest.mark.slow
def test_fleet_search_arducopter_px4_sitl(models_dir: Path, tmp_path: Path) -> None:
    """One real ArduCopter (drone-1) and one real PX4 with SIH (drone-2, which goes home) in one mission."""
    results = _fly_fleet("arducopter,px4-sitl", models_dir, tmp_path)
    assert results["autopilot"] == "arducopter,px4-sitl"
    assert [m["autopilot"] for m in results["vehicles"].values()] == ["arducopter", "px4-sitl"]


def test_one_autopilot_name_flies_every_vehicle() -> None:
    fleet = SCENARIOS["fleet-search"]
    assert autopilot_names(fleet, None) == ("ardupilot",) * 3  # the mock fleet keeps its three
    assert autopilot_names(fleet, "px4") == ("px4",) * 3
    assert autopilot_names(fleet, "arducopter") == ("arducopter",) * REAL_FLEET_VEHICLES
    assert autopilot_names(SCENARIOS["follow"], "px4-sitl") == ("px4-sitl",)
    assert for_autopilots(SCENARIOS["follow"], ("arducopter",)) is SCENARIOS["follow"]
    assert for_autopilots(fleet, ("ardupilot",)) is fleet


def test_a_comma_list_gives_each_vehicle_its_autopilot() -> None:
    fleet = SCENARIOS["fleet-search"]
    names = autopilot_names(fleet, "arducopter,px4-sitl")
    assert names == ("arducopter", "px4-sitl")
    mixed = for_autopilots(fleet, names)
    assert mixed.vehicles == 2 and mixed.fleet is not None and mixed.fleet.leaves == 1
    real = for_autopilots(fleet, ("arducopter",))
    assert real.vehicles == 2 and real.fleet is not None and real.fleet.leaves == 1
    three = for_autopilots(fleet, autopilot_names(fleet, "ardupilot,px4,ardupilot"))
    assert three.vehicles == 3 and three.fleet == fleet.fleet
    with pytest.raises(ValueError, match="flies 1 vehicle"):
        autopilot_names(SCENARIOS["follow"], "arducopter,px4-sitl")
    with pytest.raises(ValueError, match="unknown"):
        autopilot_names(fleet, "arducopter,betaflight")


def test_the_cli_takes_a_comma_list(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    args = parser.parse_args(["run", "fleet-search", "--autopilot", "arducopter, px4-sitl"])
    assert args.autopilot == "arducopter,px4-sitl"
    with pytest.raises(SystemExit):
        parser.parse_args(["run", "fleet-search", "--autopilot", "arducopter,nope"])
    assert "invalid choice: 'nope'" in capsys.readouterr().err
