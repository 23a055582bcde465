"""YOLOX-nano through onnxruntime: the back-end's offline superset detector (COCO-80 classes).

Pre-processing follows the upstream release: BGR 0-255 float, letterboxed into the top-left corner of a
416x416 canvas filled with 114, no normalisation. The 2022 export outputs raw grid predictions
(1, 3549, 85) that are decoded here: strides 8/16/32, centre = (grid + offset) * stride,
size = exp(log-size) * stride, then per superset: score = objectness x P(any of its classes), NMS.
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

STRIDES = (8, 16, 32)
PAD_VALUE = 114


def _grids(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid cell coordinates and strides for every output row, in the export's order."""
    cells, strides = [], []
    for stride in STRIDES:
        n = size // stride
        ys, xs = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        cells.append(np.stack((xs, ys), axis=-1).reshape(-1, 2))
        strides.append(np.full((n * n, 1), stride))
    return np.concatenate(cells).astype(np.float32), np.concatenate(strides).astype(np.float32)


class YoloxDetector:
    """`detect(image_bgr, classes)` -> detections in the image's pixels, best first."""

    def __init__(
        self,
        model_path: str | Path,
        score_threshold: float = 0.3,
        nms_threshold: float = 0.45,
        input_size: int = 416,
        threads: int = 0,
    ) -> None:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads  # 0: onnxruntime's default (all cores)
        self._session = ort.InferenceSession(str(model_path), options, providers=["CPUExecutionProvider"])
        self.input_name = self._session.get_inputs()[0].name
        self.name = Path(model_path).stem  # yolox_nano, or yolox_nano_int8 for the quantised model
        self.input_size = input_size
        self.score_threshold = score_threshold
        self.nms_threshold = nms_threshold
        self._grid, self._stride = _grids(input_size)

    def preprocess(self, image_bgr: np.ndarray) -> tuple[np.ndarray, float]:
        """The network's input (1x3xSxS float32, letterboxed) and the frame-to-input scale."""
        h, w = image_bgr.shape[:2]
        ratio = min(self.input_size / h, self.input_size / w)
        nh, nw = max(1, int(round(h * ratio))), max(1, int(round(w * ratio)))
        canvas = np.full((self.input_size, self.input_size, 3), PAD_VALUE, dtype=np.uint8)
        canvas[:nh, :nw] = cv2.resize(image_bgr, (nw, nh), interpolation=cv2.INTER_LINEAR)
        blob = canvas.transpose(2, 0, 1)[None].astype(np.float32)
        return blob, ratio

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
            raise ValueError(f"expected a BGR image H x W x 3, got shape {image_bgr.shape}")
        groups = {name: [COCO_CLASSES.index(c) for c in coco_classes_for(name)] for name in classes}
        stand_ins = {tuple(groups[name]) for name in classes if is_stand_in(name)}
        blob, ratio = self.preprocess(image_bgr)
        raw = self._session.run(None, {self.input_name: blob})[0][0]
        # score <= objectness: drop weak rows before any other work.
        rows = np.flatnonzero(raw[:, 4] >= self.score_threshold)
        if rows.size == 0:
            return []
        raw = raw[rows]
        centres = (raw[:, :2] + self._grid[rows]) * self._stride[rows]
        sizes = np.exp(np.clip(raw[:, 2:4], -10, 10)) * self._stride[rows]
        xyxy = np.concatenate((centres - sizes / 2, centres + sizes / 2), axis=1) / ratio
        h, w = image_bgr.shape[:2]
        xyxy = np.clip(xyxy, 0, [w, h, w, h])
        detections: list[Detection] = []
        for wanted in dict.fromkeys(tuple(g) for g in groups.values()):
            detections += self._superset(xyxy, raw, list(wanted), wanted in stand_ins)
        return sorted(detections, key=lambda d: -d.score)

    def _superset(
        self, xyxy: np.ndarray, raw: np.ndarray, wanted: list[int], stand_in: bool = False
    ) -> list[Detection]:
        """One superset's boxes: score = objectness x the chance that the object is any of its classes
        (YOLOX's class outputs are independent sigmoids, and a thing between two of them, a pick-up between
        car and truck, splits its probability among them), one NMS over the superset (the same object under
        two of its classes is one candidate), labelled with its likeliest class. A stand-in superset (a bag,
        which COCO has no class for: `backend.supersets.is_stand_in`) scores objectness x the chance that
        the object is none of the classes outside it (not a person, an animal or a vehicle): its own class
        outputs are all low for a thing that is none of them."""
        probabilities = raw[:, 5:][:, wanted]
        if stand_in:
            outside = [i for i in range(len(COCO_CLASSES)) if i not in set(wanted)]
            scores = raw[:, 4] * np.prod(1.0 - raw[:, 5:][:, outside], axis=1)
        else:
            scores = raw[:, 4] * (1.0 - np.prod(1.0 - probabilities, axis=1))
        mask = scores >= self.score_threshold
        if not mask.any():
            return []
        boxes, scores = xyxy[mask], scores[mask]
        labels = np.asarray(wanted)[probabilities[mask].argmax(axis=1)]
        return superset_detections(boxes, scores, labels, self.nms_threshold)
