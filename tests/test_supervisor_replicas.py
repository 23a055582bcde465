"""Two back-end replicas on one real redis-server: the supervisor page of either shows the whole fleet, and
a vehicle's report to one replica is pushed live to a page streaming from the other (select: -k replicas).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from backend_tools.fleet_services import RedisServer
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve
from tests.test_supervisor_page import read_events

SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}


@pytest.fixture(scope="module")
def replicas(models_dir: Path) -> Iterator[tuple[str, str]]:
    with RedisServer() as redis_server:
        config = BackendConfig(
            auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
            detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
            verifier=VerifierConfig(kind="none"),
            sessions=SessionConfig(store="redis", redis_url=redis_server.url),
        )
        with serve(create_app(config)) as first, serve(create_app(config)) as second:
            yield first, second


def _report(url: str, vehicle: str, state: str) -> None:
    response = httpx.post(
        f"{url}/v1/vehicles/{vehicle}/status",
        json={"mission_id": "m-1", "state": state},
        headers={"Authorization": f"Bearer {VEHICLE_TOKENS[vehicle]}"},
        timeout=10,
    )
    assert response.status_code == 200, response.text


def test_replicas_each_show_the_whole_fleet(replicas: tuple[str, str]) -> None:
    first, second = replicas
    _report(first, "drone-1", "SEARCH")
    _report(second, "drone-2", "TRACK")
    for url in replicas:
        state = httpx.get(f"{url}/supervisor/api/state", headers=SUPERVISOR, timeout=10).json()
        assert {v["id"]: v["state"] for v in state["vehicles"]} == {"drone-1": "SEARCH", "drone-2": "TRACK"}


def test_replicas_push_a_report_made_on_the_other_replica(replicas: tuple[str, str]) -> None:
    first, second = replicas
    _report(first, "drone-1", "SEARCH")
    with (
        httpx.Client(base_url=second, timeout=15) as client,
        client.stream("GET", "/supervisor/events", headers=SUPERVISOR) as stream,
    ):
        lines = stream.iter_lines()
        read_events(lines, 1)
        started = time.monotonic()
        _report(first, "drone-1", "AWAITING_SUPERVISOR")
        (pushed,) = read_events(lines, 1)
        took = time.monotonic() - started
    assert next(v for v in pushed["vehicles"] if v["id"] == "drone-1")["state"] == "AWAITING_SUPERVISOR"
    assert took < 5.0, took  # pushed on the change, not at the 15 s keep-alive
