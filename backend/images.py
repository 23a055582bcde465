"""Decoding an uploaded keyframe safely: JPEG or PNG only, checked size, a clear reason when it fails."""

from __future__ import annotations

import cv2
import numpy as np

JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class ImageError(ValueError):
    """An upload that is not a usable image; `status` is the HTTP status that fits (400, 413 or 415)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG header without decoding; None for JPEG (decoded to find out)."""
    if data.startswith(PNG_MAGIC) and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def decode_image(data: bytes, max_pixels: int) -> np.ndarray:
    """A BGR uint8 image from JPEG/PNG bytes; ImageError names what is wrong."""
    if not data:
        raise ImageError("the image part is empty")
    if not (data.startswith(JPEG_MAGIC) or data.startswith(PNG_MAGIC)):
        raise ImageError("the image must be JPEG or PNG (unrecognised file signature)", status=415)
    size = _header_size(data)
    if size is not None and size[0] * size[1] > max_pixels:
        raise ImageError(f"image of {size[0]}x{size[1]} pixels exceeds the limit of {max_pixels} pixels", 413)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise ImageError("the image could not be decoded (corrupt or truncated JPEG/PNG)")
    if image.shape[0] * image.shape[1] > max_pixels:
        raise ImageError(
            f"image of {image.shape[1]}x{image.shape[0]} pixels exceeds the limit of {max_pixels} pixels", 413
        )
    return image


def encode_jpeg(image_bgr: np.ndarray, quality: int) -> bytes:
    ok, buffer = cv2.imencode(".jpg", image_bgr, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise ImageError("JPEG encoding failed")
    return bytes(buffer.tobytes())
