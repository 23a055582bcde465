"""The status report's optional fields (reason, heading, track box, progress, search, find): range-checked
and bounded on the way in, stored, and served back as they came (CONTRACT section 1)."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from tests.backend_fixtures import SUPERVISOR, auth, backend_config

FULL: dict[str, Any] = {
    "mission_id": "m-1",
    "state": "SEARCHING",
    "prompt": "an injured man in a gray shirt",
    "position": [47.3977, 8.5456],
    "altitude_m": 30.0,
    "reason": "waiting for the autopilot's HEARTBEAT on udpin:0.0.0.0:14550",
    "heading_deg": 271.5,
    "track_box": [100.0, 80.0, 140.0, 180.0],
    "frame_id": 1234,
    "track_id": "7be4dec8ac3b",
    "progress": {"keyframes": 120, "detections": 66, "candidates": 3, "rejected": 1},
    "search": {
        "area": [[47.397, 8.545], [47.398, 8.545], [47.398, 8.547], [47.397, 8.547]],
        "coverage": 0.42,
        "covered": [[[47.397, 8.545], [47.3975, 8.545], [47.3975, 8.546], [47.397, 8.546]]],
        "mission_item": 4,
        "mission_items": 12,
        "mode": "AUTO",
    },
    "find": {
        "candidate_id": "c-17",
        "position": [47.39781, 8.54567],
        "sigma_m": 2.5,
        "time": 1732200000.5,
        "seen_at": 1732199955.0,
        "prompt": "an injured man in a gray shirt",
        "confirmed_by": "supervisor page",
    },
}


@pytest.fixture(scope="module")
def client(models_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(backend_config(models_dir))) as test_client:
        yield test_client


def test_status_fields_are_stored_and_served_back(client: TestClient) -> None:
    response = client.post("/v1/vehicles/drone-1/status", headers=auth(), json=FULL)
    assert response.status_code == 200, response.text
    served = client.get("/v1/vehicles/drone-1/status", headers=auth()).json()
    fleet = client.get("/v1/vehicles", headers={"Authorization": f"Bearer {SUPERVISOR}"}).json()
    for body in (response.json(), served, fleet[0]):
        assert {k: body[k] for k in FULL} == {
            **FULL,
            "search": {**FULL["search"], "pod": None},
            "find": {**FULL["find"], "crop_jpeg_b64": None, "crop_box": None},
        }
    # Every new field is optional: an old companion's report still fits.
    minimal = client.post("/v1/vehicles/drone-1/status", headers=auth(), json={"state": "IDLE"})
    assert minimal.status_code == 200 and minimal.json()["reason"] == "" and minimal.json()["search"] is None


def _with(path: str, value: object) -> dict[str, Any]:
    body = copy.deepcopy(FULL)
    *parents, last = path.split(".")
    node: Any = body
    for key in parents:
        node = node[key]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return body


_DELETE = object()
SQUARE = [[47.0, 8.0], [47.0, 8.1], [47.1, 8.1], [47.1, 8.0]]


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        ("position", [91.0, 8.0], "position"),
        ("position", [47.0, -181.0], "position"),
        ("altitude_m", 1e9, "altitude_m"),
        ("reason", "x" * 201, "reason"),
        ("heading_deg", 400.0, "heading_deg"),
        ("track_box", [140.0, 80.0, 100.0, 180.0], "track_box"),
        ("track_box", [-5.0, 80.0, 100.0, 180.0], "track_box"),
        ("track_box", [1.0, 2.0, 3.0], "track_box"),
        ("frame_id", _DELETE, "frame_id"),
        ("frame_id", -1, "frame_id"),
        ("progress.keyframes", -1, "keyframes"),
        ("search.coverage", 1.5, "coverage"),
        ("search.area", [[47.0, 8.0]] * 201, "area"),
        ("search.area", [[47.0, 8.0, 3.0]], "area"),
        ("search.area", [[-95.0, 8.0]], "area"),
        ("search.covered", [SQUARE] * 21, "covered"),
        ("search.covered", [[[47.0, 8.0]] * 100] * 6, "covered"),
        ("search.mission_item", -2, "mission_item"),
        ("search.mode", "M" * 33, "mode"),
        ("find.position", [47.0, 200.0], "position"),
        ("find.sigma_m", -1.0, "sigma_m"),
        ("find.candidate_id", "../../etc", "candidate_id"),
        ("find.confirmed_by", "x" * 65, "confirmed_by"),
        ("find.time", -5.0, "time"),
        ("find.seen_at", -5.0, "seen_at"),
        ("find.seen_at", 1e300, "seen_at"),
    ],
)
def test_out_of_range_status_fields_are_422_naming_the_field(
    client: TestClient, path: str, value: object, field: str
) -> None:
    response = client.post("/v1/vehicles/drone-1/status", headers=auth(), json=_with(path, value))
    assert response.status_code == 422, response.text
    assert field in str(response.json()["detail"])


@pytest.mark.parametrize(
    "body",
    [
        b'{"state": "x", "heading_deg": NaN}',
        b'{"state": "x", "search": {"coverage": Infinity}}',
        b'{"state": "x", "find": {"candidate_id": "c", "position": [47, NaN], "sigma_m": 1, "time": 1, '
        b'"confirmed_by": "gcs"}}',
        b'{"state": "x", "find": {"candidate_id": "c", "position": [47, 8], "sigma_m": 1, "time": 1, '
        b'"seen_at": NaN, "confirmed_by": "gcs"}}',
    ],
)
def test_non_finite_status_fields_are_422(client: TestClient, body: bytes) -> None:
    response = client.post(
        "/v1/vehicles/drone-1/status", headers={**auth(), "Content-Type": "application/json"}, content=body
    )
    assert response.status_code == 422
