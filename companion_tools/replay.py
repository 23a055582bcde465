"""Re-running a recorded mission through the behaviours and finding where the decisions differ.

The flight record (`companion.flight_record`) holds a `replay_start` entry (the mission config and the
behaviour state just before the mission started) and then every `step`: the event, the actions the
state machine returned, and the mode it ended in. Replaying feeds the same events, in order, through
today's `behaviors.mission.step` (optionally with another configuration) and compares actions and
modes step by step. After a difference the replay carries on from its own state, so later steps show
how far the change propagates.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from behaviors import event_codec
from behaviors.mission import State, step
from behaviors.mission_config import MissionConfig
from companion.flight_record import EVENTS_FILE, read_events


class RecordError(Exception):
    """A folder that is not a replayable flight record; the message says what is missing."""


@dataclass(frozen=True)
class RecordedStep:
    index: int
    event: dict[str, Any]
    actions: list[dict[str, Any]]
    mode: str


@dataclass(frozen=True)
class Difference:
    index: int
    time_s: float
    event_type: str
    recorded_mode: str
    replayed_mode: str
    recorded_actions: list[dict[str, Any]]
    replayed_actions: list[dict[str, Any]]

    def describe(self) -> str:
        lines = [f"step {self.index} at t={self.time_s:.3f} s ({self.event_type}):"]
        if self.recorded_mode != self.replayed_mode:
            lines.append(f"  mode: recorded {self.recorded_mode}, replayed {self.replayed_mode}")
        if self.recorded_actions != self.replayed_actions:
            lines.append(f"  recorded actions: {_compact(self.recorded_actions)}")
            lines.append(f"  replayed actions: {_compact(self.replayed_actions)}")
        return "\n".join(lines)


@dataclass(frozen=True)
class ReplayReport:
    folder: Path
    steps: int
    differences: tuple[Difference, ...]

    @property
    def identical(self) -> bool:
        return not self.differences

    def to_json(self) -> dict[str, Any]:
        return {
            "folder": str(self.folder),
            "steps": self.steps,
            "differences": [vars(d) for d in self.differences],
        }


@dataclass(frozen=True)
class Recording:
    config: MissionConfig
    start: State
    steps: tuple[RecordedStep, ...]


def _compact(actions: list[dict[str, Any]]) -> str:
    text = json.dumps(actions, separators=(",", ":"))
    return text if len(text) <= 400 else text[:397] + "..."


def load_recording(folder: Path) -> Recording:
    """The recorded config, start state and steps of a mission folder."""
    if not (folder / EVENTS_FILE).is_file():
        raise RecordError(f"{folder}: no {EVENTS_FILE}; not a flight record folder")
    entries = read_events(folder)
    start = next((e for e in entries if e.get("kind") == "replay_start"), None)
    if start is None:
        raise RecordError(
            f"{folder}: the record has no replay_start entry (recorded before a mission started?)"
        )
    try:
        config = event_codec.decode_as(start["config"], MissionConfig)
        state = event_codec.decode_as(start["state"], State)
    except (KeyError, event_codec.CodecError) as exc:
        raise RecordError(f"{folder}: replay_start cannot be decoded: {exc}") from exc
    steps: list[RecordedStep] = []
    for entry in entries:
        if entry.get("kind") != "step":
            continue
        if not isinstance(entry.get("event"), dict) or not isinstance(entry.get("actions"), list):
            raise RecordError(f"{folder}: step {len(steps)} has no event or actions")
        steps.append(RecordedStep(len(steps), entry["event"], entry["actions"], str(entry.get("mode", ""))))
    return Recording(config, state, tuple(steps))


def replay(
    recording: Recording,
    folder: Path,
    config: MissionConfig | None = None,
    progress: Callable[[Iterable[RecordedStep]], Iterable[RecordedStep]] = lambda steps: steps,
) -> ReplayReport:
    """Run every recorded event through `step` (with `config`, default: the recorded one) and compare."""
    mission_config = config or recording.config
    state = recording.start
    differences: list[Difference] = []
    for recorded in progress(recording.steps):
        try:
            event = event_codec.decode_event(recorded.event)
        except event_codec.CodecError as exc:
            raise RecordError(f"{folder}: step {recorded.index}: {exc}") from exc
        state, actions = step(state, event, mission_config)
        replayed = [event_codec.encode_action(a) for a in actions]
        # Compare as JSON text: the record went through JSON too (tuples became lists, NaN a string).
        same_actions = json.dumps(replayed) == json.dumps(recorded.actions)
        if not same_actions or state.mode.value != recorded.mode:
            differences.append(
                Difference(
                    recorded.index,
                    event.time_s,
                    type(event).__name__,
                    recorded.mode,
                    state.mode.value,
                    recorded.actions,
                    json.loads(json.dumps(replayed)),
                )
            )
    return ReplayReport(folder, len(recording.steps), tuple(differences))
