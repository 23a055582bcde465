"""Before a mission starts: can the back-end search for its prompt? Asked off the MAVLink reader thread.

`cloudtrack.gcs_protocol.GcsProtocol` asks this gate for a start's verdict; the first time it answers None
(the GCS gets MAV_RESULT_IN_PROGRESS) and asks the back-end (`POST /v1/prompts/check`) on a thread of its
own; the final COMMAND_ACK follows when the answer is in:
- the back-end can search for it: ACCEPTED; when it warns that the prompt's words name something outside
  the given superset, the warning goes to the GCS after the start ("PROMPT WARNING: ...");
- it cannot (422: a class its detector has no name for, with the nearest ones): DENIED, and the reason
  goes to the GCS as a STATUSTEXT ("START REFUSED: ...");
- it refuses this vehicle's token (401/403): DENIED, named as such;
- it does not answer (down, unreachable, busy, no answer within the check's time): ACCEPTED, with a
  warning that the search waits for the back-end, which the status keeps saying until it answers.
Verdicts are kept for `keep_s` (the same start sent again is answered at once).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

from behaviors.mission_commands import StartMission
from cloudtrack.gcs_protocol import StartVerdict

log = logging.getLogger(__name__)


class PromptClient(Protocol):
    """`cloudtrack.api_client.BackendClient` as the check uses it."""

    url: str

    def check_prompt(self, prompt: str, superset: str | None = None) -> object: ...


def auth_reason(status: int | None, detail: str) -> str:
    """A refused token, said as such (never "unreachable")."""
    return f"the back-end refused this vehicle's token (HTTP {status}: {detail}); check [backend] token"


def verdict_for(error: Exception | None, url: str) -> StartVerdict:
    """The verdict on a check that answered (`error` None) or failed with `error` (a BackendError)."""
    if error is None:
        return StartVerdict(True)
    status = getattr(error, "status", None)
    detail = str(getattr(error, "detail", "") or error)
    if status in (401, 403):
        return StartVerdict(False, auth_reason(status, detail))
    if status is not None and 400 <= status < 500 and status != 429:
        return StartVerdict(False, f"the back-end cannot search for this: {detail}")
    return StartVerdict(True, f"waiting for the back-end at {url}: {detail}")


class StartCheck:
    """The start gate: asks the back-end once per (prompt, superset) and remembers the verdict."""

    def __init__(
        self,
        client: PromptClient,
        keep_s: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
        on_verdict: Callable[[StartVerdict], None] | None = None,
    ) -> None:
        """`on_verdict` hears each verdict the back-end gave (the operator's notices keep a refusal)."""
        self._on_verdict = on_verdict
        self._client = client
        self._keep_s = keep_s
        self._clock = clock
        self._lock = threading.Lock()
        self._verdicts: dict[tuple[str, str], tuple[StartVerdict, float]] = {}
        self._asking: dict[tuple[str, str], Callable[[], None]] = {}

    def __call__(self, start: StartMission, done: Callable[[], None]) -> StartVerdict | None:
        key = (start.prompt, start.superset)
        with self._lock:
            known = self._verdicts.get(key)
            if known is not None and self._clock() - known[1] < self._keep_s:
                return known[0]
            if key in self._asking:
                return None  # already being asked: one answer for all the copies of this start
            self._asking[key] = done
        threading.Thread(target=self._ask, args=(key,), name="start-check", daemon=True).start()
        return None

    def _ask(self, key: tuple[str, str]) -> None:
        prompt, superset = key
        try:
            answer = self._client.check_prompt(prompt, superset or None)
            verdict = verdict_for(None, self._client.url)
            warning = getattr(answer, "warning", None)
            if warning:
                verdict = StartVerdict(True, f"PROMPT WARNING: {warning}")
        except Exception as exc:  # the BackendError's status says which kind of failure it was
            verdict = verdict_for(exc, self._client.url)
        if not verdict.accepted or verdict.reason:
            log.warning("mission start %r: %s", prompt, verdict.reason)
        with self._lock:
            self._verdicts[key] = (verdict, self._clock())
            done = self._asking.pop(key)
        if self._on_verdict is not None:
            self._on_verdict(verdict)
        done()
