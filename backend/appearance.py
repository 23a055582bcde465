"""A small appearance descriptor for remembering candidates the supervisor rejected.

A hue-saturation histogram (16 x 8 bins, 128 floats) of the candidate's own box: cheap, insensitive to
scale and small pose changes, and small enough to keep hundreds per mission or send between replicas.
"""

from __future__ import annotations

import cv2
import numpy as np

from behaviors.geometry import Box

HUE_BINS = 16
SAT_BINS = 8


def descriptor(image_bgr: np.ndarray, box: Box) -> list[float]:
    """The L1-normalised HS histogram of the pixels inside `box` (clamped to the image)."""
    height, width = image_bgr.shape[:2]
    inside = box.clamped(width, height)
    x1, y1 = int(inside.x), int(inside.y)
    x2, y2 = max(int(np.ceil(inside.x2)), x1 + 1), max(int(np.ceil(inside.y2)), y1 + 1)
    patch = image_bgr[y1:y2, x1:x2]
    if patch.size == 0:
        return [0.0] * (HUE_BINS * SAT_BINS)
    hsv = cv2.cvtColor(patch, cv2.COLOR_BGR2HSV)
    hist = cv2.calcHist([hsv], [0, 1], None, [HUE_BINS, SAT_BINS], [0, 180, 0, 256]).flatten()
    total = float(hist.sum())
    return [float(v) / total for v in hist] if total > 0 else [0.0] * len(hist)


def similarity(a: list[float], b: list[float]) -> float:
    """Histogram correlation in [-1, 1]; 1 for identical appearance. 0 for mismatched or empty input."""
    if len(a) != len(b) or not a:
        return 0.0
    va, vb = np.asarray(a, np.float32), np.asarray(b, np.float32)
    if not va.any() or not vb.any():
        return 0.0
    return float(cv2.compareHist(va, vb, cv2.HISTCMP_CORREL))
