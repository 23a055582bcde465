"""`cloudtrack-sim up` with the real autopilots and the search world: the commands it prints, run as printed,
fly the area-search rehearsal (survey, the mission mode, start, reject the look-alike, confirm the person
described) on the real ArduCopter SITL and the real PX4 SITL; Ctrl-C stops everything. Select: -k sim_up.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SIM = str(Path(sys.executable).with_name("cloudtrack-sim"))
GCS = str(Path(sys.executable).with_name("cloudtrack-gcs"))
HOME_LAT = 47.397742
LOOKALIKE_NORTH_M, TARGET_NORTH_M = 60.0, 90.0  # sitl/world.py, fixed_search_world
CANDIDATE = re.compile(r"CANDIDATE (?:AWAITING|REVERIFIED) \w+ at (-?\d+\.\d+),")


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _north_m(output: str) -> float:
    found = CANDIDATE.findall(output)
    assert found, output
    return (float(found[-1]) - HOME_LAT) * 111_195.0


@pytest.mark.slow
@pytest.mark.timeout(480)
@pytest.mark.parametrize(("autopilot", "mission_mode"), [("arducopter", "AUTO"), ("px4-sitl", "MISSION")])
def test_sim_up_search_rehearsal_on_the_real_autopilots(
    tmp_path: Path, models_dir: Path, autopilot: str, mission_mode: str
) -> None:
    backend_port, gcs_port = _free_port(socket.SOCK_STREAM), _free_port(socket.SOCK_DGRAM)
    command = [
        SIM, "up", "--autopilot", autopilot, "--scenario", "search", "--backend-port", str(backend_port),
        "--gcs-port", str(gcs_port), "--work-dir", str(tmp_path / "up"), "--model-dir", str(models_dir),
    ]  # fmt: skip
    stack = subprocess.Popen(
        command, cwd=REPO, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), start_new_session=True,
    )  # fmt: skip
    assert stack.stdout is not None
    printed: list[str] = []
    log = tmp_path / "up" / "companion.log"
    try:
        deadline = time.monotonic() + 180
        while not any("or decide on the supervisor page" in line for line in printed):
            line = stack.stdout.readline()
            assert line or stack.poll() is None, "cloudtrack-sim up ended:\n" + "".join(printed)
            printed.append(line)
            assert time.monotonic() < deadline, "cloudtrack-sim up did not come up:\n" + "".join(printed)
        text = "".join(printed)
        assert "camera world     'search' (seed 1)" in text and "survey           at 10 m with a 15 m" in text

        def run(words: list[str], timeout: float = 150) -> str:
            done = subprocess.run([GCS, *words[1:]], capture_output=True, text=True, timeout=timeout)
            out = done.stdout + done.stderr
            tail = log.read_text()[-3000:] if log.is_file() else ""
            assert done.returncode == 0, f"{shlex.join(words)}\n{out}\ncompanion log:\n{tail}"
            return out

        by_verb: dict[str, list[str]] = {}  # the printed commands, by what they do
        for words in (
            shlex.split(line.split("#")[0]) for line in printed if line.startswith("  cloudtrack-gcs")
        ):
            verb = next(
                w for w in words[1:] if w in ("survey", "mode", "start", "watch", "reject", "confirm")
            )
            by_verb[verb] = words
        assert "uploaded 7 items, read back and checked" in run(by_verb["survey"])
        assert by_verb["mode"][-1] == mission_mode
        assert f"HEARTBEAT shows {mission_mode}" in run(by_verb["mode"])
        assert "STARTED: a person in a green shirt (person)" in run(by_verb["start"])
        assert abs(_north_m(run(by_verb["watch"])) - LOOKALIKE_NORTH_M) < 5.0  # the look-alike first
        assert "REJECTED: supervisor rejected" in run(by_verb["reject"])
        assert abs(_north_m(run(by_verb["watch"])) - TARGET_NORTH_M) < 5.0  # the survey went on to the person
        assert "FOUND" in run(by_verb["confirm"])
    finally:
        stack.send_signal(signal.SIGINT)
        try:
            rest, _ = stack.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(stack.pid, signal.SIGKILL)
            rest, _ = stack.communicate()
    assert stack.returncode == 0 and rest.strip().endswith("stopped"), rest
