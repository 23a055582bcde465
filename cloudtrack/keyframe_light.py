"""A keyframe's mean luma, for the low-light rule of `behaviors.scene_light` (the companion's map and
`cloudtrack-backend pod-curve` measure it the same way)."""

from __future__ import annotations

import numpy as np

STRIDE = 4  # every 4th pixel each way: a mean over tens of thousands of pixels, about 0.1 ms a frame


def mean_luma(image: np.ndarray) -> float:
    """Mean luma (0-255, Rec. 601 weights as OpenCV's grey conversion) of a BGR or grey 8-bit image."""
    sample = image[::STRIDE, ::STRIDE]
    if sample.size == 0:
        return 0.0
    if sample.ndim == 2:
        return float(sample.mean())
    b, g, r = (float(sample[..., c].mean()) for c in range(3))
    return 0.114 * b + 0.587 * g + 0.299 * r
