"""The supervisor's web page: vehicles, the candidate each one awaits a decision on, Confirm / Reject.

Routes (all under /supervisor):
  GET  /supervisor                      the page (static HTML; it holds no data, so it needs no token)
  GET  /supervisor/static/{name}        its script and style sheet
  GET  /supervisor/api/state            the snapshot (`backend.schemas.SupervisorSnapshot`), as JSON
  GET  /supervisor/api/enabled          {"enabled": bool}: whether a supervisor token is configured (no token)
  GET  /supervisor/events               the same snapshot pushed as Server-Sent Events on every change
  GET  /supervisor/api/vehicles/{v}/candidates/{c}/crop.jpg    the crop the verifier saw
  GET  /supervisor/api/vehicles/{v}/finds/{m}/{c}/crop.jpg      a confirmed find's crop
  GET  /supervisor/api/vehicles/{v}/keyframe.jpg                the newest keyframe (the snapshot has its boxes)

The page's Confirm / Reject go to the API's one decision endpoint, `POST /v1/vehicles/{v}/decisions`
with `?require_awaiting=true` (`backend.routers.vehicles`): stored in the session store (on disk or in
Redis before the 201) as the vehicle's next decision, which the companion picks up when it polls its
session, so the page works with no MAVLink ground station.

Everything but the page itself takes the supervisor's bearer token (`auth.supervisor_token`, through
`backend.dependencies.SupervisorCaller`: 401 without it, 403 for a vehicle's token). With no supervisor
token configured (the default) the page says how to turn it on instead of asking for a token that does not
exist. The page shows the whole fleet from the shared store, whichever replica answers, and its event
stream is woken by the store's changes (backend.change_feed), not by polling per client.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response, StreamingResponse

from backend.dependencies import (
    CandidateId,
    Feed,
    MissionId,
    Sessions,
    Settings,
    StreamLimits,
    VehicleId,
    View,
    require_supervisor,
)
from backend.images import ImageError, b64_image_bytes, is_jpeg
from backend.schemas import SupervisorEnabled, SupervisorSnapshot
from backend.supervisor_view import STREAM_BUILD_MIN_S, missions_content, view_content

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
STATIC_FILES = {
    "supervisor.js": "text/javascript; charset=utf-8",
    "supervisor.css": "text/css; charset=utf-8",
}
_NO_STORE = {"Cache-Control": "no-store"}
_AUTHED = [Depends(require_supervisor)]

router = APIRouter(prefix="/supervisor", tags=["supervisor"])


@router.get("", include_in_schema=False)
def page() -> FileResponse:
    return FileResponse(
        STATIC_DIR / "supervisor.html", media_type="text/html; charset=utf-8", headers=_NO_STORE
    )


@router.get("/static/{name}", include_in_schema=False)
def static(name: str) -> FileResponse:
    if name not in STATIC_FILES:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no static file {name!r}")
    return FileResponse(STATIC_DIR / name, media_type=STATIC_FILES[name], headers=_NO_STORE)


@router.get("/api/enabled")
def enabled(settings: Settings) -> SupervisorEnabled:
    """Whether the supervisor endpoints are on (a supervisor token is configured); needs no token."""
    return SupervisorEnabled(enabled=bool(settings.auth.supervisor_token))


@router.get("/api/state", dependencies=_AUTHED)
def state(view: View) -> SupervisorSnapshot:
    """Every vehicle's state and the candidate it awaits a decision on."""
    return view.snapshot()


@router.get("/events", dependencies=_AUTHED)
async def events(request: Request, view: View, feed: Feed, limits: StreamLimits) -> StreamingResponse:
    """Server-Sent Events: `state` (the whole snapshot) first and when vehicles come or go, `vehicle` (one
    vehicle's view) when only it changed, `fleet` ({"missions": [...]}, the merged maps) when they changed,
    `ages` when reports arrived (also beside the others), comments as keep-alive. Built at most once per STREAM_BUILD_MIN_S."""

    async def stream() -> AsyncIterator[str]:
        opened = time.monotonic()
        yield "retry: 1000\n\n"
        version = feed.version
        sent: dict[str, str] | None = None  # vehicle id -> its content as last sent
        sent_fleet = ""  # the missions' merged maps as last sent
        reported: dict[str, float] = {}
        # A stream ends after max_stream_s and the page reconnects at once: a server shutting down
        # (uvicorn waits for open responses) or a proxy's idle limit never holds a stream for long.
        while not await request.is_disconnected() and time.monotonic() - opened < limits.max_stream_s:
            built_at = time.monotonic()
            snapshot = await run_in_threadpool(view.snapshot)
            content = {v.id: view_content(v) for v in snapshot.vehicles}
            fleet = missions_content(snapshot)
            ages = {v.id: v.age_s for v in snapshot.vehicles}
            # A report that changed nothing still makes the vehicle's "last report" young again.
            reports = {vid: snapshot.server_time - age for vid, age in ages.items()}
            fresher = any(at > reported.get(vid, 0.0) + 0.05 for vid, at in reports.items())
            if sent is None or content.keys() != sent.keys():
                yield f"event: state\ndata: {snapshot.model_dump_json()}\n\n"
            else:
                told = False
                for vehicle in snapshot.vehicles:
                    if content[vehicle.id] != sent[vehicle.id]:
                        yield f"event: vehicle\ndata: {vehicle.model_dump_json()}\n\n"
                        told = True
                if fleet != sent_fleet:
                    yield f'event: fleet\ndata: {{"missions": {fleet}}}\n\n'
                    told = True
                # Every vehicle's last report, also when a merged map or another vehicle changed meanwhile.
                if fresher:
                    yield f"event: ages\ndata: {json.dumps(ages)}\n\n"
                    told = True
                if not told:
                    yield ": keep-alive\n\n"  # proxies close silent connections
            sent, reported, sent_fleet = content, reports, fleet
            remaining = limits.max_stream_s - (time.monotonic() - opened)
            version = await feed.wait(version, max(0.0, min(limits.keepalive_s, remaining)))
            # A fleet changes the store all the time: one build per STREAM_BUILD_MIN_S, not one per change.
            pause = STREAM_BUILD_MIN_S - (time.monotonic() - built_at)
            if pause > 0:
                await asyncio.sleep(pause)

    headers = {**_NO_STORE, "X-Accel-Buffering": "no"}  # nginx: pass events through unbuffered
    return StreamingResponse(stream(), media_type="text/event-stream", headers=headers)


@router.get("/api/vehicles/{vehicle_id}/candidates/{candidate_id}/crop.jpg", dependencies=_AUTHED)
def crop(vehicle_id: VehicleId, candidate_id: CandidateId, sessions: Sessions) -> Response:
    current = sessions.status(vehicle_id)
    awaiting = current.awaiting if current else None
    if awaiting is None or awaiting.candidate_id != candidate_id or not awaiting.crop_jpeg_b64:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no crop for candidate {candidate_id!r} of {vehicle_id!r}"
        )
    return _jpeg(awaiting.crop_jpeg_b64, sessions.max_crop_pixels)


@router.get("/api/vehicles/{vehicle_id}/finds/{mission_id}/{candidate_id}/crop.jpg", dependencies=_AUTHED)
def find_crop(
    vehicle_id: VehicleId, mission_id: MissionId, candidate_id: CandidateId, sessions: Sessions
) -> Response:
    """The crop of a confirmed find (it stays when the vehicle has moved on)."""
    found = [f for f in sessions.finds(vehicle_id, mission_id) if f.candidate_id == candidate_id]
    if not found or not found[0].crop_jpeg_b64:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no crop for the find {candidate_id!r} of {vehicle_id!r}"
        )
    return _jpeg(found[0].crop_jpeg_b64, sessions.max_crop_pixels)


@router.get("/api/vehicles/{vehicle_id}/keyframe.jpg", dependencies=_AUTHED)
def keyframe(vehicle_id: VehicleId, sessions: Sessions) -> Response:
    """The newest keyframe the vehicle sent to /v1/detect (the snapshot holds its boxes)."""
    kept = sessions.state.keyframe_jpeg(vehicle_id)
    if kept is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no keyframe from {vehicle_id!r}")
    return Response(kept[1], media_type="image/jpeg", headers=_NO_STORE)


def _jpeg(b64: str, max_pixels: int) -> Response:
    try:
        data = b64_image_bytes(b64)
    except ImageError as exc:
        raise HTTPException(exc.status, str(exc)) from None
    # Only bytes that are a JPEG by their header go out as image/jpeg (the store checks on the way in too).
    if not is_jpeg(data, max_pixels):
        raise HTTPException(422, "the vehicle's crop is not a JPEG image")
    return Response(data, media_type="image/jpeg", headers=_NO_STORE)
