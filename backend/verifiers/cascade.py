"""Fast then slow: the local colour check first, the VLM only for candidates it cannot rule out.

A clear local "no" (a named colour is absent from its region) ends the verification without the VLM;
"yes" and "uncertain" go on to the VLM, whose answer is final. This is the combination of fast and slow
verifiers the paper names as future work; it saves VLM calls on crowds of obviously wrong candidates.
"""

from __future__ import annotations

import time

import numpy as np

from backend.verifiers.interface import Verifier, VerifierAnswer
from behaviors.detection import Verdict


class CascadeVerifier:
    def __init__(self, fast: Verifier, slow: Verifier) -> None:
        self.fast = fast
        self.slow = slow
        self.name = f"cascade:{fast.name}+{slow.name}"

    def verify(
        self,
        crop_bgr: np.ndarray,
        target_box: tuple[float, float, float, float],
        prompt: str,
        superset: str,
        timeout_s: float,
    ) -> VerifierAnswer:
        start = time.monotonic()
        first = self.fast.verify(crop_bgr, target_box, prompt, superset, timeout_s)
        if first.verdict is Verdict.NO:
            return first
        second = self.slow.verify(
            crop_bgr, target_box, prompt, superset, max(0.001, timeout_s - (time.monotonic() - start))
        )
        justification = f"{second.justification} [fast check: {first.justification}]".strip()
        return VerifierAnswer(
            second.verdict,
            justification,
            second.verifier,
            second.box or first.box,
            second.judged,
            second.unjudged,
        )


def fast_stage(verifier: Verifier | None) -> Verifier | None:
    """The stage that answers before a slower one (a cascade's local verifier); None when `verifier` has
    no slower stage."""
    return verifier.fast if isinstance(verifier, CascadeVerifier) else None
