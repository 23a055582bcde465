"""`--video`: the simulated camera view with the companion's box, state, prompt and verdict drawn on it."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from behaviors.geometry import Box


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
        colour = (0, 255, 0) if overlay.state in ("following", "confirmed", "awaiting_confirmation") else (0, 200, 255)
        cv2.rectangle(out, (int(b.x), int(b.y)), (int(b.x2), int(b.y2)), colour, 2)
    cv2.rectangle(out, (0, 0), (out.shape[1], 44), (0, 0, 0), -1)
    top = f"{vehicle}  t={t:5.1f}s  state: {overlay.state or '-'}"
    cv2.putText(out, top, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    second = f"prompt: {overlay.prompt or '-'}   verdict: {overlay.verdict or '-'}"
    cv2.putText(out, second[:90], (6, 37), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 255, 200), 1, cv2.LINE_AA)
    if overlay.note:
        cv2.putText(out, overlay.note[:80], (6, out.shape[0] - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1,
                    cv2.LINE_AA)
    return out


class VideoWriter:
    """An mp4 written frame by frame from the camera thread; thread-safe, closes cleanly."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, size)
        if not self._writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write an mp4 video here")
        self._lock = threading.Lock()
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.write(image)
                self.frames += 1

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.release()
            self._writer = None  # type: ignore[assignment]
