"""Latency compensation: a back-end box refers to a keyframe captured earlier, not to the live frame.

`FrameRing` keeps the last N frames by id. `CatchUp` initialises a fresh tracker on the keyframe with
the back-end's box and fast-forwards it through the frames captured since, so its box matches the newest
frame. The work is bounded twice so the live rate holds: at most `per_step` tracker updates per live
frame (the catch-up spreads over several loop iterations while the live frames keep coming), and at most
`max_frames` updates in all (a long gap is subsampled evenly; the newest frame is always the last one).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

from behaviors.geometry import Box
from companion.vision.frame_sources import Frame
from companion.vision.trackers import Tracker, TrackerStep

log = logging.getLogger(__name__)


class KeyframeGoneError(Exception):
    """The keyframe an answer refers to is no longer in the ring (the answer came too late)."""


class FrameRing:
    """The most recent `capacity` frames, oldest first."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("ring capacity must be at least 1")
        self.capacity = capacity
        self._frames: deque[Frame] = deque(maxlen=capacity)

    def push(self, frame: Frame) -> None:
        """Add the newest frame. An id that does not increase means the source restarted its numbering
        (a camera stream reconnected): the old frames are dropped so no answer is matched to a frame it
        was not computed on."""
        if self._frames and frame.frame_id <= self._frames[-1].frame_id:
            log.warning(
                "frame id went from %d to %d: the source restarted; dropping %d buffered frames",
                self._frames[-1].frame_id,
                frame.frame_id,
                len(self._frames),
            )
            self._frames.clear()
        self._frames.append(frame)

    def get(self, frame_id: int) -> Frame | None:
        for frame in reversed(self._frames):
            if frame.frame_id == frame_id:
                return frame
            if frame.frame_id < frame_id:
                break
        return None

    def since(self, frame_id: int) -> list[Frame]:
        """Frames captured after `frame_id`, oldest first."""
        return [f for f in self._frames if f.frame_id > frame_id]

    @property
    def newest(self) -> Frame | None:
        return self._frames[-1] if self._frames else None

    def __len__(self) -> int:
        return len(self._frames)


@dataclass(frozen=True)
class CatchUpResult:
    frame_id: int  # the frame the tracker's box now refers to
    step: TrackerStep


class CatchUp:
    """A tracker being brought from a keyframe up to the live frame, a bounded number of updates at a time."""

    def __init__(
        self, tracker: Tracker, ring: FrameRing, keyframe_id: int, box: Box, max_frames: int, per_step: int
    ) -> None:
        keyframe = ring.get(keyframe_id)
        if keyframe is None:
            raise KeyframeGoneError(f"keyframe {keyframe_id} is no longer in the last {ring.capacity} frames")
        self.tracker = tracker
        self.ring = ring
        self.keyframe_id = keyframe_id
        self.keyframe_box = box
        self.max_frames = max_frames
        self.per_step = per_step
        self.updates = 0
        tracker.init(keyframe.image, box)
        self.last = CatchUpResult(keyframe_id, TrackerStep(box, None, True))
        # The new track's box on each frame it was brought through (the keyframe's is the start box):
        # answers about those keyframes that arrive after the take-over are judged against it.
        self.boxes: dict[int, Box | None] = {keyframe_id: box}
        backlog = len(ring.since(keyframe_id))
        # Stride so the backlog at the start fits in max_frames; frames arriving later extend it.
        self._stride = max(1, math.ceil(backlog / max_frames)) if max_frames > 0 else 1

    def box_at(self, frame_id: int) -> Box | None:
        """The new track's box on `frame_id`: from the last frame it was brought through up to it (a
        stride skips frames); None before the keyframe."""
        passed = [f for f in self.boxes if f <= frame_id]
        return self.boxes[max(passed)] if passed else None

    @property
    def done(self) -> bool:
        newest = self.ring.newest
        return newest is None or self.last.frame_id >= newest.frame_id

    def advance(self) -> bool:
        """Up to `per_step` updates towards the newest frame; True once the tracker is on it."""
        for _ in range(max(1, self.per_step)):
            pending = self.ring.since(self.last.frame_id)
            if not pending:
                break
            if self.updates + 1 >= self.max_frames:
                chosen = pending[-1]  # out of budget: one jump straight to the newest frame
            else:
                chosen = pending[min(self._stride, len(pending)) - 1]
            self.last = CatchUpResult(chosen.frame_id, self.tracker.update(chosen.image))
            self.boxes[chosen.frame_id] = self.last.step.box
            self.updates += 1
        return self.done
