"""Relations between people stated in a description (behaviors.spatial_relations) and their use in the
first acquisition (companion_tools.tracking_eval.first_candidate)."""

from __future__ import annotations

import pytest

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box
from behaviors.spatial_relations import Relation, is_between, narrow_by_relation, parse_relation, satisfies
from companion_tools.tracking_eval import first_candidate

LEFT, MIDDLE, RIGHT = Box(0, 0, 20, 50), Box(40, 5, 20, 50), Box(80, 0, 20, 50)
FAR_OFF_LINE = Box(40, 300, 20, 50)


@pytest.mark.parametrize(
    ("prompt", "relation"),
    [
        ("the person in the striped shirt walking between the man in red and the man in green", "between"),
        ("the woman in the middle of the two men", "between"),
        ("the man in the green-and-white striped shirt", None),
        ("the wakeboarder being towed to the left of the boat's wake", None),  # not viewpoint-independent
    ],
)
def test_parse_relation(prompt: str, relation: str | None) -> None:
    parsed = parse_relation(prompt)
    assert (parsed.kind if parsed else None) == relation


def test_between_is_geometric_and_symmetric() -> None:
    assert is_between(MIDDLE, LEFT, RIGHT) and is_between(MIDDLE, RIGHT, LEFT)
    assert not is_between(LEFT, MIDDLE, RIGHT) and not is_between(RIGHT, LEFT, MIDDLE)
    assert not is_between(FAR_OFF_LINE, LEFT, RIGHT)  # between in x, but far off the line joining them
    assert not is_between(MIDDLE, LEFT, LEFT)  # no line
    between = Relation("between")
    assert satisfies(between, MIDDLE, [LEFT, RIGHT]) and not satisfies(between, MIDDLE, [LEFT])


def test_narrowing_keeps_everyone_when_the_relation_cannot_be_evaluated() -> None:
    boxes = [LEFT, MIDDLE, RIGHT]
    between = Relation("between")
    assert narrow_by_relation(between, [0, 1, 2], boxes) == [1]
    assert narrow_by_relation(between, [0, 2], boxes) == [0, 2]  # nobody chosen satisfies it: no change
    assert narrow_by_relation(None, [0, 2], boxes) == [0, 2]
    assert narrow_by_relation(between, [0, 1], [LEFT, MIDDLE]) == [0, 1]  # two in view: nothing is between


def test_first_candidate_uses_the_relation_but_never_takes_a_no() -> None:
    prompt = "the person walking between the man in the red shirt and the man in the green shirt"
    left = Detection(LEFT, 0.9, verdict=Verdict.UNCERTAIN)
    middle = Detection(MIDDLE, 0.5, verdict=Verdict.UNCERTAIN)
    right = Detection(RIGHT, 0.8, verdict=Verdict.UNCERTAIN)
    assert first_candidate([left, middle, right], accept_uncertain=False, prompt=prompt) is None
    assert first_candidate([left, middle, right], accept_uncertain=True, prompt=prompt) is middle
    assert first_candidate([left, middle, right], accept_uncertain=True) is left  # no relation: best score
    rejected_middle = Detection(MIDDLE, 0.5, verdict=Verdict.NO)
    assert first_candidate([left, rejected_middle, right], accept_uncertain=True, prompt=prompt) is left
    yes_right = Detection(RIGHT, 0.8, verdict=Verdict.YES)
    assert first_candidate([left, middle, yes_right], accept_uncertain=True, prompt=prompt) is yes_right
