"""A failed connection's reason in a few words, for a person: never urllib3's nested exception text."""

from __future__ import annotations

_MARKERS = (
    ("NameResolutionError", "name resolution failed"),
    ("Name or service not known", "name resolution failed"),
    ("Temporary failure in name resolution", "name resolution failed"),
    ("Connection refused", "connection refused"),
    ("Network is unreachable", "network unreachable"),
    ("No route to host", "no route to host"),
    ("timed out", "timed out"),
    ("RemoteDisconnected", "connection closed by the server"),
    ("Connection reset", "connection reset"),
)


def connection_cause(exc: BaseException) -> str:
    """The innermost reason of a requests/urllib3 connection error, in a few words."""
    text = str(exc)
    for marker, words in _MARKERS:
        if marker in text:
            return words
    return "connection failed"
