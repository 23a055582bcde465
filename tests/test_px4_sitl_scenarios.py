"""The safety scenarios flown with the REAL PX4 (../shared/sitl/px4, v1.16 with SIH physics) instead of the mock.

Each test runs `cloudtrack-sim run SCENARIO --autopilot px4-sitl`'s code path against one PX4 shared with the
conformance half (tests/conftest.py `shared_px4`): it is started once (fresh work directory, COM_OF_LOSS_T
0.5 s, COM_OBL_RC_ACT Hold, COM_RC_OVERRIDE 3), armed and taken off to 10 m by the scripted pilot over the GCS link, and before each
scenario the GCS brings it back over home facing north in HOLD (`RealPx4.return_home`). The mission runs at real
time with the real companion process, the camera rendered from SIH's ground truth and the real back-end.
CI pays for these flights (issue 29's budget: 180 s for every real-PX4 test), so each flight carries several
faults (`flood-stall`, `link-drop-takeover` in sitl/scenarios.py) and the two offboard paths, the companion's
pymavlink one and `mavlink.use_mavsdk` (MAVSDK 4 in process), share them out (`FLIGHTS`). `pytest -k px4_sitl`
selects them (with the conformance and parameter tests).

The area search (`test_px4_sitl_search`) flies on the same PX4 after them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sitl.px4_sitl import COM_OF_LOSS_T_S, RealPx4
from sitl.scenario_runner import RunOptions, run_scenario
from sitl.scenarios import (
    FLY_TO_MIN_PROGRESS_M,
    SCENARIOS,
    STALL_MAX_COAST_M,
    stall_max_coast_m,
    standoff_max_rmse_m,
)

pytestmark = [pytest.mark.slow, pytest.mark.shares_px4]
LINKS = {"pymavlink": (), "mavsdk": ("mavlink.use_mavsdk=true",)}


@pytest.fixture
def px4(shared_px4: Any) -> RealPx4:
    vehicle: RealPx4 = shared_px4.get()
    return vehicle


def _fly(
    name: str, px4: RealPx4, link: str, models_dir: Path, tmp_path: Path, **kwargs: Any
) -> tuple[dict[str, Any], dict[str, Any]]:
    lines: list[str] = []
    results = run_scenario(
        SCENARIOS[name],
        RunOptions(
            flight_stack=px4,
            model_dir=models_dir,
            work_dir=tmp_path,
            tracker="nano",
            companion_settings=LINKS[link],
            **kwargs,
        ),
        progress=lines.append,
    )
    print("\n".join(lines))
    assert results["autopilot"] == "px4-sitl"
    m = results["vehicles"]["drone-1"]
    assert results["outcome"] == "pass", (results["failures"], lines[-15:])
    assert m["companion_exit_code"] == 0
    assert m["companion_stop_s"] is not None and m["companion_stop_s"] < 2.0
    assert m["max_commanded_speed_m_s"] <= 3.0 + 1e-6  # [safety] max_speed_m_s
    return results, m


# The CI set (issue 29's safety set within its 180 s budget): every fault the ArduCopter set flies, several to a
# flight, each link once or more. `cloudtrack-sim run SCENARIO --autopilot px4-sitl` flies any single scenario.
FLIGHTS = [
    ("flood-stall", "pymavlink"),
    ("link-drop-takeover", "mavsdk"),
]


@pytest.mark.parametrize(("scenario", "link"), FLIGHTS, ids=[f"{s}-{k}" for s, k in FLIGHTS])
def test_px4_sitl_safety_set(
    px4: RealPx4, scenario: str, link: str, models_dir: Path, tmp_path: Path
) -> None:
    results, m = _fly(scenario, px4, link, models_dir, tmp_path, json_out=tmp_path / "run.json")
    faults = results["faults"]
    assert (tmp_path / "run.json").stat().st_size > 0
    assert m["confirmed"][:1] == ["target"]
    # Mostly flown in OFFBOARD: not the 1 s stream before the companion asks for it, nor its zeros after a fault.
    assert m["setpoints_accepted"] > 0.5 * m["setpoints_received"]
    if "in_view" in SCENARIOS[scenario].checks:
        assert m["target_in_view_ratio"] >= 0.9
        assert m["standoff_rmse_m"] <= standoff_max_rmse_m("px4-sitl")
    if "flood" in faults:
        assert m["flood"]["senders"] == 200
        assert m["flood"]["setpoints"] == 0
    if "stall" in faults:
        assert m["coasted_m"]["stall"] <= stall_max_coast_m("px4-sitl")
        # PX4 took its offboard-loss failsafe (COM_OBL_RC_ACT Hold) about COM_OF_LOSS_T after the last
        # setpoint it had before the freeze, and said so.
        during = m["autopilot_during_stall"]
        assert during["mode_before"] == "OFFBOARD", during
        assert during["mode_change"]["mode"] == "HOLD", during
        assert COM_OF_LOSS_T_S <= during["mode_change"]["after_last_setpoint_s"] <= COM_OF_LOSS_T_S + 1.5, (
            during
        )
        assert during["mode_change"]["after_s"] <= COM_OF_LOSS_T_S + 1.5, during
        assert any("Failsafe" in text for text in during["texts"]), during
        # The GCS learns the cause from the companion: it stalled, and offboard ended by the failsafe.
        assert m["stall_reported"] is not None, m["statustexts_after_resume"]
        first = m["first_setpoint_after_resume"]
        assert first is None or first["speed_m_s"] <= 0.05
    if "link_down" in faults:
        holds = [e["t"] for e in m["safety_events"] if e["kind"] == "hold" and e["t"] >= faults["link_down"]]
        assert holds and holds[0] - faults["link_down"] <= 1.0, m["safety_events"]
        assert m["coasted_m"]["link_down"] <= STALL_MAX_COAST_M
    if "takeover" in faults:
        assert m["last_setpoint_after_takeover_s"] is not None and m["last_setpoint_after_takeover_s"] <= 0.2
    if "fly_to" in faults:
        assert m["fly_to_progress_m"] >= FLY_TO_MIN_PROGRESS_M


def test_px4_sitl_search(px4: RealPx4, models_dir: Path, tmp_path: Path) -> None:
    """Issue 29's area search on the real PX4: `cloudtrack-gcs survey` uploads the survey over PX4's second GCS
    link (`RealPx4.ground_url`), the pilot flies it in Mission (its DO_CHANGE_SPEED 5 m/s, which PX4 keeps after
    a resume), the companion takes OFFBOARD for the look-alike, the supervisor rejects it and Mission resumes
    at the item it broke off at (PX4's own MISSION_CURRENT on the GCS link), the described person is found."""
    _, m = _fly("search", px4, "pymavlink", models_dir, tmp_path, json_out=tmp_path / "search.json")
    assert m["survey"]["output"][-1].startswith("uploaded 7 items, read back and checked")
    assert m["rejected"] == ["decoy"] and m["confirmed"][:1] == ["target"]
    breaks = m["mission_breaks"]
    assert breaks and breaks[0]["resumed_at"] == breaks[0]["left_at"] is not None, breaks
    assert m["geolocation_error_m"] is not None and m["geolocation_error_m"] <= 3.0
    assert m["coverage_at_find"] is not None and 0.0 < m["coverage_at_find"] < 1.0
    print(
        f"px4 search: time to find {m['time_to_find_s']} s, coverage at the find {m['coverage_at_find']}, "
        f"geolocation error {m['geolocation_error_m']} m, break-offs {breaks}"
    )
