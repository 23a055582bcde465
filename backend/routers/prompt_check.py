"""Whether the back-end can search for a prompt, asked before a mission starts.

  POST /v1/prompts/check   {"prompt", "superset"}  ->  200 {"superset", "detector", "warning"}  |  422 with the reason

The companion asks when the GCS starts a mission and refuses the start (MAV_RESULT_DENIED and a
STATUSTEXT) with the back-end's own reason, instead of searching forever for a class its detector has
no name for ("an orange life buoy" on YOLOX alone: the nearest known classes). The answer is the one
`/v1/detect` would give: the same superset resolution, and the configured detector's own check on a
blank image (a closed-set detector refuses an unmapped class before it runs anything). A given superset
the prompt's words fall outside ("an orange life buoy" under "person") is searched, with a `warning` naming
what the words name, which the companion passes on to the GCS.
"""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.concurrency import run_in_threadpool

from backend.dependencies import Caller, CurrentPipeline
from backend.routers.detection import resolve_superset
from backend.schemas import ERROR_RESPONSES
from backend.supersets import UnknownSupersetError, prompt_outside_superset
from cloudtrack.api_models import PromptCheck, PromptCheckAnswer

router = APIRouter(tags=["detection"])
_BLANK = np.zeros((32, 32, 3), np.uint8)


@router.post("/v1/prompts/check", response_model=PromptCheckAnswer, responses=ERROR_RESPONSES)
async def check_prompt(body: PromptCheck, _: Caller, pipeline: CurrentPipeline) -> PromptCheckAnswer:
    """Whether `/v1/detect` would search for this prompt; 422 naming why not (and the nearest classes)."""
    superset = resolve_superset(body.prompt, body.superset)
    try:
        await run_in_threadpool(pipeline.detector.detect, _BLANK, [superset], None)
    except UnknownSupersetError as exc:
        raise HTTPException(422, str(exc)) from None
    warning = prompt_outside_superset(body.prompt, body.superset) if body.superset else None
    return PromptCheckAnswer(superset=superset, detector=pipeline.detector.name, warning=warning)
