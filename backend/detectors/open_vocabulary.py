"""Open-vocabulary superset detectors through `transformers`: Grounding DINO and OWLv2 (GPU servers).

Any superset text works ("person", "life raft", "red car"): there is no class mapping. Pre- and
post-processing are the models' own processors: Grounding DINO takes one lower-case text of phrases
separated by " . " and returns boxes with the phrases they matched; OWLv2 takes one query per class
("a photo of a person") and pads the image to a square, so its boxes are scaled to the padded side and
clipped to the image. Boxes then go through class-aware NMS. Needs the `gpu` extra (torch, transformers).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import cv2
import numpy as np

from backend.detectors.nms import class_aware_nms
from behaviors.detection import Detection
from behaviors.geometry import Box

Kind = Literal["grounding_dino", "owlv2"]
DEFAULT_MODELS: dict[str, str] = {
    "grounding_dino": "IDEA-Research/grounding-dino-tiny",
    "owlv2": "google/owlv2-base-patch16-ensemble",
}


def _label_for(matched_text: str, classes: Sequence[str]) -> str:
    """The class whose phrase Grounding DINO's matched text contains most of (it returns token spans)."""
    words = set(matched_text.lower().replace(".", " ").split())
    return max(classes, key=lambda c: (len(set(c.lower().split()) & words), -classes.index(c)))


class OpenVocabularyDetector:
    def __init__(
        self,
        kind: str,
        model: Any,
        processor: Any,
        device: str = "cpu",
        score_threshold: float = 0.3,
        text_threshold: float = 0.25,
        nms_threshold: float = 0.5,
        name: str | None = None,
    ) -> None:
        if kind not in DEFAULT_MODELS:
            raise ValueError(
                f"open-vocabulary detector kind must be one of {sorted(DEFAULT_MODELS)}, not {kind!r}"
            )
        self.kind = kind
        self.model = model.to(device).eval()
        self.processor = processor
        self.device = device
        self.score_threshold = score_threshold
        self.text_threshold = text_threshold
        self.nms_threshold = nms_threshold
        self.name = name or kind

    @classmethod
    def from_pretrained(
        cls, kind: str, model_id: str = "", device: str = "cpu", score_threshold: float = 0.3
    ) -> OpenVocabularyDetector:
        """Load weights and processor from the Hugging Face hub id or a local folder (save_pretrained)."""
        from transformers import AutoModelForZeroShotObjectDetection, AutoProcessor

        if kind not in DEFAULT_MODELS:
            raise ValueError(
                f"open-vocabulary detector kind must be one of {sorted(DEFAULT_MODELS)}, not {kind!r}"
            )
        source = model_id or DEFAULT_MODELS[kind]
        model = AutoModelForZeroShotObjectDetection.from_pretrained(source)
        processor = AutoProcessor.from_pretrained(source)  # type: ignore[no-untyped-call]
        return cls(kind, model, processor, device, score_threshold, name=f"{kind}:{source}")

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        import torch
        from PIL import Image

        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
            raise ValueError(f"expected a BGR image H x W x 3, got shape {image_bgr.shape}")
        names = [c.strip().lower() for c in classes if c.strip()]
        if not names:
            raise ValueError("no class to look for")
        height, width = image_bgr.shape[:2]
        image = Image.fromarray(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2RGB))
        with torch.inference_mode():
            if self.kind == "grounding_dino":
                inputs = self.processor(images=image, text=" . ".join(names) + " .", return_tensors="pt").to(
                    self.device
                )
                outputs = self.model(**inputs)
                result = self.processor.post_process_grounded_object_detection(
                    outputs,
                    inputs["input_ids"],
                    threshold=self.score_threshold,
                    text_threshold=self.text_threshold,
                    target_sizes=[(height, width)],
                )[0]
                labels = [_label_for(str(text), names) for text in result["text_labels"]]
            else:
                queries = [[f"a photo of a {name}" for name in names]]
                inputs = self.processor(
                    text=queries, images=image, padding=True, truncation=True, return_tensors="pt"
                ).to(self.device)
                outputs = self.model(**inputs)
                side = max(height, width)  # OWLv2 pads to a square at the bottom/right
                result = self.processor.post_process_grounded_object_detection(
                    outputs, threshold=self.score_threshold, target_sizes=[(side, side)], text_labels=[names]
                )[0]
                labels = [str(text) for text in result["text_labels"]]
        boxes = result["boxes"].detach().cpu().numpy().astype(np.float64).reshape(-1, 4)
        scores = result["scores"].detach().cpu().numpy().astype(np.float64).reshape(-1)
        if len(scores) == 0:
            return []
        boxes = np.clip(boxes, 0, [width, height, width, height])
        label_ids = np.asarray([names.index(label) for label in labels])
        detections = []
        for i in class_aware_nms(boxes, scores, label_ids, self.nms_threshold):
            box = Box.from_xyxy(*(float(v) for v in boxes[i]))
            if box.w >= 1 and box.h >= 1:
                detections.append(Detection(box=box, score=float(scores[i]), label=labels[i]))
        return detections
