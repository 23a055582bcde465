from __future__ import annotations

import pytest

from behaviors.candidate_selection import (
    alike,
    c_box,
    may_start,
    select_by_c_box,
    select_by_score,
    select_first_acquisition,
    settle_early_choice,
)
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou

YES = Detection(Box(0, 0, 10, 20), 0.4, verdict=Verdict.YES)
NO = Detection(Box(40, 0, 10, 20), 0.99, verdict=Verdict.NO)
UNSURE = Detection(Box(80, 0, 10, 20), 0.8, verdict=Verdict.UNCERTAIN)  # judged: too small, half a colour
UNJUDGED = Detection(Box(120, 0, 10, 20), 0.7, verdict=Verdict.UNCERTAIN, judged=False)
UNJUDGED_BEST = Detection(Box(160, 0, 10, 20), 0.9, verdict=Verdict.UNCERTAIN, judged=False)
NO_UNJUDGED = Detection(Box(200, 0, 10, 20), 0.95, verdict=Verdict.NO, judged=False)  # rejected before


@pytest.mark.parametrize(
    ("candidates", "accept_uncertain", "chosen"),
    [
        ([UNSURE, YES, UNJUDGED], False, YES),  # a "yes" first, whatever the scores
        ([UNSURE, YES, UNJUDGED], True, YES),
        ([UNSURE, NO], False, None),  # a judged "uncertain" waits for a "yes"
        ([UNSURE, NO], True, UNSURE),  # ...unless the mission accepts it
        ([UNJUDGED, UNSURE], False, UNJUDGED),  # nothing judged past the class: no answer will say more
        ([UNJUDGED, UNJUDGED_BEST], False, UNJUDGED_BEST),  # then the detector's best
        ([UNJUDGED, UNSURE], True, UNSURE),  # both admitted: the better score
        ([NO_UNJUDGED, NO], False, None),  # a "no" never starts
        ([], False, None),
    ],
)
def test_first_acquisition_admits_an_uncertain_only_when_nothing_could_judge_it(
    candidates: list[Detection], accept_uncertain: bool, chosen: Detection | None
) -> None:
    assert select_first_acquisition(candidates, accept_uncertain) is chosen


YES_2 = Detection(Box(240, 0, 10, 20), 0.6, verdict=Verdict.YES)
YES_3 = Detection(Box(280, 0, 10, 20), 0.5, verdict=Verdict.YES)
YES_FITS = Detection(Box(320, 0, 10, 20), 0.3, verdict=Verdict.YES, placement_ok=True)
YES_NOT_PLACED = Detection(Box(360, 0, 10, 20), 0.8, verdict=Verdict.YES, placement_ok=False)
SINGLED = Detection(Box(400, 0, 10, 20), 0.2, verdict=Verdict.UNCERTAIN, placement_ok=True, singled_out=True)


@pytest.mark.parametrize(
    ("candidates", "accept_uncertain", "chosen", "others"),
    [
        ([YES, YES_2, YES_3, UNSURE, NO], False, YES_2, 2),  # three "yes" told apart by score alone
        ([YES, YES_2, YES_3, YES_FITS], False, YES_FITS, 0),  # the placement chose it
        ([YES, YES_NOT_PLACED], False, YES, 0),  # the other does not fit where the description says
        ([YES_NOT_PLACED, YES], False, YES, 0),
        ([UNSURE, UNJUDGED, UNJUDGED_BEST], False, UNJUDGED_BEST, 1),  # nothing judged: the score chose
        ([UNSURE, UNJUDGED], True, UNSURE, 1),  # both admitted, neither judged better
        ([SINGLED, UNSURE], False, SINGLED, 0),  # the rank picks it alone
        ([YES, YES_2, NO, NO_UNJUDGED], False, YES_2, 1),  # a "no" is never alike
    ],
)
def test_alike_counts_the_others_the_search_could_have_taken_as_well(
    candidates: list[Detection], accept_uncertain: bool, chosen: Detection, others: int
) -> None:
    assert select_first_acquisition(candidates, accept_uncertain) is chosen
    assert alike(candidates, chosen, accept_uncertain) == others


def test_alike_leaves_out_what_the_search_may_not_take() -> None:
    """A candidate the mission refuses (rejected, found, already awaiting) is no alternative."""
    refused = {id(YES_3)}
    assert alike([YES, YES_2, YES_3], YES_2, False, lambda d: id(d) not in refused) == 1


@pytest.mark.parametrize(
    ("candidates", "accept_uncertain", "acted_on"),
    [
        ([YES, NO, UNSURE, UNJUDGED], False, [YES, UNJUDGED]),  # what the detection curve counts as found
        ([YES, NO, UNSURE, UNJUDGED], True, [YES, UNSURE, UNJUDGED]),
        ([SINGLED, UNSURE], False, [SINGLED]),
        ([NO, NO_UNJUDGED], True, []),
    ],
)
def test_may_start_is_what_first_acquisition_chooses_among(
    candidates: list[Detection], accept_uncertain: bool, acted_on: list[Detection]
) -> None:
    assert may_start(candidates, accept_uncertain) == acted_on
    assert select_first_acquisition(candidates, accept_uncertain) in [
        *acted_on,
        *([None] if not acted_on else []),
    ]


def test_c_box_is_l1_of_centres_and_sizes() -> None:
    prev = Box.from_center(100, 100, 20, 40)
    cand = Box.from_center(103, 96, 22, 35)
    assert c_box(prev, cand) == 3 + 4 + 2 + 5


def test_select_prefers_nearby_over_high_score() -> None:
    prev = Box.from_center(100, 100, 20, 40)
    near = Detection(Box.from_center(110, 102, 21, 41), score=0.4)
    far = Detection(Box.from_center(400, 300, 20, 40), score=0.95)
    assert select_by_c_box(prev, [far, near]) is near
    assert select_by_score([far, near]) is far


def test_select_ignores_invalid_and_handles_empty() -> None:
    prev = Box(0, 0, 10, 10)
    assert select_by_c_box(prev, []) is None
    bad = Detection(Box(0, 0, 0, 10), score=1.0)
    good = Detection(Box(50, 50, 10, 10), score=0.1)
    assert select_by_c_box(prev, [bad, good]) is good


def test_iou() -> None:
    a = Box(0, 0, 10, 10)
    assert iou(a, a) == 1.0
    assert iou(a, Box(5, 0, 10, 10)) == 50 / 150
    assert iou(a, Box(20, 20, 5, 5)) == 0.0
    assert iou(a, Box(0, 0, float("nan"), 10)) == 0.0


EARLY = Box(100, 100, 20, 50)
MOVED = Box(102, 101, 20, 50)  # the same person in the final answer's detection
BYSTANDER = Box(300, 100, 20, 50)


@pytest.mark.parametrize(
    ("final", "expected", "kept"),
    [
        ([(MOVED, Verdict.YES, 0.5), (BYSTANDER, Verdict.YES, 0.99)], MOVED, True),  # no reason to switch
        ([(MOVED, Verdict.NO, 0.9), (BYSTANDER, Verdict.YES, 0.5)], BYSTANDER, False),  # refused: moves
        ([(MOVED, Verdict.UNCERTAIN, 0.9), (BYSTANDER, Verdict.YES, 0.5)], BYSTANDER, False),
        ([(MOVED, Verdict.NO, 0.9), (BYSTANDER, Verdict.NO, 0.5)], None, False),  # accepts no one: ends
        ([(BYSTANDER, Verdict.YES, 0.5)], BYSTANDER, False),  # the early choice is not in the answer
        ([], None, False),
    ],
)
def test_settle_early_choice(
    final: list[tuple[Box, Verdict, float]], expected: Box | None, kept: bool
) -> None:
    candidates = [Detection(box, score, verdict=verdict) for box, verdict, score in final]
    chosen, was_kept = settle_early_choice(
        candidates, EARLY, lambda ds: select_first_acquisition(ds, accept_uncertain=False)
    )
    assert (chosen.box if chosen is not None else None, was_kept) == (expected, kept)
