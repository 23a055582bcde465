"""What the back-end remembers between requests: per-mission rejections, vehicle status, decisions.

One in-process store, guarded by a lock (handlers, the pipeline's threads and the supervisor routes all
use it). The state is small on purpose - a 128-float appearance descriptor per remembered candidate,
the latest status per vehicle, a bounded decision log - so several replicas can run behind a load
balancer with missions pinned to a replica (see docs/backend.md).

Rejection memory: when the supervisor rejects a candidate, its appearance (hue-saturation histogram)
and, when known, its position are kept for the mission. A later candidate in the same mission whose
appearance correlates at least `similarity` with a rejected one is answered "no" without asking the
verifier - unless both the rejection and the request carry positions and the vehicle is farther than
`radius_m` from the rejected place (a look-alike elsewhere is a new candidate).
"""

from __future__ import annotations

import base64
import contextlib
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from backend.appearance import descriptor, similarity
from backend.schemas import Decision, DecisionIn, Rejection, RejectionIn, VehicleStatus, VehicleStatusIn
from behaviors.geometry import Box

CANDIDATES_PER_MISSION = 500
DECISIONS_KEPT = 1000


class UnknownCandidateError(LookupError):
    """A rejection names a candidate id the back-end does not know and carries no crop."""


def distance_m(a: list[float], b: list[float]) -> float:
    """Great-circle distance between two [lat, lon] points in metres (haversine)."""
    lat1, lon1, lat2, lon2 = map(math.radians, (a[0], a[1], b[0], b[1]))
    h = math.sin((lat2 - lat1) / 2) ** 2 + math.cos(lat1) * math.cos(lat2) * math.sin((lon2 - lon1) / 2) ** 2
    return 2 * 6_371_000.0 * math.asin(min(1.0, math.sqrt(h)))


def crop_descriptor(crop_jpeg_b64: str, crop_box: list[float] | None = None) -> list[float]:
    """Appearance of a crop sent by a client: the candidate's box inside it, or the whole crop."""
    try:
        data = base64.b64decode(crop_jpeg_b64, validate=True)
    except ValueError as exc:
        raise ValueError("crop_jpeg_b64 is not valid base64") from exc
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None:
        raise ValueError("crop_jpeg_b64 is not a decodable JPEG/PNG image")
    h, w = image.shape[:2]
    box = Box.from_xyxy(*crop_box) if crop_box else Box(0, 0, w, h)
    if not box.clamped(w, h).is_valid():
        raise ValueError(f"crop_box {crop_box} lies outside the {w}x{h} crop")
    return descriptor(image, box)


@dataclass
class _Mission:
    last_seen: float
    candidates: OrderedDict[str, list[float]] = field(default_factory=OrderedDict)
    rejections: list[tuple[Rejection, list[float]]] = field(default_factory=list)


class SessionStore:
    def __init__(
        self,
        similarity_threshold: float = 0.85,
        radius_m: float = 150.0,
        mission_ttl_s: float = 6 * 3600.0,
        max_rejections: int = 200,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.similarity_threshold = similarity_threshold
        self.radius_m = radius_m
        self.mission_ttl_s = mission_ttl_s
        self.max_rejections = max_rejections
        self._clock = clock
        self._lock = threading.Lock()
        self._missions: dict[str, _Mission] = {}
        self._status: dict[str, VehicleStatus] = {}
        self._decisions: deque[Decision] = deque(maxlen=DECISIONS_KEPT)
        self._next_rejection = 1
        self._next_decision = 1

    def _mission(self, mission_id: str) -> _Mission:
        now = self._clock()
        for stale in [m for m, s in self._missions.items() if now - s.last_seen > self.mission_ttl_s]:
            del self._missions[stale]
        mission = self._missions.setdefault(mission_id, _Mission(now))
        mission.last_seen = now
        return mission

    # Candidates and rejections

    def remember_candidates(self, mission_id: str, candidates: list[tuple[str, list[float]]]) -> None:
        """Keep the appearance of proposed candidates so a rejection by id can be matched later."""
        with self._lock:
            cache = self._mission(mission_id).candidates
            for candidate_id, appearance in candidates:
                cache[candidate_id] = appearance
            while len(cache) > CANDIDATES_PER_MISSION:
                cache.popitem(last=False)

    def add_rejection(self, mission_id: str, rejection: RejectionIn) -> Rejection:
        """Record a rejected candidate; its appearance comes from the crop sent or the candidate id."""
        appearance = crop_descriptor(rejection.crop_jpeg_b64, rejection.crop_box) if rejection.crop_jpeg_b64 else None
        with self._lock:
            mission = self._mission(mission_id)
            if appearance is None:
                if rejection.candidate_id is None or rejection.candidate_id not in mission.candidates:
                    raise UnknownCandidateError(
                        f"candidate {rejection.candidate_id!r} is unknown in mission {mission_id!r}; send crop_jpeg_b64"
                    )
                appearance = mission.candidates[rejection.candidate_id]
            record = Rejection(
                rejection_id=self._next_rejection,
                mission_id=mission_id,
                vehicle_id=rejection.vehicle_id,
                candidate_id=rejection.candidate_id,
                position=rejection.position,
                reason=rejection.reason,
                created_at=self._clock(),
            )
            self._next_rejection += 1
            mission.rejections.append((record, appearance))
            del mission.rejections[: -self.max_rejections]
            return record

    def rejections(self, mission_id: str) -> list[Rejection]:
        with self._lock:
            mission = self._missions.get(mission_id)
            return [r for r, _ in mission.rejections] if mission else []

    def rejection_check(self, mission_id: str, vehicle_position: list[float] | None) -> Callable[[list[float]], str | None]:
        """A function telling whether a candidate's appearance matches a rejection of this mission."""
        with self._lock:
            mission = self._missions.get(mission_id)
            entries = list(mission.rejections) if mission else []

        def check(appearance: list[float]) -> str | None:
            for record, rejected in entries:
                far = (
                    record.position is not None
                    and vehicle_position is not None
                    and distance_m(record.position, vehicle_position) > self.radius_m
                )
                if far:
                    continue
                score = similarity(appearance, rejected)
                if score >= self.similarity_threshold:
                    return (
                        f"looks like candidate {record.candidate_id or record.rejection_id} that the supervisor "
                        f"rejected (appearance similarity {score:.2f})"
                    )
            return None

        return check

    # Vehicle status and supervisor decisions

    def set_status(self, vehicle_id: str, status: VehicleStatusIn) -> VehicleStatus:
        with self._lock:
            previous = self._status.get(vehicle_id)
            kept = previous.awaiting if previous is not None else None
            awaiting = status.awaiting
            if (
                awaiting is not None
                and awaiting.crop_jpeg_b64 is None
                and kept is not None
                and kept.candidate_id == awaiting.candidate_id
            ):
                # Vehicles send a candidate's crop once; later reports about the same candidate keep it.
                crop = {"crop_jpeg_b64": kept.crop_jpeg_b64, "crop_box": kept.crop_box}
                status = status.model_copy(update={"awaiting": awaiting.model_copy(update=crop)})
            record = VehicleStatus(vehicle_id=vehicle_id, updated_at=self._clock(), **status.model_dump())
            self._status[vehicle_id] = record
        return record

    def status(self, vehicle_id: str) -> VehicleStatus | None:
        with self._lock:
            return self._status.get(vehicle_id)

    def statuses(self) -> list[VehicleStatus]:
        with self._lock:
            return sorted(self._status.values(), key=lambda s: s.vehicle_id)

    def add_decision(self, vehicle_id: str, decision: DecisionIn) -> Decision:
        """Record the supervisor's confirm/reject; a reject also enters the mission's rejection memory."""
        current = self.status(vehicle_id)
        mission_id = current.mission_id if current else None
        awaiting = current.awaiting if current else None
        if decision.action == "reject" and mission_id is not None:
            same = awaiting is not None and awaiting.candidate_id == decision.candidate_id
            # Unknown candidate without a crop: the companion still gets the decision, nothing to match.
            with contextlib.suppress(UnknownCandidateError):
                self.add_rejection(
                    mission_id,
                    RejectionIn(
                        vehicle_id=vehicle_id,
                        candidate_id=decision.candidate_id,
                        crop_jpeg_b64=awaiting.crop_jpeg_b64 if same and awaiting else None,
                        crop_box=awaiting.crop_box if same and awaiting else None,
                        position=awaiting.position if same and awaiting else None,
                        reason=decision.note or "rejected by the supervisor",
                    ),
                )
        with self._lock:
            record = Decision(
                decision_id=self._next_decision,
                vehicle_id=vehicle_id,
                mission_id=mission_id,
                created_at=self._clock(),
                **decision.model_dump(),
            )
            self._next_decision += 1
            self._decisions.append(record)
        return record

    def decisions(self, vehicle_id: str, after: int = 0) -> list[Decision]:
        with self._lock:
            return [d for d in self._decisions if d.vehicle_id == vehicle_id and d.decision_id > after]
