"""Greedy non-maximum suppression, shared by the detectors."""

from __future__ import annotations

import numpy as np

from backend.supersets import COCO_CLASSES
from behaviors.detection import Detection
from behaviors.geometry import Box


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou_threshold: float) -> list[int]:
    """Indices kept by greedy non-maximum suppression, highest score first."""
    order = np.argsort(-scores, kind="stable")
    x1, y1, x2, y2 = boxes_xyxy.T
    areas = np.maximum(0, x2 - x1) * np.maximum(0, y2 - y1)
    keep: list[int] = []
    while order.size:
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        iw = np.maximum(0, np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]))
        ih = np.maximum(0, np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]))
        inter = iw * ih
        union = areas[i] + areas[rest] - inter
        overlap = np.where(union > 0, inter / np.maximum(union, 1e-9), 0)
        order = rest[overlap <= iou_threshold]
    return keep


def superset_detections(
    boxes_xyxy: np.ndarray, scores: np.ndarray, labels: np.ndarray, iou_threshold: float
) -> list[Detection]:
    """One NMS over a superset's boxes (the same object under two of its classes is one candidate),
    each labelled with its COCO class index in `labels`; boxes under a pixel wide or tall dropped."""
    detections = []
    for i in nms(boxes_xyxy, scores, iou_threshold):
        box = Box.from_xyxy(*(float(v) for v in boxes_xyxy[i]))
        if box.w >= 1 and box.h >= 1:
            detections.append(Detection(box=box, score=float(scores[i]), label=COCO_CLASSES[int(labels[i])]))
    return detections


def class_aware_nms(
    boxes_xyxy: np.ndarray, scores: np.ndarray, labels: np.ndarray, iou_threshold: float
) -> list[int]:
    """NMS within each class only: boxes are offset per class so different classes never overlap."""
    if len(scores) == 0:
        return []
    span = float(np.abs(boxes_xyxy).max()) + 1.0
    return nms(boxes_xyxy + labels[:, None].astype(np.float64) * span, scores, iou_threshold)


def merge_overlapping(
    boxes_xyxy: np.ndarray,
    scores: np.ndarray,
    labels: np.ndarray,
    cut: np.ndarray,
    iou_threshold: float,
    ios_threshold: float,
) -> tuple[list[int], np.ndarray]:
    """Class-aware greedy merge of boxes from overlapping views (whole frame and tiles), best score first.

    A box is dropped when it overlaps a kept box of its class by IoU above `iou_threshold`, or when one of
    the two is `cut` (touches a tile's inner edge) and it lies mostly inside the other (intersection over
    the smaller area above `ios_threshold`). A cut kept box grows to cover a larger dropped one, so a target
    split by a tile keeps its whole extent. The IoS rule is limited to cut boxes because people walking
    side by side also overlap mostly, and must stay apart. Returns the kept indices and their boxes.
    """
    order = np.argsort(-scores, kind="stable")
    merged = boxes_xyxy.astype(np.float64).copy()
    areas = np.maximum(0, merged[:, 2] - merged[:, 0]) * np.maximum(0, merged[:, 3] - merged[:, 1])
    keep: list[int] = []
    for j in order:
        j = int(j)
        for i in keep:
            if labels[i] != labels[j]:
                continue
            iw = max(0.0, min(merged[i, 2], merged[j, 2]) - max(merged[i, 0], merged[j, 0]))
            ih = max(0.0, min(merged[i, 3], merged[j, 3]) - max(merged[i, 1], merged[j, 1]))
            inter = iw * ih
            union = areas[i] + areas[j] - inter
            smaller = min(areas[i], areas[j])
            partial = bool(cut[i] or cut[j]) and smaller > 0 and inter / smaller > ios_threshold
            if (union > 0 and inter / union > iou_threshold) or partial:
                if partial and cut[i] and areas[j] > areas[i]:
                    merged[i] = [
                        min(merged[i, 0], merged[j, 0]),
                        min(merged[i, 1], merged[j, 1]),
                        max(merged[i, 2], merged[j, 2]),
                        max(merged[i, 3], merged[j, 3]),
                    ]
                    areas[i] = (merged[i, 2] - merged[i, 0]) * (merged[i, 3] - merged[i, 1])
                break
        else:
            keep.append(j)
    return keep, merged
