"""SIMULATION ONLY: a superset "person" detector that answers from the rendered world's ground truth.

It stands in for YOLOX in closed-loop scenarios so the back-end's real verification path (crops with a
50 px margin, then the local attribute verifier or a VLM endpoint) runs on the rendered pixels. It reads
the frame id from the frame's timecode strip (`sitl.camera_render.read_timecode`), looks up that frame's
ground truth and returns a box per visible person, with configurable misses, jitter and false
positives drawn from a generator seeded by (seed, frame id), so a run is repeatable.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from behaviors.detection import Detection
from behaviors.geometry import Box
from sitl.camera_render import TruthBox, read_timecode

TruthLookup = Callable[[int], "tuple[TruthBox, ...] | None"]


@dataclass(frozen=True)
class DetectorNoise:
    miss_rate: float = 0.05  # probability a visible person is not reported
    jitter_px: float = 1.5  # standard deviation of each box edge, pixels
    false_positives: float = 0.2  # expected spurious boxes per frame (Poisson)
    min_visible: float = 0.4  # a person less visible than this is not detected
    min_height_px: float = 8.0


class SimulatedPersonDetector:
    """`backend.detectors.SupersetDetector` for the SITL world. Only the class "person" is known."""

    name = "sitl_simulated_person"

    def __init__(self, truth: TruthLookup, render_width: int = 640, noise: DetectorNoise | None = None,
                 seed: int = 0) -> None:
        self._truth = truth
        self._render_width = render_width
        self.noise = noise or DetectorNoise()
        self.seed = seed

    def detect(self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None) -> list[Detection]:
        """Boxes of people in `image_bgr` (scaled to its size); `frame_id` is ignored: the timecode is authoritative."""
        from backend.supersets import UnknownSupersetError

        wanted = {c.strip().lower() for c in classes}
        if wanted - {"person", "people", "human"}:
            raise UnknownSupersetError(f"the simulated detector only knows 'person', not {sorted(wanted)}")
        h, w = image_bgr.shape[:2]
        scale = w / float(self._render_width)
        stamped = read_timecode(image_bgr, self._render_width)
        truth = self._truth(stamped)
        if truth is None:
            return []
        rng = np.random.default_rng([self.seed, stamped])
        n = self.noise
        out: list[Detection] = []
        for tb in truth:
            if tb.visible < n.min_visible or tb.box.h < n.min_height_px or rng.random() < n.miss_rate:
                continue
            jit = rng.normal(0.0, n.jitter_px, 4)
            box = Box.from_xyxy(tb.box.x + jit[0], tb.box.y + jit[1], tb.box.x2 + jit[2], tb.box.y2 + jit[3])
            box = box.scaled(scale, scale).clamped(w, h)
            if box.is_valid():
                # Like a real detector, more confident on bigger, unoccluded people.
                size = min(1.0, float(np.sqrt(tb.box.area)) / 40.0)
                score = 0.5 + 0.45 * size * tb.visible + rng.normal(0, 0.01)
                out.append(Detection(box, float(np.clip(score, 0.3, 0.99))))
        for _ in range(int(rng.poisson(n.false_positives))):
            bw, bh = rng.uniform(10, 30) * scale, rng.uniform(25, 60) * scale
            x, y = rng.uniform(0, max(1.0, w - bw)), rng.uniform(0, max(1.0, h - bh))
            out.append(Detection(Box(float(x), float(y), float(bw), float(bh)), float(rng.uniform(0.3, 0.5))))
        out.sort(key=lambda d: -d.score)
        return out
