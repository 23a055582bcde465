"""After an abort the companion lets go: explicit stop, the hold mode requested, then silence.

The mock's ArduCopter personality flies a GCS's GUIDED position target like the real one (no GUID_TIMEOUT on
position targets); while the companion streamed zero velocity in GUIDED after an abort, each zero cancelled
that target and the vehicle did not move (the defect seen on a real ArduCopter).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from types import SimpleNamespace
from typing import Any, cast

from behaviors.detection import Verdict
from behaviors.events import GcsCommand
from behaviors.geometry import Box
from behaviors.mission import MissionState, Target, initial_state
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.setpoint import Setpoint
from cloudtrack.gcs_protocol import CMD_ABORT
from companion.mavlink.vehicle_link import RELEASE_TIMEOUT_S
from companion.mission_runner import MissionRunner
from tests.mavlink_harness import MainLoop, autopilot, gcs, receive_until, vehicle_link, wait_for

MAV_CMD_DO_SET_MODE = 176
GUIDED = 4
POSITION_ONLY_MASK = 0b110111111000  # use x, y, z only


def _following_runner(link: Any) -> MissionRunner:
    """The companion's real main-loop executor and behaviour, in FOLLOWING with an engaged mission."""
    config = MissionConfig()
    tracker = SimpleNamespace(stop=lambda: None)  # the abort stops the tracker; no camera in this test
    runner = MissionRunner(config, cast(Any, None), cast(Any, tracker), link, cast(Any, None))
    target = Target("1", "green shirt", Verdict.YES, Box(300, 200, 40, 80), 1, time.monotonic())
    runner.state = replace(
        initial_state(config), mode=MissionState.FOLLOWING, mission=StartMission("a man", allow_engage=True),
        target=target, now_s=time.monotonic(),
    )  # fmt: skip
    return runner


def _fly_to_from_gcs(ground: Any, north: float, east: float, down: float) -> None:
    ground.send(
        lambda m: m.set_position_target_local_ned_send(
            0, 1, 1, 1, POSITION_ONLY_MASK, north, east, down, 0, 0, 0, 0, 0, 0, 0, 0
        )
    )


def test_after_abort_a_gcs_guided_position_target_moves_the_vehicle() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link), gcs(sim) as ground:
        runner = _following_runner(link)
        link.request_offboard()
        link.set_velocity(Setpoint(1.5, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0), "the companion never flew the vehicle"

        ground.send(lambda m: m.command_long_send(1, 191, CMD_ABORT, 0, 0, 0, 0, 0, 0, 0, 0))
        ack = receive_until(ground, lambda m: m.get_type() == "COMMAND_ACK" and m.command == CMD_ABORT, 3.0)
        assert ack is not None and ack.result == 0
        aborted_at = time.monotonic()
        commands = wait_for(link.commands, 2.0)
        for command in commands:
            runner._handle(GcsCommand(time.monotonic(), command))
        assert runner.state.mode is MissionState.ABORTED

        time.sleep(1.5)  # the stop, the hold mode, then silence (bounded)

        # the GCS owns the vehicle: GUIDED, then fly 10 m north
        ground.send(lambda m: m.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, GUIDED, 0, 0, 0, 0, 0))
        assert wait_for(lambda: sim.mode == "GUIDED", 3.0)
        start = sim.snapshot()
        _fly_to_from_gcs(ground, start.north + 10.0, start.east, start.down)

        def moved_m() -> float:
            return math.hypot(sim.snapshot().north - start.north, sim.snapshot().east - start.east)

        moved = wait_for(lambda: moved_m() > 5.0, 8.0)
        assert moved, "the GCS's GUIDED target did not move the vehicle after the abort"

        # it got there because the companion let go: the hold mode was requested, then nothing was sent
        assert any(mode == "LOITER" and "191" in who for _, mode, who in sim.mode_history), sim.mode_history
        loiter_at = _mode_time(sim, "LOITER")
        late = [s for s in sim.setpoints if s.src_component == 191 and s.time > loiter_at + 0.2]
        assert not late, f"{len(late)} setpoints from the companion after it let go"
        last = max(s.time for s in sim.setpoints if s.src_component == 191)
        print(
            f"\nafter abort: LOITER {loiter_at - aborted_at:.3f} s after the ACK, last companion setpoint "
            f"{last - aborted_at:.3f} s; GCS target moved the vehicle {moved_m():.1f} m"
        )


def _mode_time(sim: Any, mode: str) -> float:
    return next((t for t, m, _ in sim.mode_history if m == mode), 0.0)


def test_after_abort_on_link_loss_the_companion_falls_silent_within_the_bound() -> None:
    """The hold mode cannot be set while the link is down: zeros stop after RELEASE_TIMEOUT_S anyway."""
    safety = {"heartbeat_timeout_s": 0.5}
    with (
        autopilot("ardupilot") as sim,
        vehicle_link(sim, safety=safety) as link,
        MainLoop(link),
        gcs(sim) as ground,
    ):
        runner = _following_runner(link)
        link.request_offboard()
        link.set_velocity(Setpoint(1.5, 0.0, 0.0, 0.0))
        assert wait_for(lambda: sim.snapshot().vn > 1.0, 5.0)
        sim.set_link_down("companion", True)  # both ways: the hold-mode request cannot arrive
        cut = time.monotonic()

        def aborted() -> bool:
            for event in runner._safety_events():
                runner._handle(event)
            return runner.state.mode is MissionState.ABORTED

        assert wait_for(aborted, 3.0), "the link loss never aborted the mission"
        time.sleep(RELEASE_TIMEOUT_S + 0.5)
        sim.set_link_down("companion", False)
        back = time.monotonic()
        notice = receive_until(
            ground, lambda m: m.get_type() == "STATUSTEXT" and "ABORTED" in str(m.text), 4.0
        )
        assert notice is not None  # the abort notice lost on the dead link is repeated once it is back
        time.sleep(1.0)
        assert sim.mode == "GUIDED"  # the request never arrived...
        assert not [s for s in sim.setpoints if s.src_component == 191 and s.time > back]  # ...but silence
        start = sim.snapshot()
        _fly_to_from_gcs(ground, start.north + 10.0, start.east, start.down)
        assert wait_for(lambda: sim.snapshot().north - start.north > 5.0, 8.0), "the GCS could not fly it"
        print(
            f"\nlink cut: hold mode unanswered, companion silent after {RELEASE_TIMEOUT_S:.0f} s; the GCS flew the "
            f"vehicle once the link was back ({back - cut:.1f} s after the cut)"
        )
