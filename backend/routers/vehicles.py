"""A vehicle's session: the status it reports (with the candidate it awaits) and the supervisor's decisions.

`POST /v1/vehicles/{vehicle_id}/decisions` is the one decision endpoint, for the supervisor page and any
other supervisor client; the companion polls `GET .../decisions?after=N`.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status

from backend.auth import require_vehicle_access
from backend.dependencies import Caller, Sessions, SupervisorCaller, VehicleId
from backend.schemas import (
    ERROR_RESPONSES,
    Decision,
    DecisionIn,
    ErrorResponse,
    VehicleStatus,
    VehicleStatusIn,
)

router = APIRouter(prefix="/v1/vehicles", tags=["sessions"])


@router.post("/{vehicle_id}/status", response_model=VehicleStatus, responses=ERROR_RESPONSES)
def report_status(
    vehicle_id: VehicleId, body: VehicleStatusIn, principal: Caller, sessions: Sessions
) -> VehicleStatus:
    """The companion's state and the candidate awaiting the supervisor (crop, justification, position).

    The crop must be a JPEG (checked from its header, at most `server.max_crop_pixels`), else 413/422.
    """
    require_vehicle_access(principal, vehicle_id)
    return sessions.set_status(vehicle_id, body)


@router.get("/{vehicle_id}/status", response_model=VehicleStatus, responses=ERROR_RESPONSES)
def get_status(vehicle_id: VehicleId, principal: Caller, sessions: Sessions) -> VehicleStatus:
    require_vehicle_access(principal, vehicle_id)
    current = sessions.status(vehicle_id)
    if current is None:
        raise HTTPException(404, f"vehicle {vehicle_id!r} has not reported a status")
    return current


@router.get("", response_model=list[VehicleStatus], responses=ERROR_RESPONSES)
def list_vehicles(_: SupervisorCaller, sessions: Sessions) -> list[VehicleStatus]:
    return sessions.statuses()


@router.post(
    "/{vehicle_id}/decisions",
    response_model=Decision,
    status_code=status.HTTP_201_CREATED,
    responses={**ERROR_RESPONSES, 409: {"model": ErrorResponse}},
)
def decide(
    vehicle_id: VehicleId,
    body: DecisionIn,
    _: SupervisorCaller,
    sessions: Sessions,
    require_awaiting: Annotated[
        bool,
        Query(
            description="only if the vehicle awaits a decision on this very candidate now: 404 when it has "
            "not reported, 409 when it waits on another or none (the supervisor page sets it)"
        ),
    ] = False,
) -> Decision:
    """The supervisor confirms or rejects a candidate; a reject also enters the rejection memory.

    Both are stored (on disk, or in Redis) before the 201; a crop that cannot be read only keeps the
    reject out of the memory, never loses the decision.
    """
    if require_awaiting:
        current = sessions.status(vehicle_id)
        if current is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"vehicle {vehicle_id!r} has not reported")
        if current.awaiting is None or current.awaiting.candidate_id != body.candidate_id:
            raise HTTPException(
                status.HTTP_409_CONFLICT,
                f"{vehicle_id!r} is no longer waiting for a decision on {body.candidate_id!r}",
            )
    return sessions.add_decision(vehicle_id, body)


@router.get("/{vehicle_id}/decisions", response_model=list[Decision], responses=ERROR_RESPONSES)
def poll_decisions(
    vehicle_id: VehicleId,
    principal: Caller,
    sessions: Sessions,
    after: Annotated[int, Query(ge=0, le=2**63 - 1, description="last decision_id already seen")] = 0,
) -> list[Decision]:
    """Decisions for this vehicle newer than `after` (the companion polls this)."""
    require_vehicle_access(principal, vehicle_id)
    return sessions.decisions(vehicle_id, after)
