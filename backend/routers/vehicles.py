"""A vehicle's session: the status it reports (with the candidate it awaits) and the supervisor's decisions.

`POST /v1/vehicles/{vehicle_id}/decisions` is the one decision endpoint, for the supervisor page and any
other supervisor client; the companion polls `GET .../decisions?after=N`.
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Response, status

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
from backend.state_store import DECISIONS_KEPT_PER_VEHICLE
from cloudtrack.provenance import decided_via, decision_text

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
    responses={
        **ERROR_RESPONSES,
        200: {
            "model": Decision,
            "description": "the same decision stands already (a repeat changes nothing)",
        },
        409: {"model": ErrorResponse, "description": "another decision on this candidate stands (named)"},
    },
)
def decide(
    vehicle_id: VehicleId,
    body: DecisionIn,
    _: SupervisorCaller,
    sessions: Sessions,
    response: Response,
    require_awaiting: Annotated[
        bool,
        Query(
            description="only if the vehicle awaits a decision on this very candidate now: 404 when it has "
            "not reported, 409 when it waits on another or none (the supervisor page sets it)"
        ),
    ] = False,
) -> Decision:
    """The supervisor confirms or rejects a candidate; the first decision on a candidate stands.

    201: stored (on disk, or in Redis) before the answer; a reject also enters the rejection memory, a
    confirm is kept as a find. 200: the same decision stood already. 409: a different one of the supervisor's
    stands (the answer names who took it and through what). What the vehicle reports was decided at its GCS
    is its report, never the standing decision: it refuses nothing here. `via` says through what the
    supervisor decided ("supervisor page" from the page, "back-end API" by default). A crop that cannot be
    read only keeps a reject out of the memory, never loses the decision.
    """
    if require_awaiting:
        current = sessions.status(vehicle_id)
        if current is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"vehicle {vehicle_id!r} has not reported")
        if current.awaiting is None or current.awaiting.candidate_id != body.candidate_id:
            standing = sessions.standing_decision(vehicle_id, current.mission_id, body.candidate_id)
            if standing is not None and standing.action != body.action:
                raise HTTPException(status.HTTP_409_CONFLICT, standing_text(standing))
            if standing is None:
                raise HTTPException(
                    status.HTTP_409_CONFLICT,
                    f"{vehicle_id!r} is no longer waiting for a decision on {body.candidate_id!r}",
                )
    decision, created = sessions.add_decision(vehicle_id, body)
    if not created:
        if decision.action != body.action:
            raise HTTPException(status.HTTP_409_CONFLICT, standing_text(decision))
        response.status_code = status.HTTP_200_OK
    return decision


def standing_text(decision: Decision) -> str:
    """A refused decision's answer: the one that stands, who took it, through what and when."""
    when = time.strftime("%H:%M:%S UTC", time.gmtime(decision.created_at))
    via = decided_via(decision.source, decision.via)
    who = decision_text(via, decision.operator, decision.vehicle_id)
    done = {"confirm": "confirmed", "reject": "rejected"}[decision.action]
    return (
        f"candidate {decision.candidate_id!r} was already {done} by {who} at {when} "
        f"(decision {decision.decision_id}); that decision stands"
    )


DROPPED_HEADER = "X-Decisions-Dropped-Through"


@router.get(
    "/{vehicle_id}/decisions",
    response_model=list[Decision],
    responses={
        **ERROR_RESPONSES,
        200: {
            "description": "the decisions newer than `after`, oldest first",
            "headers": {
                DROPPED_HEADER: {
                    "description": f"the highest decision_id dropped from this vehicle's list (the newest "
                    f"{DECISIONS_KEPT_PER_VEHICLE} are kept); 0: none. An `after` below it missed decisions "
                    "no longer listed; every standing decision still holds (a contrary one gets 409)",
                    "schema": {"type": "integer"},
                }
            },
        },
    },
)
def poll_decisions(
    vehicle_id: VehicleId,
    principal: Caller,
    sessions: Sessions,
    response: Response,
    after: Annotated[int, Query(ge=0, le=2**63 - 1, description="last decision_id already seen")] = 0,
) -> list[Decision]:
    """Decisions for this vehicle newer than `after` (the companion polls this). The list holds the newest
    1,000 of the vehicle; the `X-Decisions-Dropped-Through` header names the highest id dropped before them."""
    require_vehicle_access(principal, vehicle_id)
    response.headers[DROPPED_HEADER] = str(sessions.decisions_dropped(vehicle_id))
    return sessions.decisions(vehicle_id, after)
