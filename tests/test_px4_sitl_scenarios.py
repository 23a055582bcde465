"""The safety scenarios flown with the REAL PX4 (../shared/sitl/px4, v1.16 with SIH physics) instead of the mock.

Each test runs `cloudtrack-sim run SCENARIO --autopilot px4-sitl`'s code path against one PX4 shared by the
module: it is started once (fresh work directory, COM_OF_LOSS_T 0.5 s, COM_OBL_RC_ACT Hold,
COM_RC_OVERRIDE 3), armed and taken off to 10 m by the scripted pilot over the GCS link, and before each
scenario the GCS brings it back over home facing north in HOLD (`RealPx4.return_home`). The mission runs at real
time with the real companion process, the camera rendered from SIH's ground truth and the real back-end.
Every scenario flies twice: with the companion's pymavlink offboard path and with `mavlink.use_mavsdk`
(MAVSDK 4 in process). `pytest -k px4_sitl` selects them (with the conformance and parameter tests).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from sitl.px4_sitl import COM_OF_LOSS_T_S, RealPx4, find_package, start_px4
from sitl.scenario_runner import ALTITUDE_M, HOME_ALT_M, RunOptions, _home, run_scenario
from sitl.scenarios import FLY_TO_MIN_PROGRESS_M, SCENARIOS, STALL_MAX_COAST_M

pytestmark = pytest.mark.slow
LINKS = {"pymavlink": (), "mavsdk": ("mavlink.use_mavsdk=true",)}


@pytest.fixture(scope="module")
def px4(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealPx4]:
    lat, lon = _home((0.0, 0.0))
    vehicle = start_px4(find_package(), tmp_path_factory.mktemp("px4-sitl"), (lat, lon, HOME_ALT_M), None)
    try:
        took = vehicle.fly_up(ALTITUDE_M)
        print(f"px4 airborne after {took:.1f} s ({vehicle.describe()})")
        yield vehicle
    finally:
        vehicle.gcs.stop()
        vehicle.close()


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


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_follow(px4: RealPx4, link: str, models_dir: Path, tmp_path: Path) -> None:
    _, m = _fly("follow", px4, link, models_dir, tmp_path, json_out=tmp_path / "follow.json")
    assert m["confirmed"][:1] == ["target"]
    assert m["target_in_view_ratio"] >= 0.9
    assert m["standoff_rmse_m"] <= 3.0
    assert m["setpoints_accepted"] > 0.9 * m["setpoints_received"]  # flown in OFFBOARD
    assert (tmp_path / "follow.json").stat().st_size > 0


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_takeover_mode_change(px4: RealPx4, link: str, models_dir: Path, tmp_path: Path) -> None:
    results, m = _fly("takeover", px4, link, models_dir, tmp_path)
    assert "takeover" in results["faults"]
    assert m["last_setpoint_after_takeover_s"] is not None and m["last_setpoint_after_takeover_s"] <= 0.2


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_takeover_rc_sticks(px4: RealPx4, link: str, models_dir: Path, tmp_path: Path) -> None:
    results, m = _fly("takeover-rc", px4, link, models_dir, tmp_path)
    assert "rc_takeover" in results["faults"]
    assert m["last_setpoint_after_takeover_s"] is not None and m["last_setpoint_after_takeover_s"] <= 0.2


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_abort_then_gcs_reposition_moves_the_vehicle(
    px4: RealPx4, link: str, models_dir: Path, tmp_path: Path
) -> None:
    _, m = _fly("abort-flyto", px4, link, models_dir, tmp_path)
    assert m["fly_to_progress_m"] >= FLY_TO_MIN_PROGRESS_M


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_companion_stall_and_offboard_loss_failsafe(
    px4: RealPx4, link: str, models_dir: Path, tmp_path: Path
) -> None:
    _, m = _fly("stall", px4, link, models_dir, tmp_path)
    assert m["coasted_m"]["stall"] <= STALL_MAX_COAST_M
    # PX4 took its offboard-loss failsafe (COM_OBL_RC_ACT Hold) about COM_OF_LOSS_T after the freeze, and said so.
    during = m["autopilot_during_stall"]
    assert during["mode_before"] == "OFFBOARD", during
    assert during["mode_change"]["mode"] == "HOLD", during
    assert COM_OF_LOSS_T_S <= during["mode_change"]["after_s"] <= COM_OF_LOSS_T_S + 1.5, during
    assert any("Failsafe" in text for text in during["texts"]), during
    # The GCS learns the cause from the companion: it stalled, and offboard ended by the failsafe.
    assert m["stall_reported"] is not None, m["statustexts_after_resume"]
    first = m["first_setpoint_after_resume"]
    assert first is None or first["speed_m_s"] <= 0.05


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_autopilot_link_loss(px4: RealPx4, link: str, models_dir: Path, tmp_path: Path) -> None:
    results, m = _fly("link-drop", px4, link, models_dir, tmp_path)
    down = results["faults"]["link_down"]
    holds = [e["t"] for e in m["safety_events"] if e["kind"] == "hold" and e["t"] >= down]
    assert holds and holds[0] - down <= 1.0, m["safety_events"]
    assert m["coasted_m"]["link_down"] <= STALL_MAX_COAST_M
    assert m["confirmed"] == ["target", "target"]


@pytest.mark.parametrize("link", LINKS)
def test_px4_sitl_udp_flood(px4: RealPx4, link: str, models_dir: Path, tmp_path: Path) -> None:
    _, m = _fly("flood", px4, link, models_dir, tmp_path)
    assert m["flood"]["senders"] == 200
    assert m["flood"]["setpoints"] == 0
