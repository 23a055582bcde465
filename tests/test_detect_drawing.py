"""`cloudtrack-backend detect --draw`: labels a person can read on a 1280x720 frame, never on top of each other."""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np

from backend_tools.detect_command import COLOURS, draw_candidates
from behaviors.detection import Verdict


def _frame(sequences_dir: Path) -> np.ndarray:
    image = cv2.imread(str(sequences_dir / "uav123_person12_1" / "frames" / "000001.jpg"))
    assert image is not None and image.shape[:2] == (720, 1280)
    return image


def test_draw_labels_scale_with_the_image_on_a_filled_background(sequences_dir: Path) -> None:
    image = _frame(sequences_dir)
    [label] = draw_candidates(image, [((600, 300, 660, 420), "yes 0.87", COLOURS[Verdict.YES])])
    x1, y1, x2, y2 = label
    assert y2 <= 300 and x1 >= 0 and y1 >= 0  # above its box, inside the image
    assert y2 - y1 >= 20, "label shorter than 20 px on a 720 px high frame"  # the old one: about 8 px of text
    patch = image[y1:y2, x1:x2].reshape(-1, 3)
    fill = np.all(patch == COLOURS[Verdict.YES], axis=1).mean()
    ink = np.all(patch < 60, axis=1).mean()  # dark text on the light green fill
    assert fill > 0.5 and ink > 0.05, (fill, ink)

    small = np.zeros((240, 320, 3), np.uint8)
    [small_label] = draw_candidates(small, [((100, 100, 140, 180), "yes 0.87", COLOURS[Verdict.YES])])
    assert small_label[3] - small_label[1] < y2 - y1  # smaller image, smaller text


def test_draw_labels_of_nearby_boxes_never_overlap(sequences_dir: Path) -> None:
    image = _frame(sequences_dir)
    # Five people side by side and two boxes at the top edge: labels must find room without covering another.
    boxes = [(500 + 25 * i, 300 + 6 * i, 560 + 25 * i, 420) for i in range(5)] + [
        (10, 0, 80, 90),
        (30, 2, 100, 95),
    ]
    verdicts = itertools.cycle([Verdict.YES, Verdict.NO, Verdict.UNCERTAIN])
    items = [
        (box, f"{v.value} 0.{50 + i}", COLOURS[v])
        for i, (box, v) in enumerate(zip(boxes, verdicts, strict=False))
    ]
    labels = draw_candidates(image, items)
    assert len(labels) == len(boxes)
    for a, b in itertools.combinations(labels, 2):
        assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)
    assert all(min(r[0], r[1]) >= 0 and r[2] <= 1280 and r[3] <= 720 for r in labels)
    # White text on the dark red "no" fill.
    no = labels[1]
    patch = image[no[1] : no[3], no[0] : no[2]].reshape(-1, 3)
    assert np.all(patch > 200, axis=1).mean() > 0.05
