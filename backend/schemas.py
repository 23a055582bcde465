"""The API models, re-exported: they live in `cloudtrack.api_models`, shared with the companion."""

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

__all__ = [
    "CANDIDATE_ID", "ID_FIELD", "IDENTIFIER", "NOTE_MAX", "ApiModel", "AwaitingCandidate", "Candidate", "Decision",
    "DecisionIn", "DetectMeta", "DetectResponse", "ErrorResponse", "GeoPoint", "HealthResponse", "ModelNames",
    "ModelsResponse", "Rejection", "RejectionIn", "Timings", "VehicleStatus", "VehicleStatusIn",
]
