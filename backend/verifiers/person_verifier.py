"""The local verifier (`local`): garments and posture of a person read through a learned body model.

For a person it runs the pose model (backend/verifiers/person_model.py) on the candidate box and, only
when the model finds the body (presence and shoulder/hip visibility at least 0.5):
- upper garment = the person mask inside the torso (shoulders to hips, at least as wide as the
  shoulders), lower garment = the mask along the legs (hips to knees to ankles), minus the torso;
- colour words are judged on those pixels in CIE Lab: the share whose nearest named prototype by
  CIEDE2000 is the colour (backend/verifiers/colour_names.py); "dark" is the share with L* < 35;
- posture from keypoints: torso more than 60 degrees from the image vertical is lying; an upright torso
  with knees at least 125 degrees (a walking stride included) is standing, at most 105 sitting.
Answers: yes when every named attribute is seen (a colour covering at least `present_share` of its
garment; shared out among several colours named for one garment), no when one is clearly not (under
`absent_share`, another colour covering 40 %, or another posture), otherwise uncertain.
A person the model cannot see (no body found, a garment under `min_region_px` pixels, a hat or bag it
has no region for) is `uncertain`: nothing is guessed from the box. Other objects (a car, a boat, a bag)
have no body model: their own pixels are segmented from the box (`object_mask`, GrabCut with the crop's
margin as background) and their colour is their dominant one (`object_colour`). Words it has no reading
for ("suv", "motorboat", "striped") are listed in the answer's `unjudged`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import cv2
import numpy as np

from backend.scene import ATTRIBUTE_WORDS, unjudged_words
from backend.verifiers import person_model as body
from backend.verifiers.attributes import (
    COLOUR_WORDS,
    HEAD,
    LOWER,
    LYING,
    SITTING,
    UPPER,
    UPRIGHT,
    colour_claims,
    posture_claim,
)
from backend.verifiers.colour_names import ColourNamer, srgb_to_lab, subsample, white_gains
from backend.verifiers.interface import VerifierAnswer, nothing_to_judge
from backend.verifiers.person_model import PersonModel
from behaviors.detection import Verdict
from behaviors.spatial_relations import parse_description

LYING_MIN_DEG = 60.0  # torso angle from the image vertical
UPRIGHT_MAX_DEG = 30.0
STANDING_MIN_KNEE_DEG = 125.0  # on one's feet, walking included (a stride bends the knee to ~130)
SITTING_MAX_KNEE_DEG = 105.0
DARK_PRESENT_SHARE = 0.5  # "dark": at least half the garment below L* 35
DARK_ABSENT_SHARE = 0.2
OTHER_COLOUR_SHARE = 0.4  # another colour this much of the garment, the named one under present: no
BODY_MARGIN = 0.5  # the person's extent: mask within this many torso lengths of a visible keypoint
OUTWEIGHED_RATIO = 0.5  # ...or the named colours together under half of that other colour: no


OBJECT = "object"  # the one region of a candidate that is not a person
GRABCUT_ITERATIONS = 4
MIN_OBJECT_SHARE = 0.15  # a segmentation keeping less of the box than this failed: the box's middle instead
OBJECT_MIDDLE = 0.6  # ...an ellipse over this share of the box's width and height


def object_mask(crop_bgr: np.ndarray, target_box: tuple[float, float, float, float]) -> np.ndarray:
    """The object's pixels in the crop (a boolean mask inside the box), not the road or water around it.

    OpenCV's GrabCut, started from the box: everything outside it (the 50 px margin of the crop) is
    background, colour models of both sides are fitted and the box's pixels split between them, so a car's
    box loses the asphalt at its corners and a boat's the water. Where that keeps under
    `MIN_OBJECT_SHARE` of the box (an object the colour of its surroundings, a box at the crop's edge
    with no background to learn from), the middle of the box, an ellipse, stands in for it. Deterministic:
    GrabCut's k-means seeding uses OpenCV's thread-local random generator, reseeded for every call.
    """
    height, width = crop_bgr.shape[:2]
    x, y, w, h = target_box
    x1, y1 = max(int(np.floor(x)), 0), max(int(np.floor(y)), 0)
    x2, y2 = min(int(np.ceil(x + w)), width), min(int(np.ceil(y + h)), height)
    inside = np.zeros((height, width), bool)
    if x2 - x1 < 2 or y2 - y1 < 2:
        return inside
    inside[y1:y2, x1:x2] = True
    middle = np.zeros((height, width), np.uint8)
    centre = (int(round((x1 + x2 - 1) / 2)), int(round((y1 + y2 - 1) / 2)))
    axes = (
        max(int(round(OBJECT_MIDDLE * (x2 - x1) / 2)), 1),
        max(int(round(OBJECT_MIDDLE * (y2 - y1) / 2)), 1),
    )
    cv2.ellipse(middle, centre, axes, 0, 0, 360, 1, -1)
    has_background = x1 > 0 or y1 > 0 or x2 < width or y2 < height
    if has_background and (x2 - x1) * (y2 - y1) >= 16:
        mask = np.zeros((height, width), np.uint8)
        background, foreground = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.setRNGSeed(0)
        try:
            cv2.grabCut(
                np.ascontiguousarray(crop_bgr),
                mask,
                (x1, y1, x2 - x1, y2 - y1),
                background,
                foreground,
                GRABCUT_ITERATIONS,
                cv2.GC_INIT_WITH_RECT,
            )
        except cv2.error:
            mask[:] = cv2.GC_BGD  # a degenerate colour model (a flat crop): the box's middle below
        found: np.ndarray = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)) & inside
        if found.sum() >= MIN_OBJECT_SHARE * (x2 - x1) * (y2 - y1):
            return found
    return np.asarray((middle > 0) & inside)


DOMINANT_YES = (
    0.8  # a colour covering this share of what the object's most common colour covers is its colour
)
DOMINANT_NO = 0.4  # ...one under this share of it is not


def object_colour(
    shares: dict[str, float], group: set[str], named: set[str], present: float, absent: float
) -> tuple[Verdict, str]:
    """The verdict on one colour claim about an object that is not a person (a car's paint, a hull): its
    colour is its dominant one. The named colour is "yes" when it covers at least DOMINANT_YES of what the
    object's most common colour covers (and `present` of the object), "no" under DOMINANT_NO of it or
    under `absent`; in between it is uncertain. A black car's highlights read white and a white car's
    glass black, but neither is the car's most common colour. "dark" keeps its lightness rule (most of the
    object darker than L* 35)."""
    share = sum(shares.get(c, 0.0) for c in group)
    name = "-".join(sorted(group))
    dominant, most = max(
        ((c, v) for c, v in shares.items() if c != "dark"), key=lambda cv: cv[1], default=("", 0.0)
    )
    note = f"{name} {share:.0%} of the object (most: {dominant} {most:.0%})"
    if group == {"dark"}:
        return (
            Verdict.YES
            if share >= DARK_PRESENT_SHARE
            else Verdict.NO
            if share < DARK_ABSENT_SHARE
            else Verdict.UNCERTAIN
        ), note
    if share < absent or share < DOMINANT_NO * most:
        return Verdict.NO, note
    return (Verdict.YES if share >= max(present, DOMINANT_YES * most) else Verdict.UNCERTAIN), note


@dataclass
class Observation:
    """What the model made of one box; `reason` says why it cannot judge (empty when it can)."""

    reason: str = ""
    presence: float = 0.0
    regions: dict[str, np.ndarray] = field(default_factory=dict)  # "upper"/"lower" -> N x 3 Lab
    posture: str | None = None  # "standing", "sitting", "lying" or None (cannot tell)
    posture_note: str = ""
    extent: tuple[float, float, float, float] | None = None  # the person mask's box (x, y, w, h)


def own_description(prompt: str) -> str:
    """The part of a description about the target itself: relations to someone or something else taken out
    ("between the man in the red shirt and ...", "next to the car"; `backend.scene`)."""
    return parse_description(prompt, ATTRIBUTE_WORDS).own


def judged_words(prompt: str, superset: str) -> set[str]:
    """The words of the target's own description this verifier judges: colour words with the garment they
    name (not on the head: it has no head region), and posture words."""
    tokens = re.findall(r"[a-z]+(?:-[a-z]+)*", prompt.lower())
    judged: set[str] = set()
    for i, token in enumerate(tokens):
        parts = token.split("-")
        if not any(p in COLOUR_WORDS for p in parts):
            continue
        following = tokens[i + 1 : i + 6]
        garment = next((t for t in following if t in UPPER | LOWER | HEAD), None)
        if superset == "person" and garment in HEAD:
            continue
        judged |= {token, *parts}
        if garment is not None:
            judged.add(garment)
    if posture_claim(prompt, superset) is not None:
        judged |= set(tokens) & (LYING | SITTING | UPRIGHT)
    return judged


def compound_colours(prompt: str) -> list[set[str]]:
    """Hyphenated colour pairs that name one mixed colour ("grey-blue", "blue-green"), as sets of names.

    "green-and-white" names two colours and is not one of them.
    """
    groups = []
    for first, second in re.findall(r"\b([a-z]+)-([a-z]+)\b", prompt.lower()):
        if first in COLOUR_WORDS and second in COLOUR_WORDS:
            groups.append({COLOUR_WORDS[first], COLOUR_WORDS[second]})
    return groups


# Pattern words: the garment has colours the description does not name (a grey-blue striped shirt has
# stripes of another colour, often most of it). The verifier cannot judge a pattern on a 15-40 px person;
# it only stops expecting the named colour to be the garment's main one.
PATTERNS = {
    "striped", "stripes", "stripy", "stripey", "checked", "checkered", "chequered", "plaid", "tartan",
    "patterned", "pattern", "spotted", "dotted", "polka", "floral", "flowered", "camouflage", "camo",
    "print", "printed", "hooped",
}  # fmt: skip


def patterned_regions(prompt: str) -> set[str]:
    """Garments ("upper", "lower", "whole") the description calls patterned: a pattern word followed
    within three words by the garment's noun (or by none: the whole body)."""
    tokens = re.findall(r"[a-z]+", prompt.lower())
    regions = set()
    for i, token in enumerate(tokens):
        if token in PATTERNS:
            following = tokens[i + 1 : i + 4]
            regions.add("upper" if UPPER & set(following) else "lower" if LOWER & set(following) else "whole")
    return regions


def _angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Angle at b between b->a and b->c, degrees."""
    u, v = a - b, c - b
    cos = float(np.dot(u, v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-9))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def posture_from_keypoints(
    points: np.ndarray, visibility: np.ndarray, min_visibility: float
) -> tuple[str | None, str]:
    shoulders = (points[body.L_SHOULDER] + points[body.R_SHOULDER]) / 2
    hips = (points[body.L_HIP] + points[body.R_HIP]) / 2
    axis = shoulders - hips
    tilt = float(np.degrees(np.arctan2(abs(axis[0]), -axis[1])))  # 0: head up, 90: level, 180: head down
    if tilt >= LYING_MIN_DEG:
        return "lying", f"torso {tilt:.0f} deg from vertical"
    if tilt > UPRIGHT_MAX_DEG:
        return None, f"torso {tilt:.0f} deg from vertical"
    legs = [
        (h, k, a)
        for h, k, a in ((body.L_HIP, body.L_KNEE, body.L_ANKLE), (body.R_HIP, body.R_KNEE, body.R_ANKLE))
        if min(visibility[k], visibility[a]) >= min_visibility
    ]
    if not legs:
        return None, f"torso upright ({tilt:.0f} deg), legs not visible"
    knee = float(np.mean([_angle(points[h], points[k], points[a]) for h, k, a in legs]))
    note = f"torso {tilt:.0f} deg from vertical, knees {knee:.0f} deg"
    if knee >= STANDING_MIN_KNEE_DEG:
        return "standing", note
    if knee <= SITTING_MAX_KNEE_DEG:
        return "sitting", note
    return None, note


class PersonVerifier:
    name = "local:person"

    def __init__(
        self,
        model: PersonModel | None = None,
        namer: ColourNamer | None = None,
        min_presence: float = 0.5,
        min_visibility: float = 0.5,
        min_region_px: int = 40,
        present_share: float = 0.2,
        absent_share: float = 0.05,
    ) -> None:
        self.model = model or PersonModel()
        self.namer = namer or ColourNamer.load()
        self.min_presence = min_presence
        self.min_visibility = min_visibility
        self.min_region_px = min_region_px
        self.present_share = present_share
        self.absent_share = absent_share

    def observe(self, crop_bgr: np.ndarray, target_box: tuple[float, float, float, float]) -> Observation:
        if min(target_box[2], target_box[3]) < 4:
            return Observation("box too small for the body model")
        pose = self.model.estimate(crop_bgr, target_box)
        core = [body.L_SHOULDER, body.R_SHOULDER, body.L_HIP, body.R_HIP]
        if pose.presence < self.min_presence or float(pose.visibility[core].min()) < self.min_visibility:
            return Observation(f"no body found (presence {pose.presence:.2f})", pose.presence)
        p = pose.keypoints
        ls, rs, lh, rh = p[body.L_SHOULDER], p[body.R_SHOULDER], p[body.L_HIP], p[body.R_HIP]
        torso_len = float(np.linalg.norm((ls + rs) / 2 - (lh + rh) / 2))
        width = max(float(np.linalg.norm(ls - rs)), 0.35 * torso_len, 2.0)
        upper = np.zeros(crop_bgr.shape[:2], np.uint8)
        top_l, top_r = ls + 0.1 * (lh - ls), rs + 0.1 * (rh - rs)  # below the neck
        cv2.fillConvexPoly(upper, np.round(np.array([top_l, top_r, rh, lh])).astype(np.int32), 1)
        cv2.line(
            upper,
            tuple(np.round((top_l + top_r) / 2).astype(int)),
            tuple(np.round((lh + rh) / 2).astype(int)),
            1,
            max(int(round(width)), 1),
        )
        lower = np.zeros_like(upper)
        leg_width = max(int(round(0.45 * width)), 1)
        for hip, knee, ankle in (
            (body.L_HIP, body.L_KNEE, body.L_ANKLE),
            (body.R_HIP, body.R_KNEE, body.R_ANKLE),
        ):
            chain = [p[hip]]
            if pose.visibility[knee] >= self.min_visibility:
                chain.append(p[knee])
                if pose.visibility[ankle] >= self.min_visibility:
                    chain.append(0.85 * p[ankle] + 0.15 * p[knee])  # stop above the shoe
            if len(chain) > 1:
                cv2.polylines(lower, [np.round(np.array(chain)).astype(np.int32)], False, 1, leg_width)
        upper_px = crop_bgr[(upper > 0) & pose.mask]
        lower_px = crop_bgr[(lower > 0) & (upper == 0) & pose.mask]
        gains = white_gains(crop_bgr)
        regions = {
            name: srgb_to_lab(subsample(px), gains)
            for name, px in (("upper", upper_px), ("lower", lower_px))
            if len(px) >= self.min_region_px
        }
        posture, note = posture_from_keypoints(p, pose.visibility, self.min_visibility)
        joints = p[pose.visibility >= self.min_visibility]
        reach = BODY_MARGIN * torso_len  # the head's top above the nose, hands and feet past the joints
        near = np.zeros_like(pose.mask)
        x1, y1 = np.floor(joints.min(axis=0) - reach).astype(int).clip(0)
        x2, y2 = np.ceil(joints.max(axis=0) + reach).astype(int)
        near[y1 : max(y2 + 1, y1), x1 : max(x2 + 1, x1)] = True
        extent = self.mask_extent(pose.mask & near)
        return Observation("", pose.presence, regions, posture, note, extent)

    def mask_extent(self, mask: np.ndarray) -> tuple[float, float, float, float] | None:
        """The box of the person mask (1st to 99th percentile of its pixels: a stray speck does not widen
        it); None for a mask too small to trust. The caller keeps the mask near the body's keypoints: the
        segmentation also takes in a neighbour the person touches."""
        ys, xs = np.nonzero(mask)
        if len(xs) < self.min_region_px:
            return None
        x1, x2 = np.percentile(xs, [1, 99])
        y1, y2 = np.percentile(ys, [1, 99])
        return float(x1), float(y1), float(x2 - x1 + 1), float(y2 - y1 + 1)

    def judge(
        self,
        observation: Observation,
        prompt: str,
        superset: str = "person",
        namer: ColourNamer | None = None,
    ) -> VerifierAnswer:
        """The verdict for `prompt` on an observation (separate from `observe` so a study can re-judge)."""
        namer = namer or self.namer
        prompt = own_description(prompt)
        claims = colour_claims(prompt, superset)
        posture = posture_claim(prompt, superset)
        unjudged = unjudged_words(prompt, superset, judged_words(prompt, superset))
        if not claims and posture is None:
            return nothing_to_judge(self.name, unjudged)
        if observation.reason:
            return VerifierAnswer(Verdict.UNCERTAIN, observation.reason, self.name, unjudged=unjudged)
        verdicts, notes = [], []
        if posture is not None:
            seen = observation.posture
            wanted = "standing" if posture == "upright" else posture
            verdicts.append(
                Verdict.UNCERTAIN if seen is None else Verdict.YES if seen == wanted else Verdict.NO
            )
            notes.append(f"posture {seen or 'unclear'} ({observation.posture_note})")
        compounds = compound_colours(prompt)
        patterned = patterned_regions(prompt)
        judged: list[tuple[str, set[str]]] = []  # (region, colours that together make the claim)
        for claim in claims:
            group = next((g for g in compounds if claim.colour in g), {claim.colour})
            if (claim.region, group) not in judged:
                judged.append((claim.region, group))
        for region, group in judged:
            name = "-".join(sorted(group))
            if region == "head":
                verdicts.append(Verdict.UNCERTAIN)
                notes.append(f"{name} on the head: no head region")
                continue
            parts = ["upper", "lower"] if region == "whole" else [region]
            if OBJECT in observation.regions:
                parts = [OBJECT]  # not a person: one region, the object's own pixels
            visible = [r for r in parts if r in observation.regions]
            if not visible:
                verdicts.append(Verdict.UNCERTAIN)
                notes.append(f"{region} garment too small to judge {name}")
                continue
            # "dark" is most of the garment; a colour needs a real share of it, shared out when the
            # description gives the garment several colours ("green-and-white": each 10 %, stripes of
            # one colour fade into the other in the haze). A whole-body claim ("a black wetsuit",
            # "dark clothes") holds for each garment seen.
            siblings = sum(1 for r, g in judged if r == region and g != {"dark"})
            present = DARK_PRESENT_SHARE if group == {"dark"} else self.present_share / max(siblings, 1)
            absent = DARK_ABSENT_SHARE if group == {"dark"} else self.absent_share / max(siblings, 1)
            named = set().union(*(g for r, g in judged if r == region))
            for part in visible:
                shares = namer.shares(observation.regions[part])
                share = sum(shares.get(c, 0.0) for c in group)
                if part == OBJECT:
                    verdict_of, note = object_colour(shares, group, named, present, absent)
                    verdicts.append(verdict_of)
                    notes.append(note)
                    continue
                # Clearly another colour: one colour other than the named ones (black aside: shade is black)
                # covers much of the garment while the named one stays under `present`.
                other, other_share = max(
                    ((c, v) for c, v in shares.items() if c not in named | {"black", "dark"}),
                    key=lambda cv: cv[1],
                    default=("", 0.0),
                )
                elsewhere = share < present and other_share >= OTHER_COLOUR_SHARE
                # Or a garment mostly of one unnamed colour, the named ones together a fraction of it: a
                # red shirt is not "blue" for the bluish shade in its folds. Not for a garment the
                # description calls patterned: its unnamed stripes may well be most of it.
                hues = sum(shares.get(c, 0.0) for c in named - {"dark"})
                outweighed = (
                    group != {"dark"}
                    and region not in patterned
                    and other_share >= OTHER_COLOUR_SHARE
                    and hues < OUTWEIGHED_RATIO * other_share
                )
                notes.append(
                    f"{name} {share:.0%} of "
                    + ("the object" if part == OBJECT else f"{part} garment")
                    + (f" (mostly {other}: {other_share:.0%})" if elsewhere or outweighed else "")
                )
                verdicts.append(
                    Verdict.NO
                    if share < absent or elsewhere or outweighed
                    else Verdict.YES
                    if share >= present
                    else Verdict.UNCERTAIN
                )
        if Verdict.NO in verdicts:
            verdict = Verdict.NO
        elif all(v is Verdict.YES for v in verdicts):
            verdict = Verdict.YES
        else:
            verdict = Verdict.UNCERTAIN
        return VerifierAnswer(verdict, "; ".join(notes), self.name, observation.extent, unjudged=unjudged)

    def observe_object(
        self, crop_bgr: np.ndarray, target_box: tuple[float, float, float, float]
    ) -> Observation:
        """Not a person: the object's own pixels (`object_mask`: segmented from the box, the margin around
        it taken as background) as its one region."""
        pixels = crop_bgr[object_mask(crop_bgr, target_box)]
        if len(pixels) < self.min_region_px:
            return Observation("box too small to judge colours")
        return Observation(regions={OBJECT: srgb_to_lab(subsample(pixels), white_gains(crop_bgr))})

    def verify(
        self,
        crop_bgr: np.ndarray,
        target_box: tuple[float, float, float, float],
        prompt: str,
        superset: str,
        timeout_s: float = 1.0,
    ) -> VerifierAnswer:
        prompt = own_description(prompt)
        if not colour_claims(prompt, superset) and posture_claim(prompt, superset) is None:
            return nothing_to_judge(
                self.name, unjudged_words(prompt, superset, judged_words(prompt, superset))
            )
        if superset == "person":
            return self.judge(self.observe(crop_bgr, target_box), prompt, superset)
        return self.judge(self.observe_object(crop_bgr, target_box), prompt, superset)
