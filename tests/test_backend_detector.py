"""YOLOX-nano through onnxruntime on real frames, and the superset -> COCO mapping."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from backend.config import DetectorConfig
from backend.detectors.factory import build_detector
from backend.detectors.nms import merge_overlapping, nms
from backend.detectors.tiling import TiledDetector, tile_grid
from backend.detectors.yolox import YoloxDetector
from backend.supersets import UnknownSupersetError, coco_classes_for, superset_from_prompt
from backend_tools.quantize import main as quantize_main
from behaviors.geometry import Box, iou
from cloudtrack.model_store import ModelError


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


def test_blank_image_has_no_detections_and_other_classes_are_filtered(
    detector: YoloxDetector, sequences_dir: Path
) -> None:
    assert detector.detect(np.full((480, 640, 3), 127, np.uint8), ["person"]) == []
    image = _read(sequences_dir / "uav123_person12_1" / "frames" / "000001.jpg")
    assert detector.detect(image, ["boat"]) == []


def test_a_bag_coco_has_no_class_for_is_found_among_its_things(
    detector: YoloxDetector, sequences_dir: Path
) -> None:
    """vot2015_bag's plastic bag: YOLOX calls it a frisbee, a ball or a surfboard, never a backpack,
    handbag or suitcase; searched as a bag (every inanimate COCO class) it is found, and never a person."""
    seq = sequences_dir / "vot2015_bag"
    truth = _groundtruth(seq)
    assert set(coco_classes_for("bag")) >= {"backpack", "handbag", "suitcase", "frisbee", "sports ball"}
    assert not {"person", "dog", "car"} & set(coco_classes_for("bag"))
    as_bag, as_its_three_classes, frames = 0, 0, 0
    for index in range(0, len(truth), 10):
        box = truth[index]
        assert box is not None
        image = _read(seq / "frames" / f"{index + 1:06d}.jpg")
        frames += 1
        found = detector.detect(image, ["bag"])
        assert all(d.label != "person" for d in found)
        as_bag += any(iou(box, d.box) >= 0.5 for d in found)
        three = detector.detect(image, ["backpack", "handbag", "suitcase"])
        as_its_three_classes += any(iou(box, d.box) >= 0.5 for d in three)
    print(
        f"vot2015_bag: found as a bag on {as_bag} of {frames} frames, as backpack/handbag/suitcase {as_its_three_classes}"
    )
    assert as_its_three_classes == 0
    assert as_bag >= frames // 4


class _OneRowModel:
    """A YOLOX output of one grid row: objectness and class probabilities chosen by the test."""

    def __init__(self, objectness: float, probabilities: dict[str, float], copies: int = 1) -> None:
        from backend.supersets import COCO_CLASSES

        row = np.zeros(85, np.float32)
        row[2:4] = np.log(4.0)  # 4 strides wide and tall
        row[4] = objectness
        for name, p in probabilities.items():
            row[5 + COCO_CLASSES.index(name)] = p
        self.raw = np.zeros((1, 3549, 85), np.float32)
        self.raw[0, 1000 : 1000 + copies] = row  # neighbouring cells: overlapping boxes

    def run(self, _outputs: object, _feed: object) -> list[np.ndarray]:
        return [self.raw]


def test_a_superset_scores_the_chance_of_any_of_its_classes_and_keeps_one_box_per_object(
    detector: YoloxDetector,
) -> None:
    image = np.zeros((416, 416, 3), np.uint8)
    split = YoloxDetector.__new__(YoloxDetector)
    split.__dict__.update(detector.__dict__)
    # A moped between motorbike (0.4) and bicycle (0.4): neither class alone passes 0.3 at objectness 0.6.
    split._session = _OneRowModel(0.6, {"motorbike": 0.4, "bicycle": 0.4}, copies=2)  # type: ignore[assignment]
    assert split.detect(image, ["motorbike"]) == split.detect(image, ["bicycle"]) == []
    (vehicle,) = split.detect(image, ["vehicle"])  # 0.6 x (1 - 0.6 x 0.6) = 0.384, one box for both rows
    assert vehicle.score == pytest.approx(0.384, abs=1e-3) and vehicle.label == "motorbike"
    # Two supersets asked together are scored and suppressed apart: the same rows answer both.
    both = split.detect(image, ["vehicle", "bag"])
    assert [d.label for d in both] == ["motorbike"]
    split._session = _OneRowModel(0.9, {"person": 0.9, "backpack": 0.5}, copies=2)  # type: ignore[assignment]
    # A bag is a stand-in (every inanimate class): what is likely a person is no bag.
    assert [d.label for d in split.detect(image, ["person", "bag"])] == ["person"]


def test_a_stand_in_superset_scores_an_object_that_is_none_of_the_classes_outside_it(
    detector: YoloxDetector,
) -> None:
    """A plastic bag is none of COCO's classes: every class output is low, so as "any thing" it would score
    next to nothing; as an object that is not a person, an animal or a vehicle it scores its objectness."""
    image = np.zeros((416, 416, 3), np.uint8)
    split = YoloxDetector.__new__(YoloxDetector)
    split.__dict__.update(detector.__dict__)
    split._session = _OneRowModel(0.5, {"frisbee": 0.05, "person": 0.02})  # type: ignore[assignment]
    (bag,) = split.detect(image, ["bag"])
    assert bag.score == pytest.approx(0.5 * 0.98, abs=1e-3) and bag.label == "frisbee"
    assert split.detect(image, ["frisbee"]) == []  # the class itself: 0.5 x 0.05


def test_rejects_non_bgr_input(detector: YoloxDetector) -> None:
    with pytest.raises(ValueError, match="BGR"):
        detector.detect(np.zeros((48, 64), np.uint8), ["person"])


def test_superset_mapping_and_clear_error_for_unmapped() -> None:
    assert coco_classes_for("person") == ("person",)
    assert "truck" in coco_classes_for("vehicle")
    assert coco_classes_for("Truck") == ("truck", "car")  # distant trucks are cars to YOLOX
    assert coco_classes_for("bus") == ("bus", "truck", "car")
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
        (
            "something shiny",
            "something shiny",
        ),  # no class: the phrase itself, for an open-vocabulary detector
        ("the of a", None),
    ],
)
def test_superset_from_prompt(prompt: str, superset: str | None) -> None:
    assert superset_from_prompt(prompt) == superset


def test_nms_keeps_the_best_of_overlapping_boxes() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30]], np.float32)
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.5) == [1, 2]


def test_tiles_grid_covers_the_frame_with_overlap() -> None:
    tiles = tile_grid(640, 360, 2, 0.2)
    assert len(tiles) == 2  # rows follow the aspect ratio: 2 x 360/640 rounds to 1
    (ax1, ay1, ax2, ay2), (bx1, by1, bx2, by2) = tiles
    assert (ax1, ay1, by2, bx2, ay2) == (0, 0, 360, 640, 360) and ax2 - bx1 >= 0.2 * (ax2 - ax1) - 1
    grid = tile_grid(1280, 720, 3, 0.2)
    assert len(grid) == 6 and {t[2] for t in grid} >= {1280} and {t[3] for t in grid} >= {720}
    assert tile_grid(360, 640, 1, 0.2) == [(0, 0, 360, 356), (0, 284, 360, 640)]  # portrait: 1 x 2


def test_tiles_merge_keeps_side_by_side_people_apart_and_joins_cut_boxes() -> None:
    # A child in front of an adult: IoU 0.35, but the smaller lies mostly inside (IoS 0.75); neither is cut.
    boxes = np.array([[100, 100, 120, 160], [108, 110, 124, 150]], np.float64)
    keep, _ = merge_overlapping(
        boxes, np.array([0.9, 0.8]), np.array([0, 0]), np.array([False, False]), 0.45, 0.6
    )
    assert keep == [0, 1]
    # A person cut at a tile's edge (higher score, top half) and whole in the frame pass: one whole box.
    boxes = np.array([[100, 100, 120, 130], [100, 100, 121, 160]], np.float64)
    keep, merged = merge_overlapping(
        boxes, np.array([0.9, 0.6]), np.array([0, 0]), np.array([True, False]), 0.45, 0.6
    )
    assert keep == [0] and merged[0].tolist() == [100, 100, 121, 160]


def test_tiles_find_small_people_the_whole_frame_misses(detector: YoloxDetector, sequences_dir: Path) -> None:
    tiled = TiledDetector(detector, 2)
    seq = sequences_dir / "uav123_wakeboard7"
    truth = _groundtruth(seq)
    whole_hits = tiled_hits = frames = 0
    for index in range(0, len(truth), 6):
        box = truth[index]
        if box is None:
            continue
        image = _read(seq / "frames" / f"{index + 1:06d}.jpg")
        keyframe = cv2.resize(
            image, (640, 360), interpolation=cv2.INTER_AREA
        )  # the companion's keyframe size
        target = box.scaled(0.5, 0.5)
        found = tiled.detect(keyframe, ["person"])
        assert all(d.box.x >= 0 and d.box.x2 <= 640 and d.box.y >= 0 and d.box.y2 <= 360 for d in found)
        whole_hits += any(iou(target, d.box) >= 0.5 for d in detector.detect(keyframe, ["person"]))
        tiled_hits += any(iou(target, d.box) >= 0.5 for d in found)
        frames += 1
    print(
        f"uav123_wakeboard7 at 640x360, {frames} frames: recall whole frame {whole_hits / frames:.2f}, "
        f"tiles2 {tiled_hits / frames:.2f}"
    )
    assert tiled_hits > whole_hits


def test_factory_builds_tiles_and_names_the_int8_command(models_dir: Path) -> None:
    tiled = build_detector(DetectorConfig(model_dir=str(models_dir)))  # tiles = 2 by default
    assert isinstance(tiled, TiledDetector) and tiled.columns == 2 and tiled.name == "yolox_nano"
    assert isinstance(build_detector(DetectorConfig(model_dir=str(models_dir), tiles=0)), YoloxDetector)
    with pytest.raises(ModelError, match="backend_tools.quantize"):
        build_detector(DetectorConfig(model_dir=str(models_dir), precision="int8"))


@pytest.mark.slow
def test_int8_model_is_derived_from_the_shared_weights(
    models_dir: Path, sequences_dir: Path, tmp_path: Path
) -> None:
    (tmp_path / "yolox_nano").mkdir()
    (tmp_path / "yolox_nano" / "yolox_nano.onnx").symlink_to(models_dir / "yolox_nano" / "yolox_nano.onnx")
    sequences = [str(sequences_dir / "uav123_group1_1"), str(sequences_dir / "otb_Crossing")]
    assert quantize_main([*sequences, "--model-dir", str(tmp_path), "--frames-per-sequence", "2"]) == 0
    int8 = build_detector(DetectorConfig(model_dir=str(tmp_path), precision="int8", threads=1))
    assert int8.name == "yolox_nano_int8"
    image = _read(sequences_dir / "uav123_person12_1" / "frames" / "000001.jpg")
    found = int8.detect(image, ["person"])
    assert found and all(d.label == "person" and d.box.is_valid() for d in found)


def test_parallel_tiles_find_exactly_what_one_after_another_finds(
    detector: YoloxDetector, sequences_dir: Path
) -> None:
    """`[detector] parallel_tiles` changes when the inferences run, never what they find."""
    image = cv2.resize(_read(sequences_dir / "uav123_group1_1" / "frames" / "000001.jpg"), (640, 360))
    serial = TiledDetector(detector, 2, min_side=detector.input_size)
    parallel = TiledDetector(detector, 2, min_side=detector.input_size, parallel=True)
    found = serial.detect(image, ["person"])
    assert len(found) >= 3 and parallel.detect(image, ["person"]) == found
    with ThreadPoolExecutor(4) as pool:  # several requests at once share the pool
        assert list(pool.map(lambda _: parallel.detect(image, ["person"]), range(6))) == [found] * 6


def test_tiles_leave_frames_the_model_sees_whole(detector: YoloxDetector, sequences_dir: Path) -> None:
    image = _read(sequences_dir / "otb_Crossing" / "frames" / "000001.jpg")  # 360x240, under the 416 input
    tiled = TiledDetector(detector, 2, min_side=detector.input_size)
    assert tiled.detect(image, ["person"]) == detector.detect(image, ["person"])


@pytest.mark.parametrize("module", ["backend_tools.detector_recall", "backend_tools.quantize"])
def test_detector_tools_have_help_with_examples(module: str, capsys: pytest.CaptureFixture[str]) -> None:
    import importlib

    with pytest.raises(SystemExit) as done:
        importlib.import_module(module).main(["--help"])
    assert done.value.code == 0 and "example" in capsys.readouterr().out


def test_recall_command_reports_size_bins_and_ratios(
    models_dir: Path, sequences_dir: Path, tmp_path: Path
) -> None:
    from backend_tools.detector_recall import main as recall_main

    out = tmp_path / "recall.json"
    seq = str(sequences_dir / "uav123_wakeboard7")
    args = [
        seq,
        "--model-dir",
        str(models_dir),
        "--variants",
        "fp32,fp32+tiles2",
        "--step",
        "12",
        "--json",
        str(out),
    ]
    assert recall_main(args) == 0
    figures = json.loads(out.read_text())["variants"]
    assert (
        set(figures) == {"fp32", "fp32+tiles2"}
        and figures["fp32"]["frames"] == figures["fp32+tiles2"]["frames"] > 0
    )
    assert set(figures["fp32"]["by_size"]) == {"<16", "16-32", "32-96", ">96"}
    assert figures["fp32+tiles2"]["recall"] >= figures["fp32"]["recall"]
