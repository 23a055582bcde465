"""MAVLink 2 message signing with a shared secret key (pymavlink's `setup_signing`).

With signing on, everything the companion sends is signed and every message it acts on must carry a valid
signature: commands and prompts (COMMAND_LONG, COMMAND_INT, TUNNEL) as well as the autopilot's HEARTBEAT
(the mode that ends or allows offboard control) and telemetry (GLOBAL_POSITION_INT gives the altitude for
the altitude band). pymavlink checks the signature; an unsigned or wrongly signed message is dropped before
it is decoded, counted here and logged at most once per message type every 10 s. The autopilot must sign
too (ArduPilot: signing set up from the GCS, which stores the key on the vehicle; docs/safety.md).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

REFUSAL_LOG_PERIOD_S = 10.0


def parse_signing_key(text: str) -> bytes:
    """A 32-byte key from 64 hex characters; ValueError with what is expected otherwise."""
    cleaned = text.strip()
    try:
        key = bytes.fromhex(cleaned)
    except ValueError:
        key = b""
    if len(key) != 32:
        raise ValueError(
            "MAVLink signing key must be 64 hexadecimal characters (32 bytes), e.g. from `openssl rand -hex 32`"
        )
    return key


def message_name(msg_id: int) -> str:
    from cloudtrack.mavlink_connection import mavlink

    entry = mavlink.mavlink_map.get(msg_id)
    return entry.msgname if entry is not None else f"message {msg_id}"


class SigningGuard:
    """Enables signing on a pymavlink connection and keeps a bounded record of what it refused."""

    def __init__(self, on_refused: Callable[[str], None] | None = None):
        self.refused: deque[str] = deque(maxlen=1000)
        self.refused_total = 0
        self._on_refused = on_refused
        self._last_report: dict[str, float] = {}

    def enable(self, conn: Any, key: bytes) -> None:
        conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=self._allow_unsigned)

    def _allow_unsigned(self, _mav: Any, msg_id: int) -> bool:
        # pymavlink calls this for a message that is unsigned or whose signature did not check out.
        name = message_name(msg_id)
        self.refused.append(name)
        self.refused_total += 1
        now = time.monotonic()
        if now - self._last_report.get(name, -math.inf) >= REFUSAL_LOG_PERIOD_S:
            if len(self._last_report) < 256:
                self._last_report[name] = now
            text = f"refused an unsigned or wrongly signed {name}"
            log.warning("MAVLink signing: %s (%d refused so far)", text, self.refused_total)
            if self._on_refused is not None:
                self._on_refused(text)
        return False
