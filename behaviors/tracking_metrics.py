"""Tracking accuracy as the CloudTrack paper defines it: mIoU = sum of IoU / number of ground-truth frames.

Rules: a frame with a ground-truth box and no reported box counts 0; a frame whose ground truth is
`nan` (target hidden or out of view) is excluded from the mean, but a box reported there is counted as
a false track.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from behaviors.geometry import Box, iou


@dataclass(frozen=True)
class MiouResult:
    miou: float  # nan when the sequence has no ground-truth frame
    iou_sum: float
    gt_frames: int
    false_tracks: int  # boxes reported on frames whose ground truth is nan
    missed_frames: int  # ground-truth frames with no reported box


def frame_ious(predicted: Sequence[Box | None], ground_truth: Sequence[Box | None]) -> list[float | None]:
    """IoU per frame; None where the ground truth is nan (the frame is excluded)."""
    if len(predicted) != len(ground_truth):
        raise ValueError(f"{len(predicted)} predictions for {len(ground_truth)} ground-truth frames")
    out: list[float | None] = []
    for pred, gt in zip(predicted, ground_truth, strict=True):
        if gt is None or not gt.is_valid():
            out.append(None)
        else:
            out.append(iou(pred, gt) if pred is not None else 0.0)
    return out


def mean_iou(predicted: Sequence[Box | None], ground_truth: Sequence[Box | None]) -> MiouResult:
    ious = frame_ious(predicted, ground_truth)
    gt_frames = sum(1 for v in ious if v is not None)
    total = sum(v for v in ious if v is not None)
    false_tracks = sum(1 for v, p in zip(ious, predicted, strict=True) if v is None and p is not None)
    missed = sum(1 for v, p in zip(ious, predicted, strict=True) if v is not None and p is None)
    return MiouResult(
        total / gt_frames if gt_frames else float("nan"), total, gt_frames, false_tracks, missed
    )


def pooled_miou(results: Sequence[MiouResult]) -> float:
    """mIoU over several sequences pooled frame by frame (sum of IoU / all ground-truth frames)."""
    frames = sum(r.gt_frames for r in results)
    return sum(r.iou_sum for r in results) / frames if frames else float("nan")
