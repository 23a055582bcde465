"""The FastAPI application: `create_app(config, detector=..., verifier=...)`.

Routes: `POST /v1/detect`, `GET /health`, `GET /v1/models`, and the session endpoints the companion and
the supervisor use (rejections, vehicle status, decisions). Shared objects live on `app.state`:
`config`, `pipeline`, `sessions` (backend.sessions.SessionStore over a backend.state_store.StateStore),
`scheduler`, `feed` (backend.change_feed.ChangeFeed).

Hostile input: every image's size is read from its header before decoding, and decoding runs inside the
vehicle's fair-queue slot (a flood of bombs waits behind its own sender); bodies are bounded in bytes and
in time; per-vehicle quotas (request rate, live missions, rejections per mission) answer 429 with
Retry-After.
"""

from __future__ import annotations

import os
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError

import cloudtrack
from backend.api_docs import add_offline_docs
from backend.auth import Principal, authenticated, require_supervisor, require_vehicle_access
from backend.change_feed import ChangeFeed
from backend.config import BackendConfig, SessionConfig
from backend.detectors.factory import build_detector
from backend.detectors.interface import SupersetDetector
from backend.fair_queue import FairScheduler, QueueFullError
from backend.images import ImageError, check_size, decode_image
from backend.pipeline import Pipeline
from backend.request_limits import BodyLimits
from backend.security_headers import SecurityHeaders
from backend.service_lifecycle import lifecycle_router
from backend.sessions import SessionStore, UnknownCandidateError
from backend.state_store import QuotaExceededError, SqliteStore, StateStore
from backend.supersets import UnknownSupersetError, known_supersets, superset_from_prompt
from backend.supervisor_routes import supervisor_router
from backend.verifiers.factory import build_verifier
from backend.verifiers.interface import Verifier
from behaviors.geometry import Box
from cloudtrack.api_models import (
    IDENTIFIER,
    Candidate,
    Decision,
    DecisionIn,
    DetectMeta,
    DetectResponse,
    ErrorResponse,
    HealthResponse,
    ModelNames,
    ModelsResponse,
    Rejection,
    RejectionIn,
    Timings,
    VehicleStatus,
    VehicleStatusIn,
)

ERRORS: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse} for status in (400, 401, 403, 404, 408, 413, 415, 422, 429)
}
VehicleId = Annotated[str, PathParam(pattern=IDENTIFIER)]
MissionId = Annotated[str, PathParam(pattern=IDENTIFIER)]
_UNSET = object()


def default_sqlite_path() -> Path:
    """$STATE_DIRECTORY under systemd (StateDirectory=), else $XDG_DATA_HOME (~/.local/share) /cloudtrack."""
    state_dir = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if state_dir:
        return Path(state_dir) / "backend-sessions.sqlite3"
    data_home = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data_home) / "cloudtrack" / "backend-sessions.sqlite3"


def build_state_store(s: SessionConfig) -> StateStore:
    """The configured store: SQLite (`sessions.sqlite_path`, ":memory:" for none) or Redis (`sessions.redis_url`)."""
    if s.store == "redis":
        from backend.redis_store import RedisStore

        return RedisStore(s.redis_url)
    return SqliteStore(s.sqlite_path or default_sqlite_path())


def create_app(
    config: BackendConfig,
    detector: SupersetDetector | None = None,
    verifier: Verifier | None | object = _UNSET,
    sessions: SessionStore | None = None,
) -> FastAPI:
    """The service; `detector`/`verifier` override the configured ones (pass verifier=None for none)."""
    detector = detector if detector is not None else build_detector(config.detector)
    chosen_verifier: Verifier | None = (
        build_verifier(config.verifier, config.vlm) if verifier is _UNSET else verifier  # type: ignore[assignment]
    )
    pool = ThreadPoolExecutor(max_workers=config.verifier.concurrency, thread_name_prefix="verify")
    pipeline = Pipeline(
        detector,
        chosen_verifier,
        pool,
        margin_px=config.crops.margin_px,
        max_candidates=config.detector.max_candidates,
        timeout_s=config.verifier.timeout_s,
        deadline_s=config.verifier.request_deadline_s,
        uncertain_policy=config.verifier.uncertain_policy,
    )
    s = config.sessions
    store = sessions or SessionStore(
        build_state_store(s), s.rejection_similarity, s.rejection_radius_m, s.mission_ttl_s,
        s.max_rejections_per_mission, s.max_missions_per_vehicle, config.server.max_crop_pixels,
    )
    feed = ChangeFeed(store.state)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        feed.start()
        yield
        feed.stop()
        pool.shutdown(wait=False, cancel_futures=True)

    app = FastAPI(
        lifespan=lifespan,
        docs_url=None,  # served from the package by add_offline_docs: no CDN
        redoc_url=None,
        title="CloudTrack back-end",
        version=cloudtrack.__version__,
        description="Semantic detection for many drones: superset detector, 50 px margin crops, concurrent "
        "verification, rejection memory per mission. Boxes are [x1, y1, x2, y2] in the sent image's pixels.",
    )
    app.state.config = config
    app.state.pipeline = pipeline
    app.state.sessions = store
    app.state.feed = feed
    app.state.scheduler = FairScheduler(s.detector_concurrency, s.max_queued_per_vehicle)
    app.state.started = time.time()
    app.add_middleware(BodyLimits, max_bytes=config.server.max_request_bytes, timeout_s=config.server.body_timeout_s)
    app.add_middleware(SecurityHeaders)

    @app.exception_handler(QuotaExceededError)
    async def _quota(_: Request, exc: QuotaExceededError) -> JSONResponse:
        return JSONResponse(status_code=429, content={"detail": str(exc)},
                            headers={"Retry-After": str(int(exc.retry_after_s))})

    @app.exception_handler(ImageError)
    async def _image(_: Request, exc: ImageError) -> JSONResponse:
        return JSONResponse(status_code=exc.status, content={"detail": str(exc)})

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's default echoes the input back, and JSON cannot encode a NaN or Infinity it was sent.
        errors = [{"type": e["type"], "loc": list(e["loc"]), "msg": e["msg"]} for e in exc.errors()]
        return JSONResponse(status_code=422, content={"detail": jsonable_encoder(errors)})

    _add_detection_routes(app)
    _add_session_routes(app)
    app.include_router(supervisor_router(store, feed))
    app.include_router(lifecycle_router())  # sd_notify READY/WATCHDOG/STOPPING under systemd
    add_offline_docs(app)
    return app


def admit(app: FastAPI, principal: Principal) -> None:
    """A vehicle's request-rate quota (the supervisor has none): QuotaExceededError -> 429 + Retry-After."""
    if principal.vehicle_id is None:
        return
    s: SessionConfig = app.state.config.sessions
    sessions: SessionStore = app.state.sessions
    wait = sessions.state.rate_hit(principal.vehicle_id, time.time(), s.rate_limit_requests, s.rate_limit_window_s)
    if wait is not None:
        raise QuotaExceededError(
            f"vehicle {principal.vehicle_id!r} sent more than {s.rate_limit_requests} requests in "
            f"{s.rate_limit_window_s:g} s", wait
        )


def _models(app: FastAPI) -> ModelNames:
    pipeline: Pipeline = app.state.pipeline
    return ModelNames(detector=pipeline.detector.name, verifier=pipeline.verifier_name)


def _add_detection_routes(app: FastAPI) -> None:
    @app.get("/health", response_model=HealthResponse, tags=["service"])
    def health() -> HealthResponse:
        """Liveness and load, without authentication (for load balancers)."""
        scheduler: FairScheduler = app.state.scheduler
        return HealthResponse(
            status="ok",
            version=cloudtrack.__version__,
            uptime_s=time.time() - app.state.started,
            models=_models(app),
            in_flight=scheduler.running,
            queued=scheduler.queued,
        )

    @app.get("/v1/models", response_model=ModelsResponse, responses=ERRORS, tags=["service"])
    def models(principal: Annotated[Principal, Depends(authenticated)]) -> ModelsResponse:
        config: BackendConfig = app.state.config
        names = _models(app)
        closed_set = config.detector.kind == "yolox"
        return ModelsResponse(
            detector=names.detector,
            detector_kind=config.detector.kind,
            supersets=known_supersets() if closed_set else [],
            verifier=names.verifier,
            verifier_kind=config.verifier.kind if app.state.pipeline.verifier is not None else "none",
        )

    @app.post("/v1/detect", response_model=DetectResponse, responses=ERRORS, tags=["detection"])
    async def detect(
        principal: Annotated[Principal, Depends(authenticated)],
        image: Annotated[UploadFile, File(description="the keyframe, JPEG or PNG")],
        meta: Annotated[str, Form(description="JSON object, see DetectMeta", max_length=20_000)],
    ) -> DetectResponse:
        """Detect the superset in a keyframe and verify each candidate against the full description."""
        t_received = time.perf_counter()
        try:
            fields = DetectMeta.model_validate_json(meta)
        except ValidationError as exc:
            # Echoing the input back could carry NaN/inf, which JSON cannot encode: loc + msg say enough.
            errors = [
                {"type": e["type"], "loc": ["meta", *e["loc"]], "msg": e["msg"]}
                for e in exc.errors(include_url=False, include_context=False, include_input=False)
            ]
            raise HTTPException(422, jsonable_encoder(errors)) from None
        require_vehicle_access(principal, fields.vehicle_id)
        admit(app, principal)
        superset = (fields.superset or superset_from_prompt(fields.prompt) or "").strip().lower()
        if not superset:
            raise HTTPException(422, "the prompt names no known class; set 'superset' (e.g. \"person\")")
        data = await image.read()
        config: BackendConfig = app.state.config
        check_size(data, config.server.max_image_pixels)  # a bomb is refused by its header, undecoded
        sessions: SessionStore = app.state.sessions
        await run_in_threadpool(sessions.open_mission, fields.vehicle_id, fields.mission_id)
        check = await run_in_threadpool(
            sessions.rejection_check, fields.vehicle_id, fields.mission_id, fields.vehicle_position
        )
        roi = Box.from_xyxy(*fields.roi) if fields.roi else None
        pipeline: Pipeline = app.state.pipeline
        t_queued = time.perf_counter()
        try:
            # Decoding happens inside the vehicle's slot: one vehicle's uploads decode one after another.
            async with app.state.scheduler.slot(fields.vehicle_id):
                t_queue = time.perf_counter() - t_queued
                t_decode = time.perf_counter()
                frame = await run_in_threadpool(decode_image, data, config.server.max_image_pixels)
                t_decode = time.perf_counter() - t_decode
                t_detect = time.perf_counter()
                detections = await run_in_threadpool(pipeline.detect, frame, superset, roi, fields.frame_id)
                t_detect = time.perf_counter() - t_detect
        except QueueFullError as exc:
            raise HTTPException(429, f"too many requests waiting for this vehicle: {exc}", headers={"Retry-After": "1"}) from None
        except UnknownSupersetError as exc:
            raise HTTPException(422, str(exc)) from None
        # Verification runs outside the detector slot: a slow VLM must not hold the detector, and the
        # verifier pool already bounds how many verifications run at once.
        t_verify = time.perf_counter()
        candidates = await pipeline.verify_async(frame, detections, fields.prompt, superset, check, t_received + pipeline.deadline_s)
        t_verify = time.perf_counter() - t_verify
        await run_in_threadpool(
            sessions.remember_candidates, fields.vehicle_id, fields.mission_id,
            [(c.detection.candidate_id, c.appearance) for c in candidates],
        )
        return DetectResponse(
            vehicle_id=fields.vehicle_id,
            mission_id=fields.mission_id,
            frame_id=fields.frame_id,
            capture_time=fields.capture_time,
            image_size=[int(frame.shape[1]), int(frame.shape[0])],
            superset=superset,
            candidates=[
                Candidate(
                    candidate_id=c.detection.candidate_id,
                    box=[round(v, 2) for v in c.detection.box.xyxy()],
                    score=round(c.detection.score, 4),
                    label=c.detection.label,
                    verdict=c.detection.verdict.value,
                    justification=c.detection.justification,
                    verifier=c.verifier,
                    t_verify=round(c.t_verify, 4),
                    previously_rejected=c.previously_rejected,
                )
                for c in candidates
            ],
            timings=Timings(
                t_queue=t_queue,
                t_decode=t_decode,
                t_detect=t_detect,
                t_verify=t_verify,
                t_total=time.perf_counter() - t_received,
            ),
            models=_models(app),
        )


def _add_session_routes(app: FastAPI) -> None:
    def store() -> SessionStore:
        sessions: SessionStore = app.state.sessions
        return sessions

    @app.post("/v1/missions/{mission_id}/rejections", response_model=Rejection, status_code=201, responses=ERRORS, tags=["sessions"])
    async def add_rejection(
        mission_id: MissionId, body: RejectionIn, principal: Annotated[Principal, Depends(authenticated)]
    ) -> Rejection:
        """Remember a rejected candidate: later look-alikes in this vehicle's mission are answered "no".

        The mission is the sending vehicle's (`vehicle_id`): missions are keyed by (vehicle, mission).
        """
        require_vehicle_access(principal, body.vehicle_id)
        admit(app, principal)
        try:
            # A crop is decoded in the vehicle's slot, like a keyframe (its size checked from its header first).
            async with app.state.scheduler.slot(body.vehicle_id):
                return await run_in_threadpool(store().add_rejection, mission_id, body)
        except QueueFullError as exc:
            raise HTTPException(429, f"too many requests waiting for this vehicle: {exc}", headers={"Retry-After": "1"}) from None
        except UnknownCandidateError as exc:
            raise HTTPException(404, str(exc)) from None

    @app.get("/v1/missions/{mission_id}/rejections", response_model=list[Rejection], responses=ERRORS, tags=["sessions"])
    def list_rejections(
        mission_id: MissionId,
        principal: Annotated[Principal, Depends(authenticated)],
        vehicle_id: Annotated[
            str | None, Query(pattern=IDENTIFIER, description="whose mission; default: the token's vehicle")
        ] = None,
    ) -> list[Rejection]:
        """The rejections of one vehicle's mission (the supervisor names the vehicle)."""
        vehicle = vehicle_id or principal.vehicle_id
        if vehicle is None:
            raise HTTPException(422, "the supervisor must name the vehicle: ?vehicle_id=<id>")
        require_vehicle_access(principal, vehicle)
        admit(app, principal)
        return store().rejections(vehicle, mission_id)

    @app.post("/v1/vehicles/{vehicle_id}/status", response_model=VehicleStatus, responses=ERRORS, tags=["sessions"])
    def report_status(
        vehicle_id: VehicleId, body: VehicleStatusIn, principal: Annotated[Principal, Depends(authenticated)]
    ) -> VehicleStatus:
        """The companion's state and the candidate awaiting the supervisor (crop, justification, position).

        The crop must be a JPEG (checked from its header, at most `server.max_crop_pixels`), else 413/422.
        """
        require_vehicle_access(principal, vehicle_id)
        admit(app, principal)
        return store().set_status(vehicle_id, body)

    @app.get("/v1/vehicles/{vehicle_id}/status", response_model=VehicleStatus, responses=ERRORS, tags=["sessions"])
    def get_status(vehicle_id: VehicleId, principal: Annotated[Principal, Depends(authenticated)]) -> VehicleStatus:
        require_vehicle_access(principal, vehicle_id)
        status = store().status(vehicle_id)
        if status is None:
            raise HTTPException(404, f"vehicle {vehicle_id!r} has not reported a status")
        return status

    @app.get("/v1/vehicles", response_model=list[VehicleStatus], responses=ERRORS, tags=["sessions"])
    def list_vehicles(principal: Annotated[Principal, Depends(require_supervisor)]) -> list[VehicleStatus]:
        return store().statuses()

    @app.post("/v1/vehicles/{vehicle_id}/decisions", response_model=Decision, status_code=201, responses=ERRORS, tags=["sessions"])
    def decide(
        vehicle_id: VehicleId, body: DecisionIn, principal: Annotated[Principal, Depends(require_supervisor)]
    ) -> Decision:
        """The supervisor confirms or rejects a candidate; a reject also enters the rejection memory.

        Both are stored (on disk, or in Redis) before the 201; a crop that cannot be read only keeps the
        reject out of the memory, never loses the decision.
        """
        return store().add_decision(vehicle_id, body)

    @app.get("/v1/vehicles/{vehicle_id}/decisions", response_model=list[Decision], responses=ERRORS, tags=["sessions"])
    def poll_decisions(
        vehicle_id: VehicleId,
        principal: Annotated[Principal, Depends(authenticated)],
        after: Annotated[int, Query(ge=0, description="last decision_id already seen")] = 0,
    ) -> list[Decision]:
        """Decisions for this vehicle newer than `after` (the companion polls this)."""
        require_vehicle_access(principal, vehicle_id)
        admit(app, principal)
        return store().decisions(vehicle_id, after)

