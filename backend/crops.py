"""Candidate crops: the detector's box grown by a context margin (the paper's 50 px), clamped to the image."""

from __future__ import annotations

import numpy as np

from behaviors.geometry import Box


def crop_box(box: Box, margin_px: float, width: int, height: int) -> tuple[int, int, int, int]:
    """Integer (x1, y1, x2, y2) of the margin crop inside a width x height image; at least 1x1 pixel."""
    grown = box.expanded(margin_px).clamped(width, height)
    x1, y1 = int(np.floor(grown.x)), int(np.floor(grown.y))
    x2, y2 = int(np.ceil(grown.x2)), int(np.ceil(grown.y2))
    x1, y1 = min(max(x1, 0), width - 1), min(max(y1, 0), height - 1)
    return x1, y1, max(x2, x1 + 1), max(y2, y1 + 1)


def margin_crop(image_bgr: np.ndarray, box: Box, margin_px: float) -> tuple[np.ndarray, Box]:
    """The crop around `box` and the box's position inside that crop (what a verifier should look at)."""
    height, width = image_bgr.shape[:2]
    x1, y1, x2, y2 = crop_box(box, margin_px, width, height)
    inner = Box(box.x - x1, box.y - y1, box.w, box.h).clamped(x2 - x1, y2 - y1)
    return image_bgr[y1:y2, x1:x2], inner
