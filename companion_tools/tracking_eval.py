"""Evaluating the tracking front-end on annotated sequences (the `eval` command's engine).

One run feeds a sequence's frames through `TrackingFrontend` exactly as the live loop does: the track
starts on the first ground-truth box (or the back-end's best verified candidate), and whenever the
front-end reports the target lost it asks a detector for candidates on the current frame and applies
the answer `delay_frames` later (latency-compensated, C_box or highest-score policy). Reported:
- mIoU as the paper defines it (`behaviors.tracking_metrics`): only trusted boxes count as reported
  (the drone follows nothing else); `miou_any_box` also counts the boxes flagged lost;
- FPS: frames / time of the whole onboard loop (decode, resize, tracker, loss detection, catch-up);
  the detector is excluded because it runs on the back-end, not on the drone;
- edge FPS: live-frame tracker updates / time inside `update()` alone;
- re-inits and loss events, and the loss reasons seen.

`signal_table` measures what each loss signal adds: a run without re-initialisation records every
signal on every frame, then each signal is scored against the frames where the tracker was really off
target (IoU with ground truth below `LOST_IOU`).
"""

from __future__ import annotations

import json
import math
import re
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from behaviors.candidate_selection import alike, select_first_acquisition, settle_early_choice
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box, iou
from behaviors.loss_evidence import LossEvidence, judge_frame
from behaviors.query_region import redetect_region
from behaviors.track_result import TrackResult
from behaviors.tracking_metrics import MiouResult, mean_iou, pooled_miou
from companion.config import TrackerConfig
from companion.vision.frame_sources import FolderSource, Frame
from companion.vision.loss_detection import SIGNALS, LossDetector
from companion.vision.trackers import create_tracker
from companion.vision.tracking_frontend import (
    Policy,
    TrackingFrontend,
    curve_pod,
    loss_evidence_settings,
    loss_settings,
    reinit_settings,
    support_settings,
)

LOST_IOU = 0.1  # a tracker box overlapping the ground truth less than this is off target
ON_TARGET_IOU = 0.5  # a box overlapping the ground truth this much is on the target
OFF_TARGET_IOU = 0.3  # ...and under this much, on something else

InitMode = Literal["gt", "prompt"]

# Detector: image (already resized) and frame id -> candidates in that image's pixels.
# (keyframe image, frame id, region to look in or None for the whole frame) -> the back-end's answer.
DetectFn = Callable[[np.ndarray, int, Box | None], list[Detection]]


@dataclass(frozen=True)
class SequenceData:
    name: str
    path: Path
    ground_truth: tuple[Box | None, ...]  # native pixels; None where the file says nan
    referring: str
    fps: float


def _parse_box(line: str) -> Box | None:
    values = [float(v) for v in re.split(r"[,\s]+", line.strip()) if v]
    if len(values) != 4:
        raise ValueError(f"expected x,y,w,h, got {line!r}")
    box = Box(*values)
    return box if box.is_valid() else None


def load_sequence(path: Path) -> SequenceData:
    """A sequence folder: frames/, groundtruth.txt (x,y,w,h or nan), referring.txt, source.json."""
    gt_file = path / "groundtruth.txt"
    if not gt_file.is_file():
        raise FileNotFoundError(
            f"{path}: no groundtruth.txt (expected the layout of ../shared/data/sequences)"
        )
    lines = [line for line in gt_file.read_text().splitlines() if line.strip()]
    gt = tuple(_parse_box(line) for line in lines)
    referring = (path / "referring.txt").read_text().strip() if (path / "referring.txt").is_file() else ""
    source = json.loads((path / "source.json").read_text()) if (path / "source.json").is_file() else {}
    # UAV123_10fps is subsampled to 10 fps; the other benchmarks were recorded at 30 fps.
    fps = 10.0 if "10fps" in str(source.get("dataset", "")).lower() else 30.0
    return SequenceData(path.name, path, gt, referring, fps)


def parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise ValueError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    return int(match.group(1)), int(match.group(2))


def parse_sweep(text: str) -> list[float]:
    """'0.3:0.95:0.05' -> [0.3, 0.35, ..., 0.95] (inclusive)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"sweep {text!r}: expected START:STOP:STEP, e.g. 0.3:0.95:0.05")
    start, stop, step = (float(p) for p in parts)
    if step <= 0 or stop < start:
        raise ValueError(f"sweep {text!r}: need STEP > 0 and STOP >= START")
    count = int(math.floor((stop - start) / step + 1e-9)) + 1
    return [round(start + i * step, 6) for i in range(count)]


@dataclass(frozen=True)
class EvalSettings:
    tracker: str = "nano"
    threshold: float | None = None  # t_c override; None: the configuration's value for this tracker
    signals: frozenset[str] = frozenset(SIGNALS)
    policy: Policy = "verified"
    size: tuple[int, int] | None = None  # resize frames (and boxes) to WIDTHxHEIGHT
    delay_frames: int = 0  # back-end latency in frames
    # Prompt init: a search's fast-stage answer arrives this many frames after its keyframe and starts a
    # provisional track that the final answer (`delay_frames`) confirms, moves or ends, as the mission
    # does with [backend] early_answer; None: searches wait for the final answer.
    early_frames: int | None = None
    keyframe_interval: int = 5  # frames between detector requests
    # ... while nothing is tracked or the track is lost ([backend] search_interval_s); 0: the above
    search_interval: int = 0
    max_in_flight: int = 1  # requests out at once ([backend] max_requests_in_flight)
    compensate: bool = True
    max_frames: int | None = None
    occlude: bool = False  # hide the target for 1.5 s from a third of the way in (see occlusion_span)
    reverify_interval: int = 0  # c_box/score: also re-initialise from candidates every N frames while trusted
    init: InitMode = "gt"  # first box: ground truth, or the back-end's answer to referring.txt
    accept_uncertain: bool = False  # prompt init: may an "uncertain" candidate start the track
    # A re-detection after a loss looks where flight's does (`behaviors.query_region`): the last trusted box
    # grown this much, growing to the whole frame over `region_full_frame_s`; None: always the whole frame.
    region_scale: float | None = None
    region_full_frame_s: float = 4.0
    # The target's class as a ground-truth start knows it (the description's superset): the loss signals
    # model a person's shape only for people (`[tracker] loss_model_classes`). A prompt start takes the chosen
    # candidate's label.
    target_kind: str = ""


@dataclass(frozen=True)
class AcquisitionKeyframe:
    """One back-end answer while looking for the described target (--init prompt)."""

    frame_id: int  # the keyframe the answer refers to
    answered_frame_id: int  # the frame on which the answer arrived (latency)
    candidates: int
    confirmed: int  # candidates the verifier said yes to
    target_found: bool  # some candidate is the described target (IoU >= ON_TARGET_IOU with ground truth)
    chosen_iou: float | None  # the chosen candidate's IoU with ground truth; None when none was chosen
    final: bool = True  # false: the fast stage's answer (see EvalSettings.early_frames)
    # What the back-end said about the chosen candidate: its verdict with the judged words' results, where
    # it stands (placement), and the description's words nothing judged.
    verdict: str = ""
    justification: str = ""
    placement: bool | None = None
    unjudged: tuple[str, ...] = ()
    alike: int = 0  # others the search could have taken as well: the detector's score chose among them


@dataclass
class SequenceResult:
    sequence: str
    tracker: str
    frames: int
    miou: float  # trusted boxes only: a box flagged lost counts as no box
    miou_any_box: float  # every box the tracker gave, lost or not
    fps: float
    edge_fps: float
    reinits: int
    loss_events: int
    false_tracks: int
    missed_frames: int
    detector_calls: int
    loss_reasons: dict[str, int] = field(default_factory=dict)
    ious: list[float | None] = field(default_factory=list, repr=False)
    gt_frames: int = 0
    iou_sum: float = 0.0
    # Each re-initialisation by where the track was and where it went (IoU >= ON_TARGET_IOU is "target").
    reinit_outcomes: dict[str, int] = field(default_factory=dict)
    confirmations: int = 0  # "verified": losses withdrawn because a candidate on the track supported it
    decisions: dict[str, int] = field(default_factory=dict)  # "verified": answers per action
    first_box_s: float | None = None  # sequence seconds until the first reported box (prompt init)
    acquisition: list[AcquisitionKeyframe] = field(default_factory=list)
    # (track's IoU with ground truth, framing ratio) on every answer the track's own candidate decided
    # (`FrontendStats.framing`): what the re-framing bound `reinit_max_framing_ratio` rests on.
    framing: list[tuple[float, float]] = field(default_factory=list)


class DetectionCache:
    """Detector answers per (sequence, frame, size, region), so policy comparisons and sweeps share them."""

    def __init__(self, detect: DetectFn) -> None:
        self._detect = detect
        self._cache: dict[tuple[str, int, tuple[int, int], tuple[int, ...]], list[Detection]] = {}
        self.calls = 0
        self.seconds: list[float] = []  # wall time of each real call: the back-end's answer time here

    def get(
        self, sequence: str, image: np.ndarray, frame_id: int, region: Box | None = None
    ) -> list[Detection]:
        where = tuple(round(v) for v in region.xyxy()) if region is not None else ()
        key = (sequence, frame_id, (image.shape[1], image.shape[0]), where)
        if key not in self._cache:
            self.calls += 1
            started = time.perf_counter()
            self._cache[key] = self._detect(image, frame_id, Box.from_xyxy(*where) if where else None)
            self.seconds.append(time.perf_counter() - started)
        return self._cache[key]


def acquisition_ceiling(reference: SequenceResult, delay_frames: int) -> MiouResult:
    """What a perfect acquirer could score with answers `delay_frames` late: the ground-truth-initialised
    run's IoU from the frame the first answer (on the first frame) can arrive, over all frames with
    ground truth; the frames before it count 0, as they do for --init prompt."""
    ious = reference.ious
    gt_frames = sum(v is not None for v in ious)
    kept = sum(v for v in ious[max(0, delay_frames) :] if v is not None)
    return MiouResult(kept / gt_frames if gt_frames else float("nan"), kept, gt_frames, 0, 0)


def _scaled(box: Box | None, sx: float, sy: float) -> Box | None:
    return box.scaled(sx, sy) if box is not None else None


def occlusion_span(seq: SequenceData) -> range:
    """Frames (0-based) where the occlusion stress test hides the target: 1.5 s from a third of the way in."""
    start = len(seq.ground_truth) // 3
    return range(start, min(len(seq.ground_truth) - 1, start + round(1.5 * seq.fps)))


def _occluded(image: np.ndarray, box: Box) -> np.ndarray:
    """The image with the target painted over by the mean colour of its surroundings plus noise, so a
    tracker sees background where the target was (a person walking behind a tree, a wave, a roof)."""
    h, w = image.shape[:2]
    inner = box.expanded(0.15 * max(box.w, box.h)).clamped(w, h)
    outer = inner.expanded(max(inner.w, inner.h) * 0.5).clamped(w, h)
    x1, y1, x2, y2 = (int(round(v)) for v in inner.xyxy())
    ox1, oy1, ox2, oy2 = (int(round(v)) for v in outer.xyxy())
    ring = image[oy1:oy2, ox1:ox2].reshape(-1, image.shape[2]).astype(np.float32)
    mean = ring.mean(axis=0) if len(ring) else np.full(image.shape[2], 114.0, np.float32)
    out = image.copy()
    rng = np.random.default_rng(x1 * 7919 + y1)  # deterministic per position
    noise = rng.normal(0.0, 12.0, (max(0, y2 - y1), max(0, x2 - x1), image.shape[2]))
    out[y1:y2, x1:x2] = np.clip(mean + noise, 0, 255).astype(np.uint8)
    return out


def ground_truth_for(seq: SequenceData, settings: EvalSettings) -> list[Box | None]:
    """Native-pixel ground truth as the run sees it: nan (None) while the occlusion test hides the target."""
    gt = list(seq.ground_truth)
    if settings.occlude:
        for i in occlusion_span(seq):
            gt[i] = None
    return gt


def _frames(seq: SequenceData, settings: EvalSettings) -> Iterable[tuple[Frame, float, float]]:
    """Frames (occluded and resized if asked) with the scale factors from native pixels."""
    source = FolderSource(seq.path, stop_after=settings.max_frames, fps=seq.fps)
    hidden = occlusion_span(seq) if settings.occlude else range(0)
    while True:
        frame = source.read()
        if frame is None:
            return
        index = frame.frame_id - 1
        target = seq.ground_truth[index] if index < len(seq.ground_truth) else None
        if index in hidden and target is not None:
            frame = Frame(frame.frame_id, frame.capture_time, _occluded(frame.image, target))
        sx = sy = 1.0
        if settings.size is not None:
            h, w = frame.image.shape[:2]
            sx, sy = settings.size[0] / w, settings.size[1] / h
            frame = Frame(frame.frame_id, frame.capture_time, cv2.resize(frame.image, settings.size))
        yield frame, sx, sy


def make_frontend(
    config: TrackerConfig, model_dir: Path, settings: EvalSettings, name: str = ""
) -> TrackingFrontend:
    thresholds = dict(config.score_threshold)
    if settings.threshold is not None:
        thresholds[settings.tracker] = settings.threshold
    cfg = config.model_copy(update={"score_threshold": thresholds, "loss_signals": sorted(settings.signals)})
    name = settings.tracker
    return TrackingFrontend(
        lambda: create_tracker(name, model_dir),
        loss_settings(cfg, name),
        ring_frames=cfg.ring_buffer_frames,
        max_fast_forward_frames=cfg.max_fast_forward_frames,
        catch_up_per_frame=cfg.catch_up_per_frame,
        policy=settings.policy,
        compensate=settings.compensate,
        max_c_box_sizes=cfg.max_c_box_sizes,
        reinit=reinit_settings(cfg),
        name=name,
        evidence=loss_evidence_settings(cfg),
        loss_model_classes=cfg.loss_model_classes,
        support=support_settings(cfg),
        support_pod=curve_pod(),
    )


def first_candidate(detections: Sequence[Detection], accept_uncertain: bool = False) -> Detection | None:
    """First acquisition as in flight (`behaviors.candidate_selection.select_first_acquisition`, the
    mission's choice without its rejection memory)."""
    return select_first_acquisition(detections, accept_uncertain)


def _outcome(before: float, after: float) -> str:
    src = "target" if before >= ON_TARGET_IOU else "off"
    dst = "target" if after >= ON_TARGET_IOU else "other"
    return f"{src}->{dst}"


def evaluate_sequence(
    seq: SequenceData,
    config: TrackerConfig,
    model_dir: Path,
    settings: EvalSettings,
    detections: DetectionCache | None = None,
    init_from_detector: bool = False,
    progress: Callable[[int], None] | None = None,
    early_detections: DetectionCache | None = None,
) -> SequenceResult:
    """One run over `seq`. The track starts on the first ground-truth box, or with `settings.init`
    "prompt" (or `init_from_detector`) on the back-end's answer to the sequence's description: answers
    are asked for every `keyframe_interval` frames and arrive `delay_frames` later while the sequence
    keeps running (the live frames are not held back for the back-end, as in flight). With
    `settings.early_frames` a search's fast-stage answer (`early_detections`, else the same answer)
    arrives first and may start a provisional track."""
    from_prompt = settings.init == "prompt" or init_from_detector
    frontend = make_frontend(config, model_dir, settings, seq.name)
    predicted: list[Box | None] = []
    predicted_any: list[Box | None] = []  # the tracker's box even when flagged lost (the paper's view)
    gt_used: list[Box | None] = []
    reasons: Counter[str] = Counter()
    outcomes: Counter[str] = Counter()
    acquisition: list[AcquisitionKeyframe] = []
    # As the companion's back-end worker (companion.cloud.backend_worker) sends them: up to `max_in_flight`
    # requests out (lands at frame, keyframe, detections); a keyframe asked for while all are out waits
    # (keyframe, image, region), replaced by any newer one, and goes out when an answer is back.
    # Entries are (lands at frame, keyframe, detections, final); an early answer shares its final one's slot.
    in_flight: list[tuple[int, int, list[Detection], bool]] = []
    provisional: tuple[int, Box] | None = None  # (keyframe, box chosen) of a track started early
    early_refused = False  # the final answer refused an early start: searches wait for final answers
    waiting: tuple[int, np.ndarray, Box | None] | None = None
    last_request = -(10**9)
    was_trusted = False
    had_alarm = False
    asked: list[float] = []  # seconds of each back-end request
    started = time.perf_counter()
    native_gt = ground_truth_for(seq, settings)
    if from_prompt and detections is None:
        raise ValueError("--init prompt needs a detector (the back-end pipeline)")

    def query_region(frontend: TrackingFrontend, result: TrackResult, frame: Frame) -> Box | None:
        # As in flight (behaviors.mission): a search or a check of a trusted track looks at the whole
        # frame, a re-detection after a loss at the region around the last trusted box.
        last = frontend.last_trusted_box
        if settings.region_scale is None or not frontend.tracking or result.trusted or last is None:
            return None
        height, width = frame.image.shape[:2]
        lost_for = frame.capture_time - frontend.last_trusted_time
        return redetect_region(
            last, lost_for, settings.region_scale, settings.region_full_frame_s, width, height
        )

    def ask(frame_id: int, image: np.ndarray, region: Box | None) -> list[Detection]:
        assert detections is not None  # only asked when there is a back-end to ask
        t0 = time.perf_counter()
        found = detections.get(seq.name, image, frame_id, region)
        asked.append(time.perf_counter() - t0)
        return found

    def schedule(lands: int, keyframe: int, found: list[Detection], final: bool) -> None:
        at = next((i for i, entry in enumerate(in_flight) if entry[0] > lands), len(in_flight))
        in_flight.insert(at, (lands, keyframe, found, final))

    def send(keyframe: int, image: np.ndarray, region: Box | None, now: int) -> None:
        found = ask(keyframe, image, region)
        if settings.early_frames is not None and from_prompt and not frontend.tracking and not early_refused:
            if early_detections is not None:
                t0 = time.perf_counter()
                early = early_detections.get(seq.name, image, keyframe, region)
                asked.append(time.perf_counter() - t0)
            else:
                early = found  # the configured verifier stands in for the fast stage too
            schedule(now + settings.early_frames, keyframe, early, False)
        schedule(now + settings.delay_frames, keyframe, found, True)

    def gt_at(frame_id: int) -> Box | None:
        return gt_used[frame_id - 1] if 0 < frame_id <= len(gt_used) else None

    def looked(
        keyframe: int, found: list[Detection], frame_id: int, final: bool, picked: Detection | None
    ) -> None:
        """Records an answer while looking and the candidate it starts (or keeps) the track on."""
        truth = gt_at(keyframe)
        acquisition.append(
            AcquisitionKeyframe(
                keyframe,
                frame_id,
                len(found),
                sum(d.verdict is Verdict.YES for d in found),
                truth is not None and any(iou(d.start_box, truth) >= ON_TARGET_IOU for d in found),
                (iou(picked.start_box, truth) if truth is not None else 0.0) if picked is not None else None,
                final,
                picked.verdict.value if picked is not None else "",
                picked.justification if picked is not None else "",
                picked.placement_ok if picked is not None else None,
                picked.unjudged if picked is not None else (),
                alike(found, picked, settings.accept_uncertain) if picked is not None else 0,
            )
        )

    def answer(keyframe: int, found: list[Detection], frame_id: int, final: bool = True) -> None:
        nonlocal provisional, early_refused
        if final and provisional is not None and provisional[0] == keyframe:
            # As the mission settles an early start: kept while the final verdicts accept it, else moved to
            # their choice, or ended when they accept no one.
            early_box, provisional = provisional[1], None
            chosen, kept = settle_early_choice(
                found, early_box, lambda ds: first_candidate(ds, settings.accept_uncertain)
            )
            looked(keyframe, found, frame_id, final, chosen)
            if kept:
                early_refused = False
            elif chosen is None:
                frontend.stop()
                early_refused = True
            else:
                frontend.start(keyframe, chosen.start_box, chosen.label)
            return
        if from_prompt and not frontend.tracking:
            chosen = first_candidate(found, settings.accept_uncertain)
            looked(keyframe, found, frame_id, final, chosen)
            if chosen is not None and frontend.start(keyframe, chosen.start_box, chosen.label) and not final:
                provisional = (keyframe, chosen.box)
            return
        if not final:  # a fast stage's verdicts only ever start a search's track
            return
        before = frontend.box_at(keyframe)
        chosen = frontend.apply_candidates(keyframe, found)
        truth = gt_at(keyframe)
        if chosen is not None and truth is not None:
            outcomes[_outcome(iou(before, truth) if before is not None else 0.0, iou(chosen.box, truth))] += 1

    for frame, sx, sy in _frames(seq, settings):
        index = frame.frame_id - 1
        gt = _scaled(native_gt[index], sx, sy) if index < len(native_gt) else None
        gt_used.append(gt)
        result = frontend.feed(frame)
        box = result.box if result.trusted else None
        if index == 0 and not from_prompt:
            init = _scaled(seq.ground_truth[0], sx, sy)
            if init is not None and frontend.start(frame.frame_id, init, settings.target_kind):
                box = init  # the initialisation frame reports the box it started on
        if result.lost_reason and result.lost_reason not in ("idle", "acquiring"):
            reasons[result.lost_reason] += 1
        while in_flight and in_flight[0][0] <= frame.frame_id:
            _, keyframe, found, final = in_flight.pop(0)
            if final and waiting is not None:
                sent_id, sent_image, sent_region = waiting
                waiting = None
                send(sent_id, sent_image, sent_region, frame.frame_id)
            answer(keyframe, found, frame.frame_id, final)
        if settings.policy == "verified":
            # Every answer is evidence for or against the track, so keyframes go out while trusted too.
            needs_candidates = frontend.tracking
        else:
            reverify = settings.reverify_interval > 0 and result.trusted
            needs_candidates = frontend.last_trusted_box is not None and (not result.trusted or reverify)
        needs_candidates = (needs_candidates and index > 0) or (from_prompt and not frontend.tracking)
        # As in flight, where losing the target sends a re-detection query at once (behaviors.mission).
        flagged = bool(result.lost_reason) and result.lost_reason not in ("idle", "acquiring")
        # With "verified" a signal that starts firing on a trusted track asks for evidence at once too (as
        # the mission's track check does in flight).
        alarm = bool(result.alarm)
        newly_lost = (flagged and was_trusted) or (alarm and not had_alarm)
        was_trusted, had_alarm = result.trusted, alarm
        reverify_now = settings.policy != "verified" and settings.reverify_interval > 0 and result.trusted
        interval = settings.reverify_interval if reverify_now else settings.keyframe_interval
        if not result.trusted and settings.search_interval:
            # Nothing tracked, or the track is lost: a keyframe is the only way to find it (as the mission's
            # SEARCHING and LOST ask).
            interval = settings.search_interval
        if (
            detections is not None
            and needs_candidates
            and (frame.frame_id - last_request >= interval or (newly_lost and frame.frame_id > last_request))
            and not frontend.catching_up
        ):
            region = query_region(frontend, result, frame)
            last_request = frame.frame_id
            if settings.delay_frames > 0 and sum(e[3] for e in in_flight) >= settings.max_in_flight:
                waiting = (frame.frame_id, frame.image, region)
            elif settings.delay_frames == 0:
                answer(frame.frame_id, ask(frame.frame_id, frame.image, region), frame.frame_id)
            else:
                send(frame.frame_id, frame.image, region, frame.frame_id)
        predicted.append(box)
        predicted_any.append(box if box is not None else result.box)
        if progress is not None:
            progress(1)
    loop_seconds = time.perf_counter() - started - sum(asked)
    metric: MiouResult = mean_iou(predicted, gt_used)
    metric_any = mean_iou(predicted_any, gt_used)
    ious = [
        (iou(p, g) if p is not None else 0.0) if g is not None else None
        for p, g in zip(predicted, gt_used, strict=True)
    ]
    stats = frontend.stats
    n = len(predicted)
    first = next((i for i, p in enumerate(predicted) if p is not None), None)
    return SequenceResult(
        sequence=seq.name,
        tracker=settings.tracker,
        frames=n,
        miou=metric.miou,
        miou_any_box=metric_any.miou,
        fps=n / loop_seconds if loop_seconds > 0 else float("nan"),
        edge_fps=stats.tracker_updates / stats.tracker_seconds if stats.tracker_seconds > 0 else float("nan"),
        reinits=max(0, stats.reinits - 1),  # the first start is not a re-initialisation
        loss_events=stats.loss_events,
        false_tracks=metric.false_tracks,
        missed_frames=metric.missed_frames,
        detector_calls=len(asked),
        loss_reasons=dict(reasons),
        ious=ious,
        gt_frames=metric.gt_frames,
        iou_sum=metric.iou_sum,
        reinit_outcomes=dict(outcomes),
        confirmations=stats.confirmations,
        decisions=dict(stats.decisions),
        first_box_s=first / seq.fps if first is not None else None,
        acquisition=acquisition,
        framing=[
            (iou(box, truth), ratio)
            for keyframe, box, ratio in stats.framing
            if (truth := gt_at(keyframe)) is not None
        ],
    )


def overall(results: Sequence[SequenceResult]) -> dict[str, Any]:
    """Pooled over sequences: mIoU frame by frame, FPS as total frames / total time."""
    frames = sum(r.frames for r in results)
    loop_time = sum(r.frames / r.fps for r in results if r.fps > 0)
    miou = pooled_miou(
        [MiouResult(r.miou, r.iou_sum, r.gt_frames, r.false_tracks, r.missed_frames) for r in results]
    )
    edge = [r for r in results if r.edge_fps > 0 and math.isfinite(r.edge_fps)]
    edge_time = sum(r.frames / r.edge_fps for r in edge)
    frames_gt = sum(r.gt_frames for r in results)
    return {
        "sequences": len(results),
        "frames": frames,
        "miou": miou,
        "miou_any_box": sum(r.miou_any_box * r.gt_frames for r in results) / frames_gt
        if frames_gt
        else float("nan"),
        "fps": frames / loop_time if loop_time > 0 else float("nan"),
        "edge_fps": sum(r.frames for r in edge) / edge_time if edge_time > 0 else float("nan"),
        "reinits": sum(r.reinits for r in results),
        "loss_events": sum(r.loss_events for r in results),
        # Every sequence weighs the same here, however long (the frame-pooled figure is "miou").
        "mean_miou": float(np.mean([r.miou for r in results])) if results else float("nan"),
        "reinit_outcomes": dict(sum((Counter(r.reinit_outcomes) for r in results), Counter())),
        "confirmations": sum(r.confirmations for r in results),
        "framing": framing_summary(results),
    }


def framing_summary(results: Sequence[SequenceResult]) -> dict[str, dict[str, float]]:
    """The framing ratios of tracks on target (IoU >= ON_TARGET_IOU) and off it (< OFF_TARGET_IOU):
    count, median, 95th percentile and largest."""
    samples = [s for r in results for s in r.framing]
    summary = {}
    for name, on_target in (("on_target", True), ("off_target", False)):
        ratios = np.array(
            [
                ratio
                for overlap, ratio in samples
                if (overlap >= ON_TARGET_IOU if on_target else overlap < OFF_TARGET_IOU)
            ]
        )
        summary[name] = {
            "n": len(ratios),
            "median": float(np.median(ratios)) if len(ratios) else float("nan"),
            "p95": float(np.percentile(ratios, 95)) if len(ratios) else float("nan"),
            "max": float(ratios.max()) if len(ratios) else float("nan"),
        }
    return summary


def result_dict(result: SequenceResult) -> dict[str, Any]:
    data = asdict(result)
    data.pop("ious")
    return data


@dataclass
class SignalCounts:
    fired: int = 0
    fired_lost: int = 0  # fired on a frame where the tracker was off target
    fired_on_target: int = 0  # false alarms: fired while the tracker was on target (IoU >= ON_TARGET_IOU)


@dataclass
class SignalReport:
    tracker: str
    frames: int = 0
    lost_frames: int = 0
    on_target_frames: int = 0
    counts: dict[str, SignalCounts] = field(default_factory=lambda: {s: SignalCounts() for s in SIGNALS})
    combos: dict[str, SignalCounts] = field(default_factory=dict)
    # Box extent over the ground truth's (width, height ratios): detector boxes on the target, and the
    # tracker's own boxes on keyframes where it was on target. A re-init box of another extent changes
    # what the tracker follows.
    detector_extent: list[tuple[float, float]] = field(default_factory=list)
    tracker_extent: list[tuple[float, float]] = field(default_factory=list)
    keyframes: int = 0
    target_detected: int = 0  # keyframes where some detector box is the target (IoU >= ON_TARGET_IOU)
    # The configured signals as the "verified" policy weighs them over time (behaviors.loss_evidence):
    # what untrusts the track, and for each run of off-target frames how long until it did (seconds; a
    # run never flagged is counted in `episodes_missed`).
    decided: SignalCounts = field(default_factory=SignalCounts)
    detection_delays_s: list[float] = field(default_factory=list)
    episodes_missed: int = 0


def _combos(has_score: bool) -> dict[str, frozenset[str]]:
    base = {"tracker_failed", "score"} if has_score else {"tracker_failed"}
    geometry = base | {"left_frame", "collapsed", "jump"}
    return {
        "paper (score + ok flag)" if has_score else "ok flag only": frozenset(base),
        "+ geometry": frozenset(geometry),
        "+ geometry + appearance": frozenset(geometry | {"appearance"}),
    }


def signal_table(
    seqs: Sequence[SequenceData],
    config: TrackerConfig,
    model_dir: Path,
    tracker_name: str,
    size: tuple[int, int] | None = None,
    max_frames: int | None = None,
    occlude: bool = False,
    detections: dict[str, DetectionCache | None] | None = None,
    keyframe_s: float = 1.0,
    kinds: dict[str, str] | None = None,
) -> SignalReport:
    """Track each sequence from its first box without re-initialisation and score every loss signal.

    For each signal: frames it fired on and how many of them were really off target (precision), and
    over the off-target frames how many it caught (recall = fired_lost / lost_frames), and its false
    alarms: frames it fired on while the tracker was on target. With `detections`, every
    `keyframe_s` seconds of sequence time the detector's box on the target is compared in extent with the
    ground truth.
    """
    settings = EvalSettings(tracker=tracker_name, size=size, max_frames=max_frames, occlude=occlude)
    report = SignalReport(tracker_name)
    tracker = create_tracker(tracker_name, model_dir)
    combos = _combos(tracker.has_score)
    report.combos = {name: SignalCounts() for name in combos}
    evidence_settings = loss_evidence_settings(config)
    enabled = frozenset(config.loss_signals)
    for seq in seqs:
        signals = loss_settings(config, tracker_name)
        kind = (kinds or {}).get(seq.name, "")
        weighing = evidence_settings
        if kind:  # as the front-end weighs the signals for a class outside `loss_model_classes`
            signals = replace(signals, hold_aspect=kind in config.loss_model_classes)
            weighing = replace(evidence_settings, weigh_weak=kind in config.loss_model_classes)
        detector = LossDetector(signals)
        native_gt = ground_truth_for(seq, settings)
        evidence = LossEvidence()
        episode_start: float | None = None  # time of the first frame of the current off-target run
        episode_flagged = False
        for frame, sx, sy in _frames(seq, settings):
            index = frame.frame_id - 1
            gt = _scaled(native_gt[index], sx, sy)
            if index == 0:
                if gt is None:
                    raise ValueError(f"{seq.name}: the first frame needs a ground-truth box")
                tracker.init(frame.image, gt)
                detector.reset(frame.image, gt)
                evidence = LossEvidence(time_s=frame.capture_time)
                continue
            step = tracker.update(frame.image)
            detector.check(frame.image, step)
            fired = detector.last_signals
            # Off target: no box, little overlap, or any box while the target is hidden.
            overlap = iou(step.box, gt) if step.box is not None and gt is not None else 0.0
            lost = step.box is None or gt is None or overlap < LOST_IOU
            on_target = overlap >= ON_TARGET_IOU
            report.frames += 1
            report.lost_frames += int(lost)
            report.on_target_frames += int(on_target)
            for name in SIGNALS:
                if fired[name]:
                    report.counts[name].fired += 1
                    report.counts[name].fired_lost += int(lost)
                    report.counts[name].fired_on_target += int(on_target)
            for combo, members in combos.items():
                if any(fired[s] for s in members):
                    report.combos[combo].fired += 1
                    report.combos[combo].fired_lost += int(lost)
                    report.combos[combo].fired_on_target += int(on_target)
            names = [name for name in SIGNALS if name in enabled and fired[name]]
            evidence = judge_frame(evidence, frame.capture_time, names, weighing)
            flagged = not evidence.trusted
            if flagged:
                report.decided.fired += 1
                report.decided.fired_lost += int(lost)
                report.decided.fired_on_target += int(on_target)
            if lost and episode_start is None:
                episode_start, episode_flagged = frame.capture_time, False
            if lost and flagged and not episode_flagged and episode_start is not None:
                episode_flagged = True
                report.detection_delays_s.append(frame.capture_time - episode_start)
            if not lost and episode_start is not None:
                report.episodes_missed += int(not episode_flagged)
                episode_start = None
            cache = detections.get(seq.name) if detections is not None else None
            if cache is not None and gt is not None and index % max(1, round(keyframe_s * seq.fps)) == 0:
                report.keyframes += 1
                found = [d.box for d in cache.get(seq.name, frame.image, frame.frame_id)]
                best = max(found, key=lambda b: iou(b, gt), default=None)
                if best is not None and iou(best, gt) >= ON_TARGET_IOU:
                    report.target_detected += 1
                    report.detector_extent.append((best.w / gt.w, best.h / gt.h))
                    if on_target and step.box is not None:
                        report.tracker_extent.append((step.box.w / gt.w, step.box.h / gt.h))
        if episode_start is not None:
            report.episodes_missed += int(not episode_flagged)
    return report
