"""`--video`: the simulated camera view with the companion's box, state, prompt and verdict drawn on it."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from behaviors.geometry import Box
from cloudtrack.h264_video import H264Writer

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OverlayState:
    """What the companion last reported: tracked box (camera pixels), state, prompt, verdict."""

    state: str = ""
    prompt: str = ""
    verdict: str = ""
    box: Box | None = None
    note: str = ""


def draw_overlay(image: np.ndarray, overlay: OverlayState, t: float, vehicle: str) -> np.ndarray:
    out = image.copy()
    if overlay.box is not None and overlay.box.is_valid():
        b = overlay.box
        colour = (
            (0, 255, 0)
            if overlay.state in ("following", "confirmed", "awaiting_confirmation")
            else (0, 200, 255)
        )
        cv2.rectangle(out, (int(b.x), int(b.y)), (int(b.x2), int(b.y2)), colour, 2)
    cv2.rectangle(out, (0, 0), (out.shape[1], 44), (0, 0, 0), -1)
    top = f"{vehicle}  t={t:5.1f}s  state: {overlay.state or '-'}"
    cv2.putText(out, top, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    second = f"prompt: {overlay.prompt or '-'}   verdict: {overlay.verdict or '-'}"
    cv2.putText(out, second[:90], (6, 37), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 255, 200), 1, cv2.LINE_AA)
    if overlay.note:
        cv2.putText(
            out,
            overlay.note[:80],
            (6, out.shape[0] - 14),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (0, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return out


class VideoWriter:
    """The demo's H.264 mp4 (plays in browsers), encoded on its own thread (`cloudtrack.h264_video`).

    The camera thread only queues frames; at 3-4 ms per 640x480 frame the encoder keeps up with 30 FPS,
    and a frame that finds the queue full is dropped (counted in `dropped`) rather than stall the camera.
    """

    def __init__(self, path: Path, fps: float, size: tuple[int, int]) -> None:
        self.path = path
        self.size = size
        self._writer = H264Writer(path, fps, queue_frames=60)

    @property
    def frames(self) -> int:
        return self._writer.frames_written

    @property
    def dropped(self) -> int:
        return self._writer.frames_dropped

    def write(self, image: np.ndarray, *, wait: bool = False) -> None:
        self._writer.write(image, wait=wait)

    def close(self) -> None:
        self._writer.close()
        if self._writer.error is not None or self._writer.frames_dropped:
            log.warning(
                "video %s: %d frames written, %d dropped%s",
                self.path,
                self._writer.frames_written,
                self._writer.frames_dropped,
                f", encoder error: {self._writer.error}" if self._writer.error else "",
            )
