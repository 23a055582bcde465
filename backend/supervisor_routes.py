"""The supervisor's web page: vehicles, the candidate each one awaits a decision on, Confirm / Reject.

Routes (all under /supervisor):
  GET  /supervisor                      the page (static HTML; it holds no data, so it needs no token)
  GET  /supervisor/static/{name}        its script and style sheet
  GET  /supervisor/api/state            the snapshot below, as JSON
  GET  /supervisor/api/enabled          {"enabled": bool}: whether a supervisor token is configured (no token)
  GET  /supervisor/events               the same snapshot pushed as Server-Sent Events on every change
  GET  /supervisor/api/vehicles/{v}/candidates/{c}/crop.jpg    the crop the verifier saw
  POST /supervisor/api/vehicles/{v}/candidates/{c}/decision    {"decision": "confirm" | "reject"}

Everything but the page itself takes the supervisor's bearer token (`auth.supervisor_token`) through
the API's own dependency, `backend.auth.require_supervisor` (401 without it, 403 for a vehicle's token).
With no supervisor token configured (the default) the page says how to turn it on instead of asking for a
token that does not exist. A decision is stored in the session store (on disk or in Redis before the 201)
as the vehicle's next decision; the companion picks it up when it polls its session, so the page works with
no MAVLink ground station. The page shows the whole fleet from the shared store, whichever replica answers,
and its event stream is woken by the store's changes (backend.change_feed), not by polling per client.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from backend.auth import require_supervisor
from backend.change_feed import ChangeFeed
from backend.images import ImageError, b64_image_bytes, is_jpeg
from backend.sessions import SessionStore
from cloudtrack.api_models import IDENTIFIER, NOTE_MAX, DecisionIn

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_FILES = {
    "supervisor.js": "text/javascript; charset=utf-8",
    "supervisor.css": "text/css; charset=utf-8",
}
_NO_STORE = {"Cache-Control": "no-store"}
VehicleId = Annotated[str, PathParam(pattern=IDENTIFIER)]
CandidateId = Annotated[str, PathParam(pattern=IDENTIFIER)]


class DecisionBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    decision: Literal["confirm", "reject"]
    note: str = Field("", max_length=NOTE_MAX)  # the API's own limit: 422 beyond it, never a 500


class SupervisorView:
    """Turns the session store into what the page shows, and remembers since when each candidate waits."""

    def __init__(self, store: SessionStore, clock: Callable[[], float] = time.time) -> None:
        self.store = store
        self._clock = clock
        self._first_seen: dict[tuple[str, str], float] = {}

    def snapshot(self) -> dict[str, Any]:
        now = self._clock()
        vehicles = []
        waiting: set[tuple[str, str]] = set()
        for status_ in self.store.statuses():
            candidates = []
            awaiting = status_.awaiting
            if awaiting is not None:
                key = (status_.vehicle_id, awaiting.candidate_id)
                waiting.add(key)
                first = self._first_seen.setdefault(key, min(now, status_.updated_at))
                decided = [d for d in self.store.decisions(status_.vehicle_id) if d.candidate_id == awaiting.candidate_id]
                candidates.append(
                    {
                        "id": awaiting.candidate_id,
                        "verdict": awaiting.verdict,
                        "justification": awaiting.justification,
                        "position": (
                            {"lat": awaiting.position[0], "lon": awaiting.position[1]} if awaiting.position else None
                        ),
                        "box": awaiting.box,
                        "age_s": round(max(0.0, now - first), 1),
                        "crop_url": (
                            f"/supervisor/api/vehicles/{status_.vehicle_id}/candidates/{awaiting.candidate_id}/crop.jpg"
                            if awaiting.crop_jpeg_b64
                            else None
                        ),
                        "status": {"confirm": "confirmed", "reject": "rejected"}[decided[-1].action]
                        if decided
                        else "awaiting",
                    }
                )
            vehicles.append(
                {
                    "id": status_.vehicle_id,
                    "state": status_.state,
                    "mission_id": status_.mission_id,
                    "prompt": status_.prompt,
                    "position": status_.position,
                    "altitude_m": status_.altitude_m,
                    "age_s": round(max(0.0, now - status_.updated_at), 1),
                    "candidates": candidates,
                }
            )
        # Forget candidates nobody waits on any more, so the map stays as small as the fleet.
        for key in [k for k in self._first_seen if k not in waiting]:
            del self._first_seen[key]
        return {"server_time": now, "vehicles": vehicles}


def _without_ages(snapshot: dict[str, Any]) -> str:
    """The snapshot's content minus what changes every second, to tell a real change from time passing."""
    vehicles = [
        {**v, "age_s": None, "candidates": [{**c, "age_s": None} for c in v["candidates"]]} for v in snapshot["vehicles"]
    ]
    return json.dumps(vehicles, sort_keys=True)


def supervisor_router(
    store: SessionStore, feed: ChangeFeed, *, keepalive_s: float = 15.0, max_stream_s: float = 30.0
) -> APIRouter:
    """The page's routes over the back-end's session store; include it in the app with `include_router`.

    Authentication is the API's own (`backend.auth.require_supervisor`: the app's `auth.supervisor_token`).
    """
    view = SupervisorView(store)
    router = APIRouter(prefix="/supervisor", tags=["supervisor"])
    authed = [Depends(require_supervisor)]

    @router.get("", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC_DIR / "supervisor.html", media_type="text/html; charset=utf-8", headers=_NO_STORE)

    @router.get("/static/{name}", include_in_schema=False)
    def static(name: str) -> FileResponse:
        if name not in STATIC_FILES:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no static file {name!r}")
        return FileResponse(STATIC_DIR / name, media_type=STATIC_FILES[name], headers=_NO_STORE)

    @router.get("/api/enabled")
    def enabled(request: Request) -> dict[str, bool]:
        """Whether the supervisor endpoints are on (a supervisor token is configured); needs no token."""
        return {"enabled": bool(request.app.state.config.auth.supervisor_token)}

    @router.get("/api/state", dependencies=authed)
    def state() -> dict[str, Any]:
        """Every vehicle's state and the candidate it awaits a decision on."""
        return view.snapshot()

    @router.get("/events", dependencies=authed)
    async def events(request: Request) -> StreamingResponse:
        """Server-Sent Events: `event: state` with the snapshot whenever the store changes, comments as keep-alive."""

        async def stream() -> AsyncIterator[str]:
            opened = time.monotonic()
            yield "retry: 1000\n\n"
            version = feed.version
            last = None
            # A stream ends after max_stream_s and the page reconnects at once: a server shutting down
            # (uvicorn waits for open responses) or a proxy's idle limit never holds a stream for long.
            while not await request.is_disconnected() and time.monotonic() - opened < max_stream_s:
                snapshot = await run_in_threadpool(view.snapshot)
                content = _without_ages(snapshot)
                if content != last:
                    last = content
                    yield f"event: state\ndata: {json.dumps(snapshot)}\n\n"
                else:
                    yield ": keep-alive\n\n"  # proxies close silent connections
                remaining = max_stream_s - (time.monotonic() - opened)
                version = await feed.wait(version, max(0.0, min(keepalive_s, remaining)))

        headers = {**_NO_STORE, "X-Accel-Buffering": "no"}  # nginx: pass events through unbuffered
        return StreamingResponse(stream(), media_type="text/event-stream", headers=headers)

    @router.get("/api/vehicles/{vehicle_id}/candidates/{candidate_id}/crop.jpg", dependencies=authed)
    def crop(vehicle_id: VehicleId, candidate_id: CandidateId, request: Request) -> Response:
        current = store.status(vehicle_id)
        awaiting = current.awaiting if current else None
        if awaiting is None or awaiting.candidate_id != candidate_id or not awaiting.crop_jpeg_b64:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no crop for candidate {candidate_id!r} of {vehicle_id!r}")
        try:
            data = b64_image_bytes(awaiting.crop_jpeg_b64)
        except ImageError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        # Only bytes that are a JPEG by their header go out as image/jpeg (the store checks on the way in too).
        if not is_jpeg(data, store.max_crop_pixels):
            raise HTTPException(422, "the vehicle's crop is not a JPEG image")
        return Response(data, media_type="image/jpeg", headers=_NO_STORE)

    @router.post(
        "/api/vehicles/{vehicle_id}/candidates/{candidate_id}/decision",
        dependencies=authed,
        status_code=status.HTTP_201_CREATED,
    )
    def decide(vehicle_id: VehicleId, candidate_id: CandidateId, body: DecisionBody) -> dict[str, Any]:
        """Confirm or reject the candidate the vehicle awaits a decision on; stored before the 201."""
        current = store.status(vehicle_id)
        if current is None:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"vehicle {vehicle_id!r} has not reported")
        if current.awaiting is None or current.awaiting.candidate_id != candidate_id:
            raise HTTPException(
                status.HTTP_409_CONFLICT, f"{vehicle_id!r} is no longer waiting for a decision on {candidate_id!r}"
            )
        record = store.add_decision(
            vehicle_id, DecisionIn(candidate_id=candidate_id, action=body.decision, note=body.note or "supervisor page")
        )
        return record.model_dump()

    return router
