"""Replaying a flight record through the behaviours: identical decisions, what-if configs, bad records."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from behaviors.actions import BackendQuery
from behaviors.detection import Detection, Verdict
from behaviors.events import BackendAnswer, Event, GcsCommand, TimerTick
from behaviors.geometry import Box
from behaviors.mission import initial_state, step
from behaviors.mission_commands import ConfirmCandidate, StartMission
from behaviors.mission_config import MissionConfig
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult
from companion.flight_record import EVENTS_FILE, FlightRecorder, FlightRecordObserver, read_events
from companion_tools.replay import RecordError, load_recording, replay

CLI = [sys.executable, "-m", "companion.cli"]


def fly_scripted_mission(root: Path, mission_id: str = "m-1") -> list[Path]:
    """Drive the real state machine the way the main loop does, with the flight record observing it."""
    config = MissionConfig()
    folders: list[Path] = []

    def open_mission(mid: str) -> FlightRecorder:
        recorder = FlightRecorder(root, "drone-1", mid, 50_000_000)
        folders.append(recorder.folder)
        return recorder

    observer = FlightRecordObserver(config, open_mission)
    state = initial_state(config)

    def feed(event: Event) -> tuple:
        nonlocal state
        observer.on_event(event)
        state, actions = step(state, event, config)
        observer.on_step(event, state, actions)
        return actions

    def telemetry(t: float) -> Telemetry:
        return Telemetry(t, 47.3977, 8.5456, 20.0, yaw=0.3, armed=True, mode="GUIDED", offboard_active=True)

    feed(telemetry(0.0))
    feed(TimerTick(0.05))  # before the mission: not recorded, but part of the state replay starts from
    actions = feed(GcsCommand(0.1, StartMission("a man in a red shirt", mission_id=mission_id)))
    query = next(a for a in actions if isinstance(a, BackendQuery))
    found = Detection(
        Box(300, 200, 40, 100), 0.9, verdict=Verdict.YES, justification="red shirt", candidate_id="c1"
    )
    feed(BackendAnswer(1.0, query.query_id, 5, (found,)))
    observer.on_health(1.0, True, ())
    for i in range(30):
        t = 1.0 + 0.1 * i
        feed(telemetry(t))
        feed(TrackResult(6 + i, t, Box(300 + 2 * i, 200 + i, 40, 100), 0.9, True))
        feed(TimerTick(t))
    feed(GcsCommand(4.1, ConfirmCandidate("c1")))
    assert state.mode.value == "CONFIRMED"
    observer.close()
    return folders


def run_replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, "replay", *args], capture_output=True, text=True, timeout=120)


def test_record_holds_replay_start_steps_and_readable_entries(tmp_path: Path) -> None:
    (folder,) = fly_scripted_mission(tmp_path)
    assert folder.name.endswith("_drone-1_m-1")
    entries = read_events(folder)
    kinds = [e["kind"] for e in entries]
    assert kinds[:2] == ["recording_started", "replay_start"] and kinds[-1] == "recording_closed"
    assert kinds.count("step") == 1 + 1 + 30 * 3 + 1  # start, answer, 30 x (telemetry, track, tick), confirm
    states = [(e["old"], e["new"]) for e in entries if e["kind"] == "state"]
    assert states[0] == ("IDLE", "SEARCHING") and states[-1][1] == "CONFIRMED"
    answer = next(e for e in entries if e["kind"] == "backend_answer")
    assert answer["candidates"] == [{"id": "c1", "verdict": "yes", "justification": "red shirt"}]
    decision = next(e for e in entries if e["kind"] == "supervisor_decision")
    assert decision == {**decision, "decision": "confirm", "candidate_id": "c1", "time_s": 4.1}
    assert any(e["kind"] == "health" and e["healthy"] for e in entries)
    assert all(isinstance(e["t"], float) for e in entries)


def test_recorded_mission_replays_with_no_decision_differences(tmp_path: Path) -> None:
    (folder,) = fly_scripted_mission(tmp_path)
    report = replay(load_recording(folder), folder)
    assert report.steps == 93 and report.identical

    result = run_replay(str(folder))
    assert result.returncode == 0, result.stderr
    assert "93 steps replayed" in result.stdout and "no decision differs" in result.stdout
    assert "replay" in result.stderr and "93/93" in result.stderr  # the progress bar


def test_a_different_configuration_shows_which_decisions_change(tmp_path: Path) -> None:
    (folder,) = fly_scripted_mission(tmp_path)
    out = tmp_path / "replay.json"
    result = run_replay(
        str(folder), "--set", "behavior.standoff_m=30", "--json", str(out), "--show", "2", "--no-progress"
    )
    assert result.returncode == 1, result.stderr
    assert "steps differ with the given configuration" in result.stdout
    assert "SendSetpoint" in result.stdout and "more (see --json)" in result.stdout
    report = json.loads(out.read_text())
    assert report["steps"] == 93 and len(report["differences"]) > 2
    first = report["differences"][0]
    assert first["event_type"] == "TrackResult" and first["recorded_actions"] != first["replayed_actions"]


def test_a_tampered_decision_is_found_at_its_step(tmp_path: Path) -> None:
    (folder,) = fly_scripted_mission(tmp_path)
    path = folder / EVENTS_FILE
    lines = path.read_text().splitlines()
    steps = [i for i, line in enumerate(lines) if json.loads(line)["kind"] == "step"]
    entry = json.loads(lines[steps[-1]])
    assert entry["mode"] == "CONFIRMED"
    entry["mode"] = "REJECTED"  # as if the flown code had decided otherwise
    lines[steps[-1]] = json.dumps(entry)
    path.write_text("\n".join(lines) + "\n")
    report = replay(load_recording(folder), folder)
    (difference,) = report.differences
    assert difference.index == 92 and difference.event_type == "GcsCommand"
    assert "mode: recorded REJECTED, replayed CONFIRMED" in difference.describe()


@pytest.mark.slow
def test_unusable_records_are_clear_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    result = run_replay(str(empty), "--no-progress")
    assert result.returncode == 2 and "not a flight record folder" in result.stderr

    idle = FlightRecorder(tmp_path, "drone-1", "idle", 10_000_000)
    idle.close()
    with pytest.raises(RecordError, match="no replay_start"):
        load_recording(idle.folder)

    (folder,) = fly_scripted_mission(tmp_path / "bad")
    path = folder / EVENTS_FILE
    lines = path.read_text().splitlines()
    index = next(i for i, line in enumerate(lines) if json.loads(line)["kind"] == "step")
    entry = json.loads(lines[index])
    entry["event"] = {"type": "NoSuchEvent", "time_s": 1.0}
    lines[index] = json.dumps(entry)
    path.write_text("\n".join(lines) + "\n")
    result = run_replay(str(folder), "--no-progress")
    assert result.returncode == 2 and "step 0" in result.stderr and "Traceback" not in result.stderr

    bad_config = run_replay(str(folder), "--set", "behavior.standoff_m=-3")
    assert bad_config.returncode == 2 and "behavior.standoff_m" in bad_config.stderr


def test_each_mission_gets_its_own_folder(tmp_path: Path) -> None:
    config = MissionConfig()
    opened: list[str] = []

    def open_mission(mid: str) -> FlightRecorder:
        opened.append(mid)
        return FlightRecorder(tmp_path, "drone-1", mid, 10_000_000)

    observer = FlightRecordObserver(config, open_mission)
    state = initial_state(config)
    for t, mid in ((0.0, "first"), (1.0, "second")):
        event = GcsCommand(t, StartMission("a person", mission_id=mid))
        state, actions = step(state, event, config)
        observer.on_step(event, state, actions)
    observer.close()
    assert opened == ["first", "second"]
    assert sorted(p.name.split("_")[-1] for p in tmp_path.iterdir()) == ["first", "second"]
