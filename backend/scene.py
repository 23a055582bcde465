"""What a description says about the target among everything in the keyframe, judged on the detector's boxes.

The crop verifier judges what a candidate looks like (colours, posture); this module judges what only the
whole keyframe shows (`behaviors.spatial_relations`): where the candidate stands ("the second from the
left", "next to the pier", "at the feet of the man in the green hoodie", "between the two men") and its
size among the others of its kind ("the small truck"). The description is read once per request
(`read_description`); the objects it names besides the target are looked for in the same detector call as
the target's class, and their own descriptions ("the man in the green hoodie", "the red car") are checked
by the same verifier; an object the detector has no class for ("the pier", "the intersection") is not
located, and the relation to it is reported as not judged.

The result ranks the search's first choice (`Detection.placement_ok`, `behaviors.candidate_selection`): it
never makes a candidate a "no". Relations among the target's own kind need every one of them in view, so
they are judged only on a request about the whole keyframe (no region).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

from backend.supersets import (
    STAND_INS,
    head_phrase,
    mapped_coco_classes,
    superset_from_prompt,
    vocabulary,
    words,
)
from backend.verifiers.attributes import COLOUR_WORDS, HEAD, LOWER, UPPER, colour_claims, posture_claim
from behaviors.geometry import Box
from behaviors.spatial_relations import (
    AMONG_OWN_KIND,
    UNJUDGEABLE,
    Description,
    Judgement,
    Relation,
    combine,
    judge_relation,
    parse_description,
)

# Nouns (and colour words) that make "in ...", "with ...", "wearing ..." an attribute of the target
# rather than another object: "a man in a red shirt", "with red hair", "the man in black".
GARMENT_WORDS: frozenset[str] = frozenset(UPPER | LOWER | HEAD) | frozenset({
    "clothes", "clothing", "wetsuit", "suit", "dress", "uniform", "outfit", "costume", "overalls",
    "gear", "boots", "shoes", "gloves", "scarf", "glasses", "sunglasses", "life jacket", "lifejacket",
    "top", "tee", "t-shirt", "shirts", "colours", "colors", "stripes", "paint", "paintwork", "livery",
})  # fmt: skip
ATTRIBUTE_WORDS: frozenset[str] = GARMENT_WORDS | frozenset(COLOUR_WORDS)

SMALL_WORDS = frozenset({"small", "little", "tiny", "smaller", "smallest", "short", "mini"})
LARGE_WORDS = frozenset({"large", "big", "huge", "larger", "bigger", "largest", "biggest", "giant", "tall"})
SMALL_SHARE = 0.75  # "small": at most this times the median size of the others of its kind
LARGE_SHARE = 1.33  # "large": at least this times
# Words a reader might take for another object but that belong to the camera or the whole scene.
_VIEW = frozenset({"camera", "drone", "image", "picture", "frame", "screen", "view"})


# Words that carry no claim about the target ("the", "in", "wearing") or only restate its kind.
_FUNCTION_WORDS = frozenset({
    "a", "an", "the", "this", "that", "these", "those", "some", "any", "one", "ones", "his", "her", "their",
    "its", "in", "on", "at", "with", "of", "and", "or", "wearing", "dressed", "who", "which", "is", "are",
    "was", "being", "has", "have", "find", "look", "for", "locate", "track", "follow", "search", "s",
    "someone", "somebody", "anyone", "person", "people", "thing", "object", "clothes", "clothing",
})  # fmt: skip


def unjudged_words(own: str, superset: str, judged: set[str]) -> tuple[str, ...]:
    """The target's own words nothing judged, adjacent ones kept together ("canopy roof", "suv"): every
    word but function words, the detector's own class names and the `judged` ones."""
    kind = set(_classes(superset)) | ({superset} - STAND_INS)
    kind |= {w for name in kind for w in name.split()}
    phrases: list[str] = []
    run: list[str] = []
    for token in words(own):
        parts = set(token.split("-"))
        if token in _FUNCTION_WORDS or token in kind or token in judged or parts <= judged | _FUNCTION_WORDS:
            if run:
                phrases.append(" ".join(run))
                run = []
            continue
        run.append(token)
    if run:
        phrases.append(" ".join(run))
    return tuple(dict.fromkeys(phrases))


@dataclass(frozen=True)
class Reference:
    """An object the description names besides the target."""

    phrase: str  # as written: "the man in the green hoodie"
    detector_class: str | None  # what the detector is asked for ("person"); None: nothing to ask for
    described: bool  # its phrase says more than its class (a colour, a garment): verify it


@dataclass(frozen=True)
class SceneQuery:
    """The description as the back-end judges it: the target's own words and where it stands."""

    description: Description
    superset: str
    references: dict[str, Reference]  # phrase -> the object it names
    size_word: str = ""  # "small" / "large" as written, or ""

    @property
    def own(self) -> str:
        return self.description.own

    def detector_classes(self) -> list[str]:
        """The classes to ask the detector for besides the target's own (every located reference)."""
        target = _classes(self.superset)
        extra = []
        for ref in self.references.values():
            name = ref.detector_class
            if name is not None and name not in extra and not (_classes(name) <= target and target):
                extra.append(name)
        return extra

    def same_kind(self, ref: Reference) -> bool:
        """The reference is of the target's own kind ("the red car" for a car): its boxes are the other
        candidates."""
        target = _classes(self.superset)
        return ref.detector_class is not None and bool(target) and _classes(ref.detector_class) <= target


def _classes(name: str) -> frozenset[str]:
    """The COCO classes a name stands for; for a name with none (an open-vocabulary one), itself."""
    mapped = mapped_coco_classes(name)
    return frozenset({name} if mapped is None else mapped)


def _possessor_and_head(phrase: str) -> tuple[str | None, str]:
    """ "the boat's wake" -> ("the boat", "the wake"); without a possessive, (None, phrase)."""
    match = re.match(r"^(?P<owner>.*?\b[a-z-]+)'s?\s+(?P<head>[a-z].*)$", phrase)
    if match is None:
        return None, phrase
    return match.group("owner"), match.group("head")


def _head_class(own: str) -> str | None:
    """The class an object's phrase names by its head, the last noun ("the zebra stripes" are stripes, not
    zebras; "the jet ski" is a boat): the word table's entry ending there, else that word as it is (for an
    open-vocabulary detector); None for no word."""
    tokens = [t for t in head_phrase(words(own)) if t not in _FUNCTION_WORDS or t in ("person", "people")]
    if not tokens:
        return None
    for _start, end, target in vocabulary().mentions(tokens):
        if end == len(tokens):
            return target
    head = superset_from_prompt(tokens[-1])
    return head if head is not None else tokens[-1]


def _reference(phrase: str) -> Reference:
    if not words(phrase) or set(words(phrase)) & _VIEW:
        return Reference(phrase, None, False)
    own = parse_description(phrase, ATTRIBUTE_WORDS).own
    found = _head_class(own)
    if found is None:
        return Reference(phrase, None, False)
    described = bool(colour_claims(own, found) or posture_claim(own, found))
    return Reference(phrase, found, described)


def read_description(prompt: str, superset: str) -> SceneQuery:
    """The description parsed once: the target's own words, its relations, the objects they name (a
    possessor too: "to the left of the boat's wake" names the boat apart from the target), its size word."""
    description = parse_description(prompt, ATTRIBUTE_WORDS)
    relations = list(description.relations)
    references: dict[str, Reference] = {}
    for relation in description.relations:
        if not relation.reference:
            continue
        owner, head = _possessor_and_head(relation.reference)
        references[relation.reference] = _reference(head if owner else relation.reference)
        if owner is not None and owner not in references:
            # The possessor is another object too: the target is not in it (the boat whose wake he rides).
            references[owner] = _reference(owner)
            relations.append(Relation("outside", f"not in {owner}", owner))
    size_word = next((t for t in words(description.own) if t in SMALL_WORDS | LARGE_WORDS), "")
    return SceneQuery(Description(description.own, tuple(relations)), superset, references, size_word)


@dataclass(frozen=True)
class Placement:
    """One candidate's judgement: `ok` for the search's ranking, notes for its justification, and what
    could not be judged."""

    ok: Judgement
    notes: tuple[str, ...]
    unjudged: tuple[str, ...]
    singled_out: bool = False  # an ordinal picked it (and it fits the rest)


def _size(box: Box) -> float:
    return math.sqrt(max(box.area, 0.0))


def judge_size(word: str, box: Box, others: Sequence[Box]) -> tuple[Judgement, str]:
    """ "small" / "large" against the median size of the others of its kind in view."""
    sizes = sorted(_size(b) for b in others if b != box)
    if not sizes:
        return None, f"{word}: no other of its kind in view"
    median = (
        sizes[len(sizes) // 2]
        if len(sizes) % 2
        else 0.5 * (sizes[len(sizes) // 2 - 1] + sizes[len(sizes) // 2])
    )
    ratio = _size(box) / median if median > 0 else math.inf
    if word in SMALL_WORDS:
        verdict: Judgement = True if ratio <= SMALL_SHARE else False if ratio >= 1.0 else None
    else:
        verdict = True if ratio >= LARGE_SHARE else False if ratio <= 1.0 else None
    return verdict, f"{word}: {ratio:.2f}x the median size of {len(sizes)} other(s)"


def judge_scene(
    query: SceneQuery,
    boxes: Sequence[Box],
    may_be_target: Sequence[bool],
    references: dict[str, list[Box] | None],
    view: tuple[float, float],
    whole_frame: bool,
) -> list[Placement]:
    """Every relation and the size word for each of `boxes` (the target's kind in view, the verified
    candidates first). `may_be_target`: not ruled out by the verifier (ordinals count among those);
    `references`: the located boxes of each named object that fit its own description (None: not
    located). Relations among the target's own kind need the whole keyframe (`whole_frame`)."""
    n = len(boxes)
    pool = [i for i in range(n) if may_be_target[i]]
    judged: list[list[Judgement]] = [[] for _ in range(n)]
    ranked = [False] * n  # an ordinal picked it
    notes: list[list[str]] = [[] for _ in range(n)]
    unjudged: list[str] = []
    # Relations among its own kind first: ordinals then count among those that fit the rest.
    ordered = sorted(query.description.relations, key=lambda r: r.kind == "ordinal")
    for relation in ordered:
        if relation.kind in UNJUDGEABLE:
            unjudged.append(relation.text)
            continue
        ref = query.references.get(relation.reference)
        # "between the man in red and the man in green": the others of its kind in view are the ends (the
        # reference's two descriptions are not one object's).
        among_own = relation.kind in AMONG_OWN_KIND or (
            relation.kind == "between" and (ref is None or query.same_kind(ref) or ref.detector_class is None)
        )
        located: list[Box] | None
        if among_own:
            located = list(boxes)
        elif ref is not None and query.same_kind(ref):
            located = references.get(relation.reference) or list(boxes)
        else:
            located = references.get(relation.reference)
        if (among_own or (ref is not None and query.same_kind(ref))) and not whole_frame:
            unjudged.append(f"{relation.text} (a region of the keyframe: not every one in view)")
            continue
        if located is None:
            what = relation.reference or relation.text
            unjudged.append(f"{relation.text} ({what}: not located)")
            continue
        if relation.kind == "ordinal":
            # The rank counts among the candidates that may be the target and fit the other relations.
            fitting = [i for i in pool if combine(judged[i]) is not False]
            result = judge_relation(relation, boxes, fitting, located, view)
        else:
            result = judge_relation(relation, boxes, pool, located, view)
        if all(r is None for r in result[: len(may_be_target)]):
            unjudged.append(f"{relation.text} (cannot be told here)")
        for i, r in enumerate(result):
            judged[i].append(r)
            ranked[i] = ranked[i] or (relation.kind == "ordinal" and r is True)
            notes[i].append(f"{relation.text}: {'yes' if r else 'no' if r is False else 'uncertain'}")
    if query.size_word:
        others = [boxes[i] for i in range(n)]
        for i in range(n):
            verdict, note = judge_size(query.size_word, boxes[i], others)
            judged[i].append(verdict)
            notes[i].append(note)
        if len(boxes) < 2:
            unjudged.append(f"{query.size_word} (no other of its kind in view)")
    placements = []
    for i in range(n):
        ok = combine(judged[i])
        placements.append(Placement(ok, tuple(notes[i]), tuple(unjudged), ranked[i] and ok is True))
    return placements
