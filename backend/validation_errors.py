"""The answer to invalid input: the first few validation errors and how many there were, never the input.

FastAPI's default echoes the input back (and JSON cannot encode a NaN or Infinity it was sent) and lists
every error: a status of 150,000 unknown keys once drew a 13.5 MB answer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from fastapi.encoders import jsonable_encoder

ERRORS_SHOWN = 5


def summary(errors: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """`{"detail": [the first ERRORS_SHOWN errors as {type, loc, msg}], "error_count": n}`."""
    shown = [{"type": e["type"], "loc": list(e["loc"]), "msg": e["msg"]} for e in errors[:ERRORS_SHOWN]]
    return {"detail": jsonable_encoder(shown), "error_count": len(errors)}
