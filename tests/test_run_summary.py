"""`cloudtrack-sim run`'s summary lines (issue 45): a search prints its own figures (time to find, coverage
and POD at the find, the find's position error, the break-offs and resumes) and none of the follow's control
figures, which measure a standoff the survey never flies; a follow prints them."""

from __future__ import annotations

from typing import Any

from sitl.run_summary import summary_lines
from sitl.scenarios import SCENARIOS

FOLLOW_FIGURES = {
    "confirmed": ["target"], "time_to_first_candidate_s": 4.1, "time_to_verified_candidate_s": 4.6,
    "time_to_confirmation_s": 9.0, "target_in_view_ratio": 0.97, "pixel_error_mean_px": 119.0,
    "pixel_error_p95_px": 240.5, "standoff_rmse_m": 28.1, "max_commanded_speed_m_s": 3.0,
    "setpoint_rate_hz": 10.0, "reinits": 0, "rejected": ["decoy"], "proposed": ["decoy", "target"],
}  # fmt: skip
SEARCH_FIGURES = {
    "found": True, "time_to_find_s": 61.2, "time_to_first_sighting_s": 48.0, "coverage_at_find": 0.43,
    "coverage_at_end": 0.47, "pod_at_target": 0.612, "geolocation_error_m": 1.84,
    "mission_breaks": [{"left_t": 30.1, "left_at": 3, "resumed_at": 3}, {"left_t": 52.0, "left_at": 5, "resumed_at": None}],
}  # fmt: skip


def _results(name: str, figures: dict[str, Any]) -> dict[str, Any]:
    return {
        "scenario": name, "autopilot": "ardupilot", "tracker": "nano", "outcome": "pass", "failures": [],
        "vehicles": {"drone-1": figures},
    }  # fmt: skip


def test_a_search_prints_its_figures_and_no_standoff() -> None:
    lines = summary_lines(_results("search", {**FOLLOW_FIGURES, **SEARCH_FIGURES}), SCENARIOS["search"])
    text = "\n".join(lines)
    assert lines[0] == "scenario search (ardupilot, tracker nano): PASS"
    assert lines[1] == (
        "  drone-1 search: found in 61.2 s (first sighting 48.0 s), coverage at the find 43 % (at the end 47 %), "
        "find's position error 1.84 m, POD at the person 0.61, rejected 1 of 2 proposed; mission: left at item "
        "3 (30.1 s), resumed at item 3; left at item 5 (52.0 s), not resumed"
    )
    assert lines[2].startswith("  drone-1 tracking: confirmed ['target']")
    assert "confirmation 9.0 s, in view 0.97, re-inits 0" in lines[2]
    assert (
        "standoff RMSE" not in text and "pixel error" not in text and "28.1" not in text and "119" not in text
    )
    assert lines[3].startswith("  (the follow's standoff and image-centre figures are left out")


def test_a_search_that_found_nothing_says_so() -> None:
    figures = {**FOLLOW_FIGURES, "found": False, "time_to_find_s": None, "time_to_first_sighting_s": None,
               "coverage_at_find": None, "coverage_at_end": 1.0, "pod_at_target": None,
               "geolocation_error_m": None, "mission_breaks": []}  # fmt: skip
    results = {**_results("search", figures), "outcome": "fail", "failures": ["drone-1: not found"]}
    lines = summary_lines(results, SCENARIOS["search"])
    assert lines[1].startswith(
        "  drone-1 search: NOT found (first sighting none), coverage at the end 100 %, POD at the person none"
    )
    assert "find's position error" not in lines[1] and "coverage at the find" not in lines[1]
    assert "POD at the person none reported" in lines[1] and "mission: never left the mission" in lines[1]
    assert lines[-1] == "  FAILED: drone-1: not found"


def test_a_follow_prints_its_control_figures() -> None:
    lines = summary_lines(_results("follow", FOLLOW_FIGURES), SCENARIOS["follow"])
    assert len(lines) == 2 and "time to find" not in lines[1]
    assert "pixel error 119.0/240.5 px (mean/p95), standoff RMSE 28.1 m" in lines[1]
