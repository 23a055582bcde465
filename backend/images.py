"""Decoding uploaded images safely: JPEG or PNG only, dimensions checked from the header before any decode.

Every image the service takes (keyframes, rejection crops, the crops vehicles report for the supervisor)
goes through `image_size` first: a 16000x16000 JPEG is 1 MB on the wire and 768 MB once decoded, so the
size must be known before OpenCV allocates anything.
"""

from __future__ import annotations

import base64
import binascii

import cv2
import numpy as np

JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# Start-of-frame markers carry the dimensions (baseline, extended, progressive, lossless, arithmetic...);
# 0xC4 (DHT), 0xC8 (JPG) and 0xCC (DAC) share the range but are not frames.
_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])  # TEM, RSTn: no length field
MAX_SEGMENTS_BEFORE_FRAME = 1000  # markers and fill bytes; EXIF, ICC chunks and tables are far fewer


class ImageError(ValueError):
    """An upload that is not a usable image; `status` is the HTTP status that fits (400, 413 or 415)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the first start-of-frame segment, walking the marker segments only: at most
    MAX_SEGMENTS_BEFORE_FRAME of them (a real JPEG has a few dozen; 2 MB of 4-byte segments would be a
    500,000-step walk on the event loop)."""
    i = 2
    for _ in range(MAX_SEGMENTS_BEFORE_FRAME):
        if i + 4 > len(data):
            break
        if data[i] != 0xFF:
            raise ImageError(
                "the image could not be decoded: its JPEG header is corrupt (no marker where one must be)"
            )
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _STANDALONE:
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header came first
            break
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if length < 2:
            raise ImageError(
                "the image could not be decoded: its JPEG header is corrupt (bad segment length)"
            )
        if marker in _SOF_MARKERS:
            if i + 9 > len(data):
                break
            height = int.from_bytes(data[i + 5 : i + 7], "big")
            width = int.from_bytes(data[i + 7 : i + 9], "big")
            return width, height
        i += 2 + length
    raise ImageError("the image could not be decoded: no readable JPEG frame header (truncated or corrupt)")


def image_size(data: bytes) -> tuple[int, int]:
    """(width, height) of JPEG or PNG bytes from the header alone; ImageError (415/400) otherwise."""
    if not data:
        raise ImageError("the image is empty")
    if data.startswith(PNG_MAGIC):
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ImageError("the image could not be decoded: its PNG header is truncated or corrupt")
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data.startswith(JPEG_MAGIC):
        return _jpeg_size(data)
    raise ImageError("the image must be JPEG or PNG (unrecognised file signature)", status=415)


def check_size(data: bytes, max_pixels: int) -> tuple[int, int]:
    """The header's (width, height), refused with 413 beyond `max_pixels` and 400 when empty."""
    width, height = image_size(data)
    if width <= 0 or height <= 0:
        raise ImageError(f"the image header gives an empty size {width}x{height}")
    if width * height > max_pixels:
        raise ImageError(f"image of {width}x{height} pixels exceeds the limit of {max_pixels} pixels", 413)
    return width, height


def decode_image(data: bytes, max_pixels: int) -> np.ndarray:
    """A BGR uint8 image from JPEG/PNG bytes, its size checked from the header first; ImageError if not."""
    width, height = check_size(data, max_pixels)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise ImageError("the image could not be decoded (corrupt or truncated JPEG/PNG)")
    if image.shape[:2] != (height, width):  # a header that lied about the size
        raise ImageError(
            f"the image decodes to {image.shape[1]}x{image.shape[0]}, not its header's {width}x{height}"
        )
    return image


def b64_image_bytes(text: str, what: str = "crop_jpeg_b64") -> bytes:
    """The bytes of a base64 field; ImageError(422) when it is not base64."""
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise ImageError(f"{what} is not valid base64", 422) from None


def is_jpeg(data: bytes, max_pixels: int) -> bool:
    """Whether these bytes start like a JPEG whose header gives a size within `max_pixels`."""
    try:
        return data.startswith(JPEG_MAGIC) and check_size(data, max_pixels) is not None
    except ImageError:
        return False


def encode_jpeg(image_bgr: np.ndarray, quality: int) -> bytes:
    ok, buffer = cv2.imencode(".jpg", image_bgr, [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)])
    if not ok:
        raise ImageError("JPEG encoding failed")
    return bytes(buffer.tobytes())
