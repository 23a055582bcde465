"""Where in the keyframe a back-end query looks: the region around the track, or the whole frame.

A query about a track (a check while it is followed, a re-verification, a re-detection after a loss) asks
the detector about the track's surroundings only: the region is cropped before detection, so a person of
15-40 px in a 640 px keyframe reaches the detector's 416 px input several times larger than in the whole
frame, and only the people near the track (the ones the tracker could have slid onto) compete. A search
(nothing tracked yet) looks at the whole frame.
"""

from __future__ import annotations

from behaviors.geometry import Box


def around(box: Box, scale: float, width: int, height: int) -> Box | None:
    """`box` grown `scale` times about its centre, inside a `width` x `height` image; None when nothing of
    it is inside."""
    grown = Box.from_center(box.cx, box.cy, box.w * scale, box.h * scale).clamped(width, height)
    return grown if grown.is_valid() else None


def redetect_region(
    box: Box, lost_for_s: float, scale: float, full_frame_s: float, width: int, height: int
) -> Box | None:
    """The re-detection region `lost_for_s` seconds after a loss; None once it is the whole frame.

    It starts as the last box grown `scale` times and grows geometrically (the same factor per second),
    reaching at `full_frame_s` a scale that covers the image from wherever the box was: a walking person
    hidden for a few seconds reappears several box widths away, and a fixed region misses them, while the
    first queries still look only where they most likely are.
    """
    if not (box.is_valid() and lost_for_s < full_frame_s):
        return None
    full = 2.0 * max(width / box.w, height / box.h)
    base = min(scale, full)
    grown = base * (full / base) ** (max(lost_for_s, 0.0) / full_frame_s)
    region = around(box, grown, width, height)
    if region is None or (region.w >= width and region.h >= height):
        return None
    return region
