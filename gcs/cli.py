"""`cloudtrack-gcs`: the ground side of the CloudTrack mission protocol, over any MAVLink link.

Each command waits for the companion's COMMAND_ACK (re-sending as the MAVLink command protocol allows)
and exits non-zero with a clear message when it is refused (1) or never acknowledged (3).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

from cloudtrack.gcs_protocol import (
    CMD_ABORT,
    CMD_CAMERA_TRACK_RECTANGLE,
    CMD_CONFIRM,
    CMD_REJECT,
    CMD_START,
    CMD_STATUS,
    COMMAND_NAMES,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_FAILED,
    MAV_RESULT_IN_PROGRESS,
    ON_FIND_CODES,
    PROMPT_PAYLOAD_TYPE,
    RESULT_NAMES,
    encode_prompt,
)
from cloudtrack.mavlink_connection import MavlinkEndpoint, mavlink, parse_connection
from cloudtrack.mavlink_signing import parse_signing_key
from gcs import fleet_replan, fleet_status, mode_command, survey_command, watch_command

EXIT_REFUSED, EXIT_TIMEOUT = 1, 3
IN_PROGRESS_WAIT_S = 35.0  # the companion's start check is at most [backend] start_check_s (30 s)

EXAMPLES = """\
examples:
  cloudtrack-gcs start --prompt "injured man in a gray shirt lying on the ground" --superset person
  cloudtrack-gcs start --prompt "woman in a green jacket" --allow-engage     # companion may select GUIDED/OFFBOARD
  cloudtrack-gcs confirm                    # the candidate awaiting the supervisor
  cloudtrack-gcs reject --candidate 2
  cloudtrack-gcs abort
  cloudtrack-gcs track-box 0.40 0.30 0.55 0.70   # normalised corners, as QGroundControl sends them
  cloudtrack-gcs watch --duration 60
  cloudtrack-gcs status --all --backend https://backend.example --supervisor-token-file ~/.config/cloudtrack/supervisor.token
  cloudtrack-gcs mode AUTO                  # the autopilot flies its mission (PX4: MISSION)
  cloudtrack-gcs start --prompt "man in a red cap" --print-mavproxy   # the same start as MAVProxy commands
  cloudtrack-gcs --connect tcp:192.168.1.10:5760 --signing-key-file ~/.config/cloudtrack/signing.key watch

The default link listens on udpin:0.0.0.0:14550, where `cloudtrack-sim autopilot` and most autopilots send
GCS traffic. With signing on, give the companion's 64-hex-character key in a file (--signing-key-file) or in
$CLOUDTRACK_GCS_SIGNING_KEY, never on the command line (every user of the machine sees it in `ps`).
"""


def _tunnel(mav: Any, target: tuple[int, int], payload: bytes) -> None:
    padded = list(payload) + [0] * (128 - len(payload))
    mav.tunnel_send(target[0], target[1], PROMPT_PAYLOAD_TYPE, len(payload), padded)


def _command_long(
    mav: Any, target: tuple[int, int], command: int, confirmation: int, params: list[float]
) -> None:
    mav.command_long_send(target[0], target[1], command, confirmation, *params)


SIGNING_KEY_ENV = "CLOUDTRACK_GCS_SIGNING_KEY"


def signing_key(args: argparse.Namespace) -> bytes | None:
    """The MAVLink signing key from --signing-key-file, else $CLOUDTRACK_GCS_SIGNING_KEY (None: no signing);
    ValueError for --signing-key HEX, which would show the key to every user in `ps`."""
    if args.signing_key is not None:
        raise ValueError(
            "--signing-key was removed: a key on the command line is visible to every user of this machine "
            f"(ps, /proc); put it in a file only you can read (--signing-key-file PATH) or in ${SIGNING_KEY_ENV}"
        )
    if args.signing_key_file is not None:
        try:
            text = args.signing_key_file.expanduser().read_text()
        except OSError as exc:
            raise ValueError(
                f"cannot read the signing key file {args.signing_key_file}: {exc.strerror}"
            ) from None
    else:
        text = os.environ.get(SIGNING_KEY_ENV, "")
    return parse_signing_key(text) if text.strip() else None


class GcsError(Exception):
    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


class GcsSession:
    """A GCS-side link: heartbeat, commands with acknowledgement, and the companion's messages."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.target = (args.system, args.component)
        self.endpoint = MavlinkEndpoint.open(args.connect, args.gcs_system, args.gcs_component, args.system)
        key = signing_key(args)
        if key is not None:
            # The autopilot's telemetry may be unsigned; an acknowledgement must carry the companion's signature.
            self.endpoint.conn.setup_signing(
                key, sign_outgoing=True,
                allow_unsigned_callback=lambda _mav, msg_id: msg_id != mavlink.MAVLINK_MSG_ID_COMMAND_ACK,
            )  # fmt: skip
        self._statustexts: dict[int, list[bytes]] = {}
        # The companion's lines heard while waiting for an ACK: a reply may overtake it.
        self.heard: deque[str] = deque(maxlen=16)

    def close(self) -> None:
        self.endpoint.close()

    def heartbeat(self) -> None:
        self.endpoint.send(
            lambda m: m.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        )

    def connect(self) -> None:
        """Announce ourselves until the vehicle is heard (udpin links cannot send before that)."""
        deadline = time.monotonic() + self.args.timeout
        while time.monotonic() < deadline:
            self.heartbeat()
            msg = self.endpoint.receive(timeout=0.5)
            if msg is not None and msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == self.target[0]:
                self.heartbeat()
                return
        raise GcsError(
            f"no HEARTBEAT from system {self.target[0]} on {self.args.connect} within {self.args.timeout:g} s: "
            "is the autopilot (or cloudtrack-sim autopilot) sending to this address?",
            EXIT_TIMEOUT,
        )

    def send_prompt(self, mission_id: int, superset: str, prompt: str) -> tuple[int, int]:
        payloads = encode_prompt(mission_id, superset, prompt)
        for payload in payloads:
            self.endpoint.send(partial(_tunnel, target=self.target, payload=payload))
        return len(payloads), sum(len(p) - 4 for p in payloads)

    def command(self, command: int, params: Sequence[float], resend: Any = None) -> int:
        """Send COMMAND_LONG until its COMMAND_ACK arrives; the MAV_RESULT. An IN_PROGRESS answer (the
        companion asks the back-end before a start) stops the resending and waits for the final one."""
        p = list(params) + [0.0] * (7 - len(params))
        deadline = time.monotonic() + self.args.timeout
        confirmation = 0
        in_progress = False
        while time.monotonic() < deadline:
            if not in_progress:
                self.endpoint.send(
                    partial(
                        _command_long,
                        target=self.target,
                        command=command,
                        confirmation=confirmation,
                        params=p,
                    )
                )
            resend_at = time.monotonic() + 1.0
            while time.monotonic() < min(resend_at, deadline):
                msg = self.endpoint.receive(timeout=0.2)
                if msg is None:
                    continue
                text = self.join_statustext(msg) if msg.get_type() == "STATUSTEXT" else None
                if text is not None and msg.get_srcComponent() == self.target[1]:
                    self.heard.append(text)
                if (
                    msg.get_type() == "COMMAND_ACK"
                    and msg.command == command
                    and (msg.get_srcSystem(), msg.get_srcComponent()) == self.target
                ):
                    if msg.result != MAV_RESULT_IN_PROGRESS:
                        return int(msg.result)
                    if not in_progress:
                        in_progress = True
                        name = COMMAND_NAMES.get(command, str(command))
                        print(f"{name}: in progress (the companion asks the back-end)", flush=True)
                        deadline = max(deadline, time.monotonic() + IN_PROGRESS_WAIT_S)
            if in_progress:
                continue
            confirmation = min(confirmation + 1, 255)
            self.heartbeat()
            if resend is not None:
                resend()
        name = COMMAND_NAMES.get(command, str(command))
        raise GcsError(
            f"no acknowledgement for {name} from {self.target[0]}/{self.target[1]} within {self.args.timeout:g} s: "
            "is the companion running, and does the autopilot route to it (or is the signing key wrong)?",
            EXIT_TIMEOUT,
        )

    def show(self, msg: Any) -> str | None:
        """A readable line for a message from the vehicle, printed; None for others."""
        text = self.join_statustext(msg) if msg.get_type() == "STATUSTEXT" else None
        line = self.describe(msg, text)
        if line is not None:
            print(line, flush=True)
        return line

    def describe(self, msg: Any, text: str | None = None) -> str | None:
        """A readable line for a message (`text`: a STATUSTEXT's joined line, None while chunks wait)."""
        mtype = msg.get_type()
        line = None
        src = f"{msg.get_srcSystem()}/{msg.get_srcComponent()}"
        if mtype == "STATUSTEXT":
            line = f"[{src}] {text}" if text is not None else None
        elif mtype == "NAMED_VALUE_FLOAT":
            line = f"[{src}] {msg.name} = {msg.value:.3f}"
        elif mtype == "CAMERA_TRACKING_IMAGE_STATUS":
            if msg.tracking_status & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE:
                line = (
                    f"[{src}] target at ({msg.point_x:.3f}, {msg.point_y:.3f}) box "
                    f"({msg.rec_top_x:.3f}, {msg.rec_top_y:.3f})-({msg.rec_bottom_x:.3f}, {msg.rec_bottom_y:.3f})"
                )
            else:
                line = f"[{src}] tracking idle"
        return line

    def join_statustext(self, msg: Any) -> str | None:
        """A STATUSTEXT's whole line once its last chunk is in (MAVLink 2 chunks share a non-zero id)."""
        text = bytes(msg.text, "utf-8") if isinstance(msg.text, str) else bytes(msg.text)
        text_id = getattr(msg, "id", 0)
        if not text_id:
            return text.rstrip(b"\0").decode("utf-8", "replace")
        parts = self._statustexts.setdefault(text_id, [])
        parts.append(text[:50])
        if len(text.rstrip(b"\0")) < 50:  # the last chunk is the short one
            del self._statustexts[text_id]
            return b"".join(parts).rstrip(b"\0").decode("utf-8", "replace")
        return None

    def wait_status(self, seconds: float) -> list[str]:
        """Lines from the companion for a short while (the reply to a command)."""
        lines: list[str] = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            msg = self.endpoint.receive(timeout=0.1)
            if msg is not None and msg.get_srcComponent() == self.target[1]:
                line = self.show(msg)
                if line is not None:
                    lines.append(line)
                    if msg.get_type() == "STATUSTEXT":
                        return lines
        return lines


def _report(name: str, result: int) -> int:
    text = RESULT_NAMES.get(result, str(result))
    if result == MAV_RESULT_ACCEPTED:
        print(f"{name}: {text}", flush=True)
        return 0
    print(f"error: {name} refused by the companion: {text}", file=sys.stderr, flush=True)
    return EXIT_REFUSED


def mavproxy_start_lines(args: argparse.Namespace) -> list[str]:
    """The same start as MAVProxy `message` commands (each argument is a Python expression without spaces)."""
    system, component = args.system, args.component
    payloads = encode_prompt(args.mission_id, args.superset, args.prompt)
    lines = [
        f"message TUNNEL {system} {component} {PROMPT_PAYLOAD_TYPE} {len(p)} list(bytes.fromhex('{p.hex()}'))+[0]*{128 - len(p)}"
        for p in payloads
    ]
    length = sum(len(p) - 4 for p in payloads)
    engage = 1 if args.allow_engage else 0
    on_find = ON_FIND_CODES.index(args.on_find or "")
    lines.append(
        f"message COMMAND_LONG {system} {component} {CMD_START} 0 {args.mission_id} {len(payloads)} {engage} {length} {on_find} 0 0"
    )
    return lines


def _start(session: GcsSession, args: argparse.Namespace) -> int:
    chunks, length = session.send_prompt(args.mission_id, args.superset, args.prompt)
    on_find = float(ON_FIND_CODES.index(args.on_find or ""))
    params = [args.mission_id, chunks, 1.0 if args.allow_engage else 0.0, length, on_find]

    def resend_prompt() -> None:
        session.send_prompt(args.mission_id, args.superset, args.prompt)

    result = session.command(CMD_START, params, resend=resend_prompt)
    if result == MAV_RESULT_FAILED:  # chunks lost on the way: send them again once
        resend_prompt()
        result = session.command(CMD_START, params)
    code = _report("start", result)
    session.wait_status(2.0)  # the companion's line: MISSION n STARTED, or why it refused the start
    if code == 0:
        _warnings(session, START_WARNING_WAIT_S)
    return code


START_WARNING_WAIT_S = 0.5  # the companion sends a start's warning right after its start line


def _warnings(session: GcsSession, seconds: float) -> None:
    """A warning from the companion within `seconds` (PROMPT WARNING: the words name another class)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = session.endpoint.receive(timeout=0.1)
        if msg is None or msg.get_type() != "STATUSTEXT" or msg.get_srcComponent() != session.target[1]:
            continue
        text = session.join_statustext(msg)
        if text is not None and msg.severity <= mavlink.MAV_SEVERITY_WARNING:
            print(f"[{session.target[0]}/{session.target[1]}] {text}", flush=True)
            return


def _simple(command: int, params: Sequence[float]) -> Any:
    def run(session: GcsSession, args: argparse.Namespace) -> int:
        return _report(COMMAND_NAMES[command], session.command(command, params))

    return run


DECISION_ANSWER_WAIT_S = 2.0
# The mission's answers to a confirm or reject (docs/gcs-protocol.md, "Status lines").
DECIDED = ("CONFIRMED", "REJECTED", "confirmed ", "rejected ", "FOUND")


def _decision(command: int) -> Any:
    """Confirm or reject, then the mission's answer: the ACK says only that the command was delivered, and
    the mission may still refuse it (a candidate 0 pressed just as another came to await: "press again")."""

    def run(session: GcsSession, args: argparse.Namespace) -> int:
        name = COMMAND_NAMES[command]
        session.heard.clear()
        code = _report(name, session.command(command, _candidate(args)))
        if code:
            return code

        def answer(text: str) -> int | None:
            print(f"[{session.target[0]}/{session.target[1]}] {text}", flush=True)
            if text.startswith((f"{name.upper()} REFUSED", f"{name}: ")):
                print(f"error: {name} refused by the mission: {text}", file=sys.stderr, flush=True)
                return EXIT_REFUSED
            return 0 if text.startswith(DECIDED) else None

        for early in session.heard:
            if (decided := answer(early)) is not None:
                return decided
        deadline = time.monotonic() + DECISION_ANSWER_WAIT_S
        while time.monotonic() < deadline:
            msg = session.endpoint.receive(timeout=0.1)
            if msg is None or msg.get_srcComponent() != session.target[1] or msg.get_type() != "STATUSTEXT":
                continue
            text = session.join_statustext(msg)
            if text is not None and (decided := answer(text)) is not None:
                return decided
        return 0

    return run


def _status(session: GcsSession, args: argparse.Namespace) -> int:
    """The companion's status line (it repeats it on MAV_CMD_USER_5) and what the link shows for a moment:
    tracking, the autopilot's mode, finds."""
    result = session.command(CMD_STATUS, [0.0])
    if result != MAV_RESULT_ACCEPTED:
        return _report("status", result)
    summary = watch_command.WatchSummary(session.target[0], every_s=0.0)
    line = None
    deadline = time.monotonic() + args.listen
    while time.monotonic() < deadline:
        msg = session.endpoint.receive(timeout=0.1)
        if msg is None:
            continue
        text = session.join_statustext(msg) if msg.get_type() == "STATUSTEXT" else None
        if text is not None and msg.get_srcComponent() == session.target[1] and line is None:
            line = text
        summary.feed(msg, text)
    companion = f"{session.target[0]}/{session.target[1]}"
    print(f"companion {companion}: {line if line is not None else '(no status line heard)'}", flush=True)
    print(summary.line().replace("[summary]", "link:", 1), flush=True)
    return 0 if line is not None else EXIT_TIMEOUT


def _candidate(args: argparse.Namespace) -> list[float]:
    return [float(getattr(args, "candidate", 0) or 0)]


def _track_box(session: GcsSession, args: argparse.Namespace) -> int:
    x1, y1, x2, y2 = args.x1, args.y1, args.x2, args.y2
    if not (0 <= x1 < x2 <= 1 and 0 <= y1 < y2 <= 1):
        print("error: track-box needs normalised corners 0..1 with X1 < X2 and Y1 < Y2", file=sys.stderr)
        return 2
    return _report("track-box", session.command(CMD_CAMERA_TRACK_RECTANGLE, [x1, y1, x2, y2]))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cloudtrack-gcs",
        description="Start, supervise and stop a CloudTrack mission over MAVLink (through the autopilot's routing).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--connect",
        default="udpin:0.0.0.0:14550",
        metavar="URL",
        help="MAVLink link (default udpin:0.0.0.0:14550)",
    )
    parser.add_argument("--system", type=int, default=1, help="vehicle system id (default 1)")
    parser.add_argument("--component", type=int, default=191, help="companion component id (default 191)")
    parser.add_argument("--gcs-system", type=int, default=255, help="our system id (default 255)")
    parser.add_argument(
        "--gcs-component",
        type=int,
        default=190,
        help="our component id (default 190, MAV_COMP_ID_MISSIONPLANNER)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="wait this long for an acknowledgement (default 5)",
    )
    parser.add_argument(
        "--signing-key-file", type=Path, metavar="PATH",
        help=f"file holding the MAVLink 2 signing key, 64 hex characters (default: ${SIGNING_KEY_ENV}, else "
        "no signing)",
    )  # fmt: skip
    # Removed: a key in argv is visible to every user (ps, /proc/*/cmdline). Kept only to say so.
    parser.add_argument("--signing-key", help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    start = sub.add_parser(
        "start",
        help="start a mission with a text prompt",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    start.add_argument("--prompt", required=True, help='what to find, e.g. "injured man in a gray shirt"')
    start.add_argument(
        "--superset", default="", help="detector class, e.g. person (default: derived by the back-end)"
    )
    start.add_argument(
        "--allow-engage", action="store_true", help="let the companion select GUIDED/OFFBOARD itself"
    )
    start.add_argument(
        "--mission-id", type=int, default=int(time.time()) % 256, help="0-255 (default: from the clock)"
    )
    start.add_argument(
        "--on-find",
        choices=ON_FIND_CODES[1:],
        help="what the other vehicles of this mission id do on its first confirmed find: continue, hold (where "
        "they are) or return (to launch); set once for the mission on the back-end, the first setting stands; "
        "a vehicle started without --allow-engage is told, its pilot acts (default: not set, i.e. continue)",
    )
    start.add_argument(
        "--print-mavproxy",
        action="store_true",
        help="print the MAVProxy `message` lines that send this start; send nothing",
    )
    start.set_defaults(func=_start)
    for name, command, text in (
        ("confirm", CMD_CONFIRM, "confirm the candidate awaiting the supervisor"),
        ("reject", CMD_REJECT, "reject the candidate awaiting the supervisor"),
    ):
        p = sub.add_parser(
            name,
            help=text,
            description=text,
            epilog=f"example:\n  cloudtrack-gcs {name} --candidate 2",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        p.add_argument(
            "--candidate",
            type=int,
            default=0,
            help="candidate number (default 0: the one awaiting the supervisor)",
        )
        p.set_defaults(func=_decision(command))
    abort = sub.add_parser(
        "abort",
        help="end the mission: the companion stops and holds",
        epilog="example:\n  cloudtrack-gcs abort",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    abort.set_defaults(func=_simple(CMD_ABORT, [0.0]))
    status = sub.add_parser(
        "status",
        help="print the companion's status line and what the link shows (tracking, mode, finds); --all: a "
        "line per vehicle, from the back-end",
        epilog="examples:\n  cloudtrack-gcs status\n"
        "  cloudtrack-gcs status --all --backend http://127.0.0.1:8080 --supervisor-token-file "
        "out/quickstart/supervisor-token\n"
        "  cloudtrack-gcs status --all --mission m-7      # back-end and token from "
        f"${fleet_status.BACKEND_ENV}, ${fleet_status.TOKEN_ENV}\n\n"
        "--all prints, per vehicle: id, mission, state, mode, position, coverage of its part (and the POD\n"
        "map's share at the target POD), and how long ago it last reported. The supervisor token comes\n"
        f"from a file or ${fleet_status.TOKEN_ENV}, never from the command line.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    status.add_argument(
        "--listen", type=float, default=2.0, metavar="S", help="listen this long after the answer (default 2)"
    )
    fleet_status.add_arguments(status)
    status.set_defaults(func=_status)
    box = sub.add_parser(
        "track-box", help="track what is inside a box (MAV_CMD_CAMERA_TRACK_RECTANGLE, normalised 0..1)",
        epilog="example:\n  cloudtrack-gcs track-box 0.40 0.30 0.55 0.70", formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    # Four positionals rather than nargs=4 with a tuple metavar, which Python 3.11's help formatter rejects.
    for corner in ("x1", "y1", "x2", "y2"):
        box.add_argument(corner, type=float, help=f"{corner.upper()}, normalised 0..1")
    box.set_defaults(func=_track_box)
    watch = sub.add_parser(
        "watch",
        help="print what the vehicle says, summarised, and forward its finds to a TAK map",
        description=watch_command.__doc__.split("\n\n")[1] if watch_command.__doc__ else None,
        epilog="examples:\n  cloudtrack-gcs watch --duration 60\n"
        "  cloudtrack-gcs watch --cot-url udp://239.2.3.1:6969     # finds to the ATAK devices on this network",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    watch_command.add_arguments(watch)
    watch.set_defaults(func=watch_command.run_watch)
    survey_command.add_parser(sub)
    fleet_replan.add_parser(sub)
    mode_command.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        parse_connection(args.connect)
        signing_key(args)  # a key that cannot be read or parsed stops here, before any link opens
        if args.command == "start":
            encode_prompt(args.mission_id, args.superset, args.prompt)
        if args.command == "watch":
            watch_command.check_arguments(args)  # the TAK address and certificates, before watching
        if args.command == "status":
            fleet_status.check_arguments(args)  # the back-end's address and token, for --all
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.command == "start" and args.print_mavproxy:
        print("\n".join(mavproxy_start_lines(args)))
        return 0
    if args.command == "status" and args.all:
        return fleet_status.run_all(args)  # asks the back-end: no MAVLink link
    if getattr(args, "opens_own_link", False):
        return int(args.func(args))  # survey: checks its area and plan before it opens the link
    try:
        session = GcsSession(args)
    except OSError as exc:
        print(f"error: cannot open {args.connect}: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    try:
        session.connect()
        return int(args.func(session, args))
    except GcsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.code
    finally:
        session.close()


if __name__ == "__main__":
    sys.exit(main())
