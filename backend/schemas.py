"""The back-end's models: the API's (re-exported from `cloudtrack.api_models`, shared with the companion)
and the supervisor page's own (its snapshot of the fleet), plus the error answers every route documents."""

from __future__ import annotations

from typing import Any, Literal

from cloudtrack.api_models import (
    CANDIDATE_ID,
    ID_FIELD,
    IDENTIFIER,
    NOTE_MAX,
    ApiModel,
    AwaitingCandidate,
    Candidate,
    Decision,
    DecisionIn,
    DetectMeta,
    DetectResponse,
    ErrorResponse,
    GeoPoint,
    HealthResponse,
    ModelNames,
    ModelsResponse,
    Rejection,
    RejectionIn,
    Timings,
    VehicleStatus,
    VehicleStatusIn,
)

ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse} for status in (400, 401, 403, 404, 408, 413, 415, 422, 429)
}


# The supervisor page's snapshot (GET /supervisor/api/state and each `state` event of /supervisor/events).


class LatLon(ApiModel):
    lat: float
    lon: float


class CandidateView(ApiModel):
    """The candidate a vehicle awaits a decision on, as the page shows it."""

    id: str
    verdict: Literal["yes", "no", "uncertain"]
    justification: str
    position: LatLon | None
    box: list[float]
    age_s: float = 0.0
    crop_url: str | None
    status: Literal["awaiting", "confirmed", "rejected"]


class VehicleView(ApiModel):
    id: str
    state: str
    mission_id: str | None
    prompt: str | None
    position: GeoPoint | None
    altitude_m: float | None
    age_s: float = 0.0
    candidates: list[CandidateView]


class SupervisorSnapshot(ApiModel):
    server_time: float
    vehicles: list[VehicleView]


class SupervisorEnabled(ApiModel):
    enabled: bool


__all__ = [
    "CANDIDATE_ID",
    "ERROR_RESPONSES",
    "ID_FIELD",
    "IDENTIFIER",
    "NOTE_MAX",
    "ApiModel",
    "AwaitingCandidate",
    "Candidate",
    "CandidateView",
    "Decision",
    "DecisionIn",
    "DetectMeta",
    "DetectResponse",
    "ErrorResponse",
    "GeoPoint",
    "HealthResponse",
    "LatLon",
    "ModelNames",
    "ModelsResponse",
    "Rejection",
    "RejectionIn",
    "SupervisorEnabled",
    "SupervisorSnapshot",
    "Timings",
    "VehicleStatus",
    "VehicleStatusIn",
    "VehicleView",
]
