"""What the back-end says about one candidate in a keyframe."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from behaviors.geometry import Box


class Verdict(str, Enum):
    YES = "yes"
    NO = "no"
    UNCERTAIN = "uncertain"


@dataclass(frozen=True)
class Detection:
    """One candidate: a box in keyframe pixels, the detector's score and the verifier's verdict."""

    box: Box
    score: float
    label: str = "person"
    verdict: Verdict = Verdict.UNCERTAIN
    justification: str = ""
    candidate_id: str = ""
    # Optional appearance signature (e.g. a normalised colour histogram of the crop), plain numbers so
    # the rejection memory can recognise a rejected person again; empty when the back-end sends none.
    signature: tuple[float, ...] = ()
    # The verifier's measure of the person's extent (their body, without the shadow or a neighbour the
    # detector's box may hold), when it found one. A new track starts on it (`start_box`); re-detection
    # judges the detector's box, the one every answer has, so the track's boxes stay comparable.
    body_box: Box | None = None
    # False when nothing judged the description past the detector's class: no verifier, or one that can
    # check nothing it names ("the wakeboarder being towed", "a dog"). Its "uncertain" is then the
    # whole check there will ever be, and a search may start on it (`select_first_acquisition`).
    judged: bool = True
    # Whether the candidate stands where the description places the target relative to a vehicle it
    # names: outside "the boat" a wakeboarder is towed behind, inside "the red car" someone sits in
    # (`backend.placement`). None: no such vehicle named, or none in view. Ranks, never rejects.
    placement_ok: bool | None = None

    @property
    def start_box(self) -> Box:
        return self.body_box if self.body_box is not None else self.box
