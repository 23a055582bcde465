"""The FastAPI application: `create_app(config, detector=..., verifier=...)`.

It builds the shared objects once (the pipeline, the session store over a backend.state_store.StateStore,
the fair scheduler, the change feed, the supervisor's view) and keeps them on `app.state`, where
`backend.dependencies` hands them to the routes; the routes themselves are in `backend.routers`
(health, detection, missions, vehicles, supervisor). Here too: the middleware that bounds bodies in bytes
and in time and sets the browser-hardening headers, and the error answers shared by every route
(per-vehicle quotas -> 429 with Retry-After, a refused image -> its status, invalid input -> 422).
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

import cloudtrack
from backend.api_docs import add_offline_docs
from backend.change_feed import ChangeFeed
from backend.config import BackendConfig, SessionConfig
from backend.detectors.factory import build_detector
from backend.detectors.interface import SupersetDetector
from backend.fair_queue import FairScheduler
from backend.find_export import find_report
from backend.images import ImageError
from backend.pipeline import Pipeline
from backend.request_limits import RequestLimits
from backend.routers import detection, finds, health, missions, prompt_check, supervisor, vehicles
from backend.security_headers import SecurityHeaders
from backend.service_lifecycle import lifecycle_router
from backend.sessions import SessionStore
from backend.state_store import QuotaExceededError, SqliteStore, StateStore
from backend.supervisor_view import SupervisorView
from backend.validation_errors import summary
from backend.verifiers.factory import build_verifier
from backend.verifiers.interface import Verifier
from cloudtrack.cursor_on_target import CotSender, find_event

_UNSET = object()
# The routes a vehicle calls for itself, its id in the path: where a refused token is that vehicle's.
VEHICLE_OWN_ROUTE = re.compile(r"^/v1/vehicles/([^/]+)/(?:status|decisions)$")


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
    pipeline = Pipeline.configured(config, detector, chosen_verifier, pool)
    s = config.sessions
    store = sessions or SessionStore(
        build_state_store(s),
        s.rejection_similarity,
        s.rejection_radius_m,
        s.mission_ttl_s,
        s.max_rejections_per_mission,
        s.max_missions_per_vehicle,
        config.server.max_crop_pixels,
        dropout_s=config.fleet.dropout_s,
        merge_period_s=config.fleet.merge_period_s,
        merge_in_background=True,  # a mission's merged map is merged off the requests (backend.merged_maps)
        merge_in_process=True,  # ... and off the server's GIL (backend.merge_worker)
    )
    feed = ChangeFeed(store.state)
    store.merged_maps.on_merged = lambda _mission: feed.poke()  # the pages' streams show the new map
    tak = config.tak
    sender = CotSender(tak.url, tak.tls_cert, tak.tls_key, tak.tls_ca) if tak.url else None
    if sender is not None:
        # Each find stored (or refined by the vehicle's own geolocation) goes to the TAK map, off the request.
        store.on_find = lambda find: sender.send(find_event(find_report(find), tak.callsign, tak.stale_s))

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        feed.start()
        if sender is not None:
            sender.start()
        yield
        feed.stop()
        store.merged_maps.close()
        if sender is not None:
            sender.close()
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
    # What backend.dependencies hands to the routes: built once here, never read by a route directly.
    app.state.config = config
    app.state.pipeline = pipeline
    app.state.sessions = store
    app.state.feed = feed
    app.state.scheduler = FairScheduler(s.detector_concurrency, s.max_queued_per_vehicle)
    app.state.supervisor_view = SupervisorView(store, map_tiles=config.supervisor.map_tiles)
    app.state.started = time.time()

    def refused(path: str, detail: str) -> None:
        # A bearer token nobody holds, on a route only a vehicle calls for itself (its status, its decisions):
        # that vehicle's own token, wrong or rotated, so it cannot report and the page says so. No token, a
        # route that does not exist or another vehicle's valid token (403, refused in the route) say nothing.
        own = VEHICLE_OWN_ROUTE.match(path)
        if own is not None and own.group(1) in config.auth.tokens:
            app.state.supervisor_view.note_auth_failure(
                own.group(1), f"the back-end refused this vehicle's token (401: {detail})"
            )

    app.add_middleware(
        RequestLimits,
        server=config.server,
        auth=config.auth,
        sessions=config.sessions,
        rate_hit=store.state.rate_hit,
        on_refused=refused,
        on_admitted=app.state.supervisor_view.clear_auth_failure,
    )
    tiles = urlsplit(config.supervisor.map_tiles)
    app.add_middleware(
        SecurityHeaders, tile_origin=f"{tiles.scheme}://{tiles.netloc}" if tiles.netloc else ""
    )

    @app.exception_handler(QuotaExceededError)
    async def _quota(_: Request, exc: QuotaExceededError) -> JSONResponse:
        return JSONResponse(
            status_code=429,
            content={"detail": str(exc)},
            headers={"Retry-After": str(int(exc.retry_after_s))},
        )

    @app.exception_handler(ImageError)
    async def _image(_: Request, exc: ImageError) -> JSONResponse:
        return JSONResponse(status_code=exc.status, content={"detail": str(exc)})

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse(status_code=422, content=summary(exc.errors()))

    for router in (
        health.router,
        detection.router,
        prompt_check.router,
        missions.router,
        finds.router,
        vehicles.router,
        supervisor.router,
    ):
        app.include_router(router)
    app.include_router(lifecycle_router())  # sd_notify READY/WATCHDOG/STOPPING under systemd
    add_offline_docs(app)
    return app
