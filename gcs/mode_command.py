"""`cloudtrack-gcs mode MODE`: switch the autopilot's flight mode (AUTO, LOITER, RTL, GUIDED; PX4's MISSION,
HOLD, POSCTL...) with MAV_CMD_DO_SET_MODE, as QGroundControl's mode menu does.

It waits for the autopilot's HEARTBEAT (its family, vehicle type and mode), sends the command until a
COMMAND_ACK answers, then waits until the HEARTBEAT shows the mode (PX4 acknowledges first and may refuse
after; it may also accept a mode and change nothing). It prints the answer and the mode seen; a refusal
(with the autopilot's own STATUSTEXT), a mode the autopilot does not list, or no answer is one line on
stderr. Exit codes: 0 in the mode, 1 refused, 2 unknown mode, 3 no answer.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from cloudtrack.autopilot_modes import (
    AutopilotKind,
    detect_autopilot,
    mode_for_action,
    mode_name,
    mode_names,
    set_mode_params,
)
from cloudtrack.gcs_protocol import RESULT_NAMES
from cloudtrack.mavlink_connection import mavlink

EXIT_REFUSED, EXIT_UNKNOWN, EXIT_TIMEOUT = 1, 2, 3
AUTOPILOT_COMPONENT = 1
REFUSAL_TEXT_WAIT_S = 0.5  # ArduCopter's STATUSTEXT saying why may follow its FAILED answer
FAMILY = {AutopilotKind.ARDUPILOT: "ArduPilot", AutopilotKind.PX4: "PX4"}


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "mode",
        help="switch the autopilot's flight mode (AUTO, LOITER, RTL, GUIDED; PX4: MISSION, HOLD, ...)",
        description=(__doc__ or "").split("\n\n")[1].replace("\n", " "),
        epilog="examples:\n  cloudtrack-gcs mode AUTO      # fly the uploaded survey (PX4: MISSION)\n"
        "  cloudtrack-gcs mode LOITER\n  cloudtrack-gcs mode RTL",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", metavar="MODE", help="the mode's name as the autopilot lists it (any case)")
    p.set_defaults(func=run)


class _Autopilot:
    """The autopilot's HEARTBEAT (family, type, mode), answers to DO_SET_MODE and STATUSTEXT lines."""

    def __init__(self, session: Any, gcs_system: int) -> None:
        self.session = session
        self.system = session.target[0]
        self.gcs_system = gcs_system
        self.kind: AutopilotKind | None = None
        self.vehicle_type = 0
        self.mode = ""
        self.acks: list[int] = []
        self.texts: list[str] = []

    def receive(self, timeout: float) -> None:
        msg = self.session.endpoint.receive(timeout=timeout)
        if msg is None or (msg.get_srcSystem(), msg.get_srcComponent()) != (self.system, AUTOPILOT_COMPONENT):
            return
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            kind = detect_autopilot(msg.autopilot)
            if kind is not None:
                self.kind, self.vehicle_type = kind, int(msg.type)
                self.mode = mode_name(kind, int(msg.custom_mode), self.vehicle_type)
        elif mtype == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_DO_SET_MODE:
            if getattr(msg, "target_system", 0) in (0, self.gcs_system):
                self.acks.append(int(msg.result))
        elif mtype == "STATUSTEXT":
            text = self.session.join_statustext(msg)
            if text is not None:
                self.texts.append(text)


def _unknown(kind: AutopilotKind, vehicle_type: int, name: str) -> str:
    modes = mode_names(kind, vehicle_type)
    hint = ""
    # An ArduPilot name on PX4 (or the reverse): the mode that does the same there.
    other = AutopilotKind.ARDUPILOT if kind is AutopilotKind.PX4 else AutopilotKind.PX4
    for action in ("mission", "loiter", "offboard"):
        if name == mode_for_action(other, action) and mode_for_action(kind, action) in modes:
            hint = f" (its {action} mode is {mode_for_action(kind, action)})"
            break
    return f"{FAMILY[kind]} (vehicle type {vehicle_type}) has no mode {name!r}{hint}; its modes: {', '.join(modes)}"


def run(session: Any, args: argparse.Namespace) -> int:
    name = args.name.strip().upper()
    signing = getattr(session.endpoint.conn.mav, "signing", None)
    if signing is not None and signing.sign_outgoing:
        # The autopilot's answer need not be signed (the companion's must): the HEARTBEAT confirms the mode.
        signing.allow_unsigned_callback = lambda _mav, _msg_id: True
    ap = _Autopilot(session, args.gcs_system)
    deadline = time.monotonic() + args.timeout
    while ap.kind is None and time.monotonic() < deadline:
        ap.receive(0.2)
    if ap.kind is None:
        return _fail(
            f"no autopilot HEARTBEAT from {ap.system}/{AUTOPILOT_COMPONENT} within {args.timeout:g} s: is the "
            "autopilot sending to this link?",
            EXIT_TIMEOUT,
        )
    try:
        params = set_mode_params(ap.kind, name, ap.vehicle_type)
    except ValueError:
        return _fail(_unknown(ap.kind, ap.vehicle_type, name), EXIT_UNKNOWN)
    # The name the HEARTBEAT will show (PX4's AUTO_LOITER is HOLD, whichever name was given).
    packed = int(params.custom_mode)
    if ap.kind is AutopilotKind.PX4:
        packed = int(params.custom_mode) << 16 | int(params.custom_sub_mode) << 24
    name = mode_name(ap.kind, packed, ap.vehicle_type)
    before = ap.mode
    ap.texts.clear()
    deadline = time.monotonic() + args.timeout
    resend_at = 0.0
    confirmation = 0
    while time.monotonic() < deadline:
        if not ap.acks and time.monotonic() >= resend_at:  # resend until the first answer
            session.endpoint.send(
                lambda m, c=confirmation: m.command_long_send(
                    ap.system, AUTOPILOT_COMPONENT, mavlink.MAV_CMD_DO_SET_MODE, c,
                    params.base_mode, params.custom_mode, params.custom_sub_mode, 0, 0, 0, 0,
                )
            )  # fmt: skip
            confirmation = min(confirmation + 1, 255)
            resend_at = time.monotonic() + 1.0
        ap.receive(0.1)
        refused = [
            r for r in ap.acks if r not in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)
        ]
        if refused:
            text_until = time.monotonic() + REFUSAL_TEXT_WAIT_S
            while not ap.texts and time.monotonic() < text_until:
                ap.receive(0.1)
            said = f' ("{ap.texts[-1]}")' if ap.texts else ""
            result = RESULT_NAMES.get(refused[0], str(refused[0]))
            return _fail(
                f"mode {name} refused by the autopilot: {result}{said}; it stays in {ap.mode}", EXIT_REFUSED
            )
        if mavlink.MAV_RESULT_ACCEPTED in ap.acks and ap.mode == name:
            print(
                f"mode {name}: ACCEPTED; the autopilot's HEARTBEAT shows {ap.mode} (was {before})", flush=True
            )
            return 0
    if not ap.acks:
        return _fail(
            f"no COMMAND_ACK for mode {name} from {ap.system}/{AUTOPILOT_COMPONENT} within {args.timeout:g} s "
            "(is the link two-way, or the signing key wrong?)",
            EXIT_TIMEOUT,
        )
    said = f' ("{ap.texts[-1]}")' if ap.texts else ""
    return _fail(
        f"mode {name} was accepted, but the autopilot's HEARTBEAT still shows {ap.mode} after "
        f"{args.timeout:g} s{said}",
        EXIT_REFUSED,
    )


def _fail(message: str, code: int) -> int:
    print(f"error: {message}", file=sys.stderr, flush=True)
    return code
