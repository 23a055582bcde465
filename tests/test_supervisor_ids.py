"""Issue 45: one id per candidate on the supervisor's page. The back-end's answers name every box anew each
keyframe; the page's live view names a box as the GCS, the card and the finds do (the id the candidate was
first proposed with, the tracked one's from the status), says where it stands (awaiting, confirmed), and
gives a box put to no one no id at all."""

from __future__ import annotations

import time

import cv2
import numpy as np

from backend.schemas import KeyframeCandidate
from backend.sessions import SessionStore
from backend.supervisor_view import SupervisorView
from cloudtrack.api_models import VehicleStatusIn

JPEG = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
CID = "7be4dec8ac3b"  # as the GCS named it, from the keyframe that first proposed it


def _keyframe(store: SessionStore, frame_id: int, first: str) -> None:
    """An answer with its own new ids: the tracked person (first id `first`), a refused box, a queued one."""
    boxes = [
        KeyframeCandidate(id=first, box=[100.0, 100.0, 140.0, 200.0], verdict="uncertain"),
        KeyframeCandidate(id=f"n{frame_id}", box=[300.0, 100.0, 340.0, 200.0], verdict="no"),
        KeyframeCandidate(id="q1", box=[500.0, 100.0, 540.0, 200.0], verdict="yes"),
    ]
    store.set_keyframe("d1", "m1", frame_id, JPEG, (640, 480), boxes, took_s=1.5)


def _status(store: SessionStore, state: str, frame_id: int, **extra: object) -> None:
    body = {
        "mission_id": "m1", "state": state, "prompt": "a man in a gray shirt", "frame_id": frame_id,
        "track_box": [102.0, 98.0, 141.0, 203.0], "track_id": CID, "awaiting_more": ["q1"], **extra,
    }  # fmt: skip
    store.set_status("d1", VehicleStatusIn.model_validate(body))


def _labels(view: SupervisorView) -> list[tuple[str, str]]:
    keyframe = view.snapshot().vehicles[0].keyframe
    assert keyframe is not None
    return [(c.id, c.status) for c in keyframe.candidates]


def test_the_live_view_names_boxes_as_the_gcs_and_the_card_do() -> None:
    store = SessionStore()
    view = SupervisorView(store)
    awaiting = {"candidate_id": CID, "box": [100.0, 100.0, 140.0, 200.0], "verdict": "uncertain"}
    # The keyframe that proposed it: its answer's id is the candidate's.
    _keyframe(store, 7, CID)
    _status(store, "AWAITING_SUPERVISOR", 7, awaiting=awaiting)
    assert _labels(view) == [(CID, "awaiting"), ("", ""), ("q1", "awaiting")]
    snapshot = view.snapshot().vehicles[0]
    assert snapshot.candidates[0].id == CID and snapshot.keyframe is not None
    assert snapshot.keyframe.track_id == CID and snapshot.keyframe.track_status == "awaiting"
    # Its age counts from when it arrived, not from when the answer was ready.
    assert snapshot.keyframe.age_s >= 1.5
    # A later keyframe's answer names the same person anew: the box over the track still shows the
    # candidate's own id, not the answer's.
    _keyframe(store, 8, "ca21a0ffffff")
    _status(store, "AWAITING_SUPERVISOR", 8, awaiting=awaiting)
    assert _labels(view) == [(CID, "awaiting"), ("", ""), ("q1", "awaiting")]
    # Confirmed: labelled confirmed, whatever the verifier said of this keyframe ("uncertain").
    find = {"candidate_id": CID, "position": [47.3978, 8.5457], "sigma_m": 2.0, "time": time.time(),
            "prompt": "a man in a gray shirt", "confirmed_by": "supervisor page"}  # fmt: skip
    _keyframe(store, 9, "62e552ffffff")
    _status(store, "CONFIRMED", 9, find=find, awaiting_more=[])
    assert _labels(view) == [(CID, "confirmed"), ("", ""), ("", "")]
    confirmed = view.snapshot().vehicles[0].keyframe
    assert confirmed is not None and confirmed.track_status == "confirmed"
    assert view.snapshot().vehicles[0].finds[0].candidate_id == CID
    # The status names another keyframe: no track on this one, so no box is the tracked candidate.
    _keyframe(store, 10, "0a0a0a0a0a0a")
    _status(store, "CONFIRMED", 9, find=find, awaiting_more=[])
    assert _labels(view) == [("", ""), ("", ""), ("", "")]
