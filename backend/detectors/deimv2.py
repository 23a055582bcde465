"""DEIMv2 (Atto, Femto) through onnxruntime: a DETR-style COCO-80 superset detector.

Pre-processing follows the ONNX export (../shared/models/MODELS.md): RGB scaled to 0-1, the frame resized to
SxS without letterbox. The export ranks (query, class) pairs itself and returns the top 300 as `labels`,
`boxes` (x1, y1, x2, y2 in the frame's pixels, from `orig_target_sizes`) and `scores` (sigmoid class
scores): one query appears once per class it scored, with the same box. There is no objectness, so a
superset's score is the chance that the query is any of its classes, 1 - prod(1 - p) over the classes it
scored (what YOLOX's score is without its objectness factor), and the same threshold applies.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from backend.detectors.nms import superset_detections
from backend.supersets import COCO_CLASSES, coco_classes_for, is_stand_in
from behaviors.detection import Detection


class Deimv2Detector:
    """`detect(image_bgr, classes)` -> detections in the image's pixels, best first."""

    def __init__(
        self,
        model_path: str | Path,
        score_threshold: float = 0.2,
        nms_threshold: float = 0.45,
        threads: int = 0,
    ) -> None:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads  # 0: onnxruntime's default (all cores)
        self._session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])
        inputs = {i.name: i for i in self._session.get_inputs()}
        if set(inputs) != {"images", "orig_target_sizes"}:
            raise ValueError(f"{model_path}: not a DEIMv2 export (inputs {sorted(inputs)})")
        self.input_size = int(inputs["images"].shape[2])  # 320 (Atto) or 416 (Femto), fixed in the export
        self.name = Path(model_path).stem  # deimv2_hgnetv2_atto_coco
        self.score_threshold = score_threshold
        self.nms_threshold = nms_threshold

    def preprocess(self, image_bgr: np.ndarray) -> np.ndarray:
        """The network's input: 1x3xSxS float32 RGB in 0-1, stretched to the square as in training."""
        size = (self.input_size, self.input_size)
        rgb = cv2.cvtColor(cv2.resize(image_bgr, size, interpolation=cv2.INTER_LINEAR), cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32) / np.float32(255)

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or min(image_bgr.shape[:2]) < 1:
            raise ValueError(f"expected a BGR image H x W x 3, got shape {image_bgr.shape}")
        groups = {name: [COCO_CLASSES.index(c) for c in coco_classes_for(name)] for name in classes}
        stand_ins = {tuple(groups[name]) for name in classes if is_stand_in(name)}
        h, w = image_bgr.shape[:2]
        labels, boxes, scores = self._session.run(
            None,
            {"images": self.preprocess(image_bgr), "orig_target_sizes": np.array([[w, h]], np.int64)},
        )
        labels, boxes, scores = labels.reshape(-1), boxes.reshape(-1, 4), scores.reshape(-1)
        if not len(labels) == len(boxes) == len(scores):  # a mismatched export must fail, not mis-pair
            raise ValueError(f"DEIMv2 outputs disagree: {len(labels)} labels, {len(boxes)} boxes")
        valid = (labels >= 0) & (labels < len(COCO_CLASSES))
        labels, boxes, scores = labels[valid], np.clip(boxes[valid], 0, [w, h, w, h]), scores[valid]
        # Rows of one query share its box exactly: one row per query, one column per COCO class.
        queries, row_query = np.unique(boxes, axis=0, return_inverse=True)
        probabilities = np.zeros((len(queries), len(COCO_CLASSES)), np.float64)
        probabilities[row_query.reshape(-1), labels] = scores
        detections: list[Detection] = []
        for wanted in dict.fromkeys(tuple(g) for g in groups.values()):
            detections += self._superset(queries, probabilities, list(wanted), wanted in stand_ins)
        return sorted(detections, key=lambda d: -d.score)

    def _superset(
        self, boxes: np.ndarray, probabilities: np.ndarray, wanted: list[int], stand_in: bool
    ) -> list[Detection]:
        """One superset's boxes, scored as YOLOX's without objectness, one NMS over the superset, labelled
        with the likeliest class. A stand-in (a bag: `backend.supersets.is_stand_in`) scores the chance of
        any of its classes times the chance of none outside it, as no class vouches for such a thing."""
        inside = probabilities[:, wanted]
        scores = 1.0 - np.prod(1.0 - inside, axis=1)
        if stand_in:
            outside = [i for i in range(len(COCO_CLASSES)) if i not in set(wanted)]
            scores = scores * np.prod(1.0 - probabilities[:, outside], axis=1)
        mask = scores >= self.score_threshold
        if not mask.any():
            return []
        boxes, scores, inside = boxes[mask], scores[mask], inside[mask]
        labels = np.asarray(wanted)[inside.argmax(axis=1)]
        return superset_detections(boxes, scores, labels, self.nms_threshold)
