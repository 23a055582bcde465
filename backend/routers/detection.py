"""POST /v1/detect: a vehicle's keyframe in, the superset's candidates out, each verified against the prompt.

Hostile input: the image's size is read from its header before decoding, and decoding runs inside the
vehicle's fair-queue slot (a flood of bombs waits behind its own sender).
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, File, Form, HTTPException, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from backend.auth import require_vehicle_access
from backend.dependencies import Caller, CurrentPipeline, LoadedModels, Scheduler, Sessions, Settings
from backend.fair_queue import QueueFullError
from backend.images import check_size, decode_image
from backend.request_limits import DETECT_META, json_shape_problem
from backend.schemas import ERROR_RESPONSES, Candidate, DetectMeta, DetectResponse, KeyframeCandidate, Timings
from backend.supersets import UnknownSupersetError, superset_from_prompt
from behaviors.geometry import Box

router = APIRouter(tags=["detection"])


def resolve_superset(prompt: str, superset: str | None) -> str:
    """The detector class a request searches for: its own, else the one its prompt names; 422 for none."""
    found = (superset or superset_from_prompt(prompt) or "").strip().lower()
    if not found:
        raise HTTPException(422, "the prompt names no known class; set 'superset' (e.g. \"person\")")
    return found


@router.post("/v1/detect", response_model=DetectResponse, responses=ERROR_RESPONSES)
async def detect(
    principal: Caller,
    image: Annotated[UploadFile, File(description="the keyframe, JPEG or PNG")],
    meta: Annotated[str, Form(description="JSON object, see DetectMeta", max_length=20_000)],
    settings: Settings,
    sessions: Sessions,
    pipeline: CurrentPipeline,
    scheduler: Scheduler,
    models: LoadedModels,
) -> DetectResponse:
    """Detect the superset in a keyframe and verify each candidate against the full description."""
    t_received = time.perf_counter()
    problem = json_shape_problem(meta, DETECT_META)  # bounded before pydantic sees it
    if problem is not None:
        raise HTTPException(413, f"meta: {problem}")
    try:
        fields = DetectMeta.model_validate_json(meta)
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_context=False, include_input=False)
        # The app's handler answers it as every 422: the first few errors and their count.
        raise RequestValidationError([{**e, "loc": ("meta", *e["loc"])} for e in errors]) from None
    require_vehicle_access(principal, fields.vehicle_id)
    superset = resolve_superset(fields.prompt, fields.superset)
    data = await image.read()
    check_size(data, settings.server.max_image_pixels)  # a bomb is refused by its header, undecoded
    await run_in_threadpool(sessions.open_mission, fields.vehicle_id, fields.mission_id)
    check = await run_in_threadpool(
        sessions.rejection_check, fields.vehicle_id, fields.mission_id, fields.vehicle_position
    )
    roi = Box.from_xyxy(*fields.roi) if fields.roi else None
    t_queued = time.perf_counter()
    try:
        # Decoding happens inside the vehicle's slot: one vehicle's uploads decode one after another.
        async with scheduler.slot(fields.vehicle_id):
            t_queue = time.perf_counter() - t_queued
            t_decode = time.perf_counter()
            frame = await run_in_threadpool(decode_image, data, settings.server.max_image_pixels)
            t_decode = time.perf_counter() - t_decode
            t_detect = time.perf_counter()
            sighting = await run_in_threadpool(
                pipeline.look, frame, superset, roi, fields.frame_id, fields.prompt
            )
            t_detect = time.perf_counter() - t_detect
    except QueueFullError as exc:
        raise HTTPException(
            429, f"too many requests waiting for this vehicle: {exc}", headers={"Retry-After": "1"}
        ) from None
    except UnknownSupersetError as exc:
        raise HTTPException(422, str(exc)) from None
    # Verification runs outside the detector slot: a slow VLM must not hold the detector, and the
    # verifier pool already bounds how many verifications run at once.
    early = pipeline.early_stage() if fields.stage == "early" else None
    t_verify = time.perf_counter()
    candidates = await (early or pipeline).verify_async(
        frame, sighting.candidates, fields.prompt, superset, check, t_received + pipeline.deadline_s, sighting
    )
    t_verify = time.perf_counter() - t_verify
    await run_in_threadpool(
        sessions.remember_candidates,
        fields.vehicle_id,
        fields.mission_id,
        [(c.detection.candidate_id, c.appearance) for c in candidates],
    )
    # The newest keyframe and its boxes, for the supervisor's live view.
    await run_in_threadpool(
        sessions.set_keyframe,
        fields.vehicle_id,
        fields.mission_id,
        fields.frame_id,
        data,
        (int(frame.shape[1]), int(frame.shape[0])),
        [
            KeyframeCandidate(
                id=c.detection.candidate_id,
                box=[round(v, 1) for v in c.detection.box.xyxy()],
                verdict=c.detection.verdict.value,
            )
            for c in candidates
        ],
        time.perf_counter() - t_received,
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
                body_box=(
                    [round(v, 2) for v in c.detection.body_box.xyxy()]
                    if c.detection.body_box is not None
                    else None
                ),
                score=round(c.detection.score, 4),
                label=c.detection.label,
                verdict=c.detection.verdict.value,
                justification=c.detection.justification,
                judged=c.detection.judged,
                placement_ok=c.detection.placement_ok,
                unjudged=list(c.detection.unjudged),
                singled_out=c.detection.singled_out,
                verifier=c.verifier,
                t_verify=round(c.t_verify, 4),
                previously_rejected=c.previously_rejected,
            )
            for c in candidates
        ],
        final=early is None,
        timings=Timings(
            t_queue=t_queue,
            t_decode=t_decode,
            t_detect=t_detect,
            t_verify=t_verify,
            t_total=time.perf_counter() - t_received,
        ),
        models=models,
    )
