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
