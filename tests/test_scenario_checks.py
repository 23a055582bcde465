"""The scenario checks (`sitl.scenarios.assess`) on hand-made outcomes: what makes `cloudtrack-sim run` fail."""

from __future__ import annotations

from typing import Any

import pytest

from sitl.scenarios import ABORT_MAX_SETPOINTS, SCENARIOS, VehicleOutcome, assess

GOOD: dict[str, Any] = {
    "max_commanded_speed_m_s": 2.9,
    "companion_stop_s": 0.4,
    "companion_exit_code": 0,
    "setpoint_rate_hz": 15.0,
    "setpoints_received": 300,
    "setpoints_accepted": 300,
    "target_in_view_ratio": 0.97,
    "standoff_rmse_m": 1.2,
    "fly_to_progress_m": 14.0,
    "setpoints_during_fly_to": 0,
    "setpoints_after_abort": 1,
}


def _outcome(**changes: Any) -> VehicleOutcome:
    return VehicleOutcome(
        metrics={**GOOD, **changes},
        confirmations=(10.0,),
        confirmed_ids=("target",),
        proposals=((5.0, "target"),),
        rejected_ids=(),
        lost_intervals=(),
        occlusion=None,
        last_setpoint_after_takeover_s=None,
        takeover_t=None,
        hold_times=(),
        following_after=lambda t: 20.0,
    )


@pytest.mark.parametrize(
    ("scenario", "autopilot", "changes", "failure"),
    [
        ("follow", "ardupilot", {}, None),
        ("follow", "ardupilot", {"max_commanded_speed_m_s": 3.2}, "commanded 3.2 m/s"),
        ("follow", "arducopter", {"companion_exit_code": 1}, "exit status 1"),
        ("follow", "ardupilot", {"companion_stop_s": 2.5}, "stopped in 2.5 s"),
        ("follow", "ardupilot", {"companion_stop_s": None}, "stopped in None s"),
        ("follow", "ardupilot", {"setpoint_rate_hz": 9.0}, "setpoints at 9.0 Hz"),
        ("follow", "arducopter", {"setpoints_accepted": 290}, "290 of them in GUIDED (0 departures"),
        ("follow", "ardupilot", {"setpoints_accepted": 299, "left_active_mode": 1}, None),  # one in flight
        ("follow", "ardupilot", {"setpoints_accepted": 298, "left_active_mode": 1}, "298 of them in GUIDED"),
        ("follow", "ardupilot", {"setpoints_accepted": 290, "left_active_mode": 1}, "290 of them in GUIDED"),
        ("follow", "px4", {"setpoints_accepted": 290}, None),  # PX4 needs a stream before OFFBOARD
        ("follow", "px4-sitl", {"setpoints_accepted": 290}, None),
        ("follow", "arducopter", {"standoff_rmse_m": 3.3}, "standoff RMSE 3.3 m, needs <= 3 m"),
        ("follow", "px4-sitl", {"standoff_rmse_m": 3.3}, None),  # OFFBOARD's second of setpoints first
        ("follow", "px4-sitl", {"standoff_rmse_m": 4.2}, None),
        ("follow", "px4-sitl", {"standoff_rmse_m": 5.2}, "standoff RMSE 5.2 m, needs <= 5 m"),
        ("reject", "ardupilot", {"setpoint_rate_hz": 9.0}, "nobody was rejected"),  # no rate check there
        ("abort-flyto", "ardupilot", {}, None),
        ("abort-flyto", "ardupilot", {"setpoints_after_abort": ABORT_MAX_SETPOINTS + 1}, "after the abort"),
        ("abort-flyto", "ardupilot", {"setpoints_after_abort": None}, "None setpoints after the abort"),
        ("abort-flyto", "arducopter", {"setpoints_during_fly_to": 4}, "while the GCS flew the vehicle"),
        ("abort-flyto", "ardupilot", {"fly_to_progress_m": 2.0}, "moved the vehicle 2.0 m"),
    ],
)
def test_scenario_checks_table(
    scenario: str, autopilot: str, changes: dict[str, Any], failure: str | None
) -> None:
    failures = assess(SCENARIOS[scenario], [_outcome(**changes)], {"abort": 5.0, "fly_to": 7.0}, autopilot)
    if failure is None:
        assert failures == []
    else:
        assert len(failures) == 1 and failure in failures[0], failures


@pytest.mark.parametrize(
    ("find", "failure"),
    [
        ({"error_m": 0.9}, None),
        ({"error_m": 5.8}, "needs <= 5.00 m"),  # the mock: no ground truth apart from the estimate
        ({"error_m": 5.8, "heading_error_deg": 0.5, "range_m": 27.4}, "needs <= 5.24 m"),
        # CI's PX4 find: its heading 12 deg off SIH's truth at 27 m explains 5.7 m of it
        ({"error_m": 5.8, "heading_error_deg": -12.0, "range_m": 27.4}, None),
        ({"error_m": 12.0, "heading_error_deg": -12.0, "range_m": 27.4}, "needs <= 10.70 m"),
    ],
)
def test_the_fleet_find_is_graded_apart_from_the_autopilots_heading_error(
    find: dict[str, Any], failure: str | None
) -> None:
    scenario = SCENARIOS["fleet-search"]
    fleet = {"finds": [{"vehicle_id": "drone-2", "candidate_id": "c1", **find}]}
    failures = [f for f in assess(scenario, [_outcome()], {}, "mock", fleet) if "find lies" in f]
    if failure is None:
        assert not failures
    else:
        assert len(failures) == 1 and failure in failures[0]
