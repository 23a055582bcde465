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

The area search on PX4 (`cloudtrack-sim run search --autopilot px4-sitl`) is not in this set: it failed in CI
(2026-11-26) on camera stalls, now found and fixed (a person beside the low camera made the renderer fill a
mask of hundreds of megabytes: `sitl.camera_render.unoccluded_area`; 0 stale-frame stops in the flights since, 1-4 a flight
before). It still fails 6 of 8 flights on this machine for another reason: the local verifier answers
"uncertain" (boxes 13-25 px) or once "no" for the look-alike 2 m beside the first lane, so it passes unproposed
and the described person is found from the second lane; docs/sitl.md has the runs.
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
