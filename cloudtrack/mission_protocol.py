"""The MAVLink mission protocol, ground side: upload, download, clear, set and read the current item.

https://mavlink.io/en/services/mission.html, as ArduPilot and PX4 answer it:
- upload: MISSION_COUNT; the autopilot asks for each item with MISSION_REQUEST_INT (ArduPilot also uses the
  older MISSION_REQUEST: both are answered with MISSION_ITEM_INT) and ends with MISSION_ACK;
- download: MISSION_REQUEST_LIST -> MISSION_COUNT, MISSION_REQUEST_INT -> MISSION_ITEM_INT per item, our
  MISSION_ACK;
- clear: MISSION_CLEAR_ALL -> MISSION_ACK; set current: MISSION_SET_CURRENT -> MISSION_CURRENT;
- every step is retried after `step_s` (1.5 s, the protocol's default) up to `retries` (5) times.
ArduPilot keeps its home position as item 0 of the mission (its items start at 1; what is uploaded there is
ignored and a download returns the current home); PX4's items start at 0. `MissionClient` takes and returns
the mission without that home item and reports sequence numbers as the autopilot numbers them
(`first_seq`), as MISSION_CURRENT and QGroundControl show them.

Nothing half uploaded is left active. ArduPilot writes each item into its mission as it arrives (it truncates
the stored mission to the new count first), so an upload that stops midway leaves a mix of new and old
items that AUTO would fly; PX4 writes into a spare slot and switches only on its final MISSION_ACK. When an
upload fails after the autopilot began taking items, `upload` therefore clears the mission (MISSION_CLEAR_ALL)
and says so: an empty mission cannot be flown (ArduCopter refuses AUTO, PX4 holds), whereas restoring the
previous mission would be a second upload over the same failing link, and the old plan was for another
search. An upload refused at MISSION_COUNT (e.g. more items than the autopilot stores) changes nothing on
either autopilot, and the error says the previous mission is unchanged. Uploading while the vehicle flies
its mission is refused by the caller (`gcs/survey_command.py`): ArduPilot cannot clear a running mission.
`gcs/fleet_replan.py` only appends to a running mission (every item the same, at the same number) and
flags the item PX4 is to begin the new mission at (`upload(items, current=N)`).

Works over any `MissionLink` (a `MavlinkEndpoint`, or the companion's link with a queue in front) and is
not thread-safe: one transfer at a time per link, as the protocol itself allows.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol

from behaviors.mission_items import FRAME_GLOBAL, INT_FRAMES, NAV_WAYPOINT, MissionItem

MISSION_TYPE_MISSION = 0
MAV_MISSION_ACCEPTED = 0
MAV_MISSION_ERROR = 1
MAV_MISSION_NO_SPACE = 4
MAV_MISSION_INVALID_SEQUENCE = 13
MAV_MISSION_OPERATION_CANCELLED = 15
MAV_CMD_REQUEST_MESSAGE = 512
MISSION_CURRENT_ID = 42
# Every MAV_MISSION_RESULT with what it means for the operator, in one line.
MISSION_RESULTS: dict[int, tuple[str, str]] = {
    0: ("ACCEPTED", "accepted"),
    1: ("ERROR", "the autopilot is not accepting mission changes now (a running mission cannot be cleared)"),
    2: ("UNSUPPORTED_FRAME", "an item's coordinate frame is not supported by this autopilot"),
    3: ("UNSUPPORTED", "an item's command is not supported by this autopilot"),
    4: ("NO_SPACE", "more items than the autopilot can store"),
    5: ("INVALID", "an item has an invalid parameter"),
    6: ("INVALID_PARAM1", "an item's param1 is invalid"),
    7: ("INVALID_PARAM2", "an item's param2 is invalid"),
    8: ("INVALID_PARAM3", "an item's param3 is invalid"),
    9: ("INVALID_PARAM4", "an item's param4 is invalid"),
    10: ("INVALID_PARAM5_X", "an item's latitude (x / param5) is invalid"),
    11: ("INVALID_PARAM6_Y", "an item's longitude (y / param6) is invalid"),
    12: ("INVALID_PARAM7", "an item's altitude (z / param7) is invalid"),
    13: ("INVALID_SEQUENCE", "an item arrived out of sequence"),
    14: ("DENIED", "the autopilot refuses mission changes from us (another ground station is uploading?)"),
    15: ("OPERATION_CANCELLED", "the autopilot cancelled the transfer (it timed out waiting for an item)"),
}


def mission_result_reason(code: int) -> str:
    """'NAME (what it means)' for a MAV_MISSION_RESULT."""
    name, reason = MISSION_RESULTS.get(code, (f"result {code}", "an unknown MAV_MISSION_RESULT"))
    return f"{name} ({reason})"


class MissionLink(Protocol):
    """What a transfer needs from a link (`cloudtrack.mavlink_connection.MavlinkEndpoint` has it)."""

    def send(self, build: Callable[[Any], Any]) -> bool: ...

    def receive(self, timeout: float) -> Any | None: ...


class MissionError(Exception):
    """A transfer that failed; the message is one line. `result` is the MAV_MISSION_RESULT if one came."""

    def __init__(self, message: str, result: int | None = None):
        super().__init__(message)
        self.result = result


@dataclass(frozen=True)
class MissionTimeouts:
    step_s: float = 1.5  # wait this long for the answer to each message before sending it again
    retries: int = 5


@dataclass(frozen=True)
class MissionCurrent:
    """MISSION_CURRENT: the item the autopilot flies to (its own numbering), and MAVLink 2's extensions
    where the autopilot fills them (`total`: its item count; `state`: MISSION_STATE)."""

    seq: int
    total: int | None = None
    state: int | None = None


@dataclass(frozen=True)
class DownloadedMission:
    items: tuple[MissionItem, ...]  # without ArduPilot's home item
    home: MissionItem | None  # ArduPilot's item 0 (its home position); None on PX4
    first_seq: int  # the autopilot's number for items[0]


def item_from_message(msg: Any) -> MissionItem:
    """A MISSION_ITEM_INT (or a float MISSION_ITEM, converted) as a MissionItem."""
    if msg.get_type() == "MISSION_ITEM":
        x, y = round(msg.x * 1e7), round(msg.y * 1e7)
    else:
        x, y = int(msg.x), int(msg.y)
    return MissionItem(
        int(msg.command), int(msg.frame), float(msg.param1), float(msg.param2), float(msg.param3),
        float(msg.param4), x, y, float(msg.z), bool(msg.autocontinue),
    )  # fmt: skip


def send_item(mav: Any, target: tuple[int, int], seq: int, item: MissionItem, current: bool = False) -> None:
    mav.mission_item_int_send(
        target[0], target[1], seq, item.frame, item.command, int(current), int(item.autocontinue),
        item.param1, item.param2, item.param3, item.param4, item.x, item.y, item.z, MISSION_TYPE_MISSION,
    )  # fmt: skip


# ArduPilot's item 0: overwritten by the vehicle's home, whatever is sent.
HOME_PLACEHOLDER = MissionItem(NAV_WAYPOINT, FRAME_GLOBAL, 0.0, 0.0, 0.0, 0.0, 0, 0, 0.0)


class MissionClient:
    """The mission protocol towards one autopilot (`target`: its system and component) on `link`."""

    def __init__(
        self,
        link: MissionLink,
        autopilot: str,
        target: tuple[int, int] = (1, 1),
        source: tuple[int, int] | None = None,
        timeouts: MissionTimeouts = MissionTimeouts(),
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if autopilot not in ("ardupilot", "px4"):
            raise ValueError(f"unknown autopilot {autopilot!r}: ardupilot or px4")
        self.link = link
        self.autopilot = autopilot
        self.target = target
        self.source = source  # our (system, component): answers addressed to someone else are ignored
        self.timeouts = timeouts
        self._clock = clock

    @property
    def first_seq(self) -> int:
        """The autopilot's number for the first item we upload (ArduPilot keeps home at 0)."""
        return 1 if self.autopilot == "ardupilot" else 0

    # ------------------------------------------------------------------------------------ plumbing
    def _from_target(self, msg: Any) -> bool:
        if msg.get_srcSystem() != self.target[0] or msg.get_srcComponent() != self.target[1]:
            return False
        if self.source is not None and hasattr(msg, "target_system"):
            to = (msg.target_system, getattr(msg, "target_component", 0))
            if to[0] not in (0, self.source[0]) or to[1] not in (0, self.source[1]):
                return False
        return getattr(msg, "mission_type", MISSION_TYPE_MISSION) == MISSION_TYPE_MISSION

    def _exchange(self, send: Callable[[Any], Any], accept: Callable[[Any], Any], what: str) -> Any:
        """Send, and re-send every `step_s`, until `accept(msg)` returns something other than None."""
        for _ in range(self.timeouts.retries + 1):
            self.link.send(send)
            deadline = self._clock() + self.timeouts.step_s
            while (left := deadline - self._clock()) > 0:
                msg = self.link.receive(min(left, 0.2))
                if msg is None or not self._from_target(msg):
                    continue
                answer = accept(msg)
                if answer is not None:
                    return answer
        raise MissionError(
            f"no answer to {what} from {self.target[0]}/{self.target[1]} after {self.timeouts.retries + 1} "
            f"tries {self.timeouts.step_s:g} s apart: is the autopilot connected?"
        )

    def _ack_of(self, msg: Any) -> int | None:
        return int(msg.type) if msg.get_type() == "MISSION_ACK" else None

    # -------------------------------------------------------------------------------------- upload
    def upload(self, items: Sequence[MissionItem], current: int | None = None) -> None:
        """Replace the autopilot's mission with `items` (without ArduPilot's home item); MissionError with
        a one-line reason when it fails, after clearing what the autopilot took of it (module docstring).
        `current` (the autopilot's numbering): the item sent flagged current, where PX4 begins the new mission
        (ArduPilot ignores the flag; set the current item after the upload there)."""
        wire = ([HOME_PLACEHOLDER] if self.autopilot == "ardupilot" else []) + list(items)
        count = len(wire)
        target = self.target
        requested = -1  # the highest item the autopilot has asked for
        last_sent: Callable[[Any], Any] = partial(_send_count, target=target, count=count)
        tries = 0
        read_back = False
        deadline = self._clock() + self.timeouts.step_s
        self.link.send(last_sent)
        while True:
            left = deadline - self._clock()
            if left <= 0:
                tries += 1
                if requested == count - 1 and not read_back:
                    read_back = True  # once: a dead link would make every read-back wait its own timeouts
                    if self._stored(items):
                        return  # the final MISSION_ACK was lost; the read-back shows the mission is there
                if tries > self.timeouts.retries:
                    raise self._failed(
                        f"mission upload: no answer from {target[0]}/{target[1]} after item "
                        f"{max(requested, -1) + 1} of {count} ({tries} tries {self.timeouts.step_s:g} s apart)",
                        None,
                        requested >= 0,
                    )
                self.link.send(last_sent)
                deadline = self._clock() + self.timeouts.step_s
                continue
            msg = self.link.receive(min(left, 0.2))
            if msg is None or not self._from_target(msg):
                continue
            kind = msg.get_type()
            if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                seq = int(msg.seq)
                if not 0 <= seq < count:
                    raise self._failed(
                        f"mission upload: the autopilot asked for item {seq} of {count}", None, True
                    )
                requested = max(requested, seq)
                last_sent = partial(send_item, target=target, seq=seq, item=wire[seq], current=seq == current)
                self.link.send(last_sent)
                tries = 0
                deadline = self._clock() + self.timeouts.step_s
            elif kind == "MISSION_ACK":
                result = int(msg.type)
                if result == MAV_MISSION_ACCEPTED and requested == count - 1:
                    return
                if result == MAV_MISSION_ACCEPTED:
                    continue  # an ACK for another transfer (or an early one): not ours to end on
                if result == MAV_MISSION_INVALID_SEQUENCE:
                    continue  # our re-sent item arrived twice: the autopilot asks for the next one again
                if tries > 0 and requested == count - 1 and self._stored(items):
                    return  # the answer to our re-sent last item, after the lost final MISSION_ACK
                raise self._failed(
                    f"mission upload refused by the autopilot: {mission_result_reason(result)} "
                    f"({len(items)} items sent)",
                    result,
                    requested >= 0,
                )

    def _stored(self, items: Sequence[MissionItem]) -> bool:
        """Whether the autopilot holds `items` (a read-back), e.g. after the final MISSION_ACK was lost."""
        try:
            return positions_match(self.download().items, items)
        except MissionError:
            return False

    def _failed(self, message: str, result: int | None, took_items: bool) -> MissionError:
        """The error to raise, after removing a partly written mission (module docstring)."""
        if not took_items or self.autopilot == "px4":
            return MissionError(f"{message}; the previous mission is unchanged", result)
        try:
            self._clear_partial()
        except MissionError as exc:
            return MissionError(
                f"{message}; clearing the partly written mission failed too ({exc}): clear it from the "
                "ground station before AUTO",
                result,
            )
        return MissionError(f"{message}; the partly written mission was cleared", result)

    def _clear_partial(self) -> None:
        """MISSION_CLEAR_ALL; while ArduPilot still waits for our items it refuses that, but takes a new
        upload of no items from the same sender, which empties the mission too."""
        try:
            self.clear()
            return
        except MissionError as exc:
            if exc.result != MAV_MISSION_ERROR:
                raise
        target = self.target

        def ack_of_empty(msg: Any) -> int | None:
            return self._ack_of(msg)

        result = self._exchange(partial(_send_count, target=target, count=0), ack_of_empty, "MISSION_COUNT 0")
        if result != MAV_MISSION_ACCEPTED:
            raise MissionError(f"an empty upload was refused: {mission_result_reason(result)}", result)

    # ------------------------------------------------------------------------------------ download
    def download(self) -> DownloadedMission:
        target = self.target

        def count_of(msg: Any) -> int | None:
            if msg.get_type() == "MISSION_COUNT":
                return int(msg.count)
            if msg.get_type() == "MISSION_ACK" and int(msg.type) != MAV_MISSION_ACCEPTED:
                raise MissionError(
                    f"mission download refused: {mission_result_reason(int(msg.type))}", int(msg.type)
                )
            return None

        count = self._exchange(
            lambda m: m.mission_request_list_send(target[0], target[1], MISSION_TYPE_MISSION),
            count_of,
            "MISSION_REQUEST_LIST",
        )
        items: list[MissionItem] = []
        for seq in range(count):

            def item_of(msg: Any, seq: int = seq) -> MissionItem | None:
                if msg.get_type() in ("MISSION_ITEM_INT", "MISSION_ITEM") and int(msg.seq) == seq:
                    return item_from_message(msg)
                if msg.get_type() == "MISSION_ACK" and int(msg.type) != MAV_MISSION_ACCEPTED:
                    raise MissionError(
                        f"mission download of item {seq} refused: {mission_result_reason(int(msg.type))}",
                        int(msg.type),
                    )
                return None

            items.append(
                self._exchange(
                    partial(_request_item, target=target, seq=seq), item_of, f"MISSION_REQUEST_INT {seq}"
                )
            )
        self.link.send(
            lambda m: m.mission_ack_send(target[0], target[1], MAV_MISSION_ACCEPTED, MISSION_TYPE_MISSION)
        )
        if self.autopilot == "ardupilot" and items:
            return DownloadedMission(tuple(items[1:]), items[0], 1)
        return DownloadedMission(tuple(items), None, 0)

    # --------------------------------------------------------------------------- clear and current
    def clear(self) -> None:
        target = self.target
        result = self._exchange(
            lambda m: m.mission_clear_all_send(target[0], target[1], MISSION_TYPE_MISSION),
            self._ack_of,
            "MISSION_CLEAR_ALL",
        )
        if result != MAV_MISSION_ACCEPTED:
            raise MissionError(f"mission clear refused: {mission_result_reason(result)}", result)

    def set_current(self, seq: int) -> MissionCurrent:
        """Make item `seq` (the autopilot's numbering) the one flown next; the MISSION_CURRENT that says so."""
        target = self.target

        def current_of(msg: Any) -> MissionCurrent | None:
            if msg.get_type() == "MISSION_CURRENT" and int(msg.seq) == seq:
                return _current(msg)
            if msg.get_type() == "MISSION_ACK" and int(msg.type) != MAV_MISSION_ACCEPTED:
                raise MissionError(
                    f"set current item {seq} refused: {mission_result_reason(int(msg.type))}", int(msg.type)
                )
            return None

        result: MissionCurrent = self._exchange(
            lambda m: m.mission_set_current_send(target[0], target[1], seq),
            current_of,
            f"MISSION_SET_CURRENT {seq}",
        )
        return result

    def read_current(self) -> MissionCurrent:
        """The autopilot's MISSION_CURRENT, asked for with MAV_CMD_REQUEST_MESSAGE (also taken from a stream)."""
        target = self.target

        def current_of(msg: Any) -> MissionCurrent | None:
            return _current(msg) if msg.get_type() == "MISSION_CURRENT" else None

        while self.link.receive(0.005) is not None:
            pass  # what queued before the request (a streamed MISSION_CURRENT) may be out of date

        result: MissionCurrent = self._exchange(
            lambda m: m.command_long_send(
                target[0], target[1], MAV_CMD_REQUEST_MESSAGE, 0, MISSION_CURRENT_ID, 0, 0, 0, 0, 0, 0
            ),
            current_of,
            "REQUEST_MESSAGE MISSION_CURRENT",
        )
        return result


def _send_count(mav: Any, target: tuple[int, int], count: int) -> None:
    mav.mission_count_send(target[0], target[1], count, MISSION_TYPE_MISSION)


def _request_item(mav: Any, target: tuple[int, int], seq: int) -> None:
    mav.mission_request_int_send(target[0], target[1], seq, MISSION_TYPE_MISSION)


def _current(msg: Any) -> MissionCurrent:
    total = getattr(msg, "total", None)
    state = getattr(msg, "mission_state", None)
    return MissionCurrent(
        int(msg.seq),
        int(total) if total is not None and total != 0xFFFF else None,
        int(state) if state is not None and state != 0 else None,
    )


def positions_match(a: Sequence[MissionItem], b: Sequence[MissionItem]) -> bool:
    """The same commands, and the same places and altitudes for those that fly somewhere: what a read-back
    checks (an autopilot may store other parameters with less precision, drop those its vehicle ignores, or
    report a DO_ command's frame differently: ArduPilot answers MISSION with GLOBAL; or a global frame as its
    _INT twin: PX4 answers GLOBAL_RELATIVE_ALT_INT for GLOBAL_RELATIVE_ALT)."""
    return len(a) == len(b) and all(
        x.command == y.command
        and x.has_position == y.has_position
        and (
            not x.has_position
            or (
                (INT_FRAMES.get(x.frame, x.frame), x.x, x.y) == (INT_FRAMES.get(y.frame, y.frame), y.x, y.y)
                and math.isclose(x.z, y.z, abs_tol=0.01)
            )
        )
        for x, y in zip(a, b, strict=True)
    )
