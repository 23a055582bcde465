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
    # Whether the candidate stands where the description places the target among what else is in view,
    # and has the size it says (`backend.scene`): "the second from the left", "next to the red car",
    # outside "the boat" a wakeboarder is towed behind, "the small truck". None: nothing of that could
    # be judged (no relation, or what it names is not in view). Ranks, never rejects.
    placement_ok: bool | None = None
    # The words of the description nothing judged for this candidate: words the verifier has no reading
    # for ("suv", "canopy roof") and relations to things not located ("next to the pier"). Its verdict
    # and placement hold for the rest only.
    unjudged: tuple[str, ...] = ()
    # An ordinal in the description ("the second from the left", "closest to the camera", "first in the
    # queue") picks this candidate alone among those of its kind not ruled out, and it fits the rest of
    # where the description places it. The rank identifies it where its look is uncertain.
    singled_out: bool = False

    @property
    def start_box(self) -> Box:
        return self.body_box if self.body_box is not None else self.box
