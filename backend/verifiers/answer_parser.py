"""Turning a VLM's free-text or JSON reply into yes / no / uncertain plus its justification.

Models answer "Answer: Yes.", "**Answer:** no", a bare "Yes", a JSON object, or ramble. The last
explicit answer wins; anything without one is UNCERTAIN (the caller's policy decides what that means).
"""

from __future__ import annotations

import json
import re

from behaviors.detection import Verdict

_WORDS = {
    "yes": Verdict.YES, "y": Verdict.YES, "true": Verdict.YES, "match": Verdict.YES, "matches": Verdict.YES,
    "no": Verdict.NO, "n": Verdict.NO, "false": Verdict.NO, "mismatch": Verdict.NO,
    "uncertain": Verdict.UNCERTAIN, "unsure": Verdict.UNCERTAIN, "maybe": Verdict.UNCERTAIN,
    "unknown": Verdict.UNCERTAIN, "unclear": Verdict.UNCERTAIN,
}  # fmt: skip
_ANSWER_KEYS = ("answer", "verdict", "match", "decision", "result")
_REASON_KEYS = ("justification", "reason", "reasoning", "explanation", "rationale")
_MARKER = re.compile(r"(?:final\s+)?answer\s*[*_]*\s*[:=\-]\s*[*_\"'`]*\s*([a-z]+)", re.IGNORECASE)
_BARE = re.compile(r"^[\s*_\"'`]*([a-z]+)[\s.!*_\"'`]*$", re.IGNORECASE)


def _from_json(text: str) -> tuple[Verdict, str] | None:
    start, end = text.find("{"), text.rfind("}")
    if start < 0 or end <= start:
        return None
    try:
        data = json.loads(text[start : end + 1])
    except json.JSONDecodeError:
        return None
    if not isinstance(data, dict):
        return None
    lowered = {str(k).lower(): v for k, v in data.items()}
    value = next((lowered[k] for k in _ANSWER_KEYS if k in lowered), None)
    if isinstance(value, bool):
        verdict: Verdict | None = Verdict.YES if value else Verdict.NO
    elif isinstance(value, str):
        verdict = _WORDS.get(value.strip().strip(".!").lower())
    else:
        verdict = None
    if verdict is None:
        return None
    reason = next((str(lowered[k]) for k in _REASON_KEYS if k in lowered), "")
    return verdict, reason


def parse_answer(text: str) -> tuple[Verdict, str]:
    """(verdict, justification) from a model's reply; UNCERTAIN when no explicit answer is found."""
    stripped = re.sub(r"```(?:json)?", "", text or "").strip()
    if not stripped:
        return Verdict.UNCERTAIN, ""
    parsed = _from_json(stripped)
    if parsed is not None:
        return parsed
    markers = list(_MARKER.finditer(stripped))
    for match in reversed(markers):
        verdict = _WORDS.get(match.group(1).lower())
        if verdict is not None:
            return verdict, stripped[: match.start()].strip() or stripped
    bare = _BARE.match(stripped)
    if bare and bare.group(1).lower() in _WORDS:
        return _WORDS[bare.group(1).lower()], ""
    # A reply whose last line starts with a clear yes/no ("...\nYes, the shirt is gray.").
    last_line = stripped.splitlines()[-1].strip(" *_\"'`")
    first = re.match(r"([a-z]+)\b", last_line, re.IGNORECASE)
    if first and first.group(1).lower() in ("yes", "no"):
        return _WORDS[first.group(1).lower()], stripped
    return Verdict.UNCERTAIN, stripped
