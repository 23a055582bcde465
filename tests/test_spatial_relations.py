"""Where a description places the target (behaviors.spatial_relations): the parser on a few hundred
phrasings, the judges on boxes, and the search's first choice by placement."""

from __future__ import annotations

import itertools

import pytest

from backend.scene import ATTRIBUTE_WORDS
from behaviors.candidate_selection import select_first_acquisition
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box
from behaviors.spatial_relations import (
    Relation,
    combine,
    fits_reference,
    groups,
    is_between,
    judge_ordinal,
    judge_reference,
    judge_relation,
    judge_side,
    parse_description,
    queue_order,
)

# (kind, reference, axis, rank) of each relation a phrasing states
Expected = list[tuple[str, str, str | None, int]]


def _parsed(prompt: str) -> tuple[str, Expected]:
    description = parse_description(prompt, ATTRIBUTE_WORDS)
    return description.own, [(r.kind, r.reference, r.axis, r.rank) for r in description.relations]


ORDINALS = {"first": 1, "second": 2, "third": 3, "fourth": 4, "2nd": 2, "3rd": 3, "last": -1}
DIRECTIONS = ("left", "right", "top", "bottom")
OBJECTS = ("llama", "car", "boat", "person", "kayak")


def _ordinal_table() -> list[tuple[str, str, Expected]]:
    rows = []
    for (word, rank), direction, thing in itertools.product(ORDINALS.items(), DIRECTIONS, OBJECTS):
        rows.append(
            (f"the {word} {thing} from the {direction}", f"the {thing}", [("ordinal", "", direction, rank)])
        )
    for (word, rank), direction in itertools.product(ORDINALS.items(), DIRECTIONS):
        rows.append(
            (
                f"the {word} white llama from the {direction}",
                "the white llama",
                [("ordinal", "", direction, rank)],
            )
        )
        rows.append((f"{word} from the {direction}", "", [("ordinal", "", direction, rank)]))
    for word, rank in (("first", 1), ("second", 2), ("third", 3)):
        rows.append((f"the {word} one on the left", "the one", [("ordinal", "", "left", rank)]))
    rows.append(("the last one on the right", "the one", [("ordinal", "", "right", 1)]))  # the far end there
    return rows


def _extreme_table() -> list[tuple[str, str, Expected]]:
    rows = []
    for direction, thing in itertools.product(("left", "right"), OBJECTS):
        rows.append((f"the {direction}most {thing}", f"the {thing}", [("ordinal", "", direction, 1)]))
        rows.append((f"the {direction}-most {thing}", f"the {thing}", [("ordinal", "", direction, 1)]))
        rows.append(
            (f"the {thing} furthest to the {direction}", f"the {thing}", [("ordinal", "", direction, 1)])
        )
        rows.append((f"the {thing} on the far {direction}", f"the {thing}", [("ordinal", "", direction, 1)]))
    for thing in OBJECTS:
        rows.append((f"the {thing} closest to the camera", f"the {thing}", [("ordinal", "", "near", 1)]))
        rows.append((f"the nearest {thing}", f"the {thing}", [("ordinal", "", "near", 1)]))
        rows.append((f"the {thing} nearest to the drone", f"the {thing}", [("ordinal", "", "near", 1)]))
        rows.append((f"the {thing} farthest away", f"the {thing}", [("ordinal", "", "far", 1)]))
        rows.append((f"the most distant {thing}", f"the {thing}", [("ordinal", "", "far", 1)]))
        rows.append((f"the topmost {thing}", f"the {thing}", [("ordinal", "", "top", 1)]))
        rows.append((f"the lowermost {thing}", f"the {thing}", [("ordinal", "", "bottom", 1)]))
    return rows


REFERENCES = ("the pier", "the red car", "the man in the green hoodie", "a white van", "the bench")
PREPOSITIONS = {
    "next to": "near", "beside": "near", "near": "near", "close to": "near", "alongside": "near",
    "behind": "behind", "in front of": "in_front", "ahead of": "in_front", "under": "under",
    "below": "under", "beneath": "under", "above": "above", "at the feet of": "at_feet",
    "on top of": "on", "to the left of": "left_of", "to the right of": "right_of", "left of": "left_of",
    "on the right side of": "right_of", "inside": "inside", "aboard": "inside", "following": "behind",
    "towed by": "behind",
}  # fmt: skip


def _reference_table() -> list[tuple[str, str, Expected]]:
    rows = []
    for (words, kind), reference in itertools.product(PREPOSITIONS.items(), REFERENCES):
        rows.append((f"the dog {words} {reference}", "the dog", [(kind, reference, None, 1)]))
    for reference in REFERENCES:
        rows.append(
            (
                f"a man in a red shirt next to {reference}",
                "a man in a red shirt",
                [("near", reference, None, 1)],
            )
        )
        rows.append((f"the boat closest to {reference}", "the boat", [("closest_to", reference, None, 1)]))
    return rows


FIXED: list[tuple[str, str, Expected]] = [
    # the dev set's descriptions
    ("the cyclist in the blue shirt closest to the camera", "the cyclist in the blue shirt", [("ordinal", "", "near", 1)]),
    ("the white motorboat with a canopy roof", "the white motorboat", [("with", "a canopy roof", None, 1)]),
    (
        "the dark sedan first in the queue on the left of the intersection",
        "the dark sedan",
        [("ordinal", "", "front", 1), ("left_of", "the intersection", None, 1)],
    ),
    (
        "the grey car crossing the zebra stripes in the middle of the intersection",
        "the grey car",
        [("on", "the zebra stripes", None, 1), ("middle_of", "the intersection", None, 1)],
    ),
    (
        "the white minivan at the front of the traffic at the far crosswalk",
        "the white minivan",
        [("ordinal", "", "front", 1), ("near", "the far crosswalk", None, 1)],
    ),
    (
        "the person in the grey-blue striped shirt and dark trousers walking between the man in the red shirt "
        "and the man in the green-and-white striped shirt",
        "the person in the grey-blue striped shirt and dark trousers walking",
        [("between", "the man in the red shirt and the man in the green-and-white striped shirt", None, 1)],
    ),
    ("the man in the green-and-white striped shirt", "the man in the green-and-white striped shirt", []),
    (
        "the wakeboarder being towed to the left of the boat's wake",
        "the wakeboarder being towed",
        [("left_of", "the boat's wake", None, 1)],
    ),
    ("the surfer in a black wetsuit riding the wave", "the surfer in a black wetsuit", [("on", "the wave", None, 1)]),
    ("the person in dark clothes crossing the street", "the person in dark clothes", [("on", "the street", None, 1)]),
    ("the white plastic bag on the ground", "the white plastic bag", [("on", "the ground", None, 1)]),
    # the phrasings
    ("the white SUV in the same lane", "the white suv", [("lane", "", None, 1)]),
    ("the white suv in the same lane as the red car", "the white suv", [("lane", "the red car", None, 1)]),
    ("the red boat next to the pier", "the red boat", [("near", "the pier", None, 1)]),
    ("the pink ball at the man's feet", "the pink ball", [("at_feet", "the man", None, 1)]),
    ("the ball at the dog's feet", "the ball", [("at_feet", "the dog", None, 1)]),
    (
        "the pink ball at the feet of the man in the green hoodie",
        "the pink ball",
        [("at_feet", "the man in the green hoodie", None, 1)],
    ),
    ("a man in a red shirt behind the red car", "a man in a red shirt", [("behind", "the red car", None, 1)]),
    ("the skateboarder on the ramp", "the skateboarder", [("on", "the ramp", None, 1)]),
    ("the last llama", "the llama", [("ordinal", "", "front", -1)]),
    # queues and lines
    ("first in the queue", "", [("ordinal", "", "front", 1)]),
    ("the second car in the line", "the car", [("ordinal", "", "front", 2)]),
    ("the last truck in the convoy", "the truck", [("ordinal", "", "front", -1)]),
    ("the bus at the back of the queue", "the bus", [("ordinal", "", "front", -1)]),
    ("the car at the head of the line", "the car", [("ordinal", "", "front", 1)]),
    ("the horse leading the group", "the horse", [("ordinal", "", "front", 1)]),
    ("the van in front of the queue", "the van", [("ordinal", "", "front", 1)]),
    ("the second to last car in the queue", "the car", [("ordinal", "", "front", -2)]),
    # sides among its own kind, and middles
    ("the car on the left", "the car", [("side", "", "left", 1)]),
    ("the boat on the right-hand side", "the boat", [("side", "", "right", 1)]),
    ("the middle one", "", [("between", "", None, 1)]),
    ("the cow in the middle", "the cow", [("between", "", None, 1)]),
    ("the woman in the middle of the two men", "the woman", [("between", "the two men", None, 1)]),
    ("the sheep among the cows", "the sheep", [("between", "the cows", None, 1)]),
    ("the car in the middle of the road", "the car", [("middle_of", "the road", None, 1)]),
    # attributes are not relations
    ("a man in a red shirt", "a man in a red shirt", []),
    ("a woman in a blue jacket and black trousers", "a woman in a blue jacket and black trousers", []),
    ("a man with red hair", "a man with red hair", []),
    ("someone in black", "someone in black", []),
    ("a hiker in a yellow raincoat", "a hiker in a yellow raincoat", []),
    ("a child in a pink dress", "a child in a pink dress", []),
    ("the man in the grey hoodie with a blue cap", "the man in the grey hoodie with a blue cap", []),
    ("a person lying on the ground", "a person lying", [("on", "the ground", None, 1)]),
    # objects after in / with / carrying are other objects
    ("the woman in the red car", "the woman", [("inside", "the red car", None, 1)]),
    ("a man with the dog", "a man", [("with", "the dog", None, 1)]),
    ("a man in a navy hoodie with the dog in a brown coat", "a man in a navy hoodie", [("with", "the dog in a brown coat", None, 1)]),
    ("the woman carrying a child", "the woman", [("with", "a child", None, 1)]),
    ("the man walking a dog", "the man", [("with", "a dog", None, 1)]),
    ("the cyclist riding a bicycle", "the cyclist", [("on", "a bicycle", None, 1)]),
    ("a swimmer beside the canoe", "a swimmer", [("near", "the canoe", None, 1)]),
    ("a man who fell off the boat", "a man who fell off the boat", []),  # "off" names nothing checkable
    # what boxes cannot show
    ("the car in the next lane", "the car", [("lane", "", None, 1)]),
    ("the boat heading towards the shore", "the boat", [("heading", "the shore", None, 1)]),
    ("the truck driving north", "the truck", [("heading", "", None, 1)]),
    ("the kayak moving away from the beach", "the kayak", [("heading", "the beach", None, 1)]),
    # several relations
    (
        "the second white car from the left behind the bus",
        "the white car",
        [("ordinal", "", "left", 2), ("behind", "the bus", None, 1)],
    ),
    ("the boat next to the pier on the left", "the boat", [("near", "the pier", None, 1), ("side", "", "left", 1)]),
    ("the dog between the two trees near the river", "the dog", [("between", "the two trees", None, 1), ("near", "the river", None, 1)]),
]  # fmt: skip

TABLE = _ordinal_table() + _extreme_table() + _reference_table() + FIXED


def test_the_table_has_a_few_hundred_phrasings() -> None:
    assert len(TABLE) >= 300 and len({prompt for prompt, _, _ in TABLE}) == len(TABLE)


@pytest.mark.parametrize(("prompt", "own", "relations"), TABLE, ids=[p for p, _, _ in TABLE])
def test_parse_description(prompt: str, own: str, relations: Expected) -> None:
    assert _parsed(prompt) == (own, relations)


def test_relation_texts_are_the_words_as_written() -> None:
    description = parse_description("the red boat next to the pier", ATTRIBUTE_WORDS)
    assert [r.text for r in description.relations] == ["next to the pier"]
    description = parse_description("the second white llama from the left", ATTRIBUTE_WORDS)
    assert [r.text for r in description.relations] == ["second from the left"]


# ---- judges ------------------------------------------------------------------------------------------

LEFT, MIDDLE, RIGHT = Box(0, 0, 20, 50), Box(40, 5, 20, 50), Box(80, 0, 20, 50)
FAR_OFF_LINE = Box(40, 300, 20, 50)
VIEW = (640.0, 360.0)


def test_between_is_geometric_and_symmetric() -> None:
    assert is_between(MIDDLE, LEFT, RIGHT) and is_between(MIDDLE, RIGHT, LEFT)
    assert not is_between(LEFT, MIDDLE, RIGHT) and not is_between(RIGHT, LEFT, MIDDLE)
    assert not is_between(FAR_OFF_LINE, LEFT, RIGHT)  # between in x, but far off the line joining them
    assert not is_between(MIDDLE, LEFT, LEFT)  # no line
    between = Relation("between", "between")
    assert judge_relation(between, [LEFT, MIDDLE, RIGHT], [0, 1, 2], None, VIEW) == [False, True, False]
    assert judge_relation(between, [LEFT, MIDDLE], [0, 1], None, VIEW) == [False, False]


ROW = [Box(10 + 60 * i, 100, 30, 20) for i in range(5)]  # five cars in a row, left to right


@pytest.mark.parametrize(
    ("axis", "rank", "pool", "chosen"),
    [
        ("left", 1, [0, 1, 2, 3, 4], 0),
        ("left", 2, [0, 1, 2, 3, 4], 1),
        ("left", 2, [0, 2, 3, 4], 2),  # the second among those that may be the target
        ("right", 1, [0, 1, 2, 3, 4], 4),
        ("right", 3, [0, 1, 2, 3, 4], 2),
        ("left", -1, [0, 1, 2, 3, 4], 4),  # the last from the left
        ("left", -2, [0, 1, 2, 3], 2),
        ("left", 6, [0, 1, 2, 3, 4], None),  # fewer than six: cannot be told
    ],
)
def test_ordinal_along_an_axis(axis: str, rank: int, pool: list[int], chosen: int | None) -> None:
    relation = Relation("ordinal", "x", axis=axis, rank=rank)  # type: ignore[arg-type]
    result = judge_ordinal(relation, ROW, pool, VIEW)
    if chosen is None:
        assert result == [None] * len(ROW)
    else:
        assert result == [i == chosen if i in pool else False for i in range(len(ROW))]


def test_an_ordinal_tie_is_uncertain() -> None:
    tied = [Box(100, 100, 30, 20), Box(103, 140, 30, 20), Box(300, 100, 30, 20)]
    assert judge_ordinal(Relation("ordinal", "leftmost", axis="left"), tied, [0, 1, 2], VIEW) == [None] * 3


def test_nearest_to_the_camera_is_the_lowest_foot() -> None:
    people = [Box(100, 100, 20, 50), Box(300, 180, 28, 57), Box(200, 140, 14, 32)]
    relation = Relation("ordinal", "closest to the camera", axis="near")
    assert judge_ordinal(relation, people, [0, 1, 2], VIEW) == [False, True, False]
    far = Relation("ordinal", "farthest", axis="far")
    assert judge_ordinal(far, people, [0, 1, 2], VIEW) == [True, False, False]


def test_a_queue_front_is_its_end_with_the_open_road_ahead() -> None:
    # A queue on the left half, trailing out of view at the image's left edge: its front is the right end.
    queue = [Box(5, 150, 40, 20), Box(55, 150, 40, 20), Box(105, 152, 40, 20), Box(155, 150, 40, 20)]
    assert groups(queue, [0, 1, 2, 3]) == [[0, 1, 2, 3]]
    assert queue_order(queue, [0, 1, 2, 3], VIEW) == [3, 2, 1, 0]
    first = Relation("ordinal", "first in the queue", axis="front", rank=1)
    last = Relation("ordinal", "last in the queue", axis="front", rank=-1)
    assert judge_ordinal(first, queue, [0, 1, 2, 3], VIEW) == [False, False, False, True]
    assert judge_ordinal(last, queue, [0, 1, 2, 3], VIEW) == [True, False, False, False]
    # In the middle of the view with as much room ahead of either end: which end leads cannot be told.
    centred = [Box(250, 150, 40, 20), Box(300, 150, 40, 20)]
    assert judge_ordinal(first, centred, [0, 1], VIEW) == [None, None]


def test_groups_split_far_apart_boxes() -> None:
    boxes = [Box(0, 0, 20, 20), Box(25, 0, 20, 20), Box(300, 0, 20, 20)]
    assert groups(boxes, [0, 1, 2]) == [[0, 1], [2]]


def test_side_among_its_own_kind() -> None:
    boxes = [Box(10, 100, 30, 20), Box(60, 100, 30, 20), Box(500, 100, 30, 20)]
    left = Relation("side", "on the left", axis="left")
    assert judge_side(left, boxes, [0, 1, 2]) == [True, True, False]
    assert judge_side(left, boxes, [0]) == [None, None, None]  # one alone has no side


PIER = Box(100, 100, 200, 30)


@pytest.mark.parametrize(
    ("kind", "box", "fits"),
    [
        ("near", Box(310, 100, 20, 20), True),
        ("near", Box(500, 300, 20, 20), False),
        ("behind", Box(150, 60, 30, 30), True),  # farther up the image, overlapping it in x
        ("behind", Box(150, 140, 30, 30), False),
        ("in_front", Box(150, 140, 30, 30), True),
        ("on", Box(150, 95, 20, 30), True),  # its foot on the pier
        ("on", Box(150, 200, 20, 30), False),
        ("inside", Box(120, 105, 20, 20), True),
        ("inside", Box(90, 105, 20, 20), False),
        ("under", Box(150, 140, 20, 20), True),
        ("above", Box(150, 60, 20, 20), True),
        ("left_of", Box(40, 100, 20, 30), True),
        ("left_of", Box(320, 100, 20, 30), False),
        ("right_of", Box(320, 100, 20, 30), True),
        ("middle_of", Box(190, 105, 20, 20), True),
        ("middle_of", Box(110, 105, 20, 20), False),
    ],
)
def test_relations_to_another_object(kind: str, box: Box, fits: bool) -> None:
    assert fits_reference(kind, box, PIER) is fits  # type: ignore[arg-type]


MAN = Box(300, 100, 30, 80)


@pytest.mark.parametrize(
    ("box", "fits"),
    [
        (Box(305, 170, 12, 12), True),
        (Box(340, 172, 10, 10), True),
        (Box(305, 100, 12, 12), False),
        (Box(420, 170, 12, 12), False),
    ],
)
def test_at_the_feet_of(box: Box, fits: bool) -> None:
    assert fits_reference("at_feet", box, MAN) is fits


def test_a_reference_not_located_is_not_judged_and_an_occupant_is_not_beside_its_boat() -> None:
    near = Relation("near", "next to the boat", "the boat")
    assert judge_reference(near, Box(0, 0, 10, 10), None) is None
    boat = Box(100, 100, 100, 60)
    assert judge_reference(near, Box(120, 110, 20, 30), [boat]) is False  # in it, not next to it
    assert judge_reference(near, Box(205, 110, 20, 30), [boat]) is True
    assert (
        judge_reference(Relation("inside", "in the boat", "the boat"), Box(120, 110, 20, 30), [boat]) is True
    )
    outside = Relation("outside", "not in the boat", "the boat")
    assert judge_reference(outside, Box(205, 110, 20, 30), [boat]) is True
    assert judge_reference(Relation("lane", "in the same lane"), Box(0, 0, 10, 10), [boat]) is None


def test_combine() -> None:
    assert combine([True, True]) is True and combine([True, None]) is None and combine([None, False]) is False
    assert combine([]) is None


# ---- the search's first choice ----------------------------------------------------------------------


def _d(
    x: float,
    score: float,
    verdict: Verdict,
    placed: bool | None = None,
    judged: bool = True,
    ranked: bool = False,
) -> Detection:
    return Detection(
        Box(x, 0, 10, 20), score, verdict=verdict, placement_ok=placed, judged=judged, singled_out=ranked
    )


def test_first_choice_ranks_by_verdict_then_placement_then_score() -> None:
    yes_fits, yes_open, yes_not = (
        _d(0, 0.3, Verdict.YES, True),
        _d(20, 0.9, Verdict.YES),
        _d(40, 0.8, Verdict.YES, False),
    )
    assert select_first_acquisition([yes_not, yes_open, yes_fits], False) is yes_fits
    assert select_first_acquisition([yes_not, yes_open], False) is yes_open
    assert select_first_acquisition([yes_not], False) is yes_not  # ranks, never rejects
    assert select_first_acquisition([_d(0, 0.9, Verdict.NO, True)], False) is None  # never a "no"


def test_an_uncertain_the_rank_singles_out_comes_after_a_fitting_yes() -> None:
    # "the cyclist in the blue shirt closest to the camera": his dark blue shirt reads mostly black.
    nearest = _d(0, 0.7, Verdict.UNCERTAIN, True, ranked=True)
    farther = _d(20, 0.9, Verdict.YES, False)
    assert select_first_acquisition([farther, nearest], False) is nearest
    assert select_first_acquisition([farther, nearest, _d(40, 0.5, Verdict.YES, True)], False).score == 0.5  # type: ignore[union-attr]
    # A relation several may satisfy ("between", "next to") only ranks: a judged "uncertain" still waits.
    between = _d(0, 0.7, Verdict.UNCERTAIN, True)
    assert select_first_acquisition([farther, between], False) is farther
    assert select_first_acquisition([between], False) is None
    # Nothing judged past the class: the placement decides among them ("the leftmost car").
    left, right = (
        _d(0, 0.4, Verdict.UNCERTAIN, True, judged=False),
        _d(40, 0.9, Verdict.UNCERTAIN, False, judged=False),
    )
    assert select_first_acquisition([right, left], False) is left
