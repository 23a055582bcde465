"""Relations between people that a description states and a crop-level verifier cannot judge.

"the person walking between the man in red and the man in green" names the target by where it stands
among the others. A verifier that sees one crop at a time cannot check that; the candidates' boxes can.
Only relations that read the same from any viewpoint are parsed: "between" (a drone's camera turns, so
"left of" in the image is not the speaker's left). A relation narrows a choice only where it can be
evaluated (enough candidates in view and some satisfying it); otherwise it changes nothing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from behaviors.geometry import Box

_BETWEEN = re.compile(r"\b(?:between|in the middle of|amid|amidst)\b", re.IGNORECASE)


@dataclass(frozen=True)
class Relation:
    kind: Literal["between"]
    # How far off the line joining the two others the candidate's centre may be, in that line's length.
    max_offset: float = 0.5


def parse_relation(prompt: str) -> Relation | None:
    """The viewpoint-independent relation the description states, or None."""
    return Relation("between") if _BETWEEN.search(prompt) else None


def is_between(box: Box, a: Box, b: Box, max_offset: float = 0.5) -> bool:
    """`box`'s centre projects strictly between the centres of `a` and `b`, near the line joining them."""
    ax, ay, bx, by = a.cx, a.cy, b.cx, b.cy
    dx, dy = bx - ax, by - ay
    length_sq = dx * dx + dy * dy
    if length_sq <= 0:
        return False
    t = ((box.cx - ax) * dx + (box.cy - ay) * dy) / length_sq
    offset = abs((box.cx - ax) * dy - (box.cy - ay) * dx) / math.sqrt(length_sq)
    return 0.0 < t < 1.0 and offset <= max_offset * math.sqrt(length_sq)


def satisfies(relation: Relation, box: Box, others: Sequence[Box]) -> bool:
    """Whether `box` stands in `relation` to some of `others` (every other box in view, not itself)."""
    if relation.kind == "between":
        return any(
            is_between(box, others[i], others[j], relation.max_offset)
            for i in range(len(others))
            for j in range(i + 1, len(others))
        )
    return False


def narrow_by_relation(relation: Relation | None, chosen: Sequence[int], boxes: Sequence[Box]) -> list[int]:
    """The indices of `chosen` (into `boxes`, every candidate in view) that satisfy `relation` with the
    others; all of `chosen` when there is no relation or none satisfies it."""
    if relation is None:
        return list(chosen)
    kept = [i for i in chosen if satisfies(relation, boxes[i], [b for j, b in enumerate(boxes) if j != i])]
    return kept or list(chosen)
