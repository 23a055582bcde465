"""Builds `backend/coco_vocabulary.txt`, the everyday words for every COCO class, from WordNet.

Run by a developer when the anchors below change (the table is committed, so the back-end needs neither
WordNet nor a download at run time):

    python -m backend_tools.wordnet_vocabulary --wordnet /usr/share/wordnet   # Debian's wordnet-base (WordNet 3.0)

Every COCO class (and each superset: vehicle, animal, bag, aircraft) is anchored to WordNet synsets; every
noun below an anchor in the hypernym graph is a word for the nearest anchor ("kayak" -> small boat -> boat,
"labrador retriever" -> dog, "hiker" -> person, "moose" -> animal). A word with several senses takes the
target its senses vote for, each weighted by how often it was seen in WordNet's sense-tagged corpus
(cntlist.rev) plus 1/rank, so unseen senses still count a little. A word whose mapped senses make up less
than MIN_SHARE of that weight keeps no mapping ("plant": factory and flora, rarely the planted person).
Person senses vote at PERSON_WEIGHT: WordNet lists figurative person senses for many animals and things
("tiger": a fierce person), and in a search prompt the literal thing is meant. Named instances (people,
places: "Lincoln", "Ford") are left out: their senses neither vote nor count in a word's weight.
Irregular plurals come from WordNet's exception list; regular ones are derived when a prompt
is read (`backend.supersets`). A few words newer than WordNet 3.0 (2006), or filed by WordNet away from
the class a search means, are added under the word they are a kind of (EXTRA_WORDS).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from backend.supersets import COCO_CLASSES, VOCABULARY_FILE

TABLE = VOCABULARY_FILE

# target (a COCO class name in YOLOX's spelling, or a superset) -> WordNet (lemma, sense number) anchors.
ANCHORS: dict[str, tuple[tuple[str, int], ...]] = {
    "person": (("person", 1),),
    "bicycle": (("bicycle", 1),),
    "car": (("car", 1),),
    "motorbike": (("motorcycle", 1), ("motor_scooter", 1)),
    "aeroplane": (("airplane", 1),),
    "bus": (("bus", 1),),
    "train": (("train", 1),),
    "truck": (("truck", 1),),
    "boat": (("boat", 1), ("vessel", 2)),
    "traffic light": (("traffic_light", 1),),
    "fire hydrant": (("fireplug", 1),),
    "parking meter": (("parking_meter", 1),),
    "bench": (("bench", 1),),
    "bird": (("bird", 1),),
    "cat": (("cat", 1),),
    "dog": (("dog", 1),),
    "horse": (("horse", 1),),
    "sheep": (("sheep", 1),),
    "cow": (("cattle", 1), ("cow", 1), ("cow", 2)),
    "elephant": (("elephant", 1),),
    "bear": (("bear", 1),),
    "zebra": (("zebra", 1),),
    "giraffe": (("giraffe", 1),),
    "backpack": (("backpack", 1),),
    "umbrella": (("umbrella", 1),),
    "handbag": (("bag", 4),),
    "tie": (("necktie", 1),),
    "suitcase": (("bag", 6),),
    "frisbee": (("frisbee", 1),),
    "skis": (("ski", 1),),
    "snowboard": (("snowboard", 1),),
    "sports ball": (("ball", 1),),
    "kite": (("kite", 3),),
    "baseball bat": (("baseball_bat", 1),),
    "baseball glove": (("baseball_glove", 1),),
    "skateboard": (("skateboard", 1),),
    "surfboard": (("surfboard", 1),),
    "tennis racket": (("tennis_racket", 1),),
    "bottle": (("bottle", 1),),
    "wine glass": (("wineglass", 1),),
    "cup": (("cup", 1),),
    "fork": (("fork", 1),),
    "knife": (("knife", 1), ("knife", 2)),
    "spoon": (("spoon", 1),),
    "bowl": (("bowl", 3),),
    "banana": (("banana", 2),),
    "apple": (("apple", 1),),
    "sandwich": (("sandwich", 1),),
    "orange": (("orange", 1),),
    "broccoli": (("broccoli", 2),),
    "carrot": (("carrot", 1), ("carrot", 3)),
    "hot dog": (("hotdog", 2),),
    "pizza": (("pizza", 1),),
    "donut": (("doughnut", 2),),
    "cake": (("cake", 3),),
    "chair": (("chair", 1),),
    "sofa": (("sofa", 1),),
    "pottedplant": (("pot_plant", 1),),
    "bed": (("bed", 1),),
    "diningtable": (("dining_table", 1),),
    "toilet": (("toilet", 2),),
    "tvmonitor": (("television_receiver", 1), ("monitor", 4)),
    "laptop": (("laptop", 1),),
    "mouse": (("mouse", 4),),
    "remote": (("remote_control", 1),),
    "keyboard": (("computer_keyboard", 1),),
    "cell phone": (("cellular_telephone", 1),),
    "microwave": (("microwave", 2),),
    "oven": (("oven", 1),),
    "toaster": (("toaster", 2),),
    "sink": (("sink", 1),),
    "refrigerator": (("refrigerator", 1),),
    "book": (("book", 2),),
    "clock": (("clock", 1),),
    "vase": (("vase", 1),),
    "scissors": (("scissors", 1),),
    "teddy bear": (("teddy", 1),),
    "hair drier": (("hand_blower", 1),),
    "toothbrush": (("toothbrush", 1),),
    # Supersets: whatever is below them and nearer no COCO anchor (a tractor, a moose, a helicopter).
    "vehicle": (("vehicle", 1),),
    "animal": (("animal", 1),),
    "bag": (("bag", 1),),
    "aircraft": (("aircraft", 1),),
}  # fmt: skip

# Words WordNet 3.0 lacks, or files away from the class a search means ("people" is a group there, a "driver"
# an operator beside person, a "raft" a float, a "whale" first a large person) -> the word they are a kind of.
EXTRA_WORDS: dict[str, str] = {
    # search-and-rescue usage: "a figure on the ridge", "the subject", "the injured lying by the road"
    "figure": "person", "subject": "person", "injured": "person", "missing": "person",
    "people": "person", "folk": "person", "folks": "person", "driver": "person", "police": "person",
    "bike": "bicycle", "potted plant": "pot_plant", "kayaker": "canoeist",
    "whale": "animal", "seal": "animal", "raft": "boat", "life raft": "boat", "liferaft": "boat",
    "wakeboarder": "surfer", "kitesurfer": "surfer", "windsurfer": "surfer", "paddleboarder": "surfer",
    "snowboarder": "skier", "mountain biker": "cyclist", "paraglider": "flier",
    "jet ski": "motorboat", "jetski": "motorboat", "paddleboard": "surfboard", "wakeboard": "surfboard",
    "rib": "boat", "quad bike": "motorcycle", "e-bike": "bicycle", "ebike": "bicycle",
    "suv": "car", "pickup": "pickup_truck", "motorhome": "recreational_vehicle",
}  # fmt: skip

PERSON_WEIGHT = 0.4  # a person sense's vote, against 1.0 for any other target (see the module's docstring)
MIN_SHARE = 0.2  # the least share of a word's sense weight that must map for the word to map


@dataclass
class WordNet:
    """The noun part of a WordNet 3.0 database in its original text format."""

    hypernyms: dict[int, list[int]]
    words: dict[int, list[str]]  # synset offset -> its lemmas, in file order
    senses: dict[str, list[int]]  # lemma (lower case, underscores) -> synset offsets, most frequent first
    plurals: list[tuple[str, str]]  # irregular (plural, singular) from noun.exc
    adjectives: set[str]
    counts: dict[tuple[str, int], int]  # (lemma, sense number) -> times tagged in the sense-tagged corpus
    instances: set[int]  # synsets that are named individuals ("Lincoln"), not kinds

    @classmethod
    def read(cls, folder: Path) -> WordNet:
        hypernyms: dict[int, list[int]] = {}
        words: dict[int, list[str]] = {}
        instances: set[int] = set()
        for line in (folder / "data.noun").read_text(encoding="latin-1").splitlines():
            if line.startswith("  "):
                continue  # licence header
            fields = line.split(" | ")[0].split()
            offset, count = int(fields[0]), int(fields[3], 16)
            words[offset] = [fields[4 + 2 * i] for i in range(count)]
            at = 4 + 2 * count
            pointers = int(fields[at])
            ptrs = [fields[at + 1 + 4 * i : at + 5 + 4 * i] for i in range(pointers)]
            hypernyms[offset] = [int(p[1]) for p in ptrs if p[0] == "@" and p[2] == "n"]
            if any(p[0] == "@i" for p in ptrs):
                instances.add(offset)
        senses: dict[str, list[int]] = {}
        for line in (folder / "index.noun").read_text(encoding="latin-1").splitlines():
            if line.startswith("  "):
                continue
            fields = line.split()
            synsets = int(fields[2])
            senses[fields[0]] = [int(v) for v in fields[-synsets:]]
        plurals = [tuple(line.split()[:2]) for line in (folder / "noun.exc").read_text().splitlines() if line]
        adjective_lines = (folder / "index.adj").read_text(encoding="latin-1").splitlines()
        adjectives = {line.split()[0] for line in adjective_lines if not line.startswith("  ")}
        counts: dict[tuple[str, int], int] = {}
        for line in (folder / "cntlist.rev").read_text(encoding="latin-1").splitlines():
            key, number, tagged = line.split()
            lemma, sense_key = key.split("%", 1)
            if sense_key.startswith("1:"):  # nouns
                counts[(lemma, int(number))] = int(tagged)
        return cls(hypernyms, words, senses, [(p, s) for p, s in plurals], adjectives, counts, instances)

    def synset(self, lemma: str, sense: int) -> int:
        try:
            return self.senses[lemma][sense - 1]
        except (KeyError, IndexError):
            raise ValueError(f"WordNet has no noun sense {lemma}#{sense}") from None


def _nearest_anchor(
    wordnet: WordNet, start: int, anchors: dict[int, str], cache: dict[int, str | None]
) -> str | None:
    """The target of the nearest anchor above `start` in the hypernym graph (breadth first), or None."""
    if start in cache:
        return cache[start]
    frontier, seen, found = [start], {start}, None
    while frontier and found is None:
        hits = [anchors[s] for s in frontier if s in anchors]
        if hits:
            found = hits[0]
            break
        frontier = [h for s in frontier for h in wordnet.hypernyms.get(s, []) if h not in seen]
        seen.update(frontier)
    cache[start] = found
    return found


def build(wordnet: WordNet) -> dict[str, str]:
    """Word (lower case, spaces) -> target, for every noun under an anchor."""
    anchors = {
        wordnet.synset(lemma, sense): target for target, specs in ANCHORS.items() for lemma, sense in specs
    }
    person = wordnet.synset("person", 1)
    cache: dict[int, str | None] = {}
    table: dict[str, str] = {}
    for lemma, offsets in wordnet.senses.items():
        if any(ch.isdigit() for ch in lemma) or "." in lemma:
            continue
        direct = [anchors[o] for o in offsets if o in anchors]
        votes: dict[str, float] = defaultdict(float)
        total = mapped = 0.0
        for rank, offset in enumerate(offsets, start=1):
            if offset in wordnet.instances:
                continue
            weight = wordnet.counts.get((lemma, rank), 0) + 1.0 / rank
            total += weight
            target = _nearest_anchor(wordnet, offset, anchors, cache)
            if target is not None:
                mapped += weight
                votes[target] += weight * (PERSON_WEIGHT if target == "person" and offset != person else 1.0)
        if direct:  # a word that names an anchor ("dog", "boat") means that anchor
            table[lemma.replace("_", " ")] = direct[0]
        elif votes and mapped >= MIN_SHARE * total:
            table[lemma.replace("_", " ")] = max(votes, key=lambda t: votes[t])
    for target in (*ANCHORS, *COCO_CLASSES):  # the class names themselves, in YOLOX's spelling too
        table.setdefault(target, target)
    for word, kind_of in EXTRA_WORDS.items():
        table[word] = table[kind_of.replace("_", " ")]
    for plural, singular in wordnet.plurals:
        key = singular.replace("_", " ")
        if key in table and plural.replace("_", " ") not in table:
            table[plural.replace("_", " ")] = table[key]
    return table


def adjective_words(wordnet: WordNet, table: Iterable[str]) -> set[str]:
    """Table words that are also adjectives ("orange", "young"): a noun after them is the head."""
    return {w for w in table if w.replace(" ", "_") in wordnet.adjectives}


def render(table: dict[str, str], adjectives: set[str]) -> str:
    header = (
        "# Generated by `python -m backend_tools.wordnet_vocabulary` from WordNet 3.0 (Princeton University,\n"
        "# WordNet licence); do not edit by hand.\n"
        "# word<TAB>target (COCO class or superset)<TAB>'adj' when also an adjective.\n"
    )
    rows = (f"{w}\t{t}\t{'adj' if w in adjectives else ''}".rstrip("\t") for w, t in sorted(table.items()))
    return header + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m backend_tools.wordnet_vocabulary",
        description="Regenerate backend/coco_vocabulary.txt from a WordNet 3.0 database folder.",
    )
    parser.add_argument(
        "--wordnet",
        type=Path,
        default=Path("/usr/share/wordnet"),
        help="folder with data.noun, index.noun, noun.exc, index.adj, cntlist.rev "
        "(default: Debian's wordnet-base)",
    )
    parser.add_argument("--out", type=Path, default=TABLE, help=f"output (default: {TABLE})")
    args = parser.parse_args(argv)
    wordnet = WordNet.read(args.wordnet)
    table = build(wordnet)
    args.out.write_text(render(table, adjective_words(wordnet, table)))
    print(f"{args.out}: {len(table)} words for {len(set(table.values()))} targets")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
