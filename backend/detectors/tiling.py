"""Sliced inference for small targets (SAHI-style): the whole frame plus an overlapping grid of tiles.

YOLOX-nano sees a 1280x720 keyframe at 416x234, so a 30 px person becomes 10 px and is mostly missed.
Each tile is letterboxed to the model's input on its own, so a grid of `columns` x rows tiles magnifies
targets about `columns` times (rows follow the frame's aspect ratio, tiles overlap by `overlap`). Boxes
from the tiles are shifted into the frame and merged with the whole frame's (`merge_overlapping`), so
large targets are still found whole. Costs one inference per tile plus one for the frame. Frames whose
longer side is at most `min_side` (the model's input size) are not sliced: the model already sees them at
full resolution, and tiles would only upsample them and add false detections.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from backend.detectors.interface import SupersetDetector
from backend.detectors.nms import merge_overlapping
from behaviors.detection import Detection
from behaviors.geometry import Box

EDGE_PX = 2.0  # a tile's box this close to the tile's inner edge is cut by it


def tile_grid(width: int, height: int, columns: int, overlap: float) -> list[tuple[int, int, int, int]]:
    """Tiles (x1, y1, x2, y2) covering the frame: `columns` across, rows chosen for near-square tiles."""
    rows = max(1, round(columns * height / width))

    def spans(length: int, count: int) -> list[tuple[int, int]]:
        if count <= 1:
            return [(0, length)]
        size = min(length, math.ceil(length / (count - (count - 1) * overlap)))
        starts = [round(i * (length - size) / (count - 1)) for i in range(count)]
        return [(s, s + size) for s in starts]

    return [(x1, y1, x2, y2) for y1, y2 in spans(height, rows) for x1, x2 in spans(width, columns)]


class TiledDetector:
    """Wraps any `SupersetDetector`; `detect` runs it on the whole frame and on each tile."""

    def __init__(
        self,
        inner: SupersetDetector,
        columns: int,
        overlap: float = 0.2,
        nms_threshold: float = 0.45,
        ios_threshold: float = 0.6,
        min_side: int = 0,
        parallel: bool = False,
    ) -> None:
        if columns < 1:
            raise ValueError(f"tiling needs at least 1 column, not {columns}")
        self.inner = inner
        self.columns = columns
        self.overlap = overlap
        self.nms_threshold = nms_threshold
        self.ios_threshold = ios_threshold
        self.min_side = min_side
        self.name = inner.name  # the model's name; tiling is a setting, like the score threshold
        # `parallel`: a keyframe's inferences (the whole frame and each tile) run at once, one per core at
        # most over all requests, so a lone keyframe uses the idle cores; the work is the same, the
        # latency lower (`[detector] parallel_tiles`, docs/benchmarks.md "Back-end capacity").
        self._pool = (
            ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="tiles")
            if parallel
            else None
        )

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        height, width = image_bgr.shape[:2]
        if max(height, width) <= self.min_side:
            # The model already sees this frame at full resolution: tiles would only upsample.
            return list(self.inner.detect(image_bgr, classes, frame_id))
        grid = tile_grid(width, height, self.columns, self.overlap)
        images = [image_bgr, *(np.ascontiguousarray(image_bgr[y1:y2, x1:x2]) for x1, y1, x2, y2 in grid)]
        if self._pool is not None:
            results = list(self._pool.map(lambda image: self.inner.detect(image, classes, frame_id), images))
        else:
            results = [self.inner.detect(image, classes, frame_id) for image in images]
        found = list(results[0])
        cut = [False] * len(found)
        for (x1, y1, x2, y2), tile_found in zip(grid, results[1:], strict=True):
            # Inner edges only: a box at the frame's own border is not cut by the tiling.
            edges = (x1 > 0, y1 > 0, x2 < width, y2 < height)
            for d in tile_found:
                found.append(
                    Detection(
                        box=Box(d.box.x + x1, d.box.y + y1, d.box.w, d.box.h), score=d.score, label=d.label
                    )
                )
                near = (
                    d.box.x <= EDGE_PX,
                    d.box.y <= EDGE_PX,
                    d.box.x2 >= x2 - x1 - EDGE_PX,
                    d.box.y2 >= y2 - y1 - EDGE_PX,
                )
                cut.append(any(e and n for e, n in zip(edges, near, strict=True)))
        if not found:
            return []
        boxes = np.array([d.box.xyxy() for d in found], np.float64)
        scores = np.array([d.score for d in found], np.float64)
        names = sorted({d.label for d in found})
        labels = np.array([names.index(d.label) for d in found])
        keep, merged = merge_overlapping(
            boxes, scores, labels, np.array(cut), self.nms_threshold, self.ios_threshold
        )
        return [
            Detection(
                box=Box.from_xyxy(*(float(v) for v in merged[i])), score=found[i].score, label=found[i].label
            )
            for i in keep
        ]
