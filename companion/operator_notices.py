"""Why the companion cannot do its job right now, in words the operator reads: one notice per topic.

Topics, most pressing first: the autopilot has not been heard ("waiting for the autopilot's HEARTBEAT on
udpin:0.0.0.0:14550"), the back-end refuses this vehicle's token (named as such, never "unreachable"),
the back-end does not answer ("waiting for the back-end at https://...: connection refused"), the
back-end cannot search for the mission's prompt (its 422, with the nearest classes), the last start
the companion refused, and keyframes too dark for the detection curve (`behaviors.scene_light`: the POD
map claims nothing for them). Whoever notices calls in (the main loop, the back-end session and worker
threads, the start check); the main loop says each change once — in the journal and on the GCS as a STATUSTEXT —
and every status report to the back-end carries the most pressing one as its `reason`, so the supervisor
page shows it too. Thread-safe; nothing here blocks.
"""

from __future__ import annotations

import threading

from cloudtrack.gcs_protocol import clip_reason

TOPICS = ("autopilot", "auth", "backend", "search", "start", "light")


def backend_problem(error: BaseException, url: str, request: str = "search") -> tuple[str, str]:
    """(topic, words) for a failed back-end request (`request`: "search", a keyframe; "status", the
    session's report and decisions): a refused token, a refused request, or silence."""
    status = getattr(error, "status", None)
    detail = str(getattr(error, "detail", "") or error)
    if status in (401, 403):
        words = f"the back-end refused this vehicle's token (HTTP {status}: {detail}); check [backend] token"
        return "auth", words
    if status is not None and status < 500 and status != 429:
        if request == "search" and status == 422:
            return "search", f"the back-end cannot search for this mission: {detail}"
        return "search", f"the back-end refused the {request} request (HTTP {status}: {detail})"
    return "backend", f"waiting for the back-end at {url}: {detail}"


class OperatorNotices:
    def __init__(self, autopilot_address: str = "", backend_url: str = "") -> None:
        self.autopilot_address = autopilot_address
        self.backend_url = backend_url
        self._lock = threading.Lock()
        self._current: dict[str, str] = {}
        self._changes: list[tuple[str, str | None]] = []

    def set(self, topic: str, text: str | None) -> None:
        """The notice of `topic` (None: it no longer holds); a change is queued to be said once."""
        assert topic in TOPICS, topic
        text = clip_reason(text) if text else None
        with self._lock:
            if self._current.get(topic) == text:
                return
            if text is None:
                self._current.pop(topic, None)
            else:
                self._current[topic] = text
            self._changes.append((topic, text))

    def autopilot_heard(self, heard: bool) -> None:
        self.set(
            "autopilot",
            None if heard else f"waiting for the autopilot's HEARTBEAT on {self.autopilot_address}",
        )

    def backend_answered(self) -> None:
        """A request succeeded: the back-end is there and takes the token (a refused search stays)."""
        self.set("auth", None)
        self.set("backend", None)

    def backend_failed(self, error: BaseException, request: str = "search") -> None:
        topic, text = backend_problem(error, self.backend_url, request)
        if topic != "backend":
            self.set("backend", None)  # it answered, with a refusal
        self.set(topic, text)

    def search_accepted(self) -> None:
        self.set("search", None)

    def current(self) -> str:
        """The most pressing notice, or "" when all is well."""
        with self._lock:
            return next((self._current[t] for t in TOPICS if t in self._current), "")

    def changes(self) -> list[tuple[str, str | None]]:
        """What changed since the last call, in order: (topic, the new notice or None once it cleared)."""
        with self._lock:
            changes, self._changes = self._changes, []
        return changes
