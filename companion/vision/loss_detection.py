"""Deciding that the tracker has lost its target, from several independent signals.

The paper re-initialises when the tracker's score falls below t_c. That alone misses NanoTrack jumping to
a similar-looking person (its score stayed at 0.64 or more), and CSRT/KCF/MIL have no score at all, so
the score is one signal among:
- "tracker_failed": OpenCV's own ok flag is false;
- "score": score below t_c (trackers with a score only);
- "left_frame": less than `min_visible_fraction` of the box is inside the image;
- "collapsed": box narrower/shorter than `min_box_px`, its area changed by more than
  `max_scale_change` times in one frame, or its width/height ratio changed by more than
  `max_aspect_change` times since the tracker's first box after (re)initialisation (a tracker sliding
  off a standing person onto a roof or a patch of ground flattens its box; only for targets that keep
  their shape, `LossSettings.hold_aspect`);
- "jump": the centre moved more than `max_jump_box_sizes` box sizes (sqrt of area) or
  `max_jump_fraction` of the image diagonal in one frame;
- "appearance": the colour histogram inside the box drifted from the target as first seen
  (Bhattacharyya distance above `appearance_drift_threshold`).

`LossDetector.check` returns the first enabled signal that fired, in the order above, and keeps every
signal's value in `last_signals` (the evaluation measures what each one adds).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from behaviors.geometry import Box
from companion.vision.trackers import TrackerStep

SIGNALS = ("tracker_failed", "score", "left_frame", "collapsed", "jump", "appearance")

# Hue x saturation bins: coarse enough to survive pose and scale changes, fine enough to tell
# a green-striped shirt from a grey one.
_HIST_BINS = (16, 8)
_PATCH_SIDE = 48  # the box interior is resized to at most this many pixels per side before the histogram


@dataclass(frozen=True)
class LossSettings:
    score_threshold: float | None = None  # t_c; None: this tracker has no score
    min_visible_fraction: float = 0.5
    min_box_px: float = 4.0
    max_scale_change: float = 3.0
    max_jump_box_sizes: float = 1.5
    max_jump_fraction: float = 0.35
    appearance_drift_threshold: float = 0.6
    appearance_rate: float = 0.1  # weight of each trusted frame in the appearance model
    max_aspect_change: float = 2.0  # width/height ratio change since (re)initialisation: "collapsed"
    enabled: frozenset[str] = field(default_factory=lambda: frozenset(SIGNALS))
    # The aspect test models a target that keeps its shape (a standing or walking person); a car turning
    # under the camera, a bird or a ball changes its width/height all the time (`[tracker] loss_model_classes`).
    hold_aspect: bool = True

    def __post_init__(self) -> None:
        unknown = set(self.enabled) - set(SIGNALS)
        if unknown:
            raise ValueError(f"unknown loss signal(s) {sorted(unknown)}; known: {', '.join(SIGNALS)}")


def parse_signals(text: str) -> frozenset[str]:
    """'all', 'none' or a comma list such as 'score,jump' (used by the eval command)."""
    text = text.strip().lower()
    if text == "all":
        return frozenset(SIGNALS)
    if text in ("", "none"):
        return frozenset()
    names = frozenset(part.strip() for part in text.split(",") if part.strip())
    unknown = names - set(SIGNALS)
    if unknown:
        raise ValueError(f"unknown loss signal(s) {sorted(unknown)}; known: {', '.join(SIGNALS)}, all, none")
    return names


def appearance_histogram(frame: np.ndarray, box: Box) -> np.ndarray | None:
    """Normalised hue-saturation histogram of the central 80 % of the box; None if the box is off-image."""
    h, w = frame.shape[:2]
    inner = Box.from_center(box.cx, box.cy, box.w * 0.8, box.h * 0.8).clamped(w, h)
    x1, y1, x2, y2 = (int(round(v)) for v in inner.xyxy())
    if x2 - x1 < 2 or y2 - y1 < 2:
        return None
    patch = frame[y1:y2, x1:x2]
    scale = _PATCH_SIDE / max(patch.shape[0], patch.shape[1])
    if scale < 1.0:
        patch = cv2.resize(patch, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    if patch.ndim == 2:
        patch = cv2.cvtColor(patch, cv2.COLOR_GRAY2BGR)
    hsv = cv2.cvtColor(patch, cv2.COLOR_BGR2HSV)
    hist = cv2.calcHist([hsv], [0, 1], None, list(_HIST_BINS), [0, 180, 0, 256])
    total = float(hist.sum())
    # numpy, not cv2.normalize: the latter cost ~0.3 ms per call here (thread-pool dispatch for 128 bins).
    return hist / total if total > 0 else hist


def appearance_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Bhattacharyya distance between two histograms: 0 identical, 1 nothing in common."""
    return float(cv2.compareHist(a, b, cv2.HISTCMP_BHATTACHARYYA))


class LossDetector:
    """Per-track loss state: the target's appearance model and the previous box.

    The appearance model starts as the target first seen and follows it slowly (exponential average
    over trusted frames only): against the first-seen histogram alone, the true target drifted past a
    Bhattacharyya distance of 0.6 on three of the five sequences through pose and light changes, while
    the slowly adapting model keeps the true target below 0.65 at the 95th percentile and puts most
    nearby non-target boxes above it (docs/tracking.md).
    """

    def __init__(self, settings: LossSettings) -> None:
        self.settings = settings
        self.last_signals: dict[str, bool] = dict.fromkeys(SIGNALS, False)
        self._template: np.ndarray | None = None
        self._prev: Box | None = None
        self._reference: Box | None = None  # the tracker's first box since the last reset
        self._hist: np.ndarray | None = None

    def reset(
        self, frame: np.ndarray, box: Box, keep_template: bool = False, current: Box | None = None
    ) -> None:
        """Start a track on `box` in `frame`; `keep_template` keeps the appearance model (re-initialisation).
        `current` is where a fast-forwarded tracker now is (the jump check starts from there)."""
        if not keep_template or self._template is None:
            self._template = appearance_histogram(frame, box)
        self._prev = current or box
        # The shape reference is the tracker's own first box, not the given one: VitTrack reframes a
        # 17x50 pedestrian as 23x31 on its first update and keeps that shape while on target.
        self._reference = None

    def refresh(self, frame: np.ndarray, box: Box) -> None:
        """A back-end answer confirmed that `box` in `frame` is the target: the shape reference restarts
        from the tracker's next box and the appearance model moves halfway to this view of the target."""
        hist = appearance_histogram(frame, box)
        if self._template is None or hist is None:
            self._template = hist if hist is not None else self._template
        else:
            self._template = 0.5 * self._template + 0.5 * hist
        self._prev = box
        self._reference = None

    def check(self, frame: np.ndarray, step: TrackerStep) -> str:
        """The first enabled signal that fired ("" while the target is trusted); every signal is kept in
        `last_signals`. A trusted step updates the appearance model."""
        self.last_signals = self._signals(frame, step)
        reason = first_reason(self.last_signals, self.settings.enabled)
        if not reason and self._template is not None and self._hist is not None:
            rate = self.settings.appearance_rate
            self._template = (1.0 - rate) * self._template + rate * self._hist
        return reason

    def _signals(self, frame: np.ndarray, step: TrackerStep) -> dict[str, bool]:
        s = self.settings
        fired = dict.fromkeys(SIGNALS, False)
        self._hist = None
        fired["tracker_failed"] = not step.ok or step.box is None
        fired["score"] = (
            s.score_threshold is not None and step.score is not None and step.score < s.score_threshold
        )
        box = step.box
        if box is None:
            return fired
        h, w = frame.shape[:2]
        visible = box.clamped(w, h).area / box.area if box.area > 0 else 0.0
        fired["left_frame"] = visible < s.min_visible_fraction
        prev = self._prev
        collapsed = box.w < s.min_box_px or box.h < s.min_box_px
        if prev is not None and prev.area > 0 and box.area > 0:
            ratio = box.area / prev.area
            collapsed = collapsed or max(ratio, 1.0 / ratio) > s.max_scale_change
            moved = math.hypot(box.cx - prev.cx, box.cy - prev.cy)
            fired["jump"] = moved > s.max_jump_box_sizes * math.sqrt(prev.area) or moved > (
                s.max_jump_fraction * math.hypot(w, h)
            )
        if self._reference is None and box.is_valid():
            self._reference = box
        ref = self._reference
        if s.hold_aspect and ref is not None and ref.is_valid() and box.w > 0 and box.h > 0:
            change = (box.w / box.h) / (ref.w / ref.h)
            collapsed = collapsed or max(change, 1.0 / change) > s.max_aspect_change
        fired["collapsed"] = collapsed
        if self._template is not None and "appearance" in s.enabled:
            self._hist = appearance_histogram(frame, box)
            fired["appearance"] = self._hist is None or (
                appearance_distance(self._template, self._hist) > s.appearance_drift_threshold
            )
        self._prev = box
        return fired


def first_reason(fired: dict[str, bool], enabled: Iterable[str]) -> str:
    chosen = set(enabled)
    return next((name for name in SIGNALS if name in chosen and fired.get(name)), "")
