"""The tracker interface on real OpenCV trackers, real weights and real frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import pytest

from behaviors.geometry import Box, iou
from cloudtrack.model_store import ModelError
from companion.vision.trackers import (
    TrackerUnavailableError,
    _factory,
    available_trackers,
    create_tracker,
)

SEQUENCE = "otb_Crossing"  # small frames (360x240): every tracker runs fast on it
WEIGHTLESS = ("csrt", "kcf", "mil")


def _frames(sequences_dir: Path, count: int) -> tuple[list, list[Box]]:
    seq = sequences_dir / SEQUENCE
    gt = [
        Box(*map(float, line.split(",")))
        for line in (seq / "groundtruth.txt").read_text().splitlines()[:count]
    ]
    frames = [cv2.imread(str(seq / "frames" / f"{i:06d}.jpg")) for i in range(1, count + 1)]
    return frames, gt


def test_available_trackers_match_this_opencv_build() -> None:
    names = available_trackers()
    for name in ("nano", "vit", "dasiamrpn", *WEIGHTLESS):
        assert name in names
    # GOTURN is listed exactly when the build still has it (OpenCV 5.0 removed it).
    assert ("goturn" in names) == (_factory("TrackerGOTURN") is not None)


@pytest.mark.parametrize("name", ["nano", "vit", *WEIGHTLESS])
def test_tracker_follows_the_target_on_a_real_sequence(
    name: str, models_dir: Path, sequences_dir: Path
) -> None:
    frames, gt = _frames(sequences_dir, 16)
    tracker = create_tracker(name, models_dir)
    assert tracker.name == name
    assert tracker.has_score == (name in ("nano", "vit"))
    tracker.init(frames[0], gt[0])
    ious = []
    for frame, truth in zip(frames[1:], gt[1:], strict=True):
        step = tracker.update(frame)
        if tracker.has_score:
            # nano and vit report a real score in [0, 1] on every step.
            assert step.score is not None and 0.0 <= step.score <= 1.0
        else:
            # CSRT/KCF/MIL: -1 on OpenCV 5.0 and no getTrackingScore on 4.x both mean "no score".
            assert step.score is None
        if step.ok:
            assert step.box is not None and step.box.is_valid()
        ious.append(iou(step.box, truth) if step.box is not None else 0.0)
    assert sum(ious) / len(ious) > 0.4, (name, ious)


def test_init_restarts_cleanly_on_a_new_box(models_dir: Path, sequences_dir: Path) -> None:
    frames, gt = _frames(sequences_dir, 12)
    tracker = create_tracker("nano", models_dir)
    tracker.init(frames[0], gt[0])
    for frame in frames[1:6]:
        tracker.update(frame)
    tracker.init(frames[6], gt[6])
    step = tracker.update(frames[7])
    assert step.box is not None and iou(step.box, gt[7]) > 0.4


def test_dasiamrpn_without_weights_names_the_file_and_the_fix(tmp_path: Path) -> None:
    with pytest.raises(ModelError) as err:
        create_tracker("dasiamrpn", tmp_path)
    message = str(err.value)
    assert "dasiamrpn_model.onnx" in message and str(tmp_path) in message
    assert "models download dasiamrpn" in message


def test_goturn_is_reported_clearly(tmp_path: Path) -> None:
    if _factory("TrackerGOTURN") is None:
        with pytest.raises(TrackerUnavailableError, match="not provided by this OpenCV build"):
            create_tracker("goturn", tmp_path)
    else:  # OpenCV 4.x still has it: then the missing weights are the error
        with pytest.raises(ModelError, match="goturn.prototxt"):
            create_tracker("goturn", tmp_path)


def test_unknown_tracker_name() -> None:
    with pytest.raises(TrackerUnavailableError, match="unknown tracker 'boosting'"):
        create_tracker("boosting", Path("."))


def test_corrupt_nano_weights_are_refused_before_opencv(models_dir: Path, tmp_path: Path) -> None:
    target = tmp_path / "nanotrack_v2"
    target.mkdir()
    shutil.copy(models_dir / "nanotrack_v2" / "nanotrack_backbone_sim.onnx", target)
    (target / "nanotrack_head_sim.onnx").write_bytes(b"not an onnx file")
    with pytest.raises(ModelError, match="corrupt"):
        create_tracker("nano", tmp_path)


def test_bad_boxes_and_update_before_init(models_dir: Path, sequences_dir: Path) -> None:
    frames, _ = _frames(sequences_dir, 1)
    tracker = create_tracker("kcf", models_dir)
    with pytest.raises(RuntimeError, match="before init"):
        tracker.update(frames[0])
    with pytest.raises(ValueError, match="invalid box"):
        tracker.init(frames[0], Box(10, 10, 0, 5))
    with pytest.raises(ValueError, match="outside"):
        tracker.init(frames[0], Box(5000, 5000, 20, 20))
