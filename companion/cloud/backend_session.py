"""The companion's session with the back-end beside the keyframes: status, supervisor decisions, rejections.

A background thread, once a `period_s`: posts the vehicle's status (state, prompt, position and the
candidate awaiting the supervisor, with its small JPEG crop from `companion.cloud.candidate_crop`; the crop
goes up once per candidate, the back-end keeps it, and it is sent again every CROP_REFRESH_S so a
restarted back-end recovers it; the same for the mission's find and its crop) so the supervisor page
shows it, fetches the supervisor's new decisions and turns them into Confirm/Reject commands, and sends
queued rejections so the back-end never proposes a rejected candidate again in this mission. For a fleet
mission it sets the mission's `on_find` once when the start gave one (the first setting stands: a refusal
says which), and asks every FLEET_POLL_S what the fleet orders this vehicle (`fleet_order()`, acted on by
behaviors/fleet_order.py). Nothing here blocks the main loop; every failure is logged and retried on the
next round. `last_success()` feeds the lost-back-end watchdog.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from behaviors.mission_commands import ConfirmCandidate, MissionCommand, RejectCandidate
from cloudtrack.api_models import Decision, FleetOrder
from cloudtrack.provenance import decided_via, gcs_text

log = logging.getLogger(__name__)

CROP_REFRESH_S = 30.0
FLEET_POLL_S = 2.0  # a find's order reaches the fleet within this (and a round), at half a request a second
_CROP_FIELDS = ("crop_jpeg_b64", "crop_box")


class SessionClient(Protocol):
    """The parts of `cloudtrack.api_client.BackendClient` the session uses."""

    def report_status(self, state: str, vehicle_id: str | None = None, **fields: Any) -> object: ...

    def reject(
        self,
        candidate_id: str | None,
        crop_bgr: Any = None,
        position: Any = None,
        reason: str = "",
        mission_id: str | None = None,
    ) -> object: ...

    def decisions(self, after: int = 0, vehicle_id: str | None = None) -> list[Decision]: ...

    def set_on_find(self, mission_id: str, on_find: str) -> object: ...

    def fleet_order(self, mission_id: str) -> FleetOrder: ...


class BackendSession:
    def __init__(
        self,
        client: SessionClient,
        period_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        on_result: Callable[[BaseException | None], None] | None = None,
    ) -> None:
        """`on_result(None)` after each round that reached the back-end, `on_result(error)` after one that
        failed (the operator's notices say why, once; nothing is logged per round)."""
        self._on_result = on_result
        self._client = client
        self._period = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._status: dict[str, Any] | None = None
        self._rejections: deque[tuple[str, tuple[float, float] | None, str | None]] = deque(maxlen=100)
        self._commands: deque[MissionCommand] = deque(maxlen=100)
        self._shared: deque[str] = deque(maxlen=100)  # ids of rejections the back-end took, not yet told
        self._last_success: float | None = None
        self._after = 0
        self._primed = False  # decisions made before we started are history, not commands
        self._crop_sent: tuple[str, float] | None = None  # (candidate id, when) of the last crop delivered
        self._find_crop_sent: tuple[str, float] | None = None  # the same for the find's crop
        self._on_find: tuple[str, str] | None = None  # (mission, setting) still to be set on the back-end
        self._on_find_refused = ""  # why the back-end kept another setting (for the operator)
        self._fleet: FleetOrder | None = None  # the back-end's latest order for this vehicle
        self._fleet_asked = -float("inf")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="backend-session", daemon=True)

    def start(self) -> BackendSession:
        self._thread.start()
        return self

    def update(self, status: dict[str, Any]) -> None:
        with self._lock:
            self._status = dict(status)

    def reject(self, candidate_id: str, position: tuple[float, float] | None) -> None:
        with self._lock:
            mission = self._status.get("mission_id") if self._status else None
            if mission is None:
                log.warning("rejection of %s not sent: no mission", candidate_id)
                return
            self._rejections.append((candidate_id, position, mission))

    def set_on_find(self, mission_id: str, on_find: str) -> None:
        """Set the mission's on_find on the back-end (once, on the next rounds until it answers)."""
        with self._lock:
            self._on_find = (mission_id, on_find)
            self._on_find_refused = ""
            self._fleet = None

    def fleet_order(self) -> FleetOrder | None:
        """What the fleet mission orders this vehicle, as the back-end last said (None: not asked yet)."""
        with self._lock:
            return self._fleet

    def on_find_refused(self) -> str:
        """Why the start's on_find did not stand ("" while it did, or none was given)."""
        with self._lock:
            return self._on_find_refused

    def commands(self) -> list[MissionCommand]:
        with self._lock:
            drained = list(self._commands)
            self._commands.clear()
        return drained

    def shared_rejections(self) -> list[str]:
        """Candidate ids whose rejection the back-end has taken since the last call (it judges candidates
        against them from then on)."""
        with self._lock:
            drained = list(self._shared)
            self._shared.clear()
        return drained

    def last_success(self) -> float | None:
        with self._lock:
            return self._last_success

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the rounds; waits up to `timeout_s` for a round in progress (its request is left to end on
        its own: the thread is a daemon, and nothing it would still send is needed once stopping)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            try:
                self._round()
            except Exception as exc:  # unreachable, refused, malformed: the watchdog sees last_success age
                log.debug("back-end session round failed: %s", exc)
                if self._on_result is not None:
                    self._on_result(exc)
            else:
                if self._on_result is not None:
                    self._on_result(None)

    def _round(self) -> None:
        with self._lock:
            status = dict(self._status) if self._status else None
            pending = list(self._rejections)
        if status is not None:
            fields = {k: v for k, v in status.items() if k != "state" and v is not None}
            awaiting = fields.get("awaiting")
            crop_id = None
            if isinstance(awaiting, dict) and awaiting.get("crop_jpeg_b64"):
                crop_id = awaiting.get("candidate_id")
                sent = self._crop_sent
                if sent is not None and sent[0] == crop_id and self._clock() - sent[1] < CROP_REFRESH_S:
                    fields["awaiting"] = {k: v for k, v in awaiting.items() if k not in _CROP_FIELDS}
                    crop_id = None  # the back-end already holds this candidate's crop
            find = fields.get("find")
            find_id = None
            if isinstance(find, dict) and find.get("crop_jpeg_b64"):
                find_id = find.get("candidate_id")
                sent = self._find_crop_sent
                if sent is not None and sent[0] == find_id and self._clock() - sent[1] < CROP_REFRESH_S:
                    fields["find"] = {k: v for k, v in find.items() if k != "crop_jpeg_b64"}
                    find_id = None  # stored with the find already
            self._client.report_status(str(status.get("state", "IDLE")), **fields)
            if crop_id is not None:
                self._crop_sent = (crop_id, self._clock())
            if find_id is not None:
                self._find_crop_sent = (find_id, self._clock())
        for candidate_id, position, mission in pending:
            taken = False
            try:
                self._client.reject(
                    candidate_id or None, position=position, reason="supervisor rejected", mission_id=mission
                )
                taken = True
            except Exception as exc:
                if getattr(exc, "retryable", True):
                    raise  # unreachable or busy: the same rejection goes again next round
                # Refused for good (unknown candidate, bad request): sending it again cannot help.
                log.warning("back-end refused the rejection of %s: %s", candidate_id, exc)
            with self._lock:
                self._rejections.popleft()
                if taken and candidate_id:
                    self._shared.append(candidate_id)
        self._fleet_round(status)
        decisions = self._client.decisions(after=self._after)
        with self._lock:
            for d in decisions:
                self._after = max(self._after, d.decision_id)
                if not self._primed or d.source == "vehicle":
                    continue  # history, or this vehicle's own decision (from its GCS) recorded by the back-end
                cid = d.candidate_id
                self._commands.append(
                    # The GCS line names who and through what: "supervisor page", "Ops via back-end API".
                    ConfirmCandidate(cid, by=gcs_text(decided_via(d.source, d.via), d.operator))
                    if d.action == "confirm"
                    else RejectCandidate(cid)
                )
            self._primed = True
            self._last_success = self._clock()

    def _fleet_round(self, status: dict[str, Any] | None) -> None:
        """The start's on_find set once, then the fleet's order for this vehicle's mission."""
        mission = status.get("mission_id") if status else None
        with self._lock:
            pending = self._on_find
        if pending is not None:
            try:
                self._client.set_on_find(*pending)
                refused = ""
            except Exception as exc:
                if getattr(exc, "status", None) != 409:
                    raise  # unreachable or busy: set again next round
                refused = f"on_find {pending[1]} refused: {getattr(exc, 'detail', exc)}"
                log.warning("%s", refused)
            with self._lock:
                if self._on_find == pending:
                    self._on_find, self._on_find_refused = None, refused
        if not mission or self._clock() - self._fleet_asked < FLEET_POLL_S:
            return
        self._fleet_asked = self._clock()
        order = self._client.fleet_order(str(mission))
        with self._lock:
            self._fleet = order if order.mission_id == str(mission) else None
