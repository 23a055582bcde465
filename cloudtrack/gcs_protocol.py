"""The GCS mission protocol over MAVLink, companion side, and the codec `cloudtrack-gcs` shares.

Mission start carries a free-text prompt, which no standard command has room for. It travels in TUNNEL
messages with a private payload type (PROMPT_PAYLOAD_TYPE, in the range >= 32768 MAVLink leaves to
private use), then MAV_CMD_USER_1 in a COMMAND_LONG announces it and is answered by COMMAND_ACK. Why
TUNNEL rather than chunked STATUSTEXT: TUNNEL is addressed (target_system/target_component), so an
autopilot routes it only to the link where the companion was seen instead of flooding every GCS console;
it holds 128 bytes per message, so a prompt needs one to four; it is signed like any message; and MAVProxy
sends it with its stock `message` command. Payload: version (1), mission id, chunk index, chunk count,
then UTF-8 bytes of "SUPERSET|PROMPT" (SUPERSET may be empty).

COMMAND_LONG (or COMMAND_INT, same params 1-4) to (vehicle, companion component), obeyed only from the
system ids in `[mavlink] gcs_system_ids`; anyone else is answered MAV_RESULT_DENIED and logged:
  MAV_CMD_USER_1 start:   p1 mission id (0-255), p2 chunk count, p3 allow engage (0/1), p4 text bytes,
                          p5 (COMMAND_INT: x) the fleet's on_find: 0 not set, 1 continue, 2 hold, 3 return
  MAV_CMD_USER_2 abort
  MAV_CMD_USER_3 confirm: p1 candidate number (0: the one awaiting the supervisor)
  MAV_CMD_USER_4 reject:  p1 candidate number (0: the one awaiting the supervisor)
  MAV_CMD_USER_5 status:  re-send the latest status line
plus the camera-tracking protocol: MAV_CMD_REQUEST_MESSAGE(CAMERA_INFORMATION) (and the older
MAV_CMD_REQUEST_CAMERA_INFORMATION), MAV_CMD_CAMERA_TRACK_RECTANGLE, MAV_CMD_CAMERA_TRACK_POINT,
MAV_CMD_CAMERA_STOP_TRACKING. docs/gcs-protocol.md has every field and sequence.
"""

from __future__ import annotations

import logging
import math
import re
import time
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from behaviors.geometry import Box
from behaviors.mission_commands import (
    AbortMission,
    ConfirmCandidate,
    MissionCommand,
    RejectCandidate,
    StartMission,
    StopTracking,
    TrackRectangle,
)
from cloudtrack.mavlink_connection import mavlink

log = logging.getLogger(__name__)

PROMPT_PAYLOAD_TYPE = 49421  # private TUNNEL payload type ("CLOUD" on a phone keypad, roughly)
PROMPT_FORMAT_VERSION = 1
CHUNK_HEADER = 4
CHUNK_TEXT_BYTES = 128 - CHUNK_HEADER
MAX_CHUNKS = 8
MAX_PROMPT_CHARS = 400
PROMPT_TTL_S = 60.0
ON_FIND_CODES = ("", "continue", "hold", "return")  # the start's p5

# Numbers from pymavlink's generated dialect, never written out here.
CMD_START, CMD_ABORT, CMD_CONFIRM, CMD_REJECT, CMD_STATUS = (
    int(mavlink.MAV_CMD_USER_1), int(mavlink.MAV_CMD_USER_2), int(mavlink.MAV_CMD_USER_3),
    int(mavlink.MAV_CMD_USER_4), int(mavlink.MAV_CMD_USER_5),
)  # fmt: skip
CMD_REQUEST_MESSAGE = int(mavlink.MAV_CMD_REQUEST_MESSAGE)
CMD_REQUEST_CAMERA_INFORMATION = int(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION)
CMD_CAMERA_TRACK_POINT = int(mavlink.MAV_CMD_CAMERA_TRACK_POINT)
CMD_CAMERA_TRACK_RECTANGLE = int(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE)
CMD_CAMERA_STOP_TRACKING = int(mavlink.MAV_CMD_CAMERA_STOP_TRACKING)
MSG_ID_CAMERA_INFORMATION = int(mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION)
CAMERA_COMMANDS = {
    CMD_REQUEST_MESSAGE, CMD_REQUEST_CAMERA_INFORMATION, CMD_CAMERA_TRACK_POINT, CMD_CAMERA_TRACK_RECTANGLE,
    CMD_CAMERA_STOP_TRACKING,
}  # fmt: skip
COMMAND_NAMES = {
    CMD_START: "start", CMD_ABORT: "abort", CMD_CONFIRM: "confirm", CMD_REJECT: "reject", CMD_STATUS: "status",
    CMD_CAMERA_TRACK_RECTANGLE: "track-rectangle", CMD_CAMERA_TRACK_POINT: "track-point",
    CMD_CAMERA_STOP_TRACKING: "stop-tracking",
}  # fmt: skip

MAV_RESULT_ACCEPTED = int(mavlink.MAV_RESULT_ACCEPTED)
MAV_RESULT_TEMPORARILY_REJECTED = int(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
MAV_RESULT_DENIED = int(mavlink.MAV_RESULT_DENIED)
MAV_RESULT_UNSUPPORTED = int(mavlink.MAV_RESULT_UNSUPPORTED)
MAV_RESULT_FAILED = int(mavlink.MAV_RESULT_FAILED)
# COMMAND_ACK results as the ground tools print them.
RESULT_NAMES = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
}
MAV_RESULT_IN_PROGRESS = int(mavlink.MAV_RESULT_IN_PROGRESS)
MAV_SEVERITY_CRITICAL = int(mavlink.MAV_SEVERITY_CRITICAL)
MAV_SEVERITY_WARNING = int(mavlink.MAV_SEVERITY_WARNING)
MAV_SEVERITY_NOTICE = int(mavlink.MAV_SEVERITY_NOTICE)
MAV_SEVERITY_INFO = int(mavlink.MAV_SEVERITY_INFO)
STATUSTEXT_BYTES = 50
NAMED_VALUE_BYTES = 10
CAMERA_CAP_FLAGS_HAS_TRACKING_POINT = int(mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT)
CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE = int(mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE)

_SUPERSET = re.compile(r"^[A-Za-z][A-Za-z _-]{0,31}$")


# ------------------------------------------------------------------------------------ prompt codec
def validate_prompt(prompt: str, superset: str = "") -> str:
    """The reason a prompt cannot be used, or "" when it can."""
    if not prompt.strip():
        return "the prompt is empty"
    if len(prompt) > MAX_PROMPT_CHARS:
        return f"the prompt has {len(prompt)} characters; at most {MAX_PROMPT_CHARS}"
    if any(unicodedata.category(c).startswith("C") for c in prompt):
        return "the prompt contains control characters"
    if "|" in superset or (superset and not _SUPERSET.match(superset)):
        return "the superset class must be a word like 'person' (letters, spaces, - or _; at most 32)"
    return ""


def encode_prompt(mission_id: int, superset: str, prompt: str) -> list[bytes]:
    """The TUNNEL payloads (each at most 128 bytes) carrying one mission's prompt."""
    reason = validate_prompt(prompt, superset)
    if reason:
        raise ValueError(reason)
    if not 0 <= mission_id <= 255:
        raise ValueError("mission id must be 0-255")
    text = f"{superset.strip()}|{prompt.strip()}".encode()
    pieces = [text[i : i + CHUNK_TEXT_BYTES] for i in range(0, len(text), CHUNK_TEXT_BYTES)]
    if len(pieces) > MAX_CHUNKS:
        raise ValueError(f"the prompt is too long for {MAX_CHUNKS} TUNNEL messages")
    return [bytes([PROMPT_FORMAT_VERSION, mission_id, i, len(pieces)]) + p for i, p in enumerate(pieces)]


@dataclass(frozen=True)
class PromptChunk:
    mission_id: int
    index: int
    count: int
    data: bytes


def decode_chunk(payload_type: int, payload: bytes) -> PromptChunk | None:
    """A prompt chunk from a TUNNEL payload (trimmed to payload_length); None if it is not one of ours."""
    if (
        payload_type != PROMPT_PAYLOAD_TYPE
        or len(payload) < CHUNK_HEADER
        or payload[0] != PROMPT_FORMAT_VERSION
    ):
        return None
    mission_id, index, count = payload[1], payload[2], payload[3]
    if not 0 < count <= MAX_CHUNKS or index >= count:
        return None
    return PromptChunk(mission_id, index, count, payload[CHUNK_HEADER:])


def parse_prompt_text(text: bytes) -> tuple[str, str]:
    """(superset, prompt) from the reassembled bytes; ValueError with the reason if unusable."""
    try:
        decoded = text.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError("the prompt is not valid UTF-8") from exc
    superset, sep, prompt = decoded.partition("|")
    if not sep:
        raise ValueError("the prompt text must be SUPERSET|PROMPT")
    reason = validate_prompt(prompt, superset)
    if reason:
        raise ValueError(reason)
    return superset.strip(), prompt.strip()


class PromptAssembler:
    """Collects chunks per mission id until the announcing command arrives."""

    def __init__(self) -> None:
        self._chunks: dict[int, tuple[float, int, dict[int, bytes]]] = {}

    def add(self, chunk: PromptChunk, now: float) -> None:
        _, count, parts = self._chunks.get(chunk.mission_id, (now, chunk.count, {}))
        if count != chunk.count:
            parts = {}  # a new prompt reusing the mission id replaces the old one
        parts[chunk.index] = chunk.data
        self._chunks[chunk.mission_id] = (now, chunk.count, parts)
        for mid in [m for m, (t, _, _) in self._chunks.items() if now - t > PROMPT_TTL_S]:
            del self._chunks[mid]

    def take(self, mission_id: int, count: int, length: int) -> bytes:
        """The assembled text; ValueError naming what is missing or inconsistent."""
        if mission_id not in self._chunks:
            raise LookupError(f"no prompt received for mission {mission_id}; send the TUNNEL chunks first")
        _, have_count, parts = self._chunks[mission_id]
        if have_count != count:
            raise LookupError(
                f"mission {mission_id}: {have_count} chunks announced in TUNNEL, {count} in the command"
            )
        missing = [i for i in range(count) if i not in parts]
        if missing:
            raise LookupError(f"mission {mission_id}: chunks {missing} missing")
        text = b"".join(parts[i] for i in range(count))
        if len(text) != length:
            raise LookupError(f"mission {mission_id}: {len(text)} bytes received, {length} announced")
        del self._chunks[mission_id]
        return text


# --------------------------------------------------------------------------------- status helpers
def statustext_chunks(text: str) -> list[tuple[bytes, int]]:
    """STATUSTEXT pieces of at most 50 bytes with their chunk_seq (MAVLink 2 long-text rule). A receiver
    knows the last chunk by its null terminator, so a long text of exactly 50k bytes ends with an empty one."""
    data = text.encode("utf-8")[: STATUSTEXT_BYTES * 20]
    pieces = [data[i : i + STATUSTEXT_BYTES] for i in range(0, max(len(data), 1), STATUSTEXT_BYTES)]
    if len(pieces) > 1 and len(pieces[-1]) == STATUSTEXT_BYTES:
        pieces.append(b"")
    return [(p, i) for i, p in enumerate(pieces)]


def value_name(name: str) -> bytes:
    encoded = name.encode("ascii", "replace")
    if not encoded or len(encoded) > NAMED_VALUE_BYTES:
        raise ValueError(f"NAMED_VALUE_FLOAT name {name!r} must be 1-{NAMED_VALUE_BYTES} ASCII characters")
    return encoded


# ------------------------------------------------------------------------------ companion handler
@dataclass(frozen=True)
class StartVerdict:
    """Whether a mission start may go ahead (the back-end can search for its prompt), and why not; or, for
    an accepted start, what the operator should know (the back-end did not answer: the search waits)."""

    accepted: bool
    reason: str = ""


# Asked before a start is delivered: the verdict, or None while it is being found out (`done()` is called
# once, from another thread, when it is known; a start asked again meanwhile gets None without a new call).
StartGate = Callable[[StartMission, Callable[[], None]], "StartVerdict | None"]
REASON_CHARS = 200  # a refusal's reason on the GCS: four STATUSTEXT chunks at most


def clip_reason(text: str, limit: int = REASON_CHARS) -> str:
    """A reason short enough for the GCS, cut at a word."""
    text = " ".join(text.split())
    if len(text) <= limit:
        return text
    return text[: limit - 1].rsplit(" ", 1)[0] + "…"


class GcsReplies(Protocol):
    """Where the handler delivers commands and sends replies; VehicleLink implements it."""

    def deliver(self, command: MissionCommand) -> None: ...

    def ack(self, msg: Any, result: int) -> None: ...  # sent as the component the command was addressed to
    def status(self, text: str, severity: int = MAV_SEVERITY_INFO) -> None: ...
    def camera_information(self, image_size: tuple[int, int], component: int) -> None: ...
    def latest_status(self) -> None: ...


class GcsProtocol:
    """Turns the GCS's COMMAND_LONG and TUNNEL messages addressed to this component into mission commands,
    delivered before the COMMAND_ACK goes out.

    The camera-tracking commands are also taken when addressed to `camera_component` (QGroundControl sends
    them only to camera components, 100-105); mission commands only to `component_id`.
    """

    def __init__(
        self,
        system_id: int,
        component_id: int,
        camera_component: int,
        image_size: Callable[[], tuple[int, int]],
        replies: GcsReplies,
        allowed_systems: frozenset[int] = frozenset({255}),
        start_gate: StartGate | None = None,
    ):
        self._allowed = allowed_systems
        self._start_gate = start_gate
        self._last_refusal_log = -math.inf
        self.refused = 0
        self._system = system_id
        self._component = component_id
        self._camera = camera_component
        self._image_size = image_size
        self._replies = replies
        self._prompts = PromptAssembler()

    def handle(self, msg: Any, now: float) -> None:
        mtype = msg.get_type()
        if mtype not in ("TUNNEL", "COMMAND_LONG", "COMMAND_INT") or msg.target_system != self._system:
            return
        ours = msg.target_component == self._component
        camera = bool(self._camera) and msg.target_component == self._camera and mtype != "TUNNEL"
        if not (ours or camera):
            return
        if msg.get_srcSystem() not in self._allowed:
            self._refuse(msg, mtype)
            return
        if mtype == "TUNNEL":
            chunk = decode_chunk(msg.payload_type, bytes(msg.payload[: max(0, min(msg.payload_length, 128))]))
            if chunk is not None:
                self._prompts.add(chunk, now)
        elif ours or msg.command in CAMERA_COMMANDS:
            self._command(msg)
        else:
            self._replies.ack(msg, MAV_RESULT_UNSUPPORTED)

    def _refuse(self, msg: Any, mtype: str) -> None:
        """A sender not on the allow-list: DENIED for a command, nothing for a TUNNEL; logged every 10 s
        at most."""
        self.refused += 1
        if mtype != "TUNNEL":
            self._replies.ack(msg, MAV_RESULT_DENIED)
        now = time.monotonic()
        if now - self._last_refusal_log >= 10.0:
            self._last_refusal_log = now
            log.warning(
                "refused %s from system %d component %d: not in [mavlink] gcs_system_ids (%d refused so far)",
                mtype if mtype == "TUNNEL" else COMMAND_NAMES.get(msg.command, str(msg.command)),
                msg.get_srcSystem(), msg.get_srcComponent(), self.refused,
            )  # fmt: skip

    def _command(self, msg: Any) -> None:
        cmd = msg.command
        name = COMMAND_NAMES.get(cmd, str(cmd))
        try:
            command = self._decode(msg)
        except LookupError as exc:  # incomplete: the GCS may resend
            log.warning("GCS %s refused: %s", name, exc)
            self._replies.ack(msg, MAV_RESULT_FAILED)
            self._replies.status(f"{name.upper()} FAILED: {exc}", MAV_SEVERITY_WARNING)
            return
        except ValueError as exc:  # malformed: resending the same will not help
            log.warning("GCS %s refused: %s", name, exc)
            self._replies.ack(msg, MAV_RESULT_DENIED)
            self._replies.status(f"{name.upper()} REFUSED: {exc}", MAV_SEVERITY_WARNING)
            return
        if command is None and cmd not in (CMD_STATUS, CMD_REQUEST_MESSAGE, CMD_REQUEST_CAMERA_INFORMATION):
            self._replies.ack(msg, MAV_RESULT_UNSUPPORTED)
            return
        verdict: StartVerdict | None = None
        if isinstance(command, StartMission) and self._start_gate is not None:
            start = command
            verdict = self._start_gate(start, lambda: self._start_decided(msg, start))
            if verdict is None:  # being asked: the final answer follows (MAVLink's long-running command)
                self._replies.ack(msg, MAV_RESULT_IN_PROGRESS)
                return
            if not verdict.accepted:
                self._refuse_start(msg, verdict.reason)
                return
        if command is not None:
            self._replies.deliver(command)  # before the ACK: whoever sees the ACK can rely on delivery
        self._replies.ack(msg, MAV_RESULT_ACCEPTED)
        if cmd == CMD_STATUS:
            self._replies.latest_status()
        elif cmd in (CMD_REQUEST_MESSAGE, CMD_REQUEST_CAMERA_INFORMATION):
            self._replies.camera_information(self._image_size(), msg.target_component)
        elif isinstance(command, StartMission):
            self._started(command, verdict)
            return
        log.info("GCS command %s accepted: %s", name, command)

    def _start_decided(self, msg: Any, start: StartMission) -> None:
        """The gate's verdict on a start answered IN_PROGRESS: the final COMMAND_ACK, and the start itself."""
        assert self._start_gate is not None
        verdict = self._start_gate(start, lambda: None)
        if verdict is None:
            return
        if not verdict.accepted:
            self._refuse_start(msg, verdict.reason)
            return
        self._replies.deliver(start)
        self._replies.ack(msg, MAV_RESULT_ACCEPTED)
        self._started(start, verdict)

    def _refuse_start(self, msg: Any, reason: str) -> None:
        log.warning("GCS start refused: %s", reason)
        self._replies.ack(msg, MAV_RESULT_DENIED)
        self._replies.status(f"START REFUSED: {clip_reason(reason)}", MAV_SEVERITY_WARNING)

    def _started(self, start: StartMission, verdict: StartVerdict | None = None) -> None:
        superset = f" ({start.superset})" if start.superset else ""
        self._replies.status(f"MISSION {start.mission_id} STARTED: {start.prompt}{superset}")
        if verdict is not None and verdict.reason:
            self._replies.status(clip_reason(verdict.reason), MAV_SEVERITY_WARNING)
        log.info("GCS command start accepted: %s", start)

    def _decode(self, msg: Any) -> MissionCommand | None:
        cmd, p = msg.command, (msg.param1, msg.param2, msg.param3, msg.param4)
        if cmd == CMD_START:
            mission_id, count, length = (
                _whole(p[0], 0, 255),
                _whole(p[1], 1, MAX_CHUNKS),
                _whole(p[3], 1, 1024),
            )
            fifth = msg.param5 if hasattr(msg, "param5") else float(getattr(msg, "x", 0))
            on_find = ON_FIND_CODES[_whole(fifth, 0, len(ON_FIND_CODES) - 1)]
            superset, prompt = parse_prompt_text(self._prompts.take(mission_id, count, length))
            return StartMission(
                prompt, superset, allow_engage=p[2] >= 0.5, mission_id=str(mission_id), on_find=on_find
            )
        if cmd == CMD_ABORT:
            return AbortMission("gcs")
        if cmd in (CMD_CONFIRM, CMD_REJECT):
            number = _whole(p[0], 0, 1_000_000)
            candidate = str(number) if number else ""
            return ConfirmCandidate(candidate, by="gcs") if cmd == CMD_CONFIRM else RejectCandidate(candidate)
        if cmd == CMD_CAMERA_TRACK_RECTANGLE:
            return TrackRectangle(self._rectangle(*p))
        if cmd == CMD_CAMERA_TRACK_POINT:
            # Radius is normalised to the image width (0 = one pixel); a tracker needs some box around it.
            x, y, radius = p[0], p[1], max(p[2], 0.02)
            width, height = self._image_size()
            half_y = radius * width / height
            return TrackRectangle(self._rectangle(x - radius, y - half_y, x + radius, y + half_y))
        if cmd == CMD_CAMERA_STOP_TRACKING:
            return StopTracking()
        if cmd in (CMD_REQUEST_MESSAGE, CMD_REQUEST_CAMERA_INFORMATION):
            if cmd == CMD_REQUEST_MESSAGE and _whole(p[0], 0, 1 << 24) != MSG_ID_CAMERA_INFORMATION:
                raise ValueError(f"message {int(p[0])} is not provided by the companion")
            return None
        return None

    def _rectangle(self, x1: float, y1: float, x2: float, y2: float) -> Box:
        values = (x1, y1, x2, y2)
        if not all(-0.5 <= v <= 1.5 for v in values) or x2 <= x1 or y2 <= y1:
            raise ValueError("the rectangle needs normalised corners 0..1 with top-left before bottom-right")
        width, height = self._image_size()
        box = Box.from_xyxy(x1 * width, y1 * height, x2 * width, y2 * height).clamped(width, height)
        if box.w < 1 or box.h < 1:
            raise ValueError("the rectangle lies outside the image")
        return box


def _whole(value: float, low: int, high: int) -> int:
    if not math.isfinite(value) or not low <= value <= high or value != int(value):
        raise ValueError(f"expected a whole number {low}-{high}, got {value}")
    return int(value)
