"""The box-fraction colour verifier (`local-hsv`): colours from fixed parts of the box, no model.

Kept for comparison with the person-model verifier (`local`, backend/verifiers/person_verifier.py), which
shares this module's reading of the prompt (`colour_claims`, `posture_claim`).

It reads colour words in the description and the garment they belong to ("gray shirt" -> upper body,
"blue jeans" -> lower body, "red cap" -> head, "black wetsuit" / "white bag" -> the whole box), measures the share of each
colour's pixels in that part of the box (HSV rules), and answers:
  yes        every named colour covers at least `present_fraction` of its region,
  no         some named colour covers less than `absent_fraction` (clearly not there),
  uncertain  otherwise, or when the description names nothing it can judge from pixels.
For a person it also judges posture words from the box's shape: "lying" / "collapsed" needs a box
wider than tall (height/width <= 0.8), "standing" / "walking" one clearly taller (>= 1.6); anything in
between - a standing person seen from straight above is a blob - is uncertain.
It cannot read injuries, age, gender or patterns; it says so instead of guessing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np

from backend.verifiers.interface import VerifierAnswer, nothing_to_judge
from behaviors.detection import Verdict

COLOUR_WORDS = {
    "black": "black", "dark": "dark", "white": "white", "gray": "gray", "grey": "gray", "silver": "gray",
    "red": "red", "maroon": "red", "orange": "orange", "yellow": "yellow", "green": "green", "olive": "green",
    "blue": "blue", "navy": "blue", "turquoise": "blue", "cyan": "blue", "purple": "purple", "violet": "purple",
    "pink": "pink", "brown": "brown",
}  # fmt: skip
UPPER = {
    "shirt",
    "tshirt",
    "t",
    "top",
    "jacket",
    "coat",
    "sweater",
    "hoodie",
    "jumper",
    "vest",
    "blouse",
    "jersey",
    "sweatshirt",
    "anorak",
    "fleece",
    "raincoat",
    "parka",
    "tank",
}
LOWER = {"pants", "trousers", "jeans", "shorts", "skirt", "leggings"}
HEAD = {"cap", "hat", "helmet", "beanie", "hood", "hair"}
# Region of the box per garment, as fractions (top, bottom, left, right); the head and feet are left out.
REGIONS = {
    "head": (0.0, 0.18, 0.25, 0.75),
    "upper": (0.18, 0.5, 0.2, 0.8),
    "lower": (0.55, 0.9, 0.25, 0.75),
    "whole": (0.1, 0.9, 0.15, 0.85),
}


# Hue ranges (OpenCV units, 0-179) of the chromatic colours; red wraps around 0.
HUES = {
    "red": (-15, 8),
    "orange": (8, 20),
    "brown": (5, 22),
    "yellow": (20, 34),
    "green": (34, 85),
    "blue": (85, 130),
    "purple": (130, 150),
    "pink": (150, 170),
}


def _hue_in(h: np.ndarray, low: float, high: float) -> np.ndarray:
    return (
        ((h >= low) & (h < high))
        | ((h >= low + 180) & (h < high + 180))
        | ((h >= low - 180) & (h < high - 180))
    )


def colour_masks(hsv: np.ndarray, hue_slack: float = 0.0) -> dict[str, np.ndarray]:
    """Boolean pixel masks per colour name (OpenCV HSV: H 0-179, S and V 0-255).

    `hue_slack` widens every hue range on both sides: a teal shirt is "green" to some people and "blue"
    to others, and the verifier should not rule out either.
    """
    h, s, v = (hsv[..., i].astype(np.int16) for i in range(3))
    chromatic = (s >= 45) & (v >= 50)
    masks = {
        "black": v < 60,
        "dark": v < 90,
        "white": (s < 40) & (v > 170),
        "gray": (s < 50) & (v >= 60) & (v <= 190),
    }
    for name, (low, high) in HUES.items():
        masks[name] = chromatic & _hue_in(h, low - hue_slack, high + hue_slack)
    masks["orange"] &= v >= 150
    masks["brown"] = (s >= 50) & (v >= 40) & (v < 150) & _hue_in(h, 5 - hue_slack, 22 + hue_slack)
    masks["pink"] &= v >= 150
    return masks


SITTING = {"sitting", "sits", "seated", "squatting", "kneeling"}
LYING = {"lying", "lies", "laying", "prone", "collapsed", "fallen", "unconscious", "sprawled"}
UPRIGHT = {"standing", "stands", "walking", "walks", "running", "runs", "upright"}
LYING_MAX_RATIO = 0.8  # box height / width
UPRIGHT_MIN_RATIO = 1.6


def posture_claim(prompt: str, superset: str = "person") -> str | None:
    """ "lying", "sitting" or "upright" when the description of a person says so, else None."""
    if superset != "person":
        return None
    words = set(re.findall(r"[a-z]+", prompt.lower()))
    if words & LYING:
        return "lying"
    if words & SITTING:
        return "sitting"
    if words & UPRIGHT:
        return "upright"
    return None


def posture_verdict(claim: str, target_box: tuple[float, float, float, float]) -> tuple[Verdict, str]:
    ratio = target_box[3] / max(target_box[2], 1e-6)
    if claim == "sitting":
        return Verdict.UNCERTAIN, f"box height/width {ratio:.1f} cannot tell sitting"
    if claim == "lying":
        verdict = (
            Verdict.YES
            if ratio <= LYING_MAX_RATIO
            else Verdict.NO
            if ratio >= UPRIGHT_MIN_RATIO
            else Verdict.UNCERTAIN
        )
    else:
        verdict = (
            Verdict.YES
            if ratio >= UPRIGHT_MIN_RATIO
            else Verdict.NO
            if ratio <= LYING_MAX_RATIO
            else Verdict.UNCERTAIN
        )
    return verdict, f"box height/width {ratio:.1f} for {claim}"


@dataclass(frozen=True)
class ColourClaim:
    colour: str
    region: str  # "head", "upper", "lower" or "whole"


def colour_claims(prompt: str, superset: str = "person") -> list[ColourClaim]:
    """The colour words of a description and the body region each belongs to."""
    tokens = re.findall(r"[a-z]+", prompt.lower())
    claims: list[ColourClaim] = []
    for i, token in enumerate(tokens):
        if token not in COLOUR_WORDS:
            continue
        region = "whole"
        if superset == "person":
            for following in tokens[i + 1 : i + 6]:
                if following in UPPER:
                    region = "upper"
                    break
                if following in LOWER:
                    region = "lower"
                    break
                if following in HEAD:
                    region = "head"
                    break
        claim = ColourClaim(COLOUR_WORDS[token], region)
        if claim not in claims:
            claims.append(claim)
    return claims


def region_fractions(
    crop_bgr: np.ndarray, target_box: tuple[float, float, float, float], region: str, hue_slack: float = 0.0
) -> dict[str, float]:
    """Share of each colour's pixels in one region of the target box."""
    x, y, w, h = target_box
    top, bottom, left, right = REGIONS[region]
    y1, y2 = int(y + top * h), max(int(y + bottom * h), int(y + top * h) + 1)
    x1, x2 = int(x + left * w), max(int(x + right * w), int(x + left * w) + 1)
    patch = crop_bgr[max(y1, 0) : max(y2, 0), max(x1, 0) : max(x2, 0)]
    if patch.size == 0:
        return {}
    hsv = cv2.cvtColor(np.ascontiguousarray(patch), cv2.COLOR_BGR2HSV)
    return {name: float(mask.mean()) for name, mask in colour_masks(hsv, hue_slack).items()}


class AttributeVerifier:
    name = "local:colours"

    def __init__(
        self, present_fraction: float = 0.12, absent_fraction: float = 0.03, hue_slack: float = 8.0
    ) -> None:
        self.present_fraction = present_fraction
        self.absent_fraction = absent_fraction
        self.hue_slack = hue_slack

    def verify(
        self,
        crop_bgr: np.ndarray,
        target_box: tuple[float, float, float, float],
        prompt: str,
        superset: str,
        timeout_s: float = 1.0,
    ) -> VerifierAnswer:
        claims = colour_claims(prompt, superset)
        posture = posture_claim(prompt, superset)
        if not claims and posture is None:
            return nothing_to_judge(self.name)
        notes, verdicts = [], []
        if posture is not None:
            verdict, note = posture_verdict(posture, target_box)
            verdicts.append(verdict)
            notes.append(note)
        for claim in claims:
            share = region_fractions(crop_bgr, target_box, claim.region, self.hue_slack).get(
                claim.colour, 0.0
            )
            notes.append(
                f"{claim.colour} {share:.0%} of {claim.region} body"
                if superset == "person"
                else f"{claim.colour} {share:.0%} of the box"
            )
            if share >= self.present_fraction:
                verdicts.append(Verdict.YES)
            elif share < self.absent_fraction:
                verdicts.append(Verdict.NO)
            else:
                verdicts.append(Verdict.UNCERTAIN)
        if Verdict.NO in verdicts:
            verdict = Verdict.NO
        elif all(v is Verdict.YES for v in verdicts):
            verdict = Verdict.YES
        else:
            verdict = Verdict.UNCERTAIN
        return VerifierAnswer(verdict, "; ".join(notes), self.name)
