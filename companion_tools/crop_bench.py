"""Bytes the supervisor's candidate crop costs per candidate, against the keyframe it rides beside.

For each labelled sequence (`groundtruth.txt`: x,y,w,h per frame in native pixels), every `--step`-th
frame's target is cropped from the native frame as the companion does (`companion.cloud.candidate_crop`)
and the frame is encoded as the keyframe the back-end gets (`cloudtrack.api_client.encode_keyframe`).
Printed: per sequence the native size, the box's height in keyframe pixels, the crop's pixels and JPEG
bytes, the keyframe's bytes; then the totals (median and maximum).

    python -m companion_tools.crop_bench /work/shared/data/sequences
"""

from __future__ import annotations

import argparse
import base64
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np

from behaviors.geometry import Box
from cloudtrack.api_client import encode_keyframe
from companion.cloud.candidate_crop import KEYFRAME_WIDTH, candidate_crop


def _boxes(sequence: Path) -> list[Box | None]:
    out: list[Box | None] = []
    for line in (sequence / "groundtruth.txt").read_text().splitlines():
        try:
            x, y, w, h = (float(v) for v in line.replace("\t", ",").split(",")[:4])
        except ValueError:
            out.append(None)
            continue
        out.append(Box(x, y, w, h) if w > 1 and h > 1 else None)
    return out


Row = tuple[int, int, float, float, tuple[int, int], int, int]


def measure(sequence: Path, step: int) -> list[Row]:
    """(native width, height, box height in keyframe px, in native px, crop (w, h), crop bytes, keyframe
    bytes) per frame."""
    frames = sorted((sequence / "frames").glob("*.jpg"))
    rows = []
    for index, box in list(enumerate(_boxes(sequence)))[::step]:
        if box is None or index >= len(frames):
            continue
        image = cv2.imread(str(frames[index]))
        if image is None:
            continue
        crop = candidate_crop(image, box, keyframe_width=KEYFRAME_WIDTH)
        if crop is None:
            continue
        jpeg = base64.b64decode(crop["crop_jpeg_b64"])
        decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert decoded is not None  # encoded here a moment ago
        keyframe, scale = encode_keyframe(image, KEYFRAME_WIDTH, 80)
        height, width = image.shape[:2]
        rows.append(
            (
                width,
                height,
                box.h * scale,
                box.h,
                (decoded.shape[1], decoded.shape[0]),
                len(jpeg),
                len(keyframe),
            )
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sequences", type=Path, help="a folder of sequences (frames/, groundtruth.txt)")
    parser.add_argument("--step", type=int, default=25, help="every n-th frame (default 25)")
    args = parser.parse_args(argv)
    every: list[Row] = []
    print(
        "| sequence | native | box height, keyframe px | box height, native px | crop px (median) "
        "| crop KB median / max | keyframe KB median / max |"
    )
    print("|---|---|---|---|---|---|---|")
    for sequence in sorted(p for p in args.sequences.iterdir() if (p / "groundtruth.txt").exists()):
        rows = measure(sequence, max(1, args.step))
        if not rows:
            continue
        every += rows
        crops = [r[5] / 1000 for r in rows]
        keys = [r[6] / 1000 for r in rows]
        heights = [r[2] for r in rows]
        native = [r[3] for r in rows]
        sides = sorted(rows, key=lambda r: r[4][0] * r[4][1])[len(rows) // 2][4]
        print(
            f"| {sequence.name} | {rows[0][0]}x{rows[0][1]} | {min(heights):.0f}-{max(heights):.0f} "
            f"| {min(native):.0f}-{max(native):.0f} "
            f"| {sides[0]}x{sides[1]} | {statistics.median(crops):.1f} / {max(crops):.1f} "
            f"| {statistics.median(keys):.1f} / {max(keys):.1f} |"
        )
    if not every:
        print("no labelled frames found", file=sys.stderr)
        return 1
    crops = [r[5] / 1000 for r in every]
    keys = [r[6] / 1000 for r in every]
    both = [(r[5] + r[6]) / 1000 for r in every]
    print(
        f"\n{len(every)} candidates: crop {statistics.median(crops):.1f} KB median, {max(crops):.1f} KB max; "
        f"keyframe {statistics.median(keys):.1f} KB median, {max(keys):.1f} KB max; "
        f"keyframe + crop {statistics.median(both):.1f} KB median, {max(both):.1f} KB max"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
