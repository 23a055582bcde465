"""The MAVProxy module (`module load cloudtrack`) in a real mavproxy.py process against the mock autopilot."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from behaviors.mission_commands import AbortMission, ConfirmCandidate, RejectCandidate, StartMission
from tests.mavlink_harness import MainLoop, autopilot, vehicle_link, wait_for

ROOT = Path(__file__).resolve().parent.parent


def _mavproxy() -> str:
    found = shutil.which("mavproxy.py") or str(Path(sys.executable).parent / "mavproxy.py")
    assert Path(found).exists(), "MAVProxy is not installed: `make test` installs it (docs/gcs-protocol.md)"
    return found


@pytest.mark.slow
def test_mavproxy_module_sends_every_mission_command() -> None:
    with autopilot("ardupilot") as sim, vehicle_link(sim) as link, MainLoop(link):
        env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        proc = subprocess.Popen(
            [sys.executable, _mavproxy(), f"--master=udpout:127.0.0.1:{sim.link_port('gcs')}", "--no-state",
             "--nodtr"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT,
        )  # fmt: skip
        out: list[str] = []
        reader = threading.Thread(target=lambda: out.extend(iter(proc.stdout.readline, "")), daemon=True)  # type: ignore[union-attr]
        reader.start()
        commands: list[object] = []

        def say(line: str, expect: str) -> None:
            assert proc.stdin is not None
            proc.stdin.write(line + "\n")
            proc.stdin.flush()
            assert wait_for(lambda: any(expect in o for o in out), 10.0), (
                f"{line!r}: no {expect!r} in {''.join(out)[-2000:]}"
            )

        try:
            assert wait_for(lambda: any("Detected vehicle 1:191" in o for o in out), 20.0), "".join(out)
            say("module load cloudtrack", "Loaded module cloudtrack")
            say(
                'cloudtrack start "an injured man in a gray shirt" superset=person',
                "CloudTrack start: ACCEPTED",
            )
            say("cloudtrack confirm", "CloudTrack confirm: ACCEPTED")
            say("cloudtrack reject 2", "CloudTrack reject: ACCEPTED")
            say("cloudtrack abort", "CloudTrack abort: ACCEPTED")
            say("cloudtrack status", "CloudTrack status: ACCEPTED")
            commands.extend(link.commands())
        finally:
            proc.kill()
            proc.wait(timeout=5)
        assert commands == [
            StartMission(
                "an injured man in a gray shirt",
                "person",
                allow_engage=False,
                mission_id=commands[0].mission_id,
            ),  # type: ignore[attr-defined]
            ConfirmCandidate("", by="gcs"),
            RejectCandidate("2"),
            AbortMission("gcs"),
        ]
