"""The POD map and the keyframe counts in the vehicle status: `search.pod` (a real `PodMap.report()`) and
`keyframes` are stored and served back as sent, every bound is a 422 naming the field, and the request
limits admit a status carrying a full 4096-cell grid beside the contract's other maxima while refusing what
they refused before. Select: -k pod_status."""

from __future__ import annotations

import base64
import copy
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from backend.request_limits import json_shape_problem, route_limit
from cloudtrack import pod_map
from cloudtrack.api_models import POD_MAX_CELLS, POD_VALUES_MAX_CHARS
from tests.backend_fixtures import SUPERVISOR, auth, backend_config
from tests.pod_fixtures import AREA, pod_report

KEYFRAMES = {"analysed": 63, "stored": 12, "waiting": 2, "sent": 10, "dropped": 0}


@pytest.fixture(scope="module")
def client(models_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(backend_config(models_dir))) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def status() -> dict[str, Any]:
    return {
        "mission_id": "m-pod",
        "state": "SEARCHING",
        "position": [47.3975, 8.5455],
        # 3 keyframes too dark for the curve (behaviors/scene_light.py) laid coverage but no POD
        "search": {"area": AREA, "coverage": 0.4, "pod": {**pod_report(), "dark_looks": 3}},
        "keyframes": KEYFRAMES,
    }


def test_pod_status_grid_and_keyframes_are_stored_and_served_back(
    client: TestClient, status: dict[str, Any]
) -> None:
    assert pod_map.MAX_CELLS == POD_MAX_CELLS  # the API's bound is the grid's
    response = client.post("/v1/vehicles/drone-1/status", headers=auth(), json=status)
    assert response.status_code == 200, response.text
    served = client.get("/v1/vehicles/drone-1/status", headers=auth()).json()
    fleet = client.get("/v1/vehicles", headers={"Authorization": f"Bearer {SUPERVISOR}"}).json()
    for body in (response.json(), served, fleet[0]):
        assert body["search"]["pod"] == status["search"]["pod"] and body["keyframes"] == KEYFRAMES
    # Both are optional: a companion without a POD map or an outage store still reports.
    plain = client.post(
        "/v1/vehicles/drone-1/status", headers=auth(), json={"state": "SEARCHING", "search": {"area": AREA}}
    )
    assert plain.status_code == 200 and plain.json()["search"]["pod"] is None
    assert plain.json()["keyframes"] is None


def _grid(**changes: Any) -> dict[str, Any]:
    return {**pod_report(), **changes}


def _values(cells: bytes) -> str:
    return base64.b64encode(cells).decode()


@pytest.mark.parametrize(
    ("pod", "field"),
    [
        (_grid(rows=64, cols=65, values=_values(bytes(64 * 65))), "cols"),  # over 4096 cells
        (_grid(rows=4097, cols=1), "rows"),
        (_grid(rows=0), "rows"),
        (_grid(values=_grid()["values"][:-4]), "values"),  # fewer values than cells
        (_grid(values="@" * len(_grid()["values"])), "values"),  # not base64
        (_grid(values=_values(bytes([251]) * (55 * 74))), "values"),  # neither a POD nor "outside"
        (_grid(values="A" * 100_000), "values"),  # refused by its length, never decoded
        (_grid(origin=[91.0, 8.0]), "origin"),
        (_grid(origin=[47.0]), "origin"),
        (_grid(cell_m=0.0), "cell_m"),
        (_grid(cell_m=1e6), "cell_m"),
        (_grid(rows=64, cols=64, cell_m=4000.0, values=_values(bytes(4096))), "cols"),  # 256 km across
        (_grid(target=""), "target"),
        (_grid(target="p" * 65), "target"),
        (_grid(posture="x" * 33), "posture"),
        (_grid(target_pod=1.2), "target_pod"),
        (_grid(mean=-0.1), "mean"),
        (_grid(at_target=1.01), "at_target"),
        (_grid(looks=-1), "looks"),
        (_grid(looks=2**40), "looks"),
        ({**_grid(), "colour": "red"}, "colour"),
        ({k: v for k, v in _grid().items() if k != "values"}, "values"),
    ],
)
def test_pod_status_a_bad_grid_is_422_naming_the_field(
    client: TestClient, status: dict[str, Any], pod: dict[str, Any], field: str
) -> None:
    body = copy.deepcopy(status)
    body["search"]["pod"] = pod
    response = client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body)
    assert response.status_code == 422, response.text
    errors = response.json()["detail"]
    assert any(e["loc"][-1] == field and e["loc"][-3:-1] == ["search", "pod"] for e in errors), errors


@pytest.mark.parametrize(
    ("keyframes", "field"),
    [
        ({**KEYFRAMES, "dropped": -1}, "dropped"),
        ({**KEYFRAMES, "sent": 10**9 + 1}, "sent"),
        ({**KEYFRAMES, "stored": 1.5}, "stored"),
        ({**KEYFRAMES, "lost": 3}, "lost"),
    ],
)
def test_pod_status_bad_keyframe_counts_are_422_naming_the_field(
    client: TestClient, status: dict[str, Any], keyframes: dict[str, Any], field: str
) -> None:
    response = client.post(
        "/v1/vehicles/drone-1/status", headers=auth(), json={**status, "keyframes": keyframes}
    )
    assert response.status_code == 422, response.text
    assert any(e["loc"][-1] == field for e in response.json()["detail"])


def test_pod_status_with_a_full_grid_fits_the_request_limits_at_every_other_bound() -> None:
    """A status at the contract's bounds (search area, covered area, two crops) and a full 64 x 64 grid."""
    grid = pod_report(max_cells=POD_MAX_CELLS)
    full = {**grid, "rows": 64, "cols": 64, "values": _values(bytes(range(0, 250, 5)) * 81 + bytes(46))}
    assert len(full["values"]) == POD_VALUES_MAX_CHARS
    area = [[47.0 + i * 1e-4, 8.0] for i in range(200)]
    covered = [[[47.0 + i * 1e-4, 8.0 + r * 1e-4] for i in range(25)] for r in range(20)]
    crop = "A" * 400_000
    status: dict[str, Any] = {
        "mission_id": "m-1", "state": "SEARCH", "keyframes": KEYFRAMES,
        "search": {"area": area, "covered": covered, "coverage": 0.5, "pod": full},
        "awaiting": {"candidate_id": "c1", "box": [0, 0, 1, 1], "crop_jpeg_b64": crop},
        "find": {"candidate_id": "c1", "position": [47, 8], "sigma_m": 3, "time": 1, "confirmed_by": "gcs",
                 "crop_jpeg_b64": crop},
    }  # fmt: skip
    body = json.dumps(status).encode()
    limit = route_limit("POST", "/v1/vehicles/drone-1/status")
    assert limit.json is not None
    assert len(body) <= limit.max_bytes and json_shape_problem(body, limit.json) is None
    print(f"status with a full grid: {len(json.dumps(full))} bytes of POD map, {len(body)} in all")


def test_pod_status_a_body_over_the_limit_is_413_before_validation(client: TestClient) -> None:
    limit = route_limit("POST", "/v1/vehicles/drone-1/status").max_bytes
    body = {"state": "SEARCH", "search": {"area": AREA, "pod": _grid(values="A" * limit)}}
    response = client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body)
    assert response.status_code == 413, response.text
