"""The onboard tracking front-end: one object the main loop feeds every frame.

`feed(frame)` runs the tracker and loss detection and returns a `TrackResult`. `start(keyframe_id, box)`
begins a track on a box the behaviour chose (first acquisition, operator rectangle);
`apply_candidates(keyframe_id, detections)` re-initialises on the back-end candidate closest to the last
trusted box by the paper's C_box. Both are latency-compensated: the new tracker starts on the keyframe
and is fast-forwarded through the ring buffer a few updates per `feed`, while the current tracker (if
any) keeps reporting; the new one takes over once it reaches the live frame.

A loss is latched: once a signal fires, every result carries that `lost_reason` until the next
`start`/`apply_candidates` completes, because a tracker that jumped to a distractor usually follows it
smoothly afterwards and the per-frame signals would stop firing. Results while nothing is tracked carry
`lost_reason` "idle"; while the first acquisition is still catching up, "acquiring".
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from behaviors.candidate_selection import c_box, select_by_c_box, select_by_score
from behaviors.detection import Detection
from behaviors.geometry import Box
from behaviors.track_result import TrackResult
from companion.config import TrackerConfig
from companion.frame_sources import Frame
from companion.latency_compensation import CatchUp, FrameRing, KeyframeGoneError
from companion.loss_detection import LossDetector, LossSettings
from companion.trackers import Tracker, create_tracker

log = logging.getLogger(__name__)

Policy = Literal["c_box", "score"]


def loss_settings(config: TrackerConfig, tracker_name: str | None = None) -> LossSettings:
    name = tracker_name or config.name
    return LossSettings(
        score_threshold=config.score_threshold.get(name),
        min_visible_fraction=config.min_visible_fraction,
        min_box_px=config.min_box_px,
        max_scale_change=config.max_scale_change,
        max_jump_box_sizes=config.max_jump_box_sizes,
        max_jump_fraction=config.max_jump_fraction,
        appearance_drift_threshold=config.appearance_drift_threshold,
        max_aspect_change=config.max_aspect_change,
        enabled=frozenset(config.loss_signals),
    )


@dataclass
class FrontendStats:
    tracker_updates: int = 0  # live-frame updates
    tracker_seconds: float = 0.0  # time inside the tracker's update() on live frames
    catch_up_updates: int = 0
    catch_up_seconds: float = 0.0
    reinits: int = 0  # completed starts and re-initialisations
    loss_events: int = 0  # trusted -> lost transitions
    stale_answers: int = 0  # answers whose keyframe had left the ring
    rejected_candidates: int = 0  # nearest candidate beyond the C_box gate


class TrackingFrontend:
    def __init__(
        self,
        make_tracker: Callable[[], Tracker],
        settings: LossSettings,
        ring_frames: int = 90,
        max_fast_forward_frames: int = 45,
        catch_up_per_frame: int = 4,
        policy: Policy = "c_box",
        compensate: bool = True,
        max_c_box_sizes: float = 3.0,
    ) -> None:
        self._make_tracker = make_tracker
        self.loss = LossDetector(settings)
        self.ring = FrameRing(ring_frames)
        self.max_fast_forward_frames = max_fast_forward_frames
        self.catch_up_per_frame = catch_up_per_frame
        self.policy: Policy = policy
        self.compensate = compensate
        self.max_c_box_sizes = max_c_box_sizes
        self.stats = FrontendStats()
        self.last_trusted_box: Box | None = None
        self.last_trusted_frame_id: int | None = None
        self.last_trusted_time = 0.0
        self._tracker: Tracker | None = None
        self._catch_up: CatchUp | None = None
        self._catch_up_keeps_template = False
        self._lost_reason = ""

    @classmethod
    def from_config(
        cls, config: TrackerConfig, model_dir: Path, tracker_name: str | None = None, **kwargs: object
    ) -> TrackingFrontend:
        """A front-end for `config` (tracker weights are checked now: ModelError if missing)."""
        name = tracker_name or config.name
        create_tracker(name, model_dir)  # fail at start-up, not at the first acquisition
        return cls(
            lambda: create_tracker(name, model_dir),
            loss_settings(config, name),
            ring_frames=config.ring_buffer_frames,
            max_fast_forward_frames=config.max_fast_forward_frames,
            catch_up_per_frame=config.catch_up_per_frame,
            max_c_box_sizes=config.max_c_box_sizes,
            **kwargs,  # type: ignore[arg-type]
        )

    @property
    def tracking(self) -> bool:
        """A tracker is running (trusted or lost) or being brought up to date."""
        return self._tracker is not None or self._catch_up is not None

    @property
    def catching_up(self) -> bool:
        """A start or re-initialisation is being fast-forwarded to the live frame."""
        return self._catch_up is not None

    @property
    def lost_reason(self) -> str:
        return self._lost_reason

    def start(self, keyframe_id: int, box: Box) -> bool:
        """Track `box` as seen in frame `keyframe_id` (a new target: the appearance model restarts)."""
        return self._begin(keyframe_id, box, keep_template=False)

    def apply_candidates(self, keyframe_id: int, detections: Sequence[Detection]) -> Detection | None:
        """Re-initialise on the candidate closest to the last trusted box (C_box), or with policy "score"
        the highest detector score (the reference code's choice, ungated). With C_box, a candidate
        farther than `max_c_box_sizes` x (1 + seconds lost) x (w + h) of the last trusted box is not used.
        None when nothing was usable."""
        if self.policy == "score":
            chosen = select_by_score(detections)
        else:
            if self.last_trusted_box is None:
                return None  # no trusted box to compare with: first acquisition is the behaviour's call
            prev = self.last_trusted_box
            chosen = select_by_c_box(prev, detections)
            keyframe = self.ring.get(keyframe_id)
            lost_for = max(0.0, keyframe.capture_time - self.last_trusted_time) if keyframe is not None else 0.0
            # The longer the target has been lost, the farther it may have gone: the gate grows by its
            # base size every second since the last trusted box.
            gate = self.max_c_box_sizes * (1.0 + lost_for) * (prev.w + prev.h)
            if chosen is not None and c_box(prev, chosen.box) > gate:
                # Nothing near where the target was: re-initialising on it would follow whoever else
                # is in view (a detector's "person" is not the described person); stay lost instead.
                log.info("nearest candidate is %.0f px (C_box) from the last trusted box, gate %.0f: not used",
                         c_box(prev, chosen.box), gate)
                self.stats.rejected_candidates += 1
                return None
        if chosen is None:
            return None
        # The appearance model restarts from the candidate: a detector box frames the target differently
        # from the tracker's, and keeping the old model made every re-initialisation look lost at once.
        return chosen if self._begin(keyframe_id, chosen.box, keep_template=False) else None

    def stop(self) -> None:
        self._tracker = None
        self._catch_up = None
        self._lost_reason = ""
        self.last_trusted_box = None
        self.last_trusted_frame_id = None

    def _begin(self, keyframe_id: int, box: Box, keep_template: bool) -> bool:
        if not box.is_valid():
            log.warning("ignoring invalid box %s for frame %d", box, keyframe_id)
            return False
        tracker = self._make_tracker()
        newest = self.ring.newest
        try:
            if self.compensate:
                catch_up = CatchUp(
                    tracker,
                    self.ring,
                    keyframe_id,
                    box,
                    self.max_fast_forward_frames,
                    self.catch_up_per_frame,
                )
            elif newest is not None:
                # Uncompensated (for comparison): the keyframe's box on the newest frame.
                catch_up = CatchUp(tracker, self.ring, newest.frame_id, box, 0, 1)
            else:
                raise KeyframeGoneError("no frame received yet")
        except KeyframeGoneError as exc:
            self.stats.stale_answers += 1
            log.warning("cannot start on frame %d: %s", keyframe_id, exc)
            return False
        self._catch_up = catch_up
        self._catch_up_keeps_template = keep_template
        return True

    def feed(self, frame: Frame) -> TrackResult:
        self.ring.push(frame)
        image = frame.image
        result: TrackResult | None = None
        if self._catch_up is not None:
            started = time.perf_counter()
            before = self._catch_up.updates
            done = self._catch_up.advance()
            self.stats.catch_up_seconds += time.perf_counter() - started
            self.stats.catch_up_updates += self._catch_up.updates - before
            if done:
                result = self._take_over(frame)
        if result is not None:
            return result
        if self._tracker is None:
            reason = "acquiring" if self._catch_up is not None else "idle"
            return TrackResult(frame.frame_id, frame.capture_time, None, None, False, reason)
        started = time.perf_counter()
        step = self._tracker.update(image)
        self.stats.tracker_seconds += time.perf_counter() - started
        self.stats.tracker_updates += 1
        reason = self.loss.check(image, step)
        if self._lost_reason:
            reason = self._lost_reason
        elif reason:
            self._lost_reason = reason
            self.stats.loss_events += 1
            log.info("target lost at frame %d: %s", frame.frame_id, reason)
        if not reason and step.box is not None:
            self.last_trusted_box = step.box
            self.last_trusted_frame_id = frame.frame_id
            self.last_trusted_time = frame.capture_time
        return TrackResult(frame.frame_id, frame.capture_time, step.box, step.score, step.ok, reason)

    def _take_over(self, frame: Frame) -> TrackResult:
        """The caught-up tracker replaces the current one; its box refers to this frame."""
        assert self._catch_up is not None
        catch_up, self._catch_up = self._catch_up, None
        step = catch_up.last.step
        self._tracker = catch_up.tracker
        self._lost_reason = ""
        self.stats.reinits += 1
        keyframe = self.ring.get(catch_up.keyframe_id)
        if keyframe is not None and (self.last_trusted_frame_id or 0) < catch_up.keyframe_id:
            # The box we were told to start on is trusted as of its keyframe, whatever the tracker makes of it.
            self.last_trusted_box = catch_up.keyframe_box
            self.last_trusted_frame_id = catch_up.keyframe_id
            self.last_trusted_time = keyframe.capture_time
        if step.box is None:
            self._lost_reason = "tracker_failed"
            self.stats.loss_events += 1
            return TrackResult(frame.frame_id, frame.capture_time, None, step.score, False, self._lost_reason)
        if keyframe is not None:
            self.loss.reset(keyframe.image, catch_up.keyframe_box, self._catch_up_keeps_template, current=step.box)
        else:
            self.loss.reset(frame.image, step.box, self._catch_up_keeps_template)
        # Judge the caught-up box like any other step (score, left frame, appearance ...).
        reason = self.loss.check(frame.image, step)
        if reason:
            self._lost_reason = reason
            self.stats.loss_events += 1
        else:
            self.last_trusted_box = step.box
            self.last_trusted_frame_id = frame.frame_id
            self.last_trusted_time = frame.capture_time
        return TrackResult(frame.frame_id, frame.capture_time, step.box, step.score, step.ok, reason)
