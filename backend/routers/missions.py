"""A mission's rejection memory: the candidates the supervisor or the vehicle rejected, never proposed again;
and the mission's map over the whole fleet.

Missions are stored by (vehicle, mission): a rejection is the sending vehicle's, and holds for the other
vehicles of the same mission id where it was made (backend.sessions). `GET /v1/missions/{m}/map`: the
map of every vehicle searching the mission id, merged (backend.mission_merge) at most once per
`[fleet] merge_period_s` (backend.merged_maps). `PUT .../on_find` sets
what the fleet does on the first confirmed find (once, at the start), `GET .../fleet` tells a vehicle
what it is to do now and where the other vehicles' rejections stand. `GET .../dropouts`: the vehicles
that left the search and their unflown parts (backend.fleet_dropout).
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query
from fastapi.concurrency import run_in_threadpool

from backend.auth import require_vehicle_access
from backend.dependencies import Caller, MissionId, Scheduler, Sessions, SupervisorCaller
from backend.fair_queue import QueueFullError
from backend.schemas import (
    ERROR_RESPONSES,
    IDENTIFIER,
    ErrorResponse,
    FleetOrder,
    MergedMap,
    MissionDropouts,
    OnFindIn,
    Rejection,
    RejectionIn,
)
from backend.sessions import UnknownCandidateError

router = APIRouter(prefix="/v1/missions/{mission_id}", tags=["sessions"])


@router.post("/rejections", response_model=Rejection, status_code=201, responses=ERROR_RESPONSES)
async def add_rejection(
    mission_id: MissionId,
    body: RejectionIn,
    principal: Caller,
    sessions: Sessions,
    scheduler: Scheduler,
) -> Rejection:
    """Remember a rejected candidate: later look-alikes in this vehicle's mission are answered "no".

    The mission is the sending vehicle's (`vehicle_id`): missions are keyed by (vehicle, mission).
    """
    require_vehicle_access(principal, body.vehicle_id)
    try:
        # A crop is decoded in the vehicle's slot, like a keyframe (its size checked from its header first).
        async with scheduler.slot(body.vehicle_id):
            rejection = await run_in_threadpool(sessions.add_rejection, mission_id, body)
    except QueueFullError as exc:
        raise HTTPException(
            429, f"too many requests waiting for this vehicle: {exc}", headers={"Retry-After": "1"}
        ) from None
    except UnknownCandidateError as exc:
        raise HTTPException(404, str(exc)) from None
    if principal.vehicle_id is not None and body.candidate_id:
        # The vehicle's own reject (from its GCS): kept as its report, shown on the page; it blocks nothing.
        await run_in_threadpool(
            sessions.record_vehicle_reject, body.vehicle_id, mission_id, body.candidate_id
        )
    return rejection


@router.get("/rejections", response_model=list[Rejection], responses=ERROR_RESPONSES)
def list_rejections(
    mission_id: MissionId,
    principal: Caller,
    sessions: Sessions,
    vehicle_id: Annotated[
        str | None, Query(pattern=IDENTIFIER, description="whose mission; default: the token's vehicle")
    ] = None,
) -> list[Rejection]:
    """The rejections of one vehicle's mission (the supervisor names the vehicle)."""
    vehicle = vehicle_id or principal.vehicle_id
    if vehicle is None:
        raise HTTPException(422, "the supervisor must name the vehicle: ?vehicle_id=<id>")
    require_vehicle_access(principal, vehicle)
    return sessions.rejections(vehicle, mission_id)


@router.get("/map", response_model=MergedMap, responses=ERROR_RESPONSES)
def mission_map(mission_id: MissionId, _: SupervisorCaller, sessions: Sessions) -> MergedMap:
    """The mission's map over every vehicle searching this mission id: the union of their search and
    covered areas, the coverage of the whole, and one POD map (1 - prod(1 - each vehicle's POD) per place).
    Merged at most once per `[fleet] merge_period_s`, off the request, and shared with the supervisor page:
    the map is served as kept meanwhile, `as_of` and `age_s` say when its vehicles' maps were read.
    404 when no vehicle has reported a map of it."""
    merged = sessions.merged_map(mission_id)
    if merged is None:
        raise HTTPException(404, f"no vehicle has reported a map of mission {mission_id!r}")
    return merged.model_copy(update={"age_s": round(max(0.0, time.time() - merged.as_of), 3)})


@router.get("/dropouts", response_model=MissionDropouts, responses=ERROR_RESPONSES)
def mission_dropouts(mission_id: MissionId, _: SupervisorCaller, sessions: Sessions) -> MissionDropouts:
    """The vehicles that left the mission's search (RTL or LAND reported, the companion's abort or a pilot's
    takeover, another mission, or silent for longer than `[fleet] dropout_s`), each with the part of its area
    that no vehicle has covered (what `cloudtrack-gcs replan` re-splits over the vehicles still searching),
    and the vehicles still searching. Worked out on each read from the vehicles' last statuses and maps.
    404 when no vehicle has reported a map of it."""
    answer = sessions.dropouts(mission_id)
    if answer is None:
        raise HTTPException(404, f"no vehicle has reported a map of mission {mission_id!r}")
    return answer


@router.put(
    "/on_find",
    response_model=OnFindIn,
    responses={
        **ERROR_RESPONSES,
        409: {"model": ErrorResponse, "description": "another on_find stands for the mission (named)"},
    },
)
def set_on_find(mission_id: MissionId, body: OnFindIn, principal: Caller, sessions: Sessions) -> OnFindIn:
    """Set what the fleet does on the mission's first confirmed find (the supervisor, or a vehicle at its
    start). The first setting stands: the same again is 200, another is 409 naming the one that stands.
    A vehicle's setting opens its search of the mission (its mission quota, 429), so it goes with it."""
    if principal.vehicle_id is not None:
        sessions.open_mission(principal.vehicle_id, mission_id)
    standing = sessions.set_on_find(mission_id, body.on_find)
    if standing != body.on_find:
        raise HTTPException(
            409, f"mission {mission_id!r} already has on_find {standing!r}; that setting stands"
        )
    return body


@router.get("/fleet", response_model=FleetOrder, responses=ERROR_RESPONSES)
def fleet_order(
    mission_id: MissionId,
    principal: Caller,
    sessions: Sessions,
    vehicle_id: Annotated[
        str | None, Query(pattern=IDENTIFIER, description="which vehicle; default: the token's vehicle")
    ] = None,
) -> FleetOrder:
    """What the vehicle is to do now in the fleet mission: "continue" until the first find is confirmed (and
    always for the vehicle that found the person), then the mission's on_find. With it, the other vehicles'
    rejections of the mission that carry a place (`rejections`): the companion proposes nobody standing there."""
    vehicle = vehicle_id or principal.vehicle_id
    if vehicle is None:
        raise HTTPException(422, "the supervisor must name the vehicle: ?vehicle_id=<id>")
    require_vehicle_access(principal, vehicle)
    return sessions.fleet_order(vehicle, mission_id)
