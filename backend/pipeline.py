"""One keyframe through the back-end: superset detection -> margin crops -> concurrent verification.

Every candidate is verified at once on a shared, bounded thread pool (`verify_pool`), each with its own
timeout and all within the request's deadline, so k candidates cost about one verification instead of
k (the reference code verifies one after another). A verification that fails or runs out of time
becomes the configured `uncertain_policy` verdict with the reason in its justification.

A verifier that measured the object's extent (the local verifier's person mask) gives the candidate's
`body_box`, sent beside the detector's box: the detector's box often takes in the person's shadow or a
neighbour, and a tracker started on such a box follows them too, so a new track starts on the body box.
None when the extent's centre falls outside the detector's box (the verifier saw someone else in the
margin).
"""

from __future__ import annotations

import asyncio
import copy
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from backend.appearance import descriptor
from backend.crops import crop_box, margin_crop
from backend.detectors.interface import SupersetDetector
from backend.scene import SceneQuery, judge_scene, read_description, unjudged_words
from backend.supersets import UnknownSupersetError, mapped_coco_classes
from backend.verifiers.cascade import fast_stage
from backend.verifiers.interface import Verifier, VerifierAnswer, VerifierError, VerifierTimeout
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box

if TYPE_CHECKING:
    from backend.config import BackendConfig

# Returns the reason a candidate with this appearance was rejected earlier, or None.
RejectionCheck = Callable[[list[float]], str | None]


@dataclass(frozen=True)
class VerifiedCandidate:
    detection: Detection  # box in the request image's pixels, verdict and justification filled in
    verifier: str
    t_verify: float
    appearance: list[float] = field(repr=False, default_factory=list)
    previously_rejected: bool = False
    crop_origin: tuple[int, int] = (0, 0)  # the margin crop's top-left corner in the request image


@dataclass(frozen=True)
class Sighting:
    """What the detector found for one request: the candidates to verify, and what the description's
    relations are judged on (`backend.scene`)."""

    candidates: list[Detection]  # the superset's best `max_candidates`, best first
    context: list[Detection]  # every detection of the superset: the candidates first, then the rest
    references: dict[str, list[Detection]]  # a named object's phrase -> its detections (absent: not located)
    query: SceneQuery | None  # None: no prompt
    view: tuple[int, int]  # the image's width and height
    whole_frame: bool  # no region: every object in view was looked at


def _belongs(detection: Detection, name: str) -> bool:
    """A detection is of the class a superset name stands for (its COCO classes, or the name itself for
    an open-vocabulary detector, which labels boxes with the phrase they matched)."""
    if detection.label == name:
        return True
    return detection.label in (mapped_coco_classes(name) or ())


def _mapped(name: str) -> bool:
    return mapped_coco_classes(name) is not None


REFERENCE_CHECKS = 5  # objects of a named kind checked against their own description, best scored first


@dataclass(frozen=True)
class PipelineResult:
    superset: str
    candidates: list[VerifiedCandidate]
    t_detect: float
    t_verify: float
    t_total: float
    detector: str
    verifier: str


def _policy_verdict(policy: str) -> Verdict:
    return {"yes": Verdict.YES, "no": Verdict.NO}.get(policy, Verdict.UNCERTAIN)


def refined_box(
    detected: Box, extent: tuple[float, float, float, float] | None, crop_origin: tuple[int, int]
) -> Box | None:
    """The verifier's extent (crop pixels) in the image's pixels when it is the detected object's: its
    centre inside the detector's box; else None (no body box)."""
    if extent is None:
        return None
    box = Box(extent[0] + crop_origin[0], extent[1] + crop_origin[1], extent[2], extent[3])
    inside = detected.x <= box.cx <= detected.x2 and detected.y <= box.cy <= detected.y2
    return box if inside and box.is_valid() else None


class Pipeline:
    def __init__(
        self,
        detector: SupersetDetector,
        verifier: Verifier | None,
        verify_pool: ThreadPoolExecutor,
        margin_px: float = 50,
        max_candidates: int = 10,
        timeout_s: float = 10.0,
        deadline_s: float = 20.0,
        uncertain_policy: str = "uncertain",
    ) -> None:
        self.detector = detector
        self.verifier = verifier
        self.verify_pool = verify_pool
        self.margin_px = margin_px
        self.max_candidates = max_candidates
        self.timeout_s = timeout_s
        self.deadline_s = deadline_s
        self.uncertain_policy = uncertain_policy

    @classmethod
    def configured(
        cls,
        config: BackendConfig,
        detector: SupersetDetector,
        verifier: Verifier | None,
        verify_pool: ThreadPoolExecutor,
    ) -> Pipeline:
        """The pipeline the back-end serves (`backend.app.create_app`) and its tools measure, from its
        configuration's crops, detector and verifier sections."""
        return cls(
            detector,
            verifier,
            verify_pool,
            margin_px=config.crops.margin_px,
            max_candidates=config.detector.max_candidates,
            timeout_s=config.verifier.timeout_s,
            deadline_s=config.verifier.request_deadline_s,
            uncertain_policy=config.verifier.uncertain_policy,
        )

    @property
    def verifier_name(self) -> str:
        return self.verifier.name if self.verifier is not None else "none"

    def early_stage(self) -> Pipeline | None:
        """This pipeline verifying with its verifier's fast stage only (the cascade's local verifier), or
        None when the verifier has no slower stage (its answers are already final)."""
        fast = fast_stage(self.verifier)
        if fast is None:
            return None
        early = copy.copy(self)
        early.verifier = fast
        return early

    def _detect(
        self, image: np.ndarray, classes: list[str], roi: Box | None, frame_id: int | None
    ) -> list[Detection]:
        if roi is None:
            return self.detector.detect(image, classes, frame_id=frame_id)
        height, width = image.shape[:2]
        area = roi.clamped(width, height)
        x1, y1, x2, y2 = int(area.x), int(area.y), int(np.ceil(area.x2)), int(np.ceil(area.y2))
        if x2 - x1 < 2 or y2 - y1 < 2:
            return []
        found = self.detector.detect(np.ascontiguousarray(image[y1:y2, x1:x2]), classes, frame_id=frame_id)
        return [replace(d, box=Box(d.box.x + x1, d.box.y + y1, d.box.w, d.box.h)) for d in found]

    def _verify_one(
        self, crop: np.ndarray, inner: Box, prompt: str, superset: str, timeout_s: float
    ) -> tuple[VerifierAnswer, float]:
        assert self.verifier is not None
        start = time.perf_counter()
        try:
            answer = self.verifier.verify(crop, inner.xywh(), prompt, superset, timeout_s)
        except VerifierTimeout as exc:
            answer = VerifierAnswer(
                _policy_verdict(self.uncertain_policy), f"verification timed out: {exc}", self.verifier.name
            )
        except VerifierError as exc:
            answer = VerifierAnswer(
                _policy_verdict(self.uncertain_policy), f"verifier failed: {exc}", self.verifier.name
            )
        if answer.verdict is Verdict.UNCERTAIN and self.uncertain_policy != "uncertain":
            answer = VerifierAnswer(
                _policy_verdict(self.uncertain_policy), answer.justification, answer.verifier
            )
        return answer, time.perf_counter() - start

    def submit(
        self,
        image: np.ndarray,
        detections: list[Detection],
        prompt: str,
        superset: str,
        rejected: RejectionCheck | None = None,
    ) -> tuple[list[VerifiedCandidate], list[tuple[int, Future[tuple[VerifierAnswer, float]]]]]:
        """Candidates with the rejection memory applied, and their verifications started on the pool."""
        candidates: list[VerifiedCandidate] = []
        pending: list[tuple[int, Future[tuple[VerifierAnswer, float]]]] = []
        for det in detections:
            det = replace(det, candidate_id=det.candidate_id or uuid.uuid4().hex[:12])
            appearance = descriptor(image, det.box)
            reason = rejected(appearance) if rejected is not None else None
            if reason is not None:
                det = replace(det, verdict=Verdict.NO, justification=reason)
                candidates.append(VerifiedCandidate(det, "rejection-memory", 0.0, appearance, True))
            elif self.verifier is None:
                own = read_description(prompt, superset).own
                nothing = unjudged_words(own, superset, set())
                candidates.append(
                    VerifiedCandidate(replace(det, judged=False, unjudged=nothing), "none", 0.0, appearance)
                )
            else:
                crop, inner = margin_crop(image, det.box, self.margin_px)
                height, width = image.shape[:2]
                origin = crop_box(det.box, self.margin_px, width, height)[:2]
                candidates.append(
                    VerifiedCandidate(det, self.verifier.name, 0.0, appearance, crop_origin=origin)
                )
                future = self.verify_pool.submit(
                    self._verify_one, crop, inner, prompt, superset, self.timeout_s
                )
                pending.append((len(candidates) - 1, future))
        return candidates, pending

    def _timed_out(self, base: VerifiedCandidate) -> VerifierAnswer:
        return VerifierAnswer(
            _policy_verdict(self.uncertain_policy),
            f"verification timed out (limit {self.timeout_s:.1f} s, request deadline {self.deadline_s:.1f} s)",
            base.verifier,
        )

    @staticmethod
    def _settle(base: VerifiedCandidate, answer: VerifierAnswer, t_verify: float) -> VerifiedCandidate:
        detection = replace(
            base.detection,
            verdict=answer.verdict,
            justification=answer.justification,
            judged=answer.judged,
            unjudged=answer.unjudged,
        )
        body = refined_box(detection.box, answer.box, base.crop_origin)
        if body is not None:
            detection = replace(detection, body_box=body)
        return replace(base, detection=detection, verifier=answer.verifier, t_verify=t_verify)

    def verify(
        self,
        image: np.ndarray,
        detections: list[Detection],
        prompt: str,
        superset: str,
        rejected: RejectionCheck | None = None,
        deadline: float | None = None,
        sighting: Sighting | None = None,
    ) -> list[VerifiedCandidate]:
        """Verify detections concurrently; `deadline` is a perf_counter() time (default: deadline_s from now).
        With the `sighting` they came from, then judge where each stands (`place`)."""
        t_start = time.perf_counter()
        deadline = deadline if deadline is not None else t_start + self.deadline_s
        candidates, pending = self.submit(image, detections, prompt, superset, rejected)
        for i, future in pending:
            wait_s = max(0.0, min(self.timeout_s, deadline - time.perf_counter()))
            try:
                answer, t_verify = future.result(timeout=wait_s)
            except FutureTimeout:
                future.cancel()  # still queued: never runs; running: its own HTTP timeout ends it
                answer, t_verify = self._timed_out(candidates[i]), time.perf_counter() - t_start
            candidates[i] = self._settle(candidates[i], answer, t_verify)
        return self.place(image, sighting, candidates, deadline) if sighting is not None else candidates

    async def verify_async(
        self,
        image: np.ndarray,
        detections: list[Detection],
        prompt: str,
        superset: str,
        rejected: RejectionCheck | None = None,
        deadline: float | None = None,
        sighting: Sighting | None = None,
    ) -> list[VerifiedCandidate]:
        """`verify` for the server: waits without holding a thread, so waiting requests cost no threads."""
        t_start = time.perf_counter()
        deadline = deadline if deadline is not None else t_start + self.deadline_s
        # Crops, appearance histograms and the rejection check are CPU work on the client's image: off
        # the event loop, like the detection.
        candidates, pending = await asyncio.get_running_loop().run_in_executor(
            None, self.submit, image, detections, prompt, superset, rejected
        )
        for i, future in pending:
            wait_s = max(0.0, min(self.timeout_s, deadline - time.perf_counter()))
            try:
                answer, t_verify = await asyncio.wait_for(asyncio.wrap_future(future), timeout=wait_s)
            except asyncio.TimeoutError:  # wait_for cancelled the future: queued ones never run
                answer, t_verify = self._timed_out(candidates[i]), time.perf_counter() - t_start
            candidates[i] = self._settle(candidates[i], answer, t_verify)
        if sighting is None:
            return candidates
        return await asyncio.to_thread(self.place, image, sighting, candidates, deadline)

    def look(
        self,
        image: np.ndarray,
        superset: str,
        roi: Box | None = None,
        frame_id: int | None = None,
        prompt: str = "",
    ) -> Sighting:
        """The superset's detections, and with the prompt the objects it names besides the target, found in
        the same detector call (a detector that cannot take their class is asked for the target alone)."""
        query = read_description(prompt, superset) if prompt else None
        wanted = query.detector_classes() if query is not None else []
        mapped = [name for name in wanted if _mapped(name)]
        # Every named class, then the ones COCO has (an open-vocabulary detector takes the rest), then the
        # target's class alone (the SITL detector knows people only).
        for extra in dict.fromkeys((tuple(wanted), tuple(mapped), ())):
            try:
                found = self._detect(image, [superset, *extra], roi, frame_id)
                break
            except UnknownSupersetError:
                if not extra:
                    raise
        own = sorted((d for d in found if _belongs(d, superset)), key=lambda d: -d.score)
        references: dict[str, list[Detection]] = {}
        for phrase, ref in query.references.items() if query is not None else ():
            if ref.detector_class is None:
                continue
            if query is not None and query.same_kind(ref):
                references[phrase] = own
            elif ref.detector_class in extra:
                seen = [d for d in found if _belongs(d, ref.detector_class)]
                if seen:
                    references[phrase] = sorted(seen, key=lambda d: -d.score)
        height, width = image.shape[:2]
        return Sighting(own[: self.max_candidates], own, references, query, (width, height), roi is None)

    def detect(
        self,
        image: np.ndarray,
        superset: str,
        roi: Box | None = None,
        frame_id: int | None = None,
        prompt: str = "",
    ) -> list[Detection]:
        """The best `max_candidates` detections of the superset, highest score first."""
        return self.look(image, superset, roi, frame_id, prompt).candidates

    def _check_references(
        self, image: np.ndarray, sighting: Sighting, deadline: float
    ) -> dict[str, list[Box] | None]:
        """Each named object's boxes that fit its own description ("the man in the green hoodie": the
        people the verifier does not rule out, those it says yes to when there are any); None where
        nothing of it was found."""
        located: dict[str, list[Box] | None] = {}
        query = sighting.query
        if query is None:
            return located
        pending: list[tuple[str, Detection, Future[tuple[VerifierAnswer, float]]]] = []
        for phrase, found in sighting.references.items():
            ref = query.references[phrase]
            if not ref.described or self.verifier is None:
                located[phrase] = [d.box for d in found]
                continue
            for det in found[:REFERENCE_CHECKS]:
                crop, inner = margin_crop(image, det.box, self.margin_px)
                assert ref.detector_class is not None  # found, so asked for by its class
                future = self.verify_pool.submit(
                    self._verify_one, crop, inner, phrase, ref.detector_class, self.timeout_s
                )
                pending.append((phrase, det, future))
        verdicts: dict[str, list[tuple[Box, Verdict]]] = {}
        for phrase, det, future in pending:
            try:
                answer, _ = future.result(
                    timeout=max(0.0, min(self.timeout_s, deadline - time.perf_counter()))
                )
                verdict = answer.verdict
            except FutureTimeout:
                future.cancel()
                verdict = Verdict.UNCERTAIN
            verdicts.setdefault(phrase, []).append((det.box, verdict))
        for phrase, judged in verdicts.items():
            yes = [box for box, v in judged if v is Verdict.YES]
            located[phrase] = yes or [box for box, v in judged if v is not Verdict.NO] or None
        return located

    def place(
        self,
        image: np.ndarray,
        sighting: Sighting,
        candidates: list[VerifiedCandidate],
        deadline: float | None = None,
    ) -> list[VerifiedCandidate]:
        """The verified candidates with what the whole keyframe says about them (`backend.scene`): where
        each stands and its size among the others (`placement_ok`, notes in the justification), and the
        description's words nothing judged (`unjudged`)."""
        query = sighting.query
        if query is None:
            return candidates
        deadline = deadline if deadline is not None else time.perf_counter() + self.deadline_s
        located = self._check_references(image, sighting, deadline)
        boxes = [c.detection.box for c in candidates]
        boxes += [d.box for d in sighting.context[len(candidates) :]]
        may_be = [c.detection.verdict is not Verdict.NO for c in candidates]
        may_be += [True] * (len(boxes) - len(candidates))  # not verified: may be the target
        placements = judge_scene(query, boxes, may_be, located, sighting.view, sighting.whole_frame)
        placed = []
        for candidate, placement in zip(candidates, placements, strict=False):
            detection = candidate.detection
            unjudged = [w for w in detection.unjudged if w != query.size_word or len(boxes) < 2]
            notes = "; ".join(placement.notes)
            justification = "; ".join(p for p in (detection.justification, notes) if p)
            detection = replace(
                detection,
                placement_ok=placement.ok,
                singled_out=placement.singled_out,
                justification=justification,
                unjudged=tuple(dict.fromkeys([*unjudged, *placement.unjudged])),
            )
            placed.append(replace(candidate, detection=detection))
        return placed

    def run(
        self,
        image: np.ndarray,
        prompt: str,
        superset: str,
        roi: Box | None = None,
        frame_id: int | None = None,
        rejected: RejectionCheck | None = None,
        started: float | None = None,
    ) -> PipelineResult:
        """Detect, crop and verify; `started` (perf_counter) lets the deadline include queueing time."""
        t0 = started if started is not None else time.perf_counter()
        sighting = self.look(image, superset, roi, frame_id, prompt)
        t_detected = time.perf_counter()
        candidates = self.verify(
            image, sighting.candidates, prompt, superset, rejected, t0 + self.deadline_s, sighting
        )
        t_end = time.perf_counter()
        return PipelineResult(
            superset=superset,
            candidates=candidates,
            t_detect=t_detected - t0,
            t_verify=t_end - t_detected,
            t_total=t_end - t0,
            detector=self.detector.name,
            verifier=self.verifier_name,
        )
