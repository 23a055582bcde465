"""MAVProxy module: the CloudTrack mission commands from a MAVProxy console (`module load cloudtrack`).

  cloudtrack start "<prompt>" [superset=person] [engage]   the prompt in TUNNEL chunks, then MAV_CMD_USER_1
  cloudtrack confirm [N]     cloudtrack reject [N]         (N: candidate number; none: the one awaiting)
  cloudtrack abort           cloudtrack status
  cloudtrack target SYS COMP                               the companion's ids (default 1 191)

The same wire protocol as `cloudtrack-gcs` (cloudtrack/gcs_protocol.py); each COMMAND_ACK is printed as
"CloudTrack <command>: <RESULT>". MAVProxy finds this module through `cloudtrack.init` (the package's
`module load cloudtrack` entry point); MAVProxy itself must be installed (see docs/gcs-protocol.md).
"""

from __future__ import annotations

import time
from typing import Any

from MAVProxy.modules.lib import mp_module

from cloudtrack.gcs_protocol import (
    CMD_ABORT,
    CMD_CONFIRM,
    CMD_REJECT,
    CMD_START,
    CMD_STATUS,
    COMMAND_NAMES,
    PROMPT_PAYLOAD_TYPE,
    RESULT_NAMES,
    encode_prompt,
)

USAGE = (
    'usage: cloudtrack start "<prompt>" [superset=WORD] [engage] | confirm [N] | reject [N] | abort | status'
    " | target SYS COMP"
)


class CloudTrackModule(mp_module.MPModule):  # type: ignore[misc]
    def __init__(self, mpstate: Any) -> None:
        super().__init__(mpstate, "cloudtrack", "CloudTrack mission commands", public=True)
        self.target = (1, 191)
        self.mission_id = int(time.time()) % 256
        self.add_command(
            "cloudtrack", self.cmd_cloudtrack, "CloudTrack mission commands",
            ["start", "confirm", "reject", "abort", "status", "target"],
        )  # fmt: skip

    def cmd_cloudtrack(self, args: list[str]) -> None:
        if not args:
            print(USAGE)
            return
        sub, rest = args[0], args[1:]
        try:
            if sub == "start":
                self._start(rest)
            elif sub in ("confirm", "reject"):
                number = float(rest[0]) if rest else 0.0
                self._command(CMD_CONFIRM if sub == "confirm" else CMD_REJECT, [number])
            elif sub == "abort":
                self._command(CMD_ABORT, [])
            elif sub == "status":
                self._command(CMD_STATUS, [])
            elif sub == "target" and len(rest) == 2:
                self.target = (int(rest[0]), int(rest[1]))
            else:
                print(USAGE)
        except ValueError as exc:
            print(f"CloudTrack: {exc}")

    def _start(self, words: list[str]) -> None:
        superset, engage, prompt_words = "", False, []
        for word in words:
            if word.startswith("superset="):
                superset = word.partition("=")[2]
            elif word == "engage":
                engage = True
            else:
                prompt_words.append(word)
        prompt = " ".join(prompt_words).strip().strip("\"'")
        self.mission_id = (self.mission_id + 1) % 256
        payloads = encode_prompt(self.mission_id, superset, prompt)  # ValueError says what is wrong
        for payload in payloads:
            padded = list(payload) + [0] * (128 - len(payload))
            self.master.mav.tunnel_send(
                self.target[0], self.target[1], PROMPT_PAYLOAD_TYPE, len(payload), padded
            )
        text_bytes = sum(len(p) - 4 for p in payloads)
        self._command(CMD_START, [self.mission_id, len(payloads), 1.0 if engage else 0.0, text_bytes])

    def _command(self, command: int, params: list[float]) -> None:
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.master.mav.command_long_send(self.target[0], self.target[1], command, 0, *p)

    def mavlink_packet(self, m: Any) -> None:
        ours = (m.get_srcSystem(), m.get_srcComponent()) == self.target
        if ours and m.get_type() == "COMMAND_ACK" and m.command in COMMAND_NAMES:
            print(f"CloudTrack {COMMAND_NAMES[m.command]}: {RESULT_NAMES.get(m.result, m.result)}")


def init(mpstate: Any) -> CloudTrackModule:
    return CloudTrackModule(mpstate)
