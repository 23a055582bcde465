"""The crop of the candidate awaiting the supervisor, as the back-end's status endpoint takes it.

Cut from the camera's native frame, not the downscaled keyframe the back-end saw: a person 12 px tall in a
640-px keyframe is 24 px in a 1280-px frame, twice the detail for the supervisor to judge. The crop keeps
the context the verifier saw (its 50 keyframe-px margin, in native pixels) and at least half the box's
size around it; the page zooms its card onto the box and shows the whole crop on click. It rides the
vehicle's status once per candidate over a 4G uplink, so it is bounded: at most `max_side_px` a side
(larger crops are scaled down), JPEG quality lowered in steps until its base64 text fits `max_b64_chars`,
then the crop shrunk in steps.
"""

from __future__ import annotations

import base64
from typing import Any

import cv2
import numpy as np

from behaviors.geometry import Box

MARGIN_PX = 50  # the back-end's crop margin, in keyframe pixels: the supervisor sees what the verifier saw
BOX_MARGIN = 0.5  # and at least half the box's longer side around it, for a large box
KEYFRAME_WIDTH = 640  # [backend] max_keyframe_width: what a keyframe pixel is in the native frame
MAX_SIDE_PX = 384
MAX_B64_CHARS = 16_000  # 12 KB of JPEG, once per candidate; well under the schema's 400 000
QUALITIES = (85, 75, 65, 55, 40, 25)


def crop_window(
    width: int, height: int, box: Box, keyframe_width: int = KEYFRAME_WIDTH, margin_px: int = MARGIN_PX
) -> tuple[int, int, int, int] | None:
    """(x1, y1, x2, y2) of the crop in the native frame of `width` x `height` for `box` (native pixels):
    the box with the verifier's margin scaled to native pixels, or half its longer side if more, clamped
    to the frame; None when the box is invalid or outside the frame."""
    if not box.is_valid():
        return None
    inside = box.clamped(width, height)
    if not inside.is_valid():
        return None
    native_per_keyframe_px = max(1.0, width / max(1, keyframe_width))
    margin = max(margin_px * native_per_keyframe_px, BOX_MARGIN * max(inside.w, inside.h))
    x1, y1 = max(0, int(inside.x - margin)), max(0, int(inside.y - margin))
    x2 = min(width, int(np.ceil(inside.x2 + margin)))
    y2 = min(height, int(np.ceil(inside.y2 + margin)))
    return x1, y1, x2, y2


def candidate_crop(
    image: np.ndarray,
    box: Box,
    keyframe_width: int = KEYFRAME_WIDTH,
    margin_px: int = MARGIN_PX,
    max_side_px: int = MAX_SIDE_PX,
    max_b64_chars: int = MAX_B64_CHARS,
) -> dict[str, Any] | None:
    """`{"crop_jpeg_b64", "crop_box"}` for `box` in the native `image` (crop_box: the candidate inside the
    crop, in the crop's pixels); None when the box is invalid or outside the image."""
    if image.ndim != 3 or image.shape[2] != 3:
        return None
    height, width = image.shape[:2]
    window = crop_window(width, height, box, keyframe_width, margin_px)
    if window is None:
        return None
    x1, y1, x2, y2 = window
    inside = box.clamped(width, height)
    window_image = image[y1:y2, x1:x2]
    scale = min(1.0, max_side_px / max(window_image.shape[:2]))
    while True:  # a noisy scene (foliage, glare) past the lowest quality: smaller, as the keyframe does
        crop = window_image
        if scale < 1.0:
            size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
            crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        for quality in QUALITIES:
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
        if max(crop.shape[:2]) <= 16:
            return None
        scale *= 0.8
