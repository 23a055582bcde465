"""Where a description places the target relative to a vehicle it names, checked on the keyframe.

"the wakeboarder being towed behind the boat" names the boat as another object: a person whose box lies
inside the boat's is one of its occupants, not the wakeboarder. "the man in the red car" names the car as
what holds the target: only people inside it fit. A crop-level verifier (a VLM sees one crop) cannot
check this; the detector's boxes of the whole keyframe can. Containment reads the same from any viewpoint
(unlike "left of"), and only vehicles people ride in are used: an occupant's box lies inside theirs (a
cyclist's does not lie inside the bicycle's). The result ranks candidates
(`behaviors.candidate_selection`); it never rejects one: a wrong parse must not make the described
person a "no".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from backend.supersets import COCO_VEHICLES, UnknownSupersetError, coco_classes_for, vocabulary, words
from behaviors.geometry import Box

# The nearest preposition before a vehicle's name (within `_LOOKBACK` words) says whether it holds the
# target ("sitting in the red car") or stands apart ("in the water near the boat"). Words that read
# either way ("of": the deck of / the left of; "from": waving from / fell from) decide nothing.
_HOLDING = frozenset(("in", "inside", "on", "onboard", "aboard", "riding", "driving", "steering"))
_APART = frozenset((
    "near", "next", "beside", "by", "behind", "under", "below", "over", "above", "off", "past", "around",
    "towards", "toward", "outside", "beyond", "alongside", "to", "than", "and", "or",
))  # fmt: skip
_LOOKBACK = 5
CARRIERS = tuple(c for c in COCO_VEHICLES if c not in ("bicycle", "motorbike"))
# A candidate is inside a vehicle when this share of its box lies within the vehicle's box.
INSIDE_SHARE = 0.8


@dataclass(frozen=True)
class NamedVehicle:
    coco_class: str  # "boat"
    holds_target: bool  # "in the boat": True; "behind the boat": False


def named_vehicles(prompt: str, superset: str) -> tuple[NamedVehicle, ...]:
    """The vehicles the description names besides the target (none of the superset's own classes) with a
    preposition that says whether it holds the target; the first mention of a class decides."""
    try:
        target_classes = set(coco_classes_for(superset))
    except UnknownSupersetError:
        target_classes = set()  # an open-vocabulary target: no vehicle is its own class
    tokens = words(prompt)
    found: dict[str, bool] = {}
    for start, _, target in vocabulary().mentions(tokens):
        if target in CARRIERS and target not in target_classes and target not in found:
            holds = _holds(tokens[max(0, start - _LOOKBACK) : start])
            if holds is not None:
                found[target] = holds
    return tuple(NamedVehicle(name, holds) for name, holds in found.items())


def _holds(before: Sequence[str]) -> bool | None:
    for word in reversed(before):
        if word in _HOLDING:
            return True
        if word in _APART:
            return False
    return None


def inside(box: Box, vehicle: Box) -> bool:
    """At least `INSIDE_SHARE` of `box`'s area lies within `vehicle`."""
    w = min(box.x2, vehicle.x2) - max(box.x, vehicle.x)
    h = min(box.y2, vehicle.y2) - max(box.y, vehicle.y)
    area = box.w * box.h
    return area > 0 and w > 0 and h > 0 and w * h >= INSIDE_SHARE * area


def placement_ok(box: Box, named: Sequence[NamedVehicle], seen: Sequence[tuple[str, Box]]) -> bool | None:
    """Whether a candidate stands where the description places the target: False inside a vehicle named
    apart from it, or outside every one seen of a class that holds it; True when every named vehicle that
    is in view agrees; None when none of them is in view (nothing to check)."""
    verdict: bool | None = None
    for vehicle in named:
        boxes = [b for label, b in seen if label == vehicle.coco_class]
        if not boxes:
            continue
        within = any(inside(box, b) for b in boxes)
        if within != vehicle.holds_target:
            return False
        verdict = True
    return verdict
