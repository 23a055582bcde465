"""What the routes need, as FastAPI dependencies: settings, the shared objects, and who is calling.

`create_app` builds each shared object once and keeps it on `app.state` (`config`, `pipeline`, `sessions`,
`scheduler`, `feed`, `supervisor_view`, `started`); the routes never read `app.state` themselves but
declare what they need (`Settings`, `Sessions`, `Caller`, ...), so a test swaps any of them with
`app.dependency_overrides`. Authentication: a vehicle's or the supervisor's bearer token (`Caller`,
`SupervisorCaller`; the token logic is `backend.auth`), read through FastAPI's `HTTPBearer` so the OpenAPI
schema declares the bearer scheme and /docs has an Authorize button; the 401 answers stay the service's own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, cast

from fastapi import Depends, HTTPException, Request
from fastapi import Path as PathParam
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from backend.auth import Principal, principal_for
from backend.change_feed import ChangeFeed
from backend.config import BackendConfig
from backend.fair_queue import FairScheduler
from backend.pipeline import Pipeline
from backend.sessions import SessionStore
from backend.supervisor_view import SupervisorView
from cloudtrack.api_models import IDENTIFIER, ModelNames

VehicleId = Annotated[str, PathParam(pattern=IDENTIFIER)]
MissionId = Annotated[str, PathParam(pattern=IDENTIFIER)]
CandidateId = Annotated[str, PathParam(pattern=IDENTIFIER)]


@dataclass(frozen=True)
class EventStreamLimits:
    """The supervisor's Server-Sent Events: a keep-alive comment this often, and a stream's longest life."""

    keepalive_s: float = 15.0
    max_stream_s: float = 30.0


def get_settings(request: Request) -> BackendConfig:
    return cast(BackendConfig, request.app.state.config)


def get_sessions(request: Request) -> SessionStore:
    return cast(SessionStore, request.app.state.sessions)


def get_pipeline(request: Request) -> Pipeline:
    return cast(Pipeline, request.app.state.pipeline)


def get_scheduler(request: Request) -> FairScheduler:
    return cast(FairScheduler, request.app.state.scheduler)


def get_feed(request: Request) -> ChangeFeed:
    return cast(ChangeFeed, request.app.state.feed)


def get_supervisor_view(request: Request) -> SupervisorView:
    return cast(SupervisorView, request.app.state.supervisor_view)


def get_started(request: Request) -> float:
    """When the app was built (time.time()), for /health's uptime."""
    return cast(float, request.app.state.started)


def get_event_stream_limits() -> EventStreamLimits:
    return EventStreamLimits()


Settings = Annotated[BackendConfig, Depends(get_settings)]
Sessions = Annotated[SessionStore, Depends(get_sessions)]
CurrentPipeline = Annotated[Pipeline, Depends(get_pipeline)]
Scheduler = Annotated[FairScheduler, Depends(get_scheduler)]
Feed = Annotated[ChangeFeed, Depends(get_feed)]
View = Annotated[SupervisorView, Depends(get_supervisor_view)]
Started = Annotated[float, Depends(get_started)]
StreamLimits = Annotated[EventStreamLimits, Depends(get_event_stream_limits)]


def get_model_names(pipeline: CurrentPipeline) -> ModelNames:
    return ModelNames(detector=pipeline.detector.name, verifier=pipeline.verifier_name)


LoadedModels = Annotated[ModelNames, Depends(get_model_names)]

bearer = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="A vehicle's token (auth.tokens) or the supervisor's (auth.supervisor_token).",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


def authenticated(request: Request, settings: Settings, _credentials: Credentials) -> Principal:
    """A vehicle or the supervisor; 401 for a missing, malformed or unknown token."""
    # The header is parsed here, not from `_credentials`, so that a malformed one gets backend.auth's answer.
    return principal_for(settings.auth, request.headers.get("authorization"))


Caller = Annotated[Principal, Depends(authenticated)]


def require_supervisor(principal: Caller) -> Principal:
    """The supervisor only: 401 without a valid token, 403 for a vehicle's."""
    if not principal.is_supervisor:
        raise HTTPException(403, "this endpoint needs the supervisor token")
    return principal


SupervisorCaller = Annotated[Principal, Depends(require_supervisor)]
