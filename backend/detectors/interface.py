"""The one interface every superset detector implements (YOLOX, Grounding DINO, OWLv2, the SITL one)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from behaviors.detection import Detection


class SupersetDetector(Protocol):
    """Finds boxes of the given classes in a BGR uint8 image (H x W x 3).

    `classes` are superset names ("person", "vehicle") or the detector's own class names; a name the
    detector cannot handle raises `backend.supersets.UnknownSupersetError`. Boxes are in the image's
    pixels; `verdict` is left UNCERTAIN (verification is the pipeline's job). `frame_id` lets a simulated
    detector look up its ground truth; real detectors ignore it.
    """

    name: str

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]: ...
