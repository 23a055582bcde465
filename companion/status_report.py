"""What the companion's status report tells the supervisor beyond the state: why, where it looks, how far the
search has come, the tracked box, and the mission's finds (CONTRACT section 1; `cloudtrack/api_models.py`
`VehicleStatusIn`).

The main loop feeds it what happens (answers, rejections, keyframes sent, confirmed candidates) and asks it
for the report's fields. Counters and finds belong to one mission: a start with another mission id begins
them again. Bounded: candidate ids are counted up to `MAX_CANDIDATE_IDS`, finds kept up to `MAX_FINDS`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from behaviors.actions import ReportCandidate
from behaviors.detection import Detection
from behaviors.geometry import Box
from behaviors.mission import MissionState, State

MAX_CANDIDATE_IDS = 10_000
MAX_FINDS = 100
REASON_MAX = 200  # VehicleStatusIn.reason


@dataclass(frozen=True)
class Find:
    """A confirmed find as the back-end and the GCS get it (`cloudtrack.api_models.Find`)."""

    candidate_id: str
    lat: float
    lon: float
    sigma_m: float
    time: float  # Unix seconds of the confirmation
    prompt: str
    confirmed_by: str
    slant_range_m: float  # camera to the person when confirmed (CAMERA_TRACKING_GEO_STATUS.dist)
    crop_jpeg_b64: str | None = None
    seen_at: float | None = None  # Unix seconds when the reported position was observed; None: not known

    def fields(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "candidate_id": self.candidate_id,
            "position": [round(self.lat, 7), round(self.lon, 7)],
            "sigma_m": round(min(self.sigma_m, 100_000.0), 2),
            "time": round(self.time, 3),
            "prompt": self.prompt[:500],
            "confirmed_by": (self.confirmed_by or "supervisor")[:64],
        }
        if self.seen_at is not None:
            out["seen_at"] = round(self.seen_at, 3)
        if self.crop_jpeg_b64:
            out["crop_jpeg_b64"] = self.crop_jpeg_b64
        return out


class StatusReport:
    """The mission's progress, finds and tracked box; one owner (the main loop), not thread-safe."""

    def __init__(
        self,
        image_size: tuple[int, int],
        keyframe_max_width: int = 640,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        # Boxes go to the back-end in the pixels of the keyframe as sent: downscaled to
        # `[backend] max_keyframe_width` (cloudtrack.api_client.encode_keyframe).
        self._image_size = image_size
        self._keyframe_scale = min(1.0, keyframe_max_width / max(1, image_size[0]))
        self._wall_clock = wall_clock
        self._mission_id: str | None = None
        self.keyframes = 0
        self.rejected = 0
        self.detections = 0  # boxes the back-end returned, every keyframe's own
        self._candidate_ids: set[str] = set()  # put to the supervisor
        self.finds: list[Find] = []
        self._keyframe: tuple[int, Box | None] | None = None  # newest keyframe sent, the track's box on it

    def start(self, mission_id: str) -> None:
        """A mission (re)started: counters and finds begin again when it is another mission."""
        if mission_id == self._mission_id:
            return
        self._mission_id = mission_id
        self.keyframes = self.rejected = self.detections = 0
        self._candidate_ids.clear()
        self.finds.clear()

    def on_answer(self, candidates: Sequence[Detection]) -> None:
        """A final answer about a keyframe of this mission."""
        self.keyframes += 1
        self.detections += len(candidates)

    def on_proposed(self, candidate_id: str) -> None:
        """A candidate was put to the supervisor (counted once however often it is reported)."""
        if candidate_id and len(self._candidate_ids) < MAX_CANDIDATE_IDS:
            self._candidate_ids.add(candidate_id)

    def on_rejection(self) -> None:
        self.rejected += 1

    def on_keyframe(self, frame_id: int, box: Box | None) -> None:
        """A keyframe went to the back-end; `box` is the trusted track on it (None: nothing tracked)."""
        self._keyframe = (frame_id, box)

    def wall_time(self, event_s: float, now_s: float, wall: float | None = None) -> float | None:
        """The Unix time of `event_s` on the mission's event clock, whose now is `now_s`; None: not known."""
        age = now_s - event_s
        if not math.isfinite(age):
            return None
        return (self._wall_clock() if wall is None else wall) - max(0.0, age)

    def find_of(self, candidate_id: str) -> Find | None:
        return next((f for f in self.finds if f.candidate_id == candidate_id), None)

    def record_find(
        self, report: ReportCandidate, prompt: str, crop_jpeg_b64: str | None, *, now_s: float
    ) -> Find | None:
        """A confirmed report: the find (new, or its position updated). None without a position. `now_s` is
        the mission's event clock now: the position's age (`report.position_s`) becomes a Unix time."""
        position = report.position
        if position is None or not all(math.isfinite(v) for v in (position.lat_deg, position.lon_deg)):
            return None
        old = self.find_of(report.candidate_id)
        wall = self._wall_clock()
        find = Find(
            report.candidate_id,
            position.lat_deg,
            position.lon_deg,
            position.sigma_m if math.isfinite(position.sigma_m) else 100_000.0,
            old.time if old is not None else wall,
            prompt,
            old.confirmed_by if old is not None else report.confirmed_by,
            position.slant_range_m,
            old.crop_jpeg_b64 if old is not None and old.crop_jpeg_b64 else crop_jpeg_b64,
            self.wall_time(report.position_s, now_s, wall),
        )
        if old is not None:
            self.finds[self.finds.index(old)] = find
        else:
            self.finds = [*self.finds, find][-MAX_FINDS:]
        return find

    def fields(self, state: State, search: dict[str, Any] | None) -> dict[str, Any]:
        """The report's console fields (everything but state, prompt, position and the awaiting candidate)."""
        out: dict[str, Any] = {"reason": state.reason[:REASON_MAX]}
        telemetry = state.telemetry
        if telemetry is not None and math.isfinite(telemetry.yaw):
            out["heading_deg"] = round(math.degrees(telemetry.yaw) % 360.0, 1)
        tracking = state.mode in (
            MissionState.FOLLOWING,
            MissionState.AWAITING_SUPERVISOR,
            MissionState.CONFIRMED,
        )
        frame_id, box = self._keyframe if self._keyframe is not None else (0, None)
        if tracking and box is not None:
            inside = box.clamped(*self._image_size)
            if inside.is_valid():
                s = self._keyframe_scale
                out["track_box"] = [round(v * s, 1) for v in inside.xyxy()]
                out["frame_id"] = frame_id
                target = state.target
                if target is not None and target.candidate_id and target.early is None:
                    out["track_id"] = target.candidate_id  # the id the GCS, the card and the finds name
        out["progress"] = {
            "keyframes": self.keyframes,
            "detections": self.detections,
            "candidates": len(self._candidate_ids),
            "rejected": self.rejected,
        }
        if search is not None:
            out["search"] = search
        if self.finds:
            out["find"] = self.finds[-1].fields()
        return out
