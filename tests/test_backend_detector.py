"""YOLOX-nano through onnxruntime on real frames, and the superset -> COCO mapping."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.detectors.nms import nms
from backend.detectors.yolox import YoloxDetector
from backend.supersets import UnknownSupersetError, coco_classes_for, superset_from_prompt
from behaviors.geometry import Box, iou


@pytest.fixture(scope="module")
def detector(models_dir: Path) -> YoloxDetector:
    return YoloxDetector(models_dir / "yolox_nano" / "yolox_nano.onnx", threads=1)


def _read(path: Path) -> np.ndarray:
    image = cv2.imread(str(path))
    assert image is not None, path
    return image


def _groundtruth(seq: Path) -> list[Box | None]:
    boxes: list[Box | None] = []
    for line in (seq / "groundtruth.txt").read_text().split():
        values = [float(v) for v in line.split(",")]
        boxes.append(None if any(np.isnan(values)) else Box(*values))
    return boxes


def test_finds_the_person_in_uav123_person12(detector: YoloxDetector, sequences_dir: Path) -> None:
    seq = sequences_dir / "uav123_person12_1"
    truth = _groundtruth(seq)
    best_ious = []
    for index in range(0, len(truth), 4):
        box = truth[index]
        assert box is not None
        image = _read(seq / "frames" / f"{index + 1:06d}.jpg")
        detections = detector.detect(image, ["person"])
        assert all(d.label == "person" for d in detections)
        best_ious.append(max((iou(box, d.box) for d in detections), default=0.0))
    recall50 = float(np.mean([v >= 0.5 for v in best_ious]))
    recall30 = float(np.mean([v >= 0.3 for v in best_ious]))
    # Figures for docs/benchmarks.md; YOLOX's boxes include the walker's long shadow, which costs IoU.
    print(f"uav123_person12_1: {len(best_ious)} frames, recall@IoU0.5 {recall50:.2f}, @IoU0.3 {recall30:.2f}")
    assert recall30 >= 0.7
    assert recall50 >= 0.6


def test_boxes_are_in_the_callers_pixels_at_any_size(detector: YoloxDetector, sequences_dir: Path) -> None:
    seq = sequences_dir / "uav123_person12_1"
    image = _read(seq / "frames" / "000001.jpg")
    truth = _groundtruth(seq)[0]
    assert truth is not None
    small = cv2.resize(image, (640, 360))
    detections = detector.detect(small, ["person"])
    assert max(iou(truth.scaled(0.5, 0.5), d.box) for d in detections) >= 0.5
    for d in detections:
        assert d.box.x >= 0 and d.box.x2 <= 640 and d.box.y >= 0 and d.box.y2 <= 360


def test_blank_image_has_no_detections_and_other_classes_are_filtered(detector: YoloxDetector, sequences_dir: Path) -> None:
    assert detector.detect(np.full((480, 640, 3), 127, np.uint8), ["person"]) == []
    image = _read(sequences_dir / "uav123_person12_1" / "frames" / "000001.jpg")
    assert detector.detect(image, ["boat"]) == []


def test_rejects_non_bgr_input(detector: YoloxDetector) -> None:
    with pytest.raises(ValueError, match="BGR"):
        detector.detect(np.zeros((48, 64), np.uint8), ["person"])


def test_superset_mapping_and_clear_error_for_unmapped() -> None:
    assert coco_classes_for("person") == ("person",)
    assert "truck" in coco_classes_for("vehicle")
    assert coco_classes_for("Truck") == ("truck",)
    assert coco_classes_for("life raft") == ("boat",)
    with pytest.raises(UnknownSupersetError, match="'life buoy'.*nearest known classes"):
        coco_classes_for("life buoy")


@pytest.mark.parametrize(
    ("prompt", "superset"),
    [
        ("an injured man in a gray shirt", "person"),
        ("the surfer in a black wetsuit riding the wave", "person"),
        ("a red kayak near the shore", "boat"),
        ("the white plastic bag on the ground", "bag"),
        ("something shiny", "something shiny"),  # no class: the phrase itself, for an open-vocabulary detector
        ("the of a", None),
    ],
)
def test_superset_from_prompt(prompt: str, superset: str | None) -> None:
    assert superset_from_prompt(prompt) == superset


def test_nms_keeps_the_best_of_overlapping_boxes() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30]], np.float32)
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.5) == [1, 2]
