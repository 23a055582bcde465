"""MAVLink 2 message signing with a shared secret key (pymavlink's `setup_signing`).

With signing on, everything the companion sends is signed. Incoming telemetry may stay unsigned (many
autopilots sign only when configured to), but the messages that carry mission and supervisor commands
(COMMAND_LONG, COMMAND_INT, TUNNEL) must carry a valid signature: pymavlink checks it, and an unsigned or
wrongly signed one is refused here and logged.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

# MAVLINK_MSG_ID_ of COMMAND_LONG, COMMAND_INT, TUNNEL: the carriers of mission and supervisor commands.
PROTECTED_MESSAGE_IDS = {76: "COMMAND_LONG", 75: "COMMAND_INT", 385: "TUNNEL"}


def parse_signing_key(text: str) -> bytes:
    """A 32-byte key from 64 hex characters; ValueError with what is expected otherwise."""
    cleaned = text.strip()
    try:
        key = bytes.fromhex(cleaned)
    except ValueError:
        key = b""
    if len(key) != 32:
        raise ValueError("MAVLink signing key must be 64 hexadecimal characters (32 bytes), e.g. from `openssl rand -hex 32`")
    return key


class SigningGuard:
    """Enables signing on a pymavlink connection and keeps a record of what it refused."""

    def __init__(self, on_refused: Callable[[str], None] | None = None):
        self.refused: list[str] = []
        self._on_refused = on_refused

    def enable(self, conn: Any, key: bytes) -> None:
        conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=self._allow_unsigned)

    def _allow_unsigned(self, _mav: Any, msg_id: int) -> bool:
        # pymavlink calls this for a message that is unsigned or whose signature did not check out.
        name = PROTECTED_MESSAGE_IDS.get(msg_id)
        if name is None:
            return True
        text = f"refused an unsigned or wrongly signed {name}"
        log.warning("MAVLink signing: %s", text)
        self.refused.append(name)
        if self._on_refused is not None:
            self._on_refused(text)
        return False
