"""Service routes: liveness and load for load balancers, and the models this back-end runs."""

from __future__ import annotations

import time

from fastapi import APIRouter

import cloudtrack
from backend.dependencies import Caller, CurrentPipeline, LoadedModels, Scheduler, Settings, Started
from backend.detectors.factory import CLOSED_SET_WEIGHTS
from backend.schemas import ERROR_RESPONSES, HealthResponse, ModelsResponse
from backend.supersets import known_supersets

router = APIRouter(tags=["service"])


@router.get("/health", response_model=HealthResponse)
def health(models: LoadedModels, scheduler: Scheduler, started: Started) -> HealthResponse:
    """Liveness and load, without authentication (for load balancers)."""
    return HealthResponse(
        status="ok",
        version=cloudtrack.__version__,
        uptime_s=time.time() - started,
        models=models,
        in_flight=scheduler.running,
        queued=scheduler.queued,
    )


@router.get("/v1/models", response_model=ModelsResponse, responses=ERROR_RESPONSES)
def models(_: Caller, settings: Settings, pipeline: CurrentPipeline, names: LoadedModels) -> ModelsResponse:
    closed_set = settings.detector.kind in CLOSED_SET_WEIGHTS
    return ModelsResponse(
        detector=names.detector,
        detector_kind=settings.detector.kind,
        supersets=known_supersets() if closed_set else [],
        verifier=names.verifier,
        verifier_kind=settings.verifier.kind if pipeline.verifier is not None else "none",
    )
