"""The closed-loop scenarios as data, the scripted GCS/supervisor, and the pass/fail rules of each.

A scenario names its world (who walks where, in which shirt), the autopilot personality, the number of
vehicles, companion settings, and timed faults relative to the first supervisor confirmation. The
scripted supervisor behaves as a person at the supervisor page would: it looks at the candidate the
companion reports, compares it with what the camera shows (the ground truth of the frame), and confirms
the right person or rejects the wrong one after a short delay.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from pymavlink import mavutil

from sitl.world import Person, World, distractor_world

log = logging.getLogger(__name__)

FaultKind = Literal["takeover", "backend_down", "backend_up", "link_down", "link_up", "restart"]


@dataclass(frozen=True)
class Fault:
    """Something the scenario does to the system, `after_confirm_s` after the first confirmation."""

    kind: FaultKind
    after_confirm_s: float
    vehicle: int = 0


@dataclass(frozen=True)
class Scenario:
    name: str
    summary: str
    autopilot: str = "ardupilot"
    vehicles: int = 1
    prompt: str = "a person in a green shirt"
    occluder_at_m: float | None = None
    decoy: bool = False  # a second person in a green shirt, nearer the drone, sitting still
    faults: tuple[Fault, ...] = ()
    follow_s: float = 18.0  # run this long after the first confirmation (after the last fault's recovery)
    max_s: float = 75.0  # give up after this long since mission start
    supervisor_delay_s: float = 1.0
    miss_rate: float = 0.05  # the simulated detector's chance of missing a visible person in a keyframe
    companion_settings: tuple[str, ...] = ()
    checks: tuple[str, ...] = field(default_factory=tuple)

    def build_world(self, seed: int) -> World:
        # The turn comes after the roof, so the occlusion happens on a straight stretch.
        turn_at = 20.0 if self.occluder_at_m is None else self.occluder_at_m + 10.0
        world = distractor_world(seed, target_start=(12.0, 0.0), occluder_at_m=self.occluder_at_m, walk_m=80.0,
                                 turn_at_m=turn_at)
        if not self.decoy:
            return world
        # The look-alike stands nearer the drone than the target, so it is bigger in the image and the
        # detector scores it higher: it is proposed first and the supervisor rejects it. (Standing: the
        # local verifier's body model finds no body in the rendered sitting figure and says uncertain.)
        decoy = Person("decoy", "green", "blue", "standing", ((8.0, -4.0),))
        return World(world.seed, (*world.people, decoy), world.blocks, world.ground_size_m, world.ground_px,
                     world.target_id)


TAKEOVER_MODE = {"ardupilot": "LOITER", "px4": "POSCTL"}

# The bound: hold within 1 s of a back-end outage or a link drop. The product's defaults
# (backend_lost_s 10 s, heartbeat_timeout_s 2 s, status every 1 s) suit real uplinks that stall for
# seconds; these scenarios tighten them so the bound holds (docs/sitl.md). The status round (POST status
# + GET decisions) must succeed every 0.2 s; 0.7 s without one is an outage. The autopilot sends HEARTBEAT
# at 10 Hz on request, so 0.6 s of silence is a dropped link.
HOLD_WITHIN_S = 1.0
OUTAGE_SETTINGS = ("safety.backend_lost_s=0.7", "backend.status_interval_s=0.2")
LINK_DROP_SETTINGS = ("safety.heartbeat_timeout_s=0.6",)

SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("follow", "follow a person in a green shirt walking at 1.5 m/s among distractors",
                 companion_settings=("recording.video=true",), checks=("confirmed_target", "in_view", "standoff")),
        Scenario("reject", "a look-alike in green is proposed first; the supervisor rejects it, the right one is confirmed",
                 decoy=True, follow_s=6.0, miss_rate=0.0, checks=("confirmed_target", "rejected_never_again")),
        Scenario("occlusion", "the target walks under a roof for about 3 s and is re-acquired after it",
                 occluder_at_m=12.0, follow_s=24.0, checks=("confirmed_target", "reacquired")),
        Scenario("takeover", "the pilot switches mode mid-follow: setpoints stop within 200 ms",
                 faults=(Fault("takeover", 5.0),), follow_s=8.0, checks=("confirmed_target", "takeover")),
        Scenario("backend-outage", "the back-end is unreachable for 6 s mid-follow: hold, then resume",
                 faults=(Fault("backend_down", 4.0), Fault("backend_up", 10.0)), follow_s=16.0,
                 companion_settings=OUTAGE_SETTINGS, checks=("confirmed_target", "outage_hold")),
        Scenario("link-drop", "the companion's MAVLink link drops for 4 s: hold, then the GCS restarts the mission",
                 faults=(Fault("link_down", 4.0), Fault("link_up", 8.0), Fault("restart", 10.0)), follow_s=22.0,
                 companion_settings=LINK_DROP_SETTINGS, checks=("confirmed_target", "link_hold")),
        Scenario("follow-px4", "the follow scenario on the PX4 personality (OFFBOARD)", autopilot="px4",
                 checks=("confirmed_target", "in_view", "standoff")),
        Scenario("two-vehicles", "two drones share one back-end; both confirm the person in green", vehicles=2,
                 follow_s=8.0, checks=("confirmed_target",)),
    )
}


@dataclass(frozen=True)
class VehicleOutcome:
    """What one vehicle's run produced, as the checks need it (times in scenario seconds)."""

    metrics: dict[str, Any]
    confirmations: tuple[float, ...]
    confirmed_ids: tuple[str, ...]  # person id the supervisor saw at each confirmation
    proposals: tuple[tuple[float, str], ...]  # (time, person id) of every candidate the companion tracked
    rejected_ids: tuple[tuple[float, str], ...]
    lost_intervals: tuple[tuple[float, float], ...]
    occlusion: tuple[float, float] | None  # when the target was hidden (visible < 0.2) after confirmation
    last_setpoint_after_takeover_s: float | None
    takeover_t: float | None
    hold_times: tuple[float, ...]
    following_after: Callable[[float], float]  # seconds spent tracking the target after time t


def assess(scenario: Scenario, outcomes: Sequence[VehicleOutcome], fault_times: dict[str, float]) -> list[str]:
    """The failed checks with the reason, empty when the scenario passed."""
    failures: list[str] = []
    for i, o in enumerate(outcomes):
        name = f"vehicle {i + 1}"
        m = o.metrics
        if "confirmed_target" in scenario.checks and (not o.confirmed_ids or o.confirmed_ids[0] != "target"):
            failures.append(f"{name}: the right person was not confirmed (confirmed: {list(o.confirmed_ids)})")
        if "in_view" in scenario.checks:
            ratio = m.get("target_in_view_ratio")
            if ratio is None or ratio < 0.9:
                failures.append(f"{name}: target in view {ratio} of the follow time, needs >= 0.9")
        if "standoff" in scenario.checks:
            rmse = m.get("standoff_rmse_m")
            if rmse is None or rmse > 3.0:
                failures.append(f"{name}: standoff RMSE {rmse} m, needs <= 3 m")
        if "rejected_never_again" in scenario.checks:
            if not o.rejected_ids:
                failures.append(f"{name}: nobody was rejected")
            for t_rej, pid in o.rejected_ids:
                again = [t for t, p in o.proposals if p == pid and t > t_rej + 0.5]
                if again:
                    failures.append(f"{name}: rejected {pid} was proposed again at {again[0]:.1f} s")
        if "reacquired" in scenario.checks:
            if o.occlusion is None:
                failures.append(f"{name}: the target was never hidden by the roof")
            else:
                start, end = o.occlusion
                if end - start < 2.0:
                    failures.append(f"{name}: occlusion lasted only {end - start:.1f} s")
                if o.following_after(end) < 5.0:
                    failures.append(f"{name}: not re-acquired after the occlusion ended at {end:.1f} s")
        if "takeover" in scenario.checks:
            late = o.last_setpoint_after_takeover_s
            if o.takeover_t is None:
                failures.append(f"{name}: no takeover happened")
            elif late is not None and late > 0.2:
                failures.append(f"{name}: setpoint {late * 1000:.0f} ms after the mode change, limit 200 ms")
        for check, down, up in (("outage_hold", "backend_down", "backend_up"), ("link_hold", "link_down", "link_up")):
            if check not in scenario.checks or down not in fault_times:
                continue
            t_down = fault_times[down]
            holds = [t for t in o.hold_times if t >= t_down]
            if not holds or holds[0] - t_down > HOLD_WITHIN_S:
                first = f"{holds[0] - t_down:.2f} s" if holds else "never"
                failures.append(f"{name}: hold {first} after the {down.replace('_', ' ')}, needs <= {HOLD_WITHIN_S:.1f} s")
            recover_from = fault_times.get("restart", fault_times.get(up, math.inf))
            if o.following_after(recover_from) < 4.0:
                failures.append(f"{name}: did not resume following after {up.replace('_', ' ')}")
    return failures


class ScriptedGcs:
    """A ground station on the autopilot's GCS link: mission start with a prompt, confirm, reject.

    Speaks the companion's GCS protocol (companion/gcs_link.py): the prompt in TUNNEL chunks, then
    MAV_CMD_USER_1; confirm/reject as MAV_CMD_USER_3/4 with candidate 0 (the one awaiting the supervisor).
    """

    def __init__(self, url: str, target_system: int = 1, target_component: int = 191) -> None:
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.target = (target_system, target_component)
        self.statustexts: list[tuple[float, str]] = []
        self.acks: list[tuple[float, int, int]] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="scripted-gcs", daemon=True)

    def start(self) -> ScriptedGcs:
        self._thread.start()
        return self

    def _run(self) -> None:
        last_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_hb >= 1.0:
                with self._lock:
                    self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                last_hb = now
            try:
                msg = self.conn.recv_match(type=["STATUSTEXT", "COMMAND_ACK"], blocking=True, timeout=0.2)
            except (OSError, ValueError):
                continue
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                self.statustexts.append((now, str(msg.text)))
            else:
                self.acks.append((now, int(msg.command), int(msg.result)))

    def _command(self, command: int, *params: float) -> None:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        with self._lock:
            self.conn.mav.command_long_send(self.target[0], self.target[1], command, 0, *p)

    def start_mission(self, prompt: str, mission_id: int, superset: str = "person", allow_engage: bool = True) -> None:
        from companion.gcs_link import CMD_START, PROMPT_PAYLOAD_TYPE, encode_prompt

        chunks = encode_prompt(mission_id, superset, prompt)
        for chunk in chunks:
            with self._lock:
                self.conn.mav.tunnel_send(self.target[0], self.target[1], PROMPT_PAYLOAD_TYPE, len(chunk),
                                          list(chunk.ljust(128, b"\0")))
        length = sum(len(c) - 4 for c in chunks)
        self._command(CMD_START, mission_id, len(chunks), 1.0 if allow_engage else 0.0, length)

    def confirm(self) -> None:
        from companion.gcs_link import CMD_CONFIRM

        self._command(CMD_CONFIRM, 0)

    def reject(self) -> None:
        from companion.gcs_link import CMD_REJECT

        self._command(CMD_REJECT, 0)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.conn.close()
