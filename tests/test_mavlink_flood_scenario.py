"""A UDP flood on the running companion (`cloudtrack-companion run`) while it follows in the SITL scenario.

The `follow` scenario runs the real companion process, tracker, back-end and mock autopilot; once the
companion is following, 200 loopback senders each send five datagrams (garbage and a forged autopilot
HEARTBEAT in LOITER) to the companion's own MAVLink port. Nothing may reach them, and the scenario must
still pass: confirmed, following, the target in view.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from cloudtrack.mavlink_connection import mavlink
from sitl.scenario_runner import RunOptions, ScenarioRun
from sitl.scenarios import SCENARIOS
from tests.mavlink_harness import wait_for
from tests.test_scenarios import _follow_checks

SENDERS = 200
LOITER = 5


@pytest.mark.slow
def test_flood_from_200_senders_while_the_companion_follows_in_the_scenario(
    models_dir: Path, tmp_path: Path
) -> None:
    lines: list[str] = []
    run = ScenarioRun(SCENARIOS["follow"], RunOptions(model_dir=models_dir, work_dir=tmp_path, tracker="nano"),
                      progress=lines.append)  # fmt: skip
    results: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: results.update(run.run()), daemon=True)
    thread.start()
    try:
        assert wait_for(lambda: run.vehicles, 60.0)
        sim = run.vehicles[0].autopilot

        def following() -> bool:
            return any(s.src_component == 191 and s.vx > 0.3 for s in list(sim.setpoints)[-50:])

        assert wait_for(following, 90.0), lines[-15:]
        companion = next(iter(sim._links["companion"].conn.clients))  # where the companion sends from
        forged = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        heartbeat = forged.heartbeat_encode(2, 3, 129, LOITER, 4).pack(forged)
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(SENDERS)]
        try:
            for round_ in range(5):
                for i, s in enumerate(socks):
                    s.sendto(heartbeat if (i + round_) % 2 else bytes([0xFD, i % 256]) * 40, companion)
            time.sleep(2.0)
            readable, _, _ = select.select(socks, [], [], 0.2)
            assert readable == [], f"{len(readable)} flooding senders received the companion's output"
        finally:
            for s in socks:
                s.close()
        lines.append(f"flood: {SENDERS} senders x 5 datagrams to {companion[0]}:{companion[1]}, no replies")
    finally:
        thread.join(timeout=300)
    print("\n".join(lines))
    assert results.get("outcome") == "pass", (results.get("failures"), lines[-15:])
    m = results["vehicles"]["drone-1"]
    assert m["companion_exit_code"] == 0  # it never crashed: it stopped cleanly on SIGTERM at the end
    _follow_checks(m)
