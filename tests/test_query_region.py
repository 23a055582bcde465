"""Where a back-end query looks (behaviors.query_region), table-tested."""

from __future__ import annotations

import pytest

from behaviors.geometry import Box
from behaviors.query_region import around, redetect_region

BOX = Box(300, 200, 20, 50)  # centre (310, 225) in a 640x480 image


@pytest.mark.parametrize(
    ("name", "box", "scale", "expected"),
    [
        ("grown about its centre", BOX, 3.0, Box(280, 150, 60, 150)),
        ("clamped to the image", Box(0, 0, 20, 50), 3.0, Box(0, 0, 40, 100)),
        ("outside the image: nothing", Box(700, 500, 20, 50), 3.0, None),
    ],
)
def test_around(name: str, box: Box, scale: float, expected: Box | None) -> None:
    assert around(box, scale, 640, 480) == expected, name


@pytest.mark.parametrize(
    ("name", "lost_for_s", "expected"),
    [
        ("at the loss: the box grown 3x", 0.0, Box(280, 150, 60, 150)),
        ("at the full-frame time: the whole frame", 4.0, None),
        ("later still: the whole frame", 9.0, None),
    ],
)
def test_redetect_region_grows_to_the_whole_frame(name: str, lost_for_s: float, expected: Box | None) -> None:
    assert redetect_region(BOX, lost_for_s, 3.0, 4.0, 640, 480) == expected, name


def test_redetect_region_grows_monotonically_until_it_covers_the_frame() -> None:
    areas = []
    for tenth in range(40):
        region = redetect_region(BOX, tenth / 10, 3.0, 4.0, 640, 480)
        areas.append(region.w * region.h if region is not None else 640 * 480)
    assert areas == sorted(areas) and areas[0] == 60 * 150 and areas[-1] <= 640 * 480
    assert redetect_region(Box(0, 0, 0, 0), 0.0, 3.0, 4.0, 640, 480) is None  # no box: the whole frame
