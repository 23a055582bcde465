"""A closed-set detector for the classes it maps, an open-vocabulary one for every other class.

With `[detector] kind = "yolox"` and `open_vocabulary = "owlv2"` (or "grounding_dino"), a prompt naming a
COCO class ("a man in a red jacket", "a kayak") runs on YOLOX on the CPU, and one naming something COCO
lacks ("a life buoy") goes to the open-vocabulary model as its own words instead of being refused.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from backend.detectors.interface import SupersetDetector
from backend.supersets import UnknownSupersetError, coco_classes_for
from behaviors.detection import Detection


class RoutingDetector:
    def __init__(self, closed_set: SupersetDetector, open_vocabulary: SupersetDetector) -> None:
        self.closed_set = closed_set
        self.open_vocabulary = open_vocabulary
        self.name = f"{closed_set.name}+{open_vocabulary.name}"

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        mapped, unmapped = [], []
        for name in classes:
            try:
                coco_classes_for(name)
                mapped.append(name)
            except UnknownSupersetError:
                unmapped.append(name)
        found = self.closed_set.detect(image_bgr, mapped, frame_id) if mapped else []
        if unmapped:
            found += self.open_vocabulary.detect(image_bgr, unmapped, frame_id)
        return found
