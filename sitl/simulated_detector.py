"""SIMULATION ONLY: a superset "person" detector that answers from the rendered world's ground truth.

It stands in for YOLOX in closed-loop scenarios so the back-end's real verification path (crops with a
50 px margin, then the local attribute verifier or a VLM endpoint) runs on the rendered pixels. The
frame is identified by the `frame_id` the companion sent (the SITL stream's own ids), else by the
timecode strip (`sitl.camera_render.read_timecode`). When the back-end hands over only a region of the
keyframe (a re-detection ROI), the region is placed in the frame by template matching against the
frame's ground-truth thumbnail. Jitter and false positives come from a generator seeded by (seed, frame
id), so a run is repeatable.

Misses come either at a fixed rate per person and keyframe (`DetectorNoise.miss_rate`, the follow
scenarios'), or from the detection curve (`DetectorNoise.curve`, `behaviors/detection_curve.py`) at the
size the person has in the keyframe (sqrt(w * h) of the truth box in keyframe pixels), dependent within a
pass exactly as the companion's POD map assumes (`cloudtrack/pod_map.py`): one latent u ~ U(0, 1) per
person and pass, the person reported in a keyframe when u < p(size), so a pass finds them with the
probability of its best look; a person not looked at for `pass_gap_s` starts a new pass with a new u. A
look, as for the map, is a keyframe showing the person within `look_range_m` of the vehicle (the
companion's `[camera] search_range_m`); nobody farther is reported, since the map claims nothing there.
The latent of a pass comes from (seed, person, pass number), so a run is repeatable given its keyframes.
`look_range_m` (either way of missing) reports nobody farther from the vehicle: with a fixed rate it keeps a
scenario's candidates where the search range puts them (search-outage times its outage by that range).
"""

from __future__ import annotations

import math
import threading
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from behaviors.detection import Detection
from behaviors.detection_curve import DetectionCurve
from behaviors.geometry import Box
from cloudtrack.pod_map import PASS_GAP_S
from sitl.camera_render import THUMB_SCALE, FrameTruth, TruthBox, read_timecode

TruthLookup = Callable[[int], "FrameTruth | None"]
MIN_MATCH = 0.8  # normalised correlation below which a region is not placed (no boxes rather than wrong ones)


@dataclass(frozen=True)
class DetectorNoise:
    miss_rate: float = 0.05  # probability a visible person is not reported
    jitter_px: float = 1.5  # standard deviation of each box edge, pixels
    false_positives: float = 0.2  # expected spurious boxes per frame (Poisson)
    min_visible: float = 0.4  # a person less visible than this is not detected
    min_height_px: float = 8.0  # (fixed rate only: the curve says how small a person is still found)
    # The detection curve instead of `miss_rate` (see the module doc), with the map's rules for a pass.
    curve: DetectionCurve | None = None
    accept_uncertain: bool = False  # the curve's "found" as the companion's [behavior] accept_uncertain
    pass_gap_s: float = PASS_GAP_S
    # Nobody farther from the vehicle is reported (either way of missing); None: anywhere in the keyframe.
    look_range_m: float | None = None


@dataclass
class Pass:
    """One pass of the curve-driven detector over a person: its latent, its looks and the best of them."""

    number: int
    latent: float
    first_s: float
    last_s: float
    looks: int = 0
    best: float = 0.0  # the curve's probability at the pass's best look
    best_size_px: float = 0.0  # the person's size at that look
    reported: int = 0  # keyframes the person was reported in


class SimulatedPersonDetector:
    """`backend.detectors.SupersetDetector` for the SITL world. Only the class "person" is known."""

    name = "sitl_simulated_person"

    def __init__(
        self, truth: TruthLookup, render_width: int = 640, noise: DetectorNoise | None = None, seed: int = 0
    ) -> None:
        self._truth = truth
        self._render_width = render_width
        self.noise = noise or DetectorNoise()
        self.seed = seed
        self._passes: dict[str, list[Pass]] = {}
        self._lock = threading.Lock()  # the back-end detects on several threads at once

    def detect(
        self, image_bgr: np.ndarray, classes: Sequence[str], frame_id: int | None = None
    ) -> list[Detection]:
        """Boxes of people in `image_bgr` (a keyframe, scaled or not, or a region of one)."""
        from backend.supersets import UnknownSupersetError

        wanted = {c.strip().lower() for c in classes}
        if wanted - {"person", "people", "human"}:
            raise UnknownSupersetError(f"the simulated detector only knows 'person', not {sorted(wanted)}")
        record = self._truth(frame_id) if frame_id is not None else None
        if record is None:
            record = self._truth(read_timecode(image_bgr, self._render_width))
        if record is None:
            return []
        placed = self._place(image_bgr, record)
        if placed is None:
            return []
        (ox, oy), scale = placed
        h, w = image_bgr.shape[:2]
        rng = np.random.default_rng([self.seed, record.frame_id])
        n = self.noise
        out: list[Detection] = []
        for tb in record.truth:
            if tb.visible < n.min_visible or not self._in_range(tb, record):
                continue
            if n.curve is None and (tb.box.h < n.min_height_px or rng.random() < n.miss_rate):
                continue
            jit = rng.normal(0.0, n.jitter_px, 4)
            box = Box.from_xyxy(tb.box.x + jit[0], tb.box.y + jit[1], tb.box.x2 + jit[2], tb.box.y2 + jit[3])
            box = Box(box.x * scale - ox, box.y * scale - oy, box.w * scale, box.h * scale)
            inside = box.clamped(w, h)
            if not inside.is_valid() or inside.area < 0.5 * box.area:
                continue  # mostly outside the region: a detector would not see this person here
            if n.curve is not None and not self._found(tb, record, scale):
                continue
            # Like a real detector, more confident on bigger, unoccluded people.
            size = min(1.0, float(np.sqrt(tb.box.area)) / 40.0)
            score = 0.5 + 0.45 * size * tb.visible + rng.normal(0, 0.01)
            out.append(Detection(inside, float(np.clip(score, 0.3, 0.99))))
        for _ in range(int(rng.poisson(n.false_positives))):
            bw, bh = rng.uniform(10, 30) * scale, rng.uniform(25, 60) * scale
            x, y = rng.uniform(0, max(1.0, w - bw)), rng.uniform(0, max(1.0, h - bh))
            out.append(Detection(Box(float(x), float(y), float(bw), float(bh)), float(rng.uniform(0.3, 0.5))))
        out.sort(key=lambda d: -d.score)
        return out

    def _found(self, tb: TruthBox, record: FrameTruth, scale: float) -> bool:
        """Whether the curve-driven detector reports `tb` in this keyframe (see the module doc)."""
        n = self.noise
        assert n.curve is not None
        size = math.sqrt(max(0.0, tb.box.w * tb.box.h)) * scale
        p = n.curve.probability(size, n.accept_uncertain)
        t = record.time_s
        with self._lock:
            passes = self._passes.setdefault(tb.person_id, [])
            # Keyframes arrive out of order (several in flight, stored ones after an outage): a look within
            # the gap of a pass's span, before or after it, belongs to that pass.
            this = next((x for x in passes if x.first_s - n.pass_gap_s <= t <= x.last_s + n.pass_gap_s), None)
            if this is None:
                person = zlib.crc32(tb.person_id.encode())
                latent = float(np.random.default_rng([self.seed, person, len(passes)]).random())
                this = Pass(len(passes), latent, t, t)
                passes.append(this)
            this.first_s, this.last_s = min(this.first_s, t), max(this.last_s, t)
            this.looks += 1
            if p > this.best:
                this.best, this.best_size_px = p, size
            found = this.latent < p
            this.reported += int(found)
        return found

    def _in_range(self, tb: TruthBox, record: FrameTruth) -> bool:
        """Within `look_range_m` of the vehicle (horizontally), where the search looks."""
        n, pose = self.noise, record.pose
        return (
            n.look_range_m is None or math.hypot(tb.north - pose.north, tb.east - pose.east) <= n.look_range_m
        )

    def passes(self, person_id: str) -> list[Pass]:
        """The curve-driven detector's passes over a person so far (empty with a fixed miss rate)."""
        with self._lock:
            return list(self._passes.get(person_id, []))

    def _place(self, image_bgr: np.ndarray, record: FrameTruth) -> tuple[tuple[float, float], float] | None:
        """((x, y) offset in this image's pixels, scale from rendered to this image's pixels)."""
        h, w = image_bgr.shape[:2]
        rw, rh = record.size
        if (w, h) == (rw, rh):
            return (0.0, 0.0), 1.0
        # A region of a full-size keyframe: find it in the thumbnail (the offset is good to about 2 px).
        gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
        small = cv2.resize(
            gray, (max(1, int(w * THUMB_SCALE)), max(1, int(h * THUMB_SCALE))), interpolation=cv2.INTER_AREA
        )
        thumb = record.thumbnail
        if small.shape[0] <= thumb.shape[0] and small.shape[1] <= thumb.shape[1] and min(small.shape) >= 4:
            scores = cv2.matchTemplate(thumb, small, cv2.TM_CCOEFF_NORMED)
            _, best, _, (x, y) = cv2.minMaxLoc(scores)
            if best >= MIN_MATCH:
                return (x / THUMB_SCALE, y / THUMB_SCALE), 1.0
        if abs(w / rw - h / rh) < 0.02:
            return (0.0, 0.0), w / rw  # the whole keyframe, downscaled by the companion
        return None
