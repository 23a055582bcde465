"""Superset classes: what the detector looks for before the verifier checks the full description.

A superset is a broad class ("person", "vehicle", "boat") that the prompt's target belongs to. Closed-set
detectors (YOLOX, COCO-80) need it mapped to their own class names; open-vocabulary detectors take the
superset text as it is. An unmapped superset is an error naming the nearest known classes, never a silent
empty answer.

The words come from `coco_vocabulary.txt`, generated from WordNet by `backend_tools.wordnet_vocabulary` (every
noun below a COCO class's synsets: "kayak", "labrador retriever", "hiker", "moose" -> animal) and read once
per process. Plurals are reduced to the singular the table knows (irregular ones are in the table).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

# The 80 COCO class names in YOLOX's output order (the names shipped beside the weights, coco.names).
COCO_CLASSES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorbike", "aeroplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "sofa", "pottedplant", "bed",
    "diningtable", "toilet", "tvmonitor", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip

# Superset name -> the COCO classes that make it up. Every COCO name also maps to itself.
COCO_ANIMALS = ("bird", "cat", "dog", "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe")
COCO_VEHICLES = ("bicycle", "car", "motorbike", "aeroplane", "bus", "train", "truck", "boat")
# Every COCO class that is not a person, an animal or a vehicle: the objects a person carries or leaves.
COCO_THINGS = tuple(c for c in COCO_CLASSES if c != "person" and c not in COCO_ANIMALS + COCO_VEHICLES)
SUPERSET_TO_COCO: dict[str, tuple[str, ...]] = {
    "person": ("person",),
    "vehicle": ("car", "truck", "bus", "motorbike", "bicycle"),
    "car": ("car", "truck"),  # a pick-up or van is often labelled truck by COCO detectors
    "boat": ("boat",),
    # An animal COCO has no class for (a deer, a goat) is searched as every COCO animal; the verifier
    # then judges the description.
    "animal": COCO_ANIMALS,
    # COCO has classes for three kinds of bag only; a plastic bag, a sandbag or a sleeping bag on the ground
    # is seen as a frisbee, a ball or a kite (measured on vot2015_bag: no backpack/handbag/suitcase box,
    # frisbee and sports-ball boxes of IoU 0.6-0.9). So a bag is searched as every inanimate COCO thing,
    # like an animal as every COCO animal, and the verifier judges the description.
    "bag": COCO_THINGS,
    "aircraft": ("aeroplane",),
    # Road vehicles seen small: YOLOX-nano calls nearly every distant road vehicle a car (on the dev set's
    # cars, vans and minivans in 640 px keyframes: 95 % of boxes scoring >= 0.3 as car or truck score so
    # as a car alone, none under 32 px as a truck alone), so a small truck or bus is searched among cars
    # too; the verifier then judges the description.
    "truck": ("truck", "car"),
    "bus": ("bus", "truck", "car"),
}
# Supersets searched as a broader set of classes than their name (a bag as every inanimate thing): a
# detection says it is one of those, never that it is the named kind. The detector's class outputs cannot
# vouch for such a thing (a plastic bag is none of COCO's classes, and its scores for all of them are low),
# so it scores them as an object that is none of the classes outside the superset (`is_stand_in`).
STAND_INS = frozenset({"bag"})


def is_stand_in(name: str) -> bool:
    """Whether a superset name stands in for a kind the detector has no class for (a bag)."""
    key = " ".join(words(name))
    return key in STAND_INS or vocabulary().lookup(key) in STAND_INS


VOCABULARY_FILE = Path(__file__).with_name("coco_vocabulary.txt")

# Words that end the prompt's head noun phrase: "the man | in a green shirt", "a red kayak | near the shore".
_HEAD_ENDS = frozenset((
    "with", "in", "on", "at", "near", "next", "beside", "by", "under", "over", "behind", "from", "into",
    "onto", "along", "across", "around", "between", "who", "that", "which", "whose", "while", "wearing",
    "carrying", "holding", "riding", "pulling", "pushing", "walking", "standing", "sitting", "lying",
    "and", "or",
))  # fmt: skip
# Words left out of an unmapped phrase passed on to an open-vocabulary detector.
_FILLER = frozenset((
    "a", "an", "the", "this", "that", "these", "those", "some", "any", "my", "our", "your", "their", "his",
    "her", "its", "one", "two", "three", "four", "five", "several", "many", "few", "find", "locate",
    "track", "follow", "search", "look", "for", "spot",
))  # fmt: skip
# After these a table word is still used as a noun ("an orange" is the fruit, "an orange kayak" is not).
_FUNCTION_WORDS = _HEAD_ENDS | _FILLER | {"is", "are", "was", "to"}


class UnknownSupersetError(ValueError):
    """A superset the detector cannot map to its classes; the message names the nearest known ones."""


@dataclass(frozen=True)
class Vocabulary:
    words: dict[str, str]  # word (lower case, spaces) -> COCO class or superset
    adjectives: frozenset[str]  # words that are also adjectives: a noun after them is the head
    longest: int  # most words in one entry

    @classmethod
    def read(cls, path: Path = VOCABULARY_FILE) -> Vocabulary:
        words: dict[str, str] = {}
        adjectives: set[str] = set()
        for line in path.read_text(encoding="utf-8").splitlines():
            if not line or line.startswith("#"):
                continue
            fields = line.split("\t")
            words[fields[0]] = fields[1]
            if len(fields) > 2 and fields[2] == "adj":
                adjectives.add(fields[0])
        return cls(words, frozenset(adjectives), max(len(w.split()) for w in words))

    def lookup(self, phrase: str) -> str | None:
        """The target of a word or phrase, singular or plural ("jet skis" -> boat), or None."""
        if phrase in self.words:
            return self.words[phrase]
        stem, _, last = phrase.rpartition(" ")
        for singular in _singulars(last):
            target = self.words.get(f"{stem} {singular}" if stem else singular)
            if target is not None:
                return target
        return None

    def mentions(self, tokens: list[str]) -> Iterator[tuple[int, int, str]]:
        """Each entry in `tokens`, left to right, the longest at each place: (start, end, its target)."""
        i = 0
        while i < len(tokens):
            match = self.match_at(tokens, i)
            if match is None:
                i += 1
                continue
            yield i, *match
            i = match[0]

    def match_at(self, tokens: list[str], i: int) -> tuple[int, str] | None:
        """The longest entry starting at tokens[i]: (its end index, its target), or None."""
        for n in range(min(self.longest, len(tokens) - i), 0, -1):
            target = self.lookup(" ".join(tokens[i : i + n]))
            if target is not None:
                return i + n, target
        return None


def _singulars(word: str) -> list[str]:
    """Regular singular forms a plural could come from; the table decides which one is a word."""
    forms = [word[:-3] + "man"] if word.endswith("men") else []  # women, firemen
    if word.endswith("ies"):
        forms.append(word[:-3] + "y")
    if word.endswith("ves"):
        forms += [word[:-3] + "f", word[:-3] + "fe"]
    sibilant = word.endswith(("ses", "xes", "zes", "ches", "shes"))  # buses, boxes; but oranges, canoes
    if word.endswith("es") and sibilant:
        forms.append(word[:-2])
    if word.endswith("s") and not word.endswith("ss"):
        forms.append(word[:-1])
    if word.endswith("es") and not sibilant:
        forms.append(word[:-2])
    return forms


@lru_cache(maxsize=1)
def vocabulary() -> Vocabulary:
    """The word table, read on first use and kept (about 19,000 words; about 20 ms)."""
    return Vocabulary.read()


def known_supersets() -> list[str]:
    return sorted(SUPERSET_TO_COCO)


def nearest_known(name: str, limit: int = 5) -> list[str]:
    """Known classes whose words are spelled closest to `name` or to its last word, the head (typos)."""
    vocab = vocabulary()
    found: list[str] = []
    for part in dict.fromkeys([name, name.rpartition(" ")[2]]):
        for word in difflib.get_close_matches(part, vocab.words, n=8, cutoff=0.8):
            target = vocab.words[word]
            if target not in found:
                found.append(target)
    return found[:limit]


@lru_cache(maxsize=4096)
def mapped_coco_classes(name: str) -> tuple[str, ...] | None:
    """The COCO classes a superset, a COCO class name or any word for one stands for ("kayaks" -> boat), or
    None. The quick question scene parsing asks of every noun; only `coco_classes_for` looks for spelling
    hints (about 0.2 s against the whole word table)."""
    key = " ".join(words(name))
    target = key if key in SUPERSET_TO_COCO or key in COCO_CLASSES else vocabulary().lookup(key)
    if target in SUPERSET_TO_COCO:
        return SUPERSET_TO_COCO[target]
    if target in COCO_CLASSES:
        return (target,)
    return None


def coco_classes_for(name: str) -> tuple[str, ...]:
    """The COCO classes `name` stands for; an unknown name is an error with the nearest known spellings."""
    mapped = mapped_coco_classes(name)
    if mapped is not None:
        return mapped
    raise UnknownSupersetError(_UnknownSuperset(name))


class _UnknownSuperset:
    """The error's message, looked up when it is read: a caller that only tries a name (the pipeline asks
    the detector for every class a prompt names, then for the ones it has) pays nothing for the hint."""

    def __init__(self, name: str) -> None:
        self.name = name

    @cached_property
    def text(self) -> str:
        nearest = nearest_known(" ".join(words(self.name)))
        # Spelling catches typos ("sailbaot"); for a thing COCO lacks the supersets are the honest list.
        hint = f"supersets: {', '.join(known_supersets())}"
        if nearest:
            hint = f"nearest known classes: {', '.join(nearest)} (by spelling); {hint}"
        return (
            f"superset {self.name!r} has no COCO mapping ({hint}); set the superset ('superset' in the request, "
            "--superset on the command line) to a COCO class or a word for one (e.g. 'boat', 'truck', "
            "'person'), or configure an open-vocabulary detector (grounding_dino, owlv2)"
        )

    def __str__(self) -> str:
        return self.text


def words(text: str) -> list[str]:
    """Lower-case words, hyphenated ones whole ("green-and-white")."""
    return re.findall(r"[a-z]+(?:-[a-z]+)*", text.lower())


def _first_target(tokens: list[str]) -> str | None:
    """The first table word in `tokens`, taking the last of a run of nouns as the head ("horse rider")."""
    vocab = vocabulary()
    found = list(vocab.mentions(tokens))
    k = 0
    while k < len(found):
        start, end, target = found[k]
        k += 1
        while k < len(found) and found[k][0] == end:
            _, end, target = found[k]  # a compound's head is its last noun: "dog walker", "orange kayak"
            k += 1
        word = " ".join(tokens[start:end])
        next_word = tokens[end] if end < len(tokens) else ""
        modifies = bool(next_word) and next_word not in _FUNCTION_WORDS and not next_word.endswith("ing")
        if word in vocab.adjectives and modifies:
            continue  # "a young man", "an orange buoy": the adjective names nothing
        return target
    return None


def _ends_head(token: str, before: list[str]) -> bool:
    """A preposition or relative word, or a participle after a noun ("a life buoy | floating ...")."""
    return token in _HEAD_ENDS or (token.endswith("ing") and any(t not in _FILLER for t in before))


def head_phrase(tokens: list[str]) -> list[str]:
    """The words of a description's head noun phrase: before "in", "with", "near", a participle ..."""
    end = next((i for i, t in enumerate(tokens) if i > 0 and _ends_head(t, tokens[:i])), len(tokens))
    return tokens[:end]


def superset_from_prompt(prompt: str) -> str | None:
    """The superset a prompt names ("the man in a gray shirt" -> "person"), or None when it names nothing.

    The prompt's head noun phrase (before "in", "with", "near", "wearing", ...) decides: "a red life raft
    with two people" is a boat search, "a group of people" a person search. A head whose words map to no
    class gives its words ("a life buoy next to a man" -> "life buoy"), never a later noun: an
    open-vocabulary detector takes that text as it is, a closed-set one answers with the nearest classes.
    Only a head with no word of its own ("the one in the red kayak") lets the rest decide.
    """
    tokens = words(prompt)
    head = head_phrase(tokens)
    target = _first_target(head)
    if target is not None:
        return target
    named = [t for t in (head[: head.index("of")] if "of" in head else head) if t not in _FILLER]
    if named:
        return " ".join(named)
    return _first_target(tokens)


@lru_cache(maxsize=256)
def prompt_outside_superset(prompt: str, superset: str) -> str | None:
    """A warning when the prompt's words name something outside the given superset ("an orange life buoy"
    under "person"); None when they name one of its classes, nothing at all, or the superset is unmapped."""
    given = mapped_coco_classes(superset)
    named = superset_from_prompt(prompt)
    if given is None or named is None:
        return None
    named_classes = mapped_coco_classes(named)
    if named_classes is not None and set(named_classes) & set(given):
        return None
    if named_classes is not None:
        what = f"the prompt names a {named}, not a {superset}"
        hint = f"; --superset {named} searches for a {named}"
    else:
        what, hint = f"the prompt's {named!r} is no {superset} (nor any COCO class)", ""
    return (
        f"{what}: the detector proposes only what it sees as a {superset} and the verifier judges that "
        f"against the words{hint}"
    )
