"""The onboard tracking front-end: one object the main loop feeds every frame.

`feed(frame)` runs the tracker and loss detection and returns a `TrackResult`. `start(keyframe_id, box)`
begins a track on a box the behaviour chose (first acquisition, operator rectangle);
`apply_candidates(keyframe_id, detections)` acts on a back-end answer by the front-end's policy: "verified"
(`behaviors.reinit_policy`: move the track only when a candidate beats it on evidence, twice in a row;
withdraw a loss a candidate on the track confirms; otherwise wait), or the paper's "c_box" (re-initialise on
the candidate closest to the last trusted box) and "score" (highest detector score, the reference code).
Starts and re-initialisations are latency-compensated: the new tracker starts on the keyframe
and is fast-forwarded through the ring buffer a few updates per `feed`, while the current tracker (if
any) keeps reporting; the new one takes over once it reaches the live frame.

With the paper's policies a loss is latched: once a signal fires, every result carries that `lost_reason`
until the next `start`/`apply_candidates` completes, because a tracker that jumped to a distractor usually
follows it smoothly afterwards and the per-frame signals would stop firing. With "verified" the signals
are weighed over time and not latched (`behaviors.loss_evidence`): no box, a box out of the image or a
jump, or two signals together, untrust the track at once; one of `[tracker] weak_loss_signals` (score,
shape, colour model) alone only after `loss_persistence_s` of alarm (measured: most of their alarms on
real footage were a few frames while the tracker was on target); a lost track is trusted again after as
long without an alarm, or at once when a back-end candidate on the track confirms it. A silent switch to
a distractor is what the keyframe evidence is for (the policy judges every answer, trusted or not). A box
holding on background (a roof the person walked under, ground at the image's edge) that no signal sees is
untrusted as "not_detected" once the answers' detector misses on it are too unlikely for a real target of
its size (`behaviors.track_support`, with the shipped detection curve); only a candidate on the track or a
re-initialisation trusts it again.
Results while nothing is tracked carry `lost_reason` "idle"; while the first acquisition is still
catching up, "acquiring".
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from behaviors.candidate_selection import c_box, select_by_c_box, select_by_score
from behaviors.detection import Detection, Verdict
from behaviors.detection_curve import CurveError
from behaviors.geometry import Box, iou
from behaviors.loss_evidence import LossEvidence, LossEvidenceSettings, judge_frame
from behaviors.reinit_policy import (
    CandidateEvidence,
    ReinitAction,
    ReinitDecision,
    ReinitSettings,
    ReinitState,
    TrackEvidence,
    decide,
    framing_ratio,
    same_object,
)
from behaviors.track_result import TrackResult
from behaviors.track_support import Support, SupportSettings, judge_answer, started
from cloudtrack.detection_curves import curve_for
from companion.config import TrackerConfig
from companion.vision.frame_sources import Frame
from companion.vision.latency_compensation import CatchUp, FrameRing, KeyframeGoneError
from companion.vision.loss_detection import (
    SIGNALS,
    LossDetector,
    LossSettings,
    appearance_distance,
    appearance_histogram,
    first_reason,
)
from companion.vision.trackers import Tracker, create_tracker

log = logging.getLogger(__name__)

# Signals that compare the target with a model of its look (or the tracker's own confidence in it). A
# detector box on the track, with nothing in view more like the target, outweighs them until the next answer.
APPEARANCE_SIGNALS = frozenset({"score", "appearance"})
# Signals that say the box itself is wrong (not who is in it): a candidate on a track lost on one of these
# re-frames it instead of only confirming it.
GEOMETRIC_SIGNALS = frozenset({"left_frame", "collapsed", "jump"})

Policy = Literal["verified", "c_box", "score"]
POLICIES: tuple[Policy, ...] = ("verified", "c_box", "score")
NOT_DETECTED = "not_detected"  # the lost reason of a track the detector's answers no longer support

# A target class and its size in keyframe pixels (sqrt(w * h)) -> the chance one answer's detector proposes
# it; None when there is no curve for that class (its misses are then no evidence).
PodBySize = Callable[[str, float], "float | None"]


def curve_pod(curve_file: str = "") -> PodBySize:
    """POD by size from the detection curves (the shipped file, or `[search] curve_file`): the curve of a
    target found and not judged "no", a lower bound on its being proposed at all (behaviors.track_support)."""
    path = Path(curve_file) if curve_file else None

    def pod(kind: str, size_px: float) -> float | None:
        try:
            curve = curve_for(kind, path)
        except CurveError:
            return None
        return curve.probability(size_px, accept_uncertain=True)

    return pod


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


def loss_evidence_settings(config: TrackerConfig) -> LossEvidenceSettings:
    unknown = set(config.weak_loss_signals) - set(SIGNALS)
    if unknown:
        raise ValueError(
            f"weak_loss_signals: unknown signal(s) {sorted(unknown)}; known: {', '.join(SIGNALS)}"
        )
    return LossEvidenceSettings(
        persistence_s=config.loss_persistence_s, weak_signals=frozenset(config.weak_loss_signals)
    )


def support_settings(config: TrackerConfig) -> SupportSettings | None:
    """The detector-miss test's settings; None when it is off (`unsupported_miss_chance = 0`)."""
    if config.unsupported_miss_chance <= 0:
        return None
    return SupportSettings(config.unsupported_miss_chance, config.unsupported_min_s)


def reinit_settings(config: TrackerConfig) -> ReinitSettings:
    return ReinitSettings(
        agree_iou=config.reinit_agree_iou,
        confirmations=config.reinit_confirmations,
        appearance_threshold=config.appearance_drift_threshold,
        appearance_margin=config.reinit_appearance_margin,
        max_framing_ratio=config.reinit_max_framing_ratio,
    )


FRAMING_KEPT = 3600  # framing samples kept: an hour of answers at one a second


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
    confirmations: int = 0  # "verified": answers whose candidate on the track withdrew a latched loss
    # "verified": trusted tracks the detector's misses untrusted (behaviors.track_support)
    not_detected: int = 0
    decisions: dict[str, int] = field(default_factory=dict)  # "verified": answers per ReinitAction
    verdicts_ignored: int = 0  # tracks whose verifier said "no" to the target it started on
    # "verified": (keyframe, track box, framing_ratio) whenever the track's own candidate decided an
    # answer (confirmed or re-framed it): how the tracker frames the object the detector found.
    framing: deque[tuple[int, Box, float]] = field(default_factory=lambda: deque(maxlen=FRAMING_KEPT))


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
        reinit: ReinitSettings | None = None,
        name: str = "",
        evidence: LossEvidenceSettings | None = None,
        loss_model_classes: Collection[str] | None = None,
        support: SupportSettings | None = None,
        support_pod: PodBySize | None = None,
        keyframe_width: int = 640,
    ) -> None:
        self._make_tracker = make_tracker
        self.loss = LossDetector(settings)
        # Target kinds the weak loss signals model (None: every target, as `settings` say).
        self.loss_model_classes = frozenset(loss_model_classes) if loss_model_classes is not None else None
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
        self._catch_up_detected = False  # the box being caught up is a detector's (a look that found it)
        self._lost_reason = ""
        self.reinit = reinit or ReinitSettings()
        # "verified": the loss signals are weighed over time (behaviors.loss_evidence), not latched.
        self.evidence = evidence or LossEvidenceSettings()
        self._evidence = LossEvidence()
        self.label = f"{name}: " if name else ""  # log lines name the sequence or camera
        self._reinit_state = ReinitState()
        self._anchor: np.ndarray | None = None  # the target as the track first saw it (appearance)
        # The keyframe this target was first tracked from: an answer about an older keyframe (a search
        # answer still in flight when the track started) says nothing about this track.
        self._target_since = 0
        # The target as the answers that confirmed the track saw it (a running mean of the confirming
        # candidates' histograms): a person's look drifts with scale and pose over a long track.
        self._confirmed_look: np.ndarray | None = None
        # Recent frame id -> tracker box, lost reason, whether a geometric signal fired on it.
        self._boxes: dict[int, tuple[Box | None, str, bool]] = {}
        self._last_box: Box | None = None
        # Tracker box size over detector box size (log, per axis), learnt from candidates that confirmed
        # the track: detector boxes frame a person differently (wider, feet included) than the tracker.
        self._extent = (0.0, 0.0)
        self._extent_samples = 0
        self._confirmed = False  # "verified": the last answer confirmed the track
        # The verifier is checked once per track against the candidate on the box the track started on
        # (the target by definition: the operator's or ground truth's box, or the verifier's own "yes").
        # One that says "no" to it cannot tell this target apart: its verdicts are not used for this track.
        self._verdicts_checked = False
        self._verdicts_used = True
        # "verified": the detector's misses on the trusted track (behaviors.track_support); off without
        # settings or a POD by size. `_kind` is the target's class, as `start` was told.
        self.support = support if support_pod is not None else None
        self._support_pod = support_pod
        self.keyframe_width = keyframe_width
        self._support = Support()
        self._not_detected = False
        self._kind = ""

    @classmethod
    def from_config(
        cls, config: TrackerConfig, model_dir: Path, tracker_name: str | None = None, **kwargs: object
    ) -> TrackingFrontend:
        """A front-end for `config` (tracker weights are checked now: ModelError if missing)."""
        name = tracker_name or config.name
        create_tracker(name, model_dir)  # fail at start-up, not at the first acquisition
        kwargs.setdefault("policy", config.reinit_policy)  # flight and eval fly the configured policy
        kwargs.setdefault("support_pod", curve_pod())
        return cls(
            lambda: create_tracker(name, model_dir),
            loss_settings(config, name),
            ring_frames=config.ring_buffer_frames,
            max_fast_forward_frames=config.max_fast_forward_frames,
            catch_up_per_frame=config.catch_up_per_frame,
            max_c_box_sizes=config.max_c_box_sizes,
            reinit=reinit_settings(config),
            evidence=loss_evidence_settings(config),
            loss_model_classes=config.loss_model_classes,
            support=support_settings(config),
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

    @property
    def alarm(self) -> str:
        """The first enabled loss signal that fired on the last frame, trusted or not ("" when none): with
        "verified" a weak alarm does not untrust the track at once, but it is a reason to ask for evidence."""
        if self._tracker is None:
            return ""
        return first_reason(self.loss.last_signals, self.loss.settings.enabled)

    def start(self, keyframe_id: int, box: Box, kind: str = "", detected: bool = False) -> bool:
        """Track `box` as seen in frame `keyframe_id` (a new target: the appearance model restarts). `kind`
        is the target's class (the candidate's detector label): for a class outside `loss_model_classes`
        (the classes the weak loss signals were measured on: people) the aspect test is off and the weak
        signals untrust nothing ("" keeps the settings as they are). `detected`: the box is a back-end
        candidate's (its keyframe is the track's first find), not an operator's or ground truth's."""
        if kind and self.loss_model_classes is not None:
            modelled = kind in self.loss_model_classes
            self.loss.settings = replace(self.loss.settings, hold_aspect=modelled)
            self.evidence = replace(self.evidence, weigh_weak=modelled)
        keyframe = self.ring.get(keyframe_id)
        self._anchor = appearance_histogram(keyframe.image, box) if keyframe is not None else None
        self._confirmed_look = None
        self._reinit_state = ReinitState()
        self._extent, self._extent_samples = (0.0, 0.0), 0
        self._verdicts_checked = False
        self._verdicts_used = True
        self._target_since = keyframe_id
        self._kind = kind
        return self._begin(keyframe_id, box, keep_template=False, detected=detected)

    def apply_candidates(self, keyframe_id: int, detections: Sequence[Detection]) -> Detection | None:
        """Re-initialise on the candidate closest to the last trusted box (C_box), or with policy "score"
        the highest detector score (the reference code's choice, ungated). With C_box, a candidate
        farther than `max_c_box_sizes` x (1 + seconds lost) x (w + h) of the last trusted box is not used.
        None when nothing was usable (or the keyframe is older than this target's track)."""
        if keyframe_id < self._target_since:
            return None
        if self.policy == "verified":
            decision = self.judge_candidates(keyframe_id, detections)
            if decision is None or decision.action is not ReinitAction.REINIT or decision.index is None:
                return None
            return detections[decision.index]
        if self.policy == "score":
            chosen = select_by_score(detections)
        else:
            if self.last_trusted_box is None:
                return None  # no trusted box to compare with: first acquisition is the behaviour's call
            prev = self.last_trusted_box
            chosen = select_by_c_box(prev, detections)
            keyframe = self.ring.get(keyframe_id)
            lost_for = (
                max(0.0, keyframe.capture_time - self.last_trusted_time) if keyframe is not None else 0.0
            )
            # The longer the target has been lost, the farther it may have gone: the gate grows by its
            # base size every second since the last trusted box.
            gate = self.max_c_box_sizes * (1.0 + lost_for) * (prev.w + prev.h)
            if chosen is not None and c_box(prev, chosen.box) > gate:
                # Nothing near where the target was: re-initialising on it would follow whoever else
                # is in view (a detector's "person" is not the described person); stay lost instead.
                log.info(
                    "%snearest candidate is %.0f px (C_box) from the last trusted box, gate %.0f: not used",
                    self.label,
                    c_box(prev, chosen.box),
                    gate,
                )
                self.stats.rejected_candidates += 1
                return None
        if chosen is None:
            return None
        # The appearance model restarts from the candidate: a detector box frames the target differently
        # from the tracker's, and keeping the old model made every re-initialisation look lost at once.
        return chosen if self._begin(keyframe_id, chosen.box, keep_template=False) else None

    def to_tracker_convention(self, box: Box) -> Box:
        """A detector box resized (about its centre) the way this track's confirmed candidates differed."""
        if self._extent_samples == 0:
            return box
        sw, sh = math.exp(self._extent[0]), math.exp(self._extent[1])
        return Box.from_center(box.cx, box.cy, box.w * sw, box.h * sh)

    def box_at(self, frame_id: int) -> Box | None:
        """The tracker's box on a recent frame (None when it had none or the frame is too old)."""
        return self._boxes.get(frame_id, (None, "idle", False))[0]

    def judge_candidates(
        self, keyframe_id: int, detections: Sequence[Detection], refused: Collection[int] = ()
    ) -> ReinitDecision | None:
        """The "verified" policy on one answer (`behaviors.reinit_policy`), carried out: a confirmation
        withdraws a latched loss, a re-initialisation starts on the winner in the tracker's convention.
        Candidates at indices in `refused` (the mission's: not acceptable as the described target) count
        as a "no": evidence about the track, never a winner. None when there is no track to judge, the
        keyframe has left the ring, or it is older than this target's track."""
        keyframe = self.ring.get(keyframe_id)
        if (
            keyframe is None
            or self._tracker is None
            or self._catch_up is not None
            or keyframe_id < self._target_since
        ):
            return None
        track_box, lost_reason, geometric = self._boxes.get(keyframe_id, (None, "idle", False))
        lost = bool(lost_reason)
        boxes = [self.to_tracker_convention(d.box) for d in detections]
        verdicts = [d.verdict for d in detections]
        if not self._verdicts_checked and track_box is not None and not lost:
            agree = self.reinit.agree_iou
            on_track = [
                v
                for box, v in sorted(zip(boxes, verdicts, strict=True), key=lambda bv: -iou(bv[0], track_box))
                if same_object(box, track_box, agree)
            ]
            if on_track:
                self._verdicts_checked = True
                self._verdicts_used = on_track[0] is not Verdict.NO
                if not self._verdicts_used:
                    self.stats.verdicts_ignored += 1
                    log.info(
                        "%sthe verifier said no to the tracked target at frame %d: its verdicts are not "
                        "used for this track",
                        self.label,
                        keyframe_id,
                    )
        if not lost and track_box is not None and self._weigh_support(keyframe, track_box, boxes):
            lost = True  # from this answer on: a candidate elsewhere may beat it, nothing on it confirms it
        if not self._verdicts_used:
            verdicts = [Verdict.UNCERTAIN] * len(detections)
        verdicts = [Verdict.NO if i in refused else v for i, v in enumerate(verdicts)]
        track = TrackEvidence(
            box=track_box,
            lost=lost,
            appearance=self._distance(keyframe.image, track_box),
            reference=self.last_trusted_box,
            gate_px=self._gate(keyframe),
            degraded=geometric or lost_reason in GEOMETRIC_SIGNALS,
        )
        evidence = [
            CandidateEvidence(box, verdict, self._distance(keyframe.image, box), detected=d.box)
            for box, verdict, d in zip(boxes, verdicts, detections, strict=True)
        ]
        decision = decide(self._reinit_state, track, evidence, self.reinit)
        self._reinit_state = decision.state
        self._confirmed = decision.action is ReinitAction.CONFIRM
        self.stats.decisions[decision.action.value] = self.stats.decisions.get(decision.action.value, 0) + 1
        if (
            decision.action in (ReinitAction.CONFIRM, ReinitAction.REINIT)
            and decision.index is not None
            and track_box is not None
            and same_object(boxes[decision.index], track_box, self.reinit.agree_iou)
        ):
            detected = detections[decision.index].box
            self.stats.framing.append((keyframe_id, track_box, framing_ratio(track_box, detected)))
        if decision.action is ReinitAction.CONFIRM and decision.index is not None:
            if not decision.state.outgrown:  # a box the policy doubts is no sample of the framing
                self._learn_extent(track_box, detections[decision.index].box)
            self._learn_look(keyframe.image, boxes[decision.index])
            if lost or self._lost_reason:
                self._withdraw_loss()
            elif self.policy == "verified":
                self._refresh_references()
        elif decision.action is ReinitAction.REINIT and decision.index is not None:
            log.info(
                "%sre-initialising on candidate %d at frame %d: %s",
                self.label,
                decision.index,
                keyframe_id,
                decision.reason,
            )
            if not self._begin(keyframe_id, boxes[decision.index], keep_template=False):
                return None
        return decision

    def _weigh_support(self, keyframe: Frame, track_box: Box, boxes: Sequence[Box]) -> bool:
        """One answer about a keyframe the track was trusted on, as a look at the tracked box: True when the
        detector's misses have now untrusted the track ("not_detected", latched until a candidate on the track
        or a re-initialisation)."""
        if self.support is None or self._support_pod is None or not track_box.is_valid():
            return False
        # Any candidate touching the box: among people standing together the detector frames them differently
        # from the tracker (measured: vit on group1_1 untrusted on target), while a box on a roof or on bare
        # ground has none at all.
        found = any(b.is_valid() and iou(b, track_box) > 0 for b in boxes)
        size = math.sqrt(track_box.area) * min(1.0, self.keyframe_width / keyframe.image.shape[1])
        pod = self._support_pod(self._kind, size)
        if pod is None:
            return False
        self._support = judge_answer(
            self._support, keyframe.frame_id, keyframe.capture_time, found, pod, self.support
        )
        if self._not_detected or not self._support.unsupported(keyframe.capture_time, self.support):
            return False
        self._not_detected = True
        self.stats.not_detected += 1
        log.info(
            "%sno candidate on the track in %d answers over %.1f s (%d found, %d missed on this track; the curve "
            "finds a %.0f px %s %.0f %% of the time): the tracker holds what the detector does not see",
            self.label,
            self._support.run,
            keyframe.capture_time - (self._support.since_s or keyframe.capture_time),
            self._support.hits,
            self._support.misses,
            size,
            self._kind,
            100 * pod,
        )
        return True

    def _distance(self, image: np.ndarray, box: Box | None) -> float | None:
        """Appearance distance to the target: as first seen, or as last confirmed, whichever is nearer."""
        if self._anchor is None or box is None:
            return None
        hist = appearance_histogram(image, box)
        if hist is None:
            return None
        models = [m for m in (self._anchor, self._confirmed_look) if m is not None]
        return min(appearance_distance(m, hist) for m in models)

    def _gate(self, keyframe: Frame) -> float:
        prev = self.last_trusted_box
        if prev is None:
            return math.inf
        lost_for = max(0.0, keyframe.capture_time - self.last_trusted_time)
        return self.max_c_box_sizes * (1.0 + lost_for) * (prev.w + prev.h)

    def _learn_extent(self, track_box: Box | None, detector_box: Box) -> None:
        if track_box is None or not track_box.is_valid() or not detector_box.is_valid():
            return
        sample = (math.log(track_box.w / detector_box.w), math.log(track_box.h / detector_box.h))
        self._extent_samples += 1
        rate = 1.0 / min(self._extent_samples, 10)  # a running mean over the last ~10 confirmations
        self._extent = tuple(  # type: ignore[assignment]
            (1.0 - rate) * old + rate * new for old, new in zip(self._extent, sample, strict=True)
        )

    def _learn_look(self, image: np.ndarray, box: Box) -> None:
        hist = appearance_histogram(image, box)
        if hist is None:
            return
        old = self._confirmed_look
        self._confirmed_look = hist if old is None else 0.5 * old + 0.5 * hist  # the last few confirmations

    def _refresh_references(self) -> None:
        """A trusted track confirmed: the loss detector's shape and appearance references follow the
        confirmed target (a pose or scale change since the start is not a loss), and any alarm time
        accumulated so far is cleared."""
        newest = self.ring.newest
        if newest is not None and self._last_box is not None:
            self.loss.refresh(newest.image, self._last_box)
            self._evidence = LossEvidence(time_s=newest.capture_time)

    def _withdraw_loss(self) -> None:
        """A candidate on the track supports it: trust it again from the newest frame, with the appearance
        and shape references restarted there (the old ones are what fired)."""
        newest = self.ring.newest
        self._lost_reason = ""
        self._not_detected = False
        if newest is not None:  # a find on the track's record, and trusted again from the newest frame
            self._support = judge_answer(self._support, newest.frame_id, newest.capture_time, True, 0.0)
        self.stats.confirmations += 1
        self._evidence = LossEvidence(time_s=newest.capture_time if newest is not None else None)
        if newest is not None and self._last_box is not None:
            self.loss.reset(newest.image, self._last_box)
            self.last_trusted_box = self._last_box
            self.last_trusted_frame_id = newest.frame_id
            self.last_trusted_time = newest.capture_time

    def stop(self) -> None:
        self._tracker = None
        self._catch_up = None
        self._lost_reason = ""
        self.last_trusted_box = None
        self.last_trusted_frame_id = None
        self._anchor = None
        self._confirmed_look = None
        self._reinit_state = ReinitState()
        self._confirmed = False
        self._evidence = LossEvidence()
        self._support = Support()
        self._not_detected = False

    def _begin(self, keyframe_id: int, box: Box, keep_template: bool, detected: bool = True) -> bool:
        if not box.is_valid():
            log.warning("%signoring invalid box %s for frame %d", self.label, box, keyframe_id)
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
            log.warning("%scannot start on frame %d: %s", self.label, keyframe_id, exc)
            return False
        self._catch_up = catch_up
        self._catch_up_keeps_template = keep_template
        self._catch_up_detected = detected
        self._confirmed = False
        return True

    def feed(self, frame: Frame) -> TrackResult:
        result = self._feed(frame)
        self._last_box = result.box
        geometric = result.box is not None and any(
            self.loss.last_signals.get(name) for name in GEOMETRIC_SIGNALS & self.loss.settings.enabled
        )
        self._boxes[frame.frame_id] = (result.box, result.lost_reason, geometric)
        oldest = frame.frame_id - self.ring.capacity
        for stale in [k for k in self._boxes if k <= oldest]:
            del self._boxes[stale]
        return result

    def _feed(self, frame: Frame) -> TrackResult:
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
        if self.policy == "verified":
            reason = self._weigh(frame.capture_time) or (NOT_DETECTED if self._not_detected else "")
        if self._lost_reason and self.policy != "verified":
            reason = self._lost_reason
        elif reason:
            if not self._lost_reason:
                self.stats.loss_events += 1
                log.info("%starget lost at frame %d: %s", self.label, frame.frame_id, reason)
            self._lost_reason = reason
        else:
            self._lost_reason = ""  # "verified" only: the signals judge each frame (see the module docstring)
        if not reason and step.box is not None:
            self.last_trusted_box = step.box
            self.last_trusted_frame_id = frame.frame_id
            self.last_trusted_time = frame.capture_time
        alarm = self.alarm if self.policy == "verified" and not reason else ""
        return TrackResult(frame.frame_id, frame.capture_time, step.box, step.score, step.ok, reason, alarm)

    def _weigh(self, time_s: float) -> str:
        """With "verified": the loss detector's signals on this frame weighed over time (persistence for a
        weak signal alone, hysteresis before trusting again); "" while trusted."""
        enabled = self.loss.settings.enabled
        fired = [name for name in SIGNALS if name in enabled and self.loss.last_signals.get(name)]
        if self._confirmed:
            # The last answer's candidate on the track outweighs a score or appearance alarm.
            fired = [name for name in fired if name not in APPEARANCE_SIGNALS]
        self._evidence = judge_frame(self._evidence, time_s, fired, self.evidence)
        return self._evidence.reason

    def _take_over(self, frame: Frame) -> TrackResult:
        """The caught-up tracker replaces the current one; its box refers to this frame."""
        assert self._catch_up is not None
        catch_up, self._catch_up = self._catch_up, None
        step = catch_up.last.step
        self._tracker = catch_up.tracker
        self._lost_reason = ""
        self._not_detected = False
        self.stats.reinits += 1
        # From its keyframe on, the track is the new one: an answer about a keyframe the catch-up passed
        # through, arriving now, judges the new track's box there (not the replaced track's, nor "no
        # track" after a first start, which let any "yes" beat it).
        for frame_id in [f for f in self._boxes if catch_up.keyframe_id <= f < frame.frame_id]:
            self._boxes[frame_id] = (catch_up.box_at(frame_id), "", False)
        keyframe = self.ring.get(catch_up.keyframe_id)
        self._support = started(
            catch_up.keyframe_id,
            keyframe.capture_time if keyframe else frame.capture_time,
            found=self._catch_up_detected,
        )
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
            self.loss.reset(
                keyframe.image, catch_up.keyframe_box, self._catch_up_keeps_template, current=step.box
            )
        else:
            self.loss.reset(frame.image, step.box, self._catch_up_keeps_template)
        # Judge the caught-up box like any other step (score, left frame, appearance ...).
        reason = self.loss.check(frame.image, step)
        if self.policy == "verified":
            self._evidence = LossEvidence(time_s=frame.capture_time)  # a new track's account
            reason = self._weigh(frame.capture_time)
        if reason:
            self._lost_reason = reason
            self.stats.loss_events += 1
        else:
            self.last_trusted_box = step.box
            self.last_trusted_frame_id = frame.frame_id
            self.last_trusted_time = frame.capture_time
        return TrackResult(frame.frame_id, frame.capture_time, step.box, step.score, step.ok, reason)
