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

import numpy as np

from backend.appearance import descriptor
from backend.crops import crop_box, margin_crop
from backend.detectors.interface import SupersetDetector
from backend.placement import named_vehicles, placement_ok
from backend.verifiers.cascade import fast_stage
from backend.verifiers.interface import Verifier, VerifierAnswer, VerifierError, VerifierTimeout
from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box

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
                candidates.append(VerifiedCandidate(replace(det, judged=False), "none", 0.0, appearance))
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
            base.detection, verdict=answer.verdict, justification=answer.justification, judged=answer.judged
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
    ) -> list[VerifiedCandidate]:
        """Verify detections concurrently; `deadline` is a perf_counter() time (default: deadline_s from now)."""
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
        return candidates

    async def verify_async(
        self,
        image: np.ndarray,
        detections: list[Detection],
        prompt: str,
        superset: str,
        rejected: RejectionCheck | None = None,
        deadline: float | None = None,
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
        return candidates

    def detect(
        self,
        image: np.ndarray,
        superset: str,
        roi: Box | None = None,
        frame_id: int | None = None,
        prompt: str = "",
    ) -> list[Detection]:
        """The best `max_candidates` detections of the superset, highest score first; with the prompt,
        each marked with whether it stands where the description places the target relative to a
        vehicle it names (`backend.placement`: the same inference finds the vehicles)."""
        vehicles = named_vehicles(prompt, superset) if prompt else ()
        extra = [v.coco_class for v in vehicles]
        found = self._detect(image, [superset, *extra], roi, frame_id)
        seen = [(d.label, d.box) for d in found if d.label in extra]
        found = [d for d in found if d.label not in extra]  # a named vehicle is context, not a candidate
        found = sorted(found, key=lambda d: -d.score)[: self.max_candidates]
        if not vehicles:
            return found
        return [replace(d, placement_ok=placement_ok(d.box, vehicles, seen)) for d in found]

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
        detections = self.detect(image, superset, roi, frame_id, prompt)
        t_detected = time.perf_counter()
        candidates = self.verify(image, detections, prompt, superset, rejected, deadline=t0 + self.deadline_s)
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
