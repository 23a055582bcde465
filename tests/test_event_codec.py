"""The event/action codec: lossless JSON round trip, clear errors, and replay of a recorded mission."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from behaviors.actions import (
    Action,
    BackendQuery,
    FlightMode,
    GcsMessage,
    Hold,
    JudgeCandidates,
    QueryPurpose,
    ReleaseControl,
    RememberRejection,
    ReportCandidate,
    RequestMode,
    SendSetpoint,
    TrackerInit,
    TrackerStop,
)
from behaviors.detection import Detection, Verdict
from behaviors.event_codec import (
    CodecError,
    decode_action,
    decode_as,
    decode_event,
    encode,
    encode_action,
    encode_event,
)
from behaviors.events import (
    AutopilotLinkLost,
    BackendAnswer,
    BackendUnreachable,
    Event,
    GcsCommand,
    PilotTakeover,
    TimerTick,
)
from behaviors.geolocation import GeoEstimate
from behaviors.geometry import Box
from behaviors.mission import State, initial_state, step
from behaviors.mission_commands import (
    AbortMission,
    ConfirmCandidate,
    RejectCandidate,
    StartMission,
    StopTracking,
    TrackRectangle,
)
from behaviors.mission_config import ConfirmAction, LostAction, MissionConfig
from behaviors.setpoint import Setpoint
from behaviors.telemetry import Telemetry
from behaviors.track_result import TrackResult

floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
finite = st.floats(-1e6, 1e6)
text = st.text(max_size=20)
boxes = st.builds(Box, floats, floats, floats, floats)
detections = st.builds(
    Detection,
    boxes,
    floats,
    text,
    st.sampled_from(Verdict),
    text,
    text,
    st.lists(finite, max_size=6).map(tuple),
)
commands = st.one_of(
    st.builds(StartMission, text, text, st.booleans(), text),
    st.builds(AbortMission, text),
    st.builds(ConfirmCandidate, text),
    st.builds(RejectCandidate, text),
    st.builds(TrackRectangle, boxes),
    st.just(StopTracking()),
)
events: st.SearchStrategy[Event] = st.one_of(
    st.builds(
        TrackResult,
        st.integers(0, 10**9),
        finite,
        st.one_of(st.none(), boxes),
        st.one_of(st.none(), floats),
        st.booleans(),
        text,
    ),
    st.builds(
        BackendAnswer,
        finite,
        st.integers(0, 10**6),
        st.integers(-1, 10**9),
        st.lists(detections, max_size=4).map(tuple),
    ),
    st.builds(
        Telemetry,
        finite,
        floats,
        floats,
        floats,
        floats,
        floats,
        floats,
        floats,
        floats,
        floats,
        st.booleans(),
        text,
        st.booleans(),
    ),
    st.builds(GcsCommand, finite, commands),
    st.builds(TimerTick, floats),
    st.builds(BackendUnreachable, finite, text),
    st.builds(AutopilotLinkLost, finite),
    st.builds(PilotTakeover, finite, text),
)
geo = st.builds(GeoEstimate, finite, finite, finite, finite, finite, finite, floats)
actions: st.SearchStrategy[Action] = st.one_of(
    st.builds(SendSetpoint, st.builds(Setpoint, floats, floats, floats, floats)),
    st.builds(Hold, text),
    st.builds(ReleaseControl, text),
    st.builds(RequestMode, st.sampled_from(FlightMode), text),
    st.builds(GcsMessage, text, st.sampled_from(["info", "warning", "critical"])),
    st.builds(
        BackendQuery,
        st.integers(0, 10**6),
        st.sampled_from(QueryPurpose),
        text,
        text,
        st.one_of(st.none(), boxes),
    ),
    st.builds(TrackerInit, boxes, st.integers(-1, 10**6), text, st.booleans()),
    st.builds(TrackerStop, text),
    st.builds(
        JudgeCandidates,
        st.integers(0, 10**6),
        st.lists(detections, max_size=3).map(tuple),
        st.lists(st.integers(0, 2), max_size=3).map(tuple),
    ),
    st.builds(ReportCandidate, text, text, st.sampled_from(Verdict), st.one_of(st.none(), geo), boxes, text),
    st.builds(RememberRejection, text, st.one_of(st.none(), geo), st.lists(finite, max_size=4).map(tuple)),
)


def through_json(data: Any) -> Any:
    return json.loads(json.dumps(data, allow_nan=False))  # strict JSON: no NaN/Infinity literals


def same(a: object, b: object) -> bool:
    """Equal, with NaN equal to NaN (dataclass equality says NaN != NaN)."""
    return json.dumps(encode(a), allow_nan=False, sort_keys=True) == json.dumps(
        encode(b), allow_nan=False, sort_keys=True
    )


@settings(max_examples=300, deadline=None)
@given(events)
def test_every_event_round_trips(event: Event) -> None:
    decoded = decode_event(through_json(encode_event(event)))
    assert type(decoded) is type(event)
    assert same(decoded, event)
    if all(math.isfinite(x) for x in _floats(encode(event))):
        assert decoded == event


@settings(max_examples=300, deadline=None)
@given(actions)
def test_every_action_round_trips(action: Action) -> None:
    decoded = decode_action(through_json(encode_action(action)))
    assert type(decoded) is type(action) and same(decoded, action)
    if all(math.isfinite(x) for x in _floats(encode(action))):
        assert decoded == action


def _floats(data: Any) -> list[float]:
    if isinstance(data, dict):
        return [x for v in data.values() for x in _floats(v)]
    if isinstance(data, list):
        return [x for v in data for x in _floats(v)]
    if isinstance(data, str) and data in ("NaN", "Infinity", "-Infinity"):
        return [math.nan]
    return [float(data)] if isinstance(data, float) else []


def test_encoding_is_readable_and_keeps_types() -> None:
    event = BackendAnswer(
        2.5,
        7,
        120,
        (Detection(Box(1, 2, 3, 4), 0.8, verdict=Verdict.YES, candidate_id="c1", signature=(0.5, 0.5)),),
    )
    data = encode_event(event)
    assert data["type"] == "BackendAnswer" and data["candidates"][0]["verdict"] == "yes"
    assert data["candidates"][0]["box"] == {"type": "Box", "x": 1, "y": 2, "w": 3, "h": 4}
    assert decode_event(data) == event
    tick = encode_event(TimerTick(math.inf))
    assert tick == {"type": "TimerTick", "time_s": "Infinity"}
    assert decode_event(tick) == TimerTick(math.inf)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"type": "Teleport", "time_s": 1.0}, "'Teleport' is not one of"),
        ({"type": "TimerTick"}, "missing field 'time_s'"),
        ({"type": "TimerTick", "time_s": "soon"}, "$.time_s: expected a number"),
        ({"type": "TimerTick", "time_s": 1.0, "extra": 1}, "unknown field(s) ['extra']"),
        (
            {"type": "GcsCommand", "time_s": 1.0, "command": {"type": "StartMission"}},
            "$.command: missing field 'prompt'",
        ),
        (
            {"type": "GcsCommand", "time_s": 1.0, "command": {"type": "TimerTick", "time_s": 1}},
            "$.command: type 'TimerTick'",
        ),
        (
            {"type": "TrackResult", "frame_id": 1.5, "time_s": 0, "box": None, "score": None, "ok": True},
            "$.frame_id: expected an integer",
        ),
        (
            {"type": "TrackResult", "frame_id": 1, "time_s": 0, "box": None, "score": None, "ok": 1},
            "$.ok: expected true or false",
        ),
        (
            {"type": "BackendAnswer", "time_s": 0, "query_id": 1, "keyframe_id": 1, "candidates": {}},
            "$.candidates: expected a list",
        ),
        (
            {
                "type": "BackendAnswer",
                "time_s": 0,
                "query_id": 1,
                "keyframe_id": 1,
                "candidates": [
                    {
                        "type": "Detection",
                        "box": {"type": "Box", "x": 0, "y": 0, "w": 1, "h": 1},
                        "score": 1,
                        "verdict": "maybe",
                    }
                ],
            },
            "$.candidates[0].verdict: 'maybe' is not a Verdict",
        ),
        ([1, 2], "fits none of"),
        (None, "null is not allowed"),
    ],
)
def test_malformed_encodings_name_the_problem(data: Any, message: str) -> None:
    with pytest.raises(CodecError) as info:
        decode_event(data)
    assert message in str(info.value)


def test_malformed_action_is_an_error() -> None:
    with pytest.raises(CodecError, match="expected type 'FlightMode'|is not a FlightMode"):
        decode_action({"type": "RequestMode", "mode": "acro", "reason": ""})


def test_state_and_config_round_trip() -> None:
    config = replace(
        MissionConfig(), lost_action=LostAction.RTL, on_confirm=ConfirmAction.ORBIT, accept_uncertain=True
    )
    assert decode_as(through_json(encode(config)), MissionConfig) == config
    state, _ = step(initial_state(config), GcsCommand(1.0, StartMission("a man in a gray shirt")), config)
    assert decode_as(through_json(encode(state)), State) == state


def _recorded_mission(config: MissionConfig) -> list[Event]:
    box_far = Box(312, 120, 16, 40)
    box_near = Box(312, 300, 16, 50)
    evs: list[Event] = [
        Telemetry(0.0, 47.0, 8.0, 20.0, offboard_active=True, mode="GUIDED"),
        GcsCommand(0.1, StartMission("an injured man in a gray shirt", allow_engage=True)),
        TimerTick(0.6),
        TimerTick(1.2),
        BackendAnswer(
            1.5,
            1,
            30,
            (Detection(box_far, 0.9, verdict=Verdict.YES, justification="gray shirt", candidate_id="c1"),),
        ),
    ]
    t = 1.6
    for i in range(40):
        box = box_far if i < 20 else box_near
        evs.append(TrackResult(100 + i, t, box, 0.9, True))
        evs.append(Telemetry(t, 47.0, 8.0, 20.0, yaw=0.01 * i, offboard_active=True, mode="GUIDED"))
        evs.append(TimerTick(t))
        t += 0.1
    evs += [
        TrackResult(200, t, None, 0.1, False, "score"),
        TimerTick(t + 2.0),
        BackendAnswer(t + 2.1, 2, 90, (Detection(box_near, 0.8, verdict=Verdict.YES, candidate_id="c9"),)),
        TrackResult(201, t + 2.2, box_near, 0.9, True),
        GcsCommand(t + 3.0, RejectCandidate()),
        TimerTick(t + 3.1),
        GcsCommand(t + 4.0, AbortMission("done")),
    ]
    return evs


def test_replaying_a_recorded_mission_gives_the_same_decisions() -> None:
    config = MissionConfig()
    recorded = _recorded_mission(config)
    state = initial_state(config)
    log: list[str] = []
    for event in recorded:
        state, acts = step(state, event, config)
        log.append(
            json.dumps(
                {"event": encode_event(event), "actions": [encode_action(a) for a in acts]}, allow_nan=False
            )
        )
    kinds = {
        json.loads(line)["actions"][i]["type"]
        for line in log
        for i in range(len(json.loads(line)["actions"]))
    }
    assert {"SendSetpoint", "TrackerInit", "ReportCandidate", "RememberRejection", "Hold"} <= kinds
    # Replay from the record alone.
    replay_config = decode_as(through_json(encode(config)), MissionConfig)
    replayed = initial_state(replay_config)
    for line in log:
        entry = json.loads(line)
        replayed, acts = step(replayed, decode_event(entry["event"]), replay_config)
        assert [encode_action(a) for a in acts] == entry["actions"]
    assert replayed == state
