"""The interface every verifier implements, and what it answers."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from behaviors.detection import Verdict


@dataclass(frozen=True)
class VerifierAnswer:
    verdict: Verdict
    justification: str
    verifier: str  # which verifier decided (a cascade names the stage)
    # The object's extent (x, y, w, h in the crop's pixels) as the verifier saw it, e.g. a body model's
    # person mask; None when it measured none. The pipeline reports it instead of the detector's box,
    # which often takes in a shadow or a neighbour.
    box: tuple[float, float, float, float] | None = None
    # False when the verifier can check nothing the description names past its class: its answer is
    # then "uncertain" for every candidate, whatever they look like.
    judged: bool = True
    # The words of the target's own description it could not judge ("suv", "canopy roof", "striped"):
    # its verdict holds for the rest only. Empty for a verifier that reads the whole description (a VLM).
    unjudged: tuple[str, ...] = ()


def nothing_to_judge(verifier: str, unjudged: tuple[str, ...] = ()) -> VerifierAnswer:
    """The answer of a verifier that can check nothing the description names past the detector's class."""
    return VerifierAnswer(
        Verdict.UNCERTAIN,
        "no colour or posture named that can be judged from pixels",
        verifier,
        judged=False,
        unjudged=unjudged,
    )


class VerifierError(Exception):
    """The verifier could not answer (HTTP error, refused request, malformed reply)."""


class VerifierTimeout(VerifierError):
    """The verifier did not answer within its time budget."""


class Verifier(Protocol):
    name: str

    def verify(
        self,
        crop_bgr: np.ndarray,
        target_box: tuple[float, float, float, float],
        prompt: str,
        superset: str,
        timeout_s: float,
    ) -> VerifierAnswer:
        """Judge whether the object at `target_box` (x, y, w, h inside the crop) matches `prompt`."""
        ...
