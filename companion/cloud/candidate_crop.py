"""The crop of the candidate awaiting the supervisor, as the back-end's status endpoint takes it.

The supervisor page shows it beside the justification; it is small on purpose (it rides the vehicle's
status over a 4G uplink): the box with a margin, scaled to at most `max_side_px`, JPEG quality lowered in
steps until its base64 text fits `max_b64_chars`.
"""

from __future__ import annotations

import base64
from typing import Any

import cv2
import numpy as np

from behaviors.geometry import Box

MARGIN_PX = 50  # the back-end's own crop margin: the supervisor sees what the verifier saw
MAX_SIDE_PX = 192
MAX_B64_CHARS = 24_000  # well under the schema's 400 000


def candidate_crop(
    image: np.ndarray,
    box: Box,
    margin_px: int = MARGIN_PX,
    max_side_px: int = MAX_SIDE_PX,
    max_b64_chars: int = MAX_B64_CHARS,
) -> dict[str, Any] | None:
    """`{"crop_jpeg_b64", "crop_box"}` for `box` in `image` (crop_box: the candidate inside the crop, in the
    crop's pixels); None when the box is invalid or outside the image."""
    if image.ndim != 3 or image.shape[2] != 3 or not box.is_valid():
        return None
    height, width = image.shape[:2]
    inside = box.clamped(width, height)
    if not inside.is_valid():
        return None
    x1, y1 = max(0, int(inside.x) - margin_px), max(0, int(inside.y) - margin_px)
    x2, y2 = min(width, int(np.ceil(inside.x2)) + margin_px), min(height, int(np.ceil(inside.y2)) + margin_px)
    crop = image[y1:y2, x1:x2]
    scale = min(1.0, max_side_px / max(crop.shape[:2]))
    if scale < 1.0:
        crop = cv2.resize(
            crop,
            (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale))),
            interpolation=cv2.INTER_AREA,
        )
    for quality in (85, 70, 55, 40, 25):
        ok, buffer = cv2.imencode(".jpg", crop, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
        if not ok:
            return None
        text = base64.b64encode(buffer.tobytes()).decode()
        if len(text) <= max_b64_chars:
            inner = [
                (inside.x - x1) * scale,
                (inside.y - y1) * scale,
                (inside.x2 - x1) * scale,
                (inside.y2 - y1) * scale,
            ]
            return {"crop_jpeg_b64": text, "crop_box": [round(v, 1) for v in inner]}
    return None
