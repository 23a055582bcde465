"""Where a description places the target: relations parsed once, judged on the keyframe's boxes.

"the second white llama from the left", "the red boat next to the pier", "the pink ball at the feet of the
man in the green hoodie", "the person walking between the man in red and the man in green": a verifier
that sees one crop at a time cannot check where the target stands; the boxes of the whole keyframe can.
`parse_description` splits a description into the words about the target itself (`Description.own`, what
a crop verifier judges) and its relations, each with the other object's phrase where it names one
(`Relation.reference`: the back-end locates it with its detector, `backend.scene`). The judges below
work on boxes only:

- among the target's own kind: an ordinal along an axis of the image ("the second from the left", "the
  leftmost", "closest to the camera", "first in the queue"), a side ("the car on the left"), "between";
- relative to another object: next to, at the feet of, behind, in front of, on, in, under, above, left or
  right of, in the middle of, with;
- never judged from boxes: lanes and headings ("in the same lane", "heading north"): `uncertain`.

Left, right, top and bottom are the image's, as the operator sees the drone's video when describing the
target; "near" and "far" read an oblique camera (the lower a box's foot in the image, the nearer).
Relations rank the first choice of a search (`behaviors.candidate_selection`); they never make a
candidate a "no", since the view turns with the drone and a misread phrase must not rule the target out.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from behaviors.geometry import Box

Axis = Literal["left", "right", "top", "bottom", "near", "far", "front"]
Kind = Literal[
    "between",  # among the others in view, or between the named ones
    "ordinal",  # rank `rank` along `axis` among the target's own kind
    "side",  # on the `axis` side of the others of its kind ("the car on the left")
    "closest_to",  # the nearest of its kind to the reference ("the boat closest to the pier")
    "near",  # next to, beside, close to, by, at, with (a companion), along
    "at_feet",
    "behind",
    "in_front",
    "on",  # on, on top of, crossing
    "inside",  # in, inside, aboard
    "outside",
    "under",
    "above",
    "left_of",
    "right_of",
    "middle_of",  # in the middle of a single named thing ("in the middle of the intersection")
    "with",  # "with X": a companion when X is an object the detector knows, else a part or attribute
    "lane",  # in the same lane: lanes are not seen in boxes
    "heading",  # heading north, towards the shore: motion is not seen in one keyframe
]
# Relations whose truth cannot be read from boxes at all: always uncertain, reported as not judged.
UNJUDGEABLE: frozenset[str] = frozenset({"lane", "heading"})
# Relations among the target's own kind (no reference object to locate).
AMONG_OWN_KIND: frozenset[str] = frozenset({"ordinal", "side"})

ORDINALS: dict[str, int] = {
    "first": 1, "1st": 1, "second": 2, "2nd": 2, "third": 3, "3rd": 3, "fourth": 4, "4th": 4,
    "fifth": 5, "5th": 5, "sixth": 6, "6th": 6, "seventh": 7, "7th": 7, "eighth": 8, "8th": 8,
    "ninth": 9, "9th": 9, "tenth": 10, "10th": 10, "last": -1, "second to last": -2,
    "second-to-last": -2, "next to last": -2, "next-to-last": -2, "penultimate": -2,
}  # fmt: skip
_DIRECTIONS: dict[str, Axis] = {
    "left": "left", "right": "right", "top": "top", "bottom": "bottom", "front": "front", "back": "front",
    "rear": "front", "near side": "near", "far side": "far", "upper": "top", "lower": "bottom",
}  # fmt: skip
# Words that name a line of things waiting or moving one behind the other.
_GROUPS = r"(?:queue|line|row|column|convoy|traffic|group|pack|procession|file|herd|flock|cars|vehicles)"
_ORD = r"(?:second[- ]to[- ]last|next[- ]to[- ]last|penultimate|first|1st|second|2nd|third|3rd|fourth|4th|fifth|5th|sixth|6th|seventh|7th|eighth|8th|ninth|9th|tenth|10th|last)"
_WORD = r"[a-z][a-z'-]*"
# A word between an ordinal and its direction ("the second white llama from the left"), never a preposition.
_GAP_WORD = rf"(?!(?:in|of|on|at|to|from|by|with|near|next|behind)\b){_WORD}"
# A noun phrase starts with one of these (so "walking a dog" names a dog, "walking on" does not).
_DETERMINERS = r"(?:the|a|an|his|her|their|its|my|our|your|this|that|two|three|some)"
_CAMERA = r"(?:the\s+)?(?:camera|drone|viewer|observer|photographer|us|me|lens)"

RelationParser = Callable[["re.Match[str]"], tuple["Relation", list[tuple[int, int]]]]


@dataclass(frozen=True)
class Relation:
    kind: Kind
    text: str  # the words as written ("second from the left", "next to the pier")
    reference: str = ""  # the other object's phrase; "" when relative to the target's own kind
    axis: Axis | None = None  # ordinal and side
    rank: int = 1  # ordinal: 1 first, 2 second ..., -1 last, -2 second to last
    # "between": how far off the line joining the two others the candidate's centre may be, in its length
    max_offset: float = 0.5


@dataclass(frozen=True)
class Description:
    own: str  # the words about the target itself, relations taken out
    relations: tuple[Relation, ...] = field(default_factory=tuple)


def _ordinal_rank(word: str) -> int:
    return ORDINALS[re.sub(r"\s+", " ", word.replace("-", " "))]


def _direction(word: str) -> Axis:
    return _DIRECTIONS[re.sub(r"\s+", " ", word)]


# Each pattern finds one relation; `reference` groups run to the next relation (filled in by the parser).
# Patterns are tried at each position in this order; the longest match at the earliest position wins.
_PATTERNS: list[tuple[str, str]] = [
    # ---- ordinals among the target's own kind ----
    # "first in the queue", "the second car in the line", "last in line"
    ("queue", rf"\b(?P<ord>{_ORD})\b(?P<gap>(?:\s+{_GAP_WORD}){{0,3}}?)\s+(?P<tail>(?:in|of)\s+(?:the\s+)?{_GROUPS})\b"),
    # "at the front of the traffic", "at the head of the queue", "at the back of the line", "leading the convoy"
    ("queue_end", rf"\b(?:at|in)\s+the\s+(?P<end>front|head|start|back|end|rear|tail)\s+of\s+(?:the\s+)?{_GROUPS}\b"),
    ("queue_end", r"\b(?P<end>in\s+front)\s+of\s+(?:the\s+)?(?:queue|line|row|traffic|convoy|column)\b"),
    ("queue_end", rf"\b(?P<end>leading)\s+(?:the\s+)?{_GROUPS}\b"),
    # "second from the left", "the third white llama from the right", "the first one on the left"
    ("ordinal", rf"\b(?P<ord>{_ORD})\b(?P<gap>(?:\s+{_GAP_WORD}){{0,4}}?)\s+(?P<tail>(?P<prep>from|on|at|to)\s+the\s+(?P<dir>left|right|top|bottom|front|back|rear))\b(?!\s+of\b)"),
    ("ordinal", rf"\b(?P<ord>{_ORD})\s+(?:one\s+)?counting\s+from\s+the\s+(?P<dir>left|right|top|bottom)\b"),
    # "the leftmost", "right-most", "furthest to the left", "on the far left"
    ("extreme", r"\b(?P<dir>left|right|top|bottom|upper|lower)[- ]?most\b"),
    ("extreme", r"\b(?:furthest|farthest|furthermost)\s+(?:to\s+the\s+)?(?P<dir>left|right)\b"),
    ("extreme", r"\b(?:on|at|to)\s+the\s+(?:far|extreme|very)\s+(?P<dir>left|right)\b"),
    ("extreme", r"\b(?:at\s+the\s+)?(?P<dir>top|bottom)\s+of\s+the\s+(?:image|picture|frame|screen|view)\b"),
    # "closest to the camera", "the nearest", "farthest away", "most distant"
    ("near_camera", rf"\b(?P<word>nearest|closest)(?:\s+(?:one|to\s+{_CAMERA}|to\s+the\s+bottom))?\b"),
    ("far_camera", rf"\b(?P<word>furthest|farthest|most\s+distant|furthermost)(?:\s+(?:one|away|back|from\s+{_CAMERA}))?\b"),
    # "the car on the left", "on the right-hand side"; "of X" makes it a relation to X (below)
    ("side", r"\b(?:on|to|at|in)\s+the\s+(?P<dir>left|right)(?:[- ]hand)?(?:\s+side)?\b(?!\s+of\b)"),
    # "in the middle", "the middle one", "in the centre" (among its own kind: between two others)
    ("middle", r"\b(?:in\s+the\s+(?:middle|centre|center)|(?:the\s+)?(?:middle|centre|center)\s+one)\b(?!\s+of\b)"),
    # ---- relations to other objects (the reference runs to the next relation) ----
    ("lane", rf"\bin\s+(?:the|its|his|her|their|my|our|this|that)(?:\s+{_WORD})?\s+lane\b(?:\s+as)?"),
    ("lane", r"\b(?:same|next|other|left|right|middle|outer|inner|fast|slow)\s+lane\b"),
    ("heading", r"\b(?:heading|driving|moving|going|walking|swimming|flying|sailing)\s+(?:north|south|east|west|towards?|away\s+from|to)\b"),
    ("heading", r"\b(?:towards?|away\s+from)\b"),
    ("between", r"\b(?:between|amid|amidst|among|amongst)\b"),
    ("between", r"\bin\s+the\s+(?:middle|centre|center)\s+of\s+(?=(?:the\s+)?(?:two|three|four|several|both|group|crowd|others|pair|rest)\b)"),
    ("middle_of", r"\bin\s+the\s+(?:middle|centre|center)\s+of\b"),
    ("at_feet", r"\b(?:at|by|near|beside)\s+the\s+(?:feet|foot)\s+of\b"),
    ("at_feet_possessive", rf"\b(?:at|by|near|beside)\s+(?P<ref>(?:{_DETERMINERS}\s+)?(?:{_WORD}\s+){{0,3}}?{_WORD})'s?\s+(?:feet|foot)\b"),
    ("closest_to", rf"\b(?:nearest|closest)\s+(?:to\s+)?(?!{_CAMERA}\b)(?={_DETERMINERS}\b)"),
    ("left_of", r"\b(?:(?:on|to|at)\s+the\s+)?left(?:[- ]hand)?(?:\s+side)?\s+of\b"),
    ("right_of", r"\b(?:(?:on|to|at)\s+the\s+)?right(?:[- ]hand)?(?:\s+side)?\s+of\b"),
    ("in_front", r"\b(?:in\s+front\s+of|ahead\s+of|followed\s+by)\b"),
    ("behind", r"\b(?:behind|following|trailing|(?:towed|pulled|chased)\s+by|at\s+the\s+back\s+of)\b"),
    ("near", r"\b(?:next\s+to|beside|besides|alongside|near|nearby|close\s+to|close\s+by|by|along|around|surrounded\s+by)\b"),
    ("under", r"\b(?:under|underneath|beneath|below)\b"),
    ("above", r"\b(?:above|over)\b"),
    ("on", r"\b(?:on\s+top\s+of|atop|crossing)\b"),
    ("inside", r"\b(?:inside|aboard|onboard|on\s+board(?:\s+of)?|within)\b"),
    ("outside", r"\b(?:outside(?:\s+of)?|out\s+of)\b"),
    # "in", "on", "at", "with" and the verbs of carrying or riding take another object only when what
    # follows is not an attribute of the target ("in a red shirt", "with a hat"): decided by the caller's
    # `attribute_words` (below).
    ("contact", r"\b(?P<prep>in|on|at|with)\s+(?=[a-z])"),
    ("contact", rf"\b(?P<prep>riding|carrying|holding|pushing|pulling|walking|towing|driving|steering)\s+(?={_DETERMINERS}\b)"),
    # A bare ordinal ("the last llama", "the first car"): the order of a line of them, front first.
    ("bare_ordinal", rf"\b(?P<ord>{_ORD})\b"),
]  # fmt: skip
_COMPILED = [(name, re.compile(pattern)) for name, pattern in _PATTERNS]
_CONTACT_KIND: dict[str, Kind] = {
    "in": "inside", "on": "on", "at": "near", "with": "with", "riding": "on", "carrying": "with",
    "holding": "with", "pushing": "with", "pulling": "with", "walking": "with", "towing": "with",
    "driving": "inside", "steering": "inside",
}  # fmt: skip
# Kinds that are followed by the other object's phrase.
_TAKES_REFERENCE: frozenset[str] = frozenset({
    "between", "closest_to", "near", "at_feet", "behind", "in_front", "on", "inside", "outside", "under",
    "above", "left_of", "right_of", "middle_of", "with", "lane",
})  # fmt: skip


@dataclass
class _Found:
    start: int
    end: int
    relation: Relation
    consumed: list[tuple[int, int]]  # spans of the prompt that belong to the relation, not to `own`
    takes_reference: bool


def _match_relation(name: str, m: re.Match[str], text: str) -> _Found | None:
    """The relation one pattern's match states, or None when the match is not one."""
    words = text[m.start() : m.end()].strip()
    span = [(m.start(), m.end())]
    if name == "queue":
        rank = _ordinal_rank(m.group("ord"))
        consumed = [(m.start("ord"), m.end("ord")), (m.start("tail"), m.end("tail"))]
        text_of = f"{m.group('ord')} {m.group('tail')}"
        return _Found(
            m.start(), m.end(), Relation("ordinal", text_of, axis="front", rank=rank), consumed, False
        )
    if name == "bare_ordinal":
        rank = _ordinal_rank(m.group("ord"))
        return _Found(m.start(), m.end(), Relation("ordinal", words, axis="front", rank=rank), span, False)
    if name == "queue_end":
        end = m.group("end")
        rank = -1 if end in ("back", "end", "rear", "tail") else 1
        return _Found(m.start(), m.end(), Relation("ordinal", words, axis="front", rank=rank), span, False)
    if name == "ordinal":
        rank = _ordinal_rank(m.group("ord"))
        axis = _direction(m.group("dir"))
        if "prep" in m.groupdict() and m.group("prep") in ("on", "at", "to") and rank < 0:
            rank = 1  # "the last one on the left": the far end on that side
        consumed = [(m.start("ord"), m.end("ord"))]
        tail_start = m.start("tail") if "tail" in m.groupdict() else m.end("ord")
        consumed.append((tail_start, m.end()))
        gap = m.group("gap").strip() if "gap" in m.groupdict() and m.group("gap") else ""
        text_of = words if not gap else f"{m.group('ord')} {text[tail_start : m.end()].strip()}"
        return _Found(m.start(), m.end(), Relation("ordinal", text_of, axis=axis, rank=rank), consumed, False)
    if name == "extreme":
        return _Found(
            m.start(),
            m.end(),
            Relation("ordinal", words, axis=_direction(m.group("dir")), rank=1),
            span,
            False,
        )
    if name in ("near_camera", "far_camera"):
        axis = "near" if name == "near_camera" else "far"
        return _Found(m.start(), m.end(), Relation("ordinal", words, axis=axis, rank=1), span, False)
    if name == "side":
        side: Axis = m.group("dir")  # type: ignore[assignment]
        return _Found(m.start(), m.end(), Relation("side", words, axis=side), span, False)
    if name == "middle":
        return _Found(m.start(), m.end(), Relation("between", words), span, False)
    if name == "heading":
        return _Found(m.start(), m.end(), Relation("heading", words), span, True)
    if name == "at_feet_possessive":
        return _Found(m.start(), m.end(), Relation("at_feet", words, reference=m.group("ref")), span, False)
    if name == "contact":
        prep = m.group("prep")
        kind = _CONTACT_KIND[prep]
        return _Found(m.start(), m.end(), Relation(kind, words), span, True)
    kind_of: Kind = name  # type: ignore[assignment]
    return _Found(m.start(), m.end(), Relation(kind_of, words), span, kind_of in _TAKES_REFERENCE)


def _next_relation(text: str, start: int, attribute_words: frozenset[str]) -> _Found | None:
    """The first relation at or after `start` (the longest of those starting there)."""
    best: _Found | None = None
    for name, pattern in _COMPILED:
        for m in pattern.finditer(text, start):
            if best is not None and m.start() > best.start:
                break
            found = _match_relation(name, m, text)
            if found is None:
                continue
            if name == "contact" and _is_attribute(text, m.end(), attribute_words):
                continue
            if best is None or (found.start, -found.end) < (best.start, -best.end):
                best = found
            break
    return best


# A phrase after "in", "on", "with" ... is the target's own attribute when its head noun (its last word
# before the next preposition, conjunction or participle) is an attribute word: a garment or a colour
# ("in a red shirt", "with red hair", "in black"); else it names another object ("in the red car").
_PHRASE_ENDS = frozenset({
    "and", "or", "in", "on", "at", "with", "of", "by", "near", "next", "behind", "between", "beside", "who",
    "that", "which", "while", "from", "to", "under", "over", "above", "below", "across", "along", "around",
})  # fmt: skip


def _is_attribute(text: str, start: int, attribute_words: frozenset[str]) -> bool:
    head = ""
    for word in re.findall(r"[a-z]+(?:-[a-z]+)*", text[start:]):
        participle = word.endswith("ing") and bool(head)
        superlative = (word.endswith("est") and len(word) >= 6) or word.endswith("most")
        if word in _PHRASE_ENDS or word in ORDINALS or participle or superlative:
            break
        head = word
    return head in attribute_words or any(part in attribute_words for part in head.split("-"))


def _reference(text: str) -> str:
    """The other object's phrase: leading "of"/"to" dropped, trailing "as" and punctuation trimmed."""
    phrase = re.sub(r"^(?:of|to|as)\s+", "", text.strip(" ,.;:"))
    return re.sub(r"\s+(?:as|and|or|,)$", "", phrase).strip(" ,.;:")


def parse_description(prompt: str, attribute_words: frozenset[str] = frozenset()) -> Description:
    """The target's own words and the relations the description states, in order.

    `attribute_words` are the words that make "in ...", "on ...", "with ..." an attribute of the target
    ("a man in a red shirt", "with a hat") instead of another object ("in the boat", "with the dog"): the
    back-end passes its garment, colour and pattern words.
    """
    text = " ".join(prompt.lower().split())
    found: list[_Found] = []
    position = 0
    while position < len(text):
        nxt = _next_relation(text, position, attribute_words)
        if nxt is None:
            break
        found.append(nxt)
        position = max(nxt.end, position + 1)
    relations = []
    for i, item in enumerate(found):
        relation = item.relation
        if item.takes_reference:
            stop = found[i + 1].start if i + 1 < len(found) else len(text)
            reference = _reference(text[item.end : stop])
            if reference:
                relation = Relation(relation.kind, f"{relation.text} {reference}", reference, relation.axis)
            item.consumed = [(item.start, stop)]
        relations.append(relation)
    # The target's own words: everything before the first relation to another object, minus the words
    # of relations among its own kind ("the second white llama from the left" -> "the white llama").
    first_reference = next((f.start for f in found if f.takes_reference), len(text))
    own = text[:first_reference]
    for item in sorted(found, key=lambda f: -f.start):
        for start, end in sorted(item.consumed, reverse=True):
            if start < len(own):
                own = own[:start] + " " + own[min(end, len(own)) :]
    return Description(" ".join(own.split()), tuple(relations))


# ---------------------------------------------------------------------------------------------------
# Judging relations on boxes. `boxes` are every candidate of the target's kind in view; judgements are
# per candidate: True (fits), False (does not), None (cannot be judged here).

Judgement = bool | None
NEAR_SIZES = 1.5  # "next to": the gap between the boxes at most this many times the larger one's size
TIE_FRACTION = 0.25  # ordinal neighbours closer than this share of their size along the axis: a tie
QUEUE_ROOM_RATIO = 1.3  # a queue's front has at least this much more free image ahead than its back
GROUP_GAP_SIZES = 1.5  # boxes this close (gap over size) belong to one group (a queue, a herd)
INSIDE_SHARE = 0.8  # a box this much within another is inside it (an occupant of a boat)
# Relations that allow the candidate to lie within the other object's box.
_HOLDS = frozenset({"inside", "on", "with", "at_feet", "middle_of", "under", "above"})


def size(box: Box) -> float:
    return math.sqrt(max(box.area, 0.0))


def gap(a: Box, b: Box) -> float:
    """The distance between two boxes (0 when they touch or overlap)."""
    dx = max(0.0, max(a.x, b.x) - min(a.x2, b.x2))
    dy = max(0.0, max(a.y, b.y) - min(a.y2, b.y2))
    return math.hypot(dx, dy)


def inside_share(box: Box, other: Box) -> float:
    """The share of `box`'s area that lies within `other`."""
    w = min(box.x2, other.x2) - max(box.x, other.x)
    h = min(box.y2, other.y2) - max(box.y, other.y)
    return w * h / box.area if w > 0 and h > 0 and box.area > 0 else 0.0


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


def fits_reference(kind: Kind, box: Box, ref: Box) -> bool:
    """Whether `box` stands in relation `kind` to one object at `ref` (the image's view: an oblique camera,
    so "behind" is farther up the image and "in front" nearer its bottom)."""
    scale = max(size(box), size(ref))
    close = gap(box, ref) <= NEAR_SIZES * scale
    overlaps_x = box.x < ref.x2 + 0.5 * ref.w and box.x2 > ref.x - 0.5 * ref.w
    if kind in ("near", "with"):
        return close
    if kind == "at_feet":
        # Its centre near the other's feet: around the bottom edge, within half the other's height.
        return abs(box.cy - ref.y2) <= 0.5 * ref.h and abs(box.cx - ref.cx) <= ref.w / 2 + 0.5 * ref.h
    if kind == "behind":
        return close and overlaps_x and box.y2 < ref.y2
    if kind == "in_front":
        return close and overlaps_x and box.y2 > ref.y2
    if kind == "on":
        return ref.x <= box.cx <= ref.x2 and ref.y <= box.y2 <= ref.y2 + 0.1 * ref.h
    if kind == "inside":
        return inside_share(box, ref) >= INSIDE_SHARE
    if kind == "outside":
        return inside_share(box, ref) < INSIDE_SHARE
    if kind == "under":
        return overlaps_x and box.cy > ref.y2 - 0.25 * ref.h and gap(box, ref) <= NEAR_SIZES * scale
    if kind == "above":
        return overlaps_x and box.y2 < ref.y + 0.25 * ref.h and gap(box, ref) <= NEAR_SIZES * scale
    if kind in ("left_of", "right_of"):
        level = abs(box.cy - ref.cy) <= max(box.h, ref.h)
        beside = box.cx < ref.x if kind == "left_of" else box.cx > ref.x2
        return level and beside
    if kind == "middle_of":
        return abs(box.cx - ref.cx) <= ref.w / 4 and abs(box.cy - ref.cy) <= ref.h / 4
    raise ValueError(f"{kind!r} is not a relation to another object")


def judge_reference(relation: Relation, box: Box, references: Sequence[Box] | None) -> Judgement:
    """`relation` to another object for one candidate: None when the object was not located
    (`references` None) or the relation cannot be read from boxes; with several located ones, it fits
    when it fits any of them ("between": some two of them). A candidate inside a named object apart from
    it (not "in", "on", "with") does not fit: an occupant of the boat is not the man next to it."""
    if relation.kind in UNJUDGEABLE or references is None:
        return None
    refs = [r for r in references if r.is_valid() and r != box]
    if relation.kind == "between":
        return any(
            is_between(box, refs[i], refs[j], relation.max_offset)
            for i in range(len(refs))
            for j in range(i + 1, len(refs))
        )
    if relation.kind == "outside":
        return all(fits_reference("outside", box, r) for r in refs)
    if relation.kind not in _HOLDS and any(inside_share(box, r) >= INSIDE_SHARE for r in refs):
        return False  # inside the object it is named apart from: one of its occupants
    return any(fits_reference(relation.kind, box, r) for r in refs)


def _axis_key(axis: Axis, box: Box) -> float:
    """Position along an axis, smallest first ("near": the lowest foot in the image first)."""
    return {
        "left": box.cx,
        "right": -box.cx,
        "top": box.cy,
        "bottom": -box.cy,
        "near": -box.y2,
        "far": box.y2,
    }[axis]


def groups(boxes: Sequence[Box], pool: Sequence[int]) -> list[list[int]]:
    """The pool split into groups of boxes each within GROUP_GAP_SIZES of another (single linkage)."""
    remaining = list(pool)
    found = []
    while remaining:
        group = [remaining.pop(0)]
        grew = True
        while grew:
            grew = False
            for i in list(remaining):
                if any(
                    gap(boxes[i], boxes[j]) <= GROUP_GAP_SIZES * max(size(boxes[i]), size(boxes[j]))
                    for j in group
                ):
                    group.append(i)
                    remaining.remove(i)
                    grew = True
        found.append(sorted(group))
    return found


def queue_order(boxes: Sequence[Box], members: Sequence[int], view: tuple[float, float]) -> list[int] | None:
    """A queue's members front first, or None when its front cannot be told.

    The queue runs along the main axis of its members' centres; its front is the end with clearly more
    free image ahead of it (a waiting line trails back along the road, often out of view, while the place
    it waits for lies ahead of its first member in view).
    """
    if len(members) < 2:
        return None
    xs = [boxes[i].cx for i in members]
    ys = [boxes[i].cy for i in members]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    syy = sum((y - my) ** 2 for y in ys)
    sxy = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True))
    angle = 0.5 * math.atan2(2 * sxy, sxx - syy)
    ux, uy = math.cos(angle), math.sin(angle)
    along = {i: (boxes[i].cx - mx) * ux + (boxes[i].cy - my) * uy for i in members}
    ordered = sorted(members, key=lambda i: along[i])
    width, height = view

    def room(i: int, dx: float, dy: float) -> float:
        """Free image from box i's centre to the frame's edge in direction (dx, dy)."""
        box = boxes[i]
        limits = []
        if dx > 1e-9:
            limits.append((width - box.cx) / dx)
        if dx < -1e-9:
            limits.append(-box.cx / dx)
        if dy > 1e-9:
            limits.append((height - box.cy) / dy)
        if dy < -1e-9:
            limits.append(-box.cy / dy)
        return min(limits) if limits else 0.0

    low_room = room(ordered[0], -ux, -uy)
    high_room = room(ordered[-1], ux, uy)
    if max(low_room, high_room) < QUEUE_ROOM_RATIO * min(low_room, high_room):
        return None
    return ordered[::-1] if high_room > low_room else ordered


def judge_ordinal(
    relation: Relation, boxes: Sequence[Box], pool: Sequence[int], view: tuple[float, float]
) -> list[Judgement]:
    """An ordinal among the pool (the candidates of the target's kind that may be it): True for the one at
    the stated rank, False for the rest of the pool; None for all when the rank cannot be told (too few,
    a tie at that rank, a queue whose front cannot be told). Candidates outside the pool: False."""
    result: list[Judgement] = [False] * len(boxes)
    undecided: list[Judgement] = [None] * len(boxes)
    axis, rank = relation.axis, relation.rank
    if axis is None or len(pool) < max(2, abs(rank)):
        return undecided
    if axis == "front":
        group = max(groups(boxes, pool), key=len)
        order = queue_order(boxes, group, view)
        if order is None or len(order) < abs(rank):
            return undecided
        chosen = order[rank - 1] if rank > 0 else order[rank]
        for i in pool:
            result[i] = i == chosen
        return result
    order = sorted(pool, key=lambda i: _axis_key(axis, boxes[i]))
    k = rank - 1 if rank > 0 else len(order) + rank
    chosen = order[k]
    for neighbour in (k - 1, k + 1):
        if 0 <= neighbour < len(order):
            other = order[neighbour]
            separation = abs(_axis_key(axis, boxes[chosen]) - _axis_key(axis, boxes[other]))
            if separation < TIE_FRACTION * min(size(boxes[chosen]), size(boxes[other])):
                return undecided
    for i in pool:
        result[i] = i == chosen
    return result


def judge_side(relation: Relation, boxes: Sequence[Box], pool: Sequence[int]) -> list[Judgement]:
    """ "the car on the left": in the left part of where the pool spreads (left of the middle of its
    leftmost and rightmost centres); None when the pool does not spread (one candidate, or all in a
    column)."""
    result: list[Judgement] = [None] * len(boxes)
    if len(pool) < 2 or relation.axis is None:
        return result
    horizontal = relation.axis in ("left", "right")
    values = [boxes[i].cx if horizontal else boxes[i].cy for i in pool]
    low, high = min(values), max(values)
    if high - low < max(size(boxes[i]) for i in pool):
        return result
    middle = (low + high) / 2
    for i in pool:
        value = boxes[i].cx if horizontal else boxes[i].cy
        result[i] = value < middle if relation.axis in ("left", "top") else value > middle
    return result


def judge_closest(
    relation: Relation, boxes: Sequence[Box], pool: Sequence[int], references: Sequence[Box] | None
) -> list[Judgement]:
    """ "the boat closest to the pier": True for the pool's nearest to any located reference."""
    result: list[Judgement] = [None] * len(boxes)
    refs = [r for r in references or () if r.is_valid()]
    if not refs or not pool:
        return result
    distance = {i: min(gap(boxes[i], r) for r in refs if r != boxes[i]) for i in pool}
    best = min(distance.values())
    for i in pool:
        result[i] = distance[i] <= best + TIE_FRACTION * size(boxes[i])
    return result


def judge_relation(
    relation: Relation,
    boxes: Sequence[Box],
    pool: Sequence[int],
    references: Sequence[Box] | None,
    view: tuple[float, float],
) -> list[Judgement]:
    """One relation for every candidate. `pool`: the candidates that may be the target (ordinals count
    among them); `references`: the located boxes of the object the relation names (None: not located;
    for "between" among its own kind, the others of its kind in view)."""
    if relation.kind in UNJUDGEABLE:
        return [None] * len(boxes)
    if relation.kind == "ordinal":
        return judge_ordinal(relation, boxes, pool, view)
    if relation.kind == "side":
        return judge_side(relation, boxes, pool)
    if relation.kind == "closest_to":
        return judge_closest(relation, boxes, pool, references)
    if relation.kind == "between" and not relation.reference:
        return [judge_reference(relation, box, boxes) for box in boxes]
    return [judge_reference(relation, box, references) for box in boxes]


def combine(judgements: Sequence[Judgement]) -> Judgement:
    """All relations together: False if any is False, True if all are True, else None."""
    if any(j is False for j in judgements):
        return False
    if judgements and all(j is True for j in judgements):
        return True
    return None
