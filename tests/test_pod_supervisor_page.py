"""The supervisor page's state carries the vehicle's POD map as the page draws it (the grid, a cell's size in
degrees, the legend's colours and sentence), the keyframes kept through outages and how many earlier
search areas the mission has; a status without the map keeps the area's. Real grids through the real API.
Select: -k pod_supervisor."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from backend.app import create_app
from backend.pod_layers import BAND_COLOURS
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import BANDS
from tests.backend_fixtures import SUPERVISOR, auth, backend_config
from tests.pod_fixtures import AREA, NEXT_AREA, pod_report

KEYFRAMES = {"analysed": 63, "stored": 12, "waiting": 2, "sent": 10, "dropped": 0}


@pytest.fixture
def client(models_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(backend_config(models_dir))) as test_client:
        yield test_client


def _report(client: TestClient, **fields: Any) -> None:
    body = {"mission_id": "m-pod", "state": "SEARCHING", **fields}
    assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body).status_code == 200


def _vehicle(client: TestClient) -> dict[str, Any]:
    state = client.get("/supervisor/api/state", headers={"Authorization": f"Bearer {SUPERVISOR}"}).json()
    (vehicle,) = state["vehicles"]
    return dict(vehicle)


def test_pod_supervisor_state_carries_the_map_its_legend_and_the_keyframe_counts(client: TestClient) -> None:
    grid = pod_report()
    _report(client, search={"area": AREA, "coverage": 0.4, "pod": grid}, keyframes=KEYFRAMES)
    vehicle = _vehicle(client)
    pod = vehicle["pod"]
    assert {k: pod[k] for k in ("rows", "cols", "values", "origin", "mean", "at_target", "target_pod")} == {
        k: grid[k] for k in ("rows", "cols", "values", "origin", "mean", "at_target", "target_pod")
    }
    assert vehicle["search"]["pod"] is None  # sent once, in `pod`
    # The grid's north-east corner from whole cells in degrees is its own frame's.
    ne = LocalFrame(*grid["origin"]).latlon(grid["cols"] * grid["cell_m"], grid["rows"] * grid["cell_m"])
    assert grid["origin"][0] + grid["rows"] * pod["cell_deg"][0] == pytest.approx(ne[0], abs=1e-9)
    assert grid["origin"][1] + grid["cols"] * pod["cell_deg"][1] == pytest.approx(ne[1], abs=1e-9)
    assert [(b["low"], b["high"], b["colour"]) for b in pod["bands"]] == [
        (low, high, colour) for (low, high), colour in zip(BANDS, BAND_COLOURS, strict=True)
    ]
    assert "blank = not analysed" in pod["meaning"] and "standing person" in pod["meaning"]
    assert vehicle["keyframes"] == KEYFRAMES and vehicle["earlier_areas"] == 0
    # A status that says nothing of the map keeps the area's; another area starts without one.
    _report(client, search={"area": AREA, "coverage": 0.45})
    assert _vehicle(client)["pod"]["values"] == grid["values"]
    _report(client, search={"area": NEXT_AREA, "coverage": 0.0})
    moved = _vehicle(client)
    assert moved["pod"] is None and moved["earlier_areas"] == 1 and moved["keyframes"] is None
