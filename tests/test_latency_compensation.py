"""Ring buffer, bounded catch-up, and the 1 s back-end delay on real sequences."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from behaviors.geometry import Box, iou
from companion.config import TrackerConfig
from companion.vision.frame_sources import Frame
from companion.vision.latency_compensation import CatchUp, FrameRing, KeyframeGoneError
from companion.vision.trackers import create_tracker
from companion.vision.tracking_frontend import TrackingFrontend
from companion_tools.tracking_eval import load_sequence


def _blank(frame_id: int) -> Frame:
    return Frame(frame_id, frame_id / 10.0, np.zeros((48, 64, 3), np.uint8))


def test_ring_keeps_the_newest_frames_in_order() -> None:
    ring = FrameRing(3)
    for i in range(1, 6):
        ring.push(_blank(i))
    assert len(ring) == 3
    assert ring.get(2) is None and ring.get(4) is not None
    assert [f.frame_id for f in ring.since(3)] == [4, 5]
    assert ring.newest is not None and ring.newest.frame_id == 5
    with pytest.raises(ValueError):
        FrameRing(0)


def test_ring_restarted_numbering_drops_old_frames_instead_of_crashing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ring = FrameRing(5)
    for i in range(1, 5):
        ring.push(_blank(i))
    ring.push(_blank(2))  # the camera stream reconnected and counts from its start again
    assert "source restarted" in caplog.text
    assert len(ring) == 1 and ring.get(4) is None and ring.newest is not None and ring.newest.frame_id == 2
    ring.push(_blank(3))
    assert [f.frame_id for f in ring.since(2)] == [3]


def test_catch_up_work_is_bounded_per_frame_and_in_total(models_dir: Path, sequences_dir: Path) -> None:
    seq = sequences_dir / "otb_Crossing"
    ring = FrameRing(60)
    for i in range(1, 41):
        ring.push(Frame(i, i / 30.0, cv2.imread(str(seq / "frames" / f"{i:06d}.jpg"))))
    box = Box(205, 151, 17, 50)
    catch_up = CatchUp(create_tracker("kcf", models_dir), ring, 1, box, max_frames=10, per_step=3)
    steps = 0
    while not catch_up.advance():
        steps += 1
        assert catch_up.updates <= 3 * steps  # never more than per_step updates per live frame
    assert catch_up.last.frame_id == 40  # ends on the newest frame
    assert catch_up.updates <= 10  # 39 frames of backlog subsampled to the budget
    # The track's box on every frame it covers: the start box on the keyframe, a skipped frame the box of
    # the last frame passed before it, nothing before the keyframe.
    assert catch_up.box_at(1) == box and catch_up.box_at(0) is None
    passed = sorted(catch_up.boxes)
    assert len(passed) == catch_up.updates + 1 and passed[-1] == 40
    skipped = next(f for f in range(1, 41) if f not in catch_up.boxes)
    assert catch_up.box_at(skipped) == catch_up.boxes[max(f for f in passed if f < skipped)]
    with pytest.raises(KeyframeGoneError):
        CatchUp(create_tracker("kcf", models_dir), FrameRing(5), 1, box, 10, 3)


def _run(seq_dir: Path, models_dir: Path, keyframe: int, delay: int, compensate: bool, after: int) -> float:
    """Start at `keyframe` with its ground truth box, the answer arriving `delay` frames later; mean IoU
    with ground truth over the `after` frames following the arrival."""
    seq = load_sequence(seq_dir)
    frontend = TrackingFrontend(
        lambda: create_tracker("nano", models_dir),
        TrackingFrontend.from_config(TrackerConfig(), models_dir).loss.settings,
        catch_up_per_frame=8,
        compensate=compensate,
    )
    ious = []
    first = keyframe - 2
    for i in range(first, keyframe + delay + after):
        image = cv2.imread(str(seq.path / "frames" / f"{i + 1:06d}.jpg"))
        result = frontend.feed(Frame(i + 1, i / seq.fps, image))
        if i == keyframe + delay - 1:
            assert frontend.start(keyframe + 1, seq.ground_truth[keyframe])  # the late answer
        elif i >= keyframe + delay:
            box = result.box if result.box is not None else None
            ious.append(iou(box, seq.ground_truth[i]) if box is not None else 0.0)
    return float(np.mean(ious))


@pytest.mark.parametrize(
    ("name", "keyframes"), [("uav123_person12_1", (20, 90, 150)), ("dtb70_Surfing06", (10, 50))]
)
@pytest.mark.slow
def test_compensated_box_beats_the_stale_one_after_a_1s_backend_delay(
    name: str, keyframes: tuple[int, ...], models_dir: Path, sequences_dir: Path
) -> None:
    seq_dir = sequences_dir / name
    delay = round(load_sequence(seq_dir).fps * 1.0)  # 1 s at the sequence's frame rate
    compensated = [_run(seq_dir, models_dir, k, delay, True, 8) for k in keyframes]
    stale = [_run(seq_dir, models_dir, k, delay, False, 8) for k in keyframes]
    assert np.mean(compensated) > np.mean(stale), (compensated, stale)
