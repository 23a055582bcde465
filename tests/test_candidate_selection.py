from __future__ import annotations

from behaviors.candidate_selection import c_box, select_by_c_box, select_by_score
from behaviors.detection import Detection
from behaviors.geometry import Box, iou


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
