"""sitl/side_by_side.py: the comparison table's rows, read from the runs' JSON (no flight here)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sitl.side_by_side import command, main, row


def _results(outcome: str = "pass", **metrics: object) -> dict[str, object]:
    base = {
        "time_to_first_candidate_s": 0.25,
        "target_in_view_ratio": 1.0,
        "standoff_rmse_m": 2.513,
        "geolocation_error_m": 0.77,
        "setpoints_accepted": 343,
        "setpoints_received": 392,
        "coasted_m": {"stall": 3.46},
        "last_setpoint_after_takeover_s": None,
    }
    failures = [] if outcome == "pass" else ["vehicle 1: the right person was not confirmed (confirmed: [])"]
    return {"outcome": outcome, "failures": failures, "vehicles": {"drone-1": {**base, **metrics}}}


def test_a_row_holds_each_column_and_the_fault_figures() -> None:
    line = row(
        "search",
        "px4-sitl",
        _results(
            mission_breaks=[{"left_at": 2, "resumed_at": 2}],
            time_to_find_s=31.91,
            coverage_at_find=0.2709,
            last_setpoint_after_takeover_s=0.0,
        ),
    )
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells == [
        "`search`",
        "PX4",
        "pass; find 31.9 s, coverage 0.271, item left->resumed 2->2",
        "0.25",
        "1",
        "2.51",
        "0.77",
        "343 / 392",
        "stall 3.5",
        "0",
    ]


def test_a_failed_run_says_why_and_missing_figures_are_dashes() -> None:
    line = row(
        "stall",
        "mock",
        _results(
            "fail",
            geolocation_error_m=None,
            coasted_m={},
            stall_reported=None,
            first_setpoint_after_resume={"speed_m_s": 1.52},
        ),
    )
    assert "fail; stall NOT reported; first after resume 1.52 m/s (the right person was not confirmed" in line
    assert line.count("–") == 3  # geolocation, coasting, takeover


@pytest.mark.parametrize(("autopilot", "flag"), [("mock", None), ("px4-sitl", "px4-sitl")])
def test_each_flight_is_the_documented_command(autopilot: str, flag: str | None, tmp_path: Path) -> None:
    cmd = command("takeover", autopilot, tmp_path / "x.json")
    assert cmd[1:6] == ["-m", "sitl.cli", "run", "takeover", "--json"]
    assert (cmd[-1] if flag else None) == flag and ("--autopilot" in cmd) == (flag is not None)


def test_table_only_prints_rows_from_the_json_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "follow-arducopter.json").write_text(json.dumps(_results()))
    assert main(["--out", str(tmp_path), "--table-only", "--scenarios", "follow", "takeover"]) == 0
    out = capsys.readouterr()
    assert out.out.splitlines()[2].startswith("| `follow` | ArduCopter | pass | 0.25 |")
    assert len(out.out.splitlines()) == 3  # header, rule, the one run there
    assert "no " in out.err and "takeover-px4-sitl.json" in out.err
