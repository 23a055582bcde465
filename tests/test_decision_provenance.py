"""Issue 44 items 6 and 8 against a real back-end on loopback (select: -k "provenance or history").

6. What a vehicle reports was decided at its GCS (`find.confirmed_by`, a reject it posts) stays labelled as
   the vehicle's report and never becomes the standing decision: the supervisor's own Reject on the page is
   taken (201, not 409). The page's snapshot, the GeoJSON and KML downloads and the Cursor-on-Target event
   name who decided and through what: the supervisor page, the back-end API with the supervisor token, the
   GCS via the vehicle. With `[tak]` set, a vehicle's claim reaches TAK as the vehicle's report only.
8. Past 1,000 decisions per vehicle the `?after=` list says which were dropped
   (`X-Decisions-Dropped-Through`), and the standing decisions still hold.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import requests
from lxml import etree

from backend.app import create_app
from backend.serving import BackgroundServer
from backend.sessions import SessionStore
from backend.state_store import DECISIONS_KEPT_PER_VEHICLE, SqliteStore
from cloudtrack.api_models import DecisionIn, VehicleStatusIn
from cloudtrack.provenance import decision_text, gcs_text
from tests.backend_fixtures import SUPERVISOR, TOKENS, backend_config
from tests.test_finds_export import TakStandIn

SUP = {"Authorization": f"Bearer {SUPERVISOR}"}
DRONE = {"Authorization": f"Bearer {TOKENS['drone-1']}"}
KML = "{http://www.opengis.net/kml/2.2}"
CLAIM = '"supervisor page" at the GCS, as reported by drone-1'


@pytest.fixture
def tak() -> Iterator[TakStandIn]:
    with TakStandIn("tcp") as stand_in:
        yield stand_in


@pytest.fixture
def server(models_dir: Path, tak: TakStandIn) -> Iterator[BackgroundServer]:
    app = create_app(backend_config(models_dir, f'tak.url="{tak.url}"'))
    with BackgroundServer(app) as running:
        yield running


def _claim(
    server: BackgroundServer, mission: str, candidate: str, by: str = "supervisor page", lat: float = 47.4
) -> None:
    """drone-1 awaits `candidate` and, in the same status, says `by` confirmed it as a find."""
    find = {"candidate_id": candidate, "position": [lat, 8.5], "sigma_m": 2.0, "time": 1732200000.0,
            "prompt": "a man in red", "confirmed_by": by}  # fmt: skip
    status = {"mission_id": mission, "state": "AWAITING_SUPERVISOR", "prompt": "a man in red",
              "awaiting": {"candidate_id": candidate, "box": [0, 0, 10, 10], "position": [lat, 8.5]},
              "find": find}  # fmt: skip
    answer = requests.post(f"{server.url}/v1/vehicles/drone-1/status", json=status, headers=DRONE, timeout=10)
    assert answer.status_code == 200, answer.text


def _decide(server: BackgroundServer, candidate: str, action: str, **extra: str) -> requests.Response:
    return requests.post(
        f"{server.url}/v1/vehicles/drone-1/decisions",
        params={"require_awaiting": "true"},
        json={"candidate_id": candidate, "action": action, **extra},
        headers=SUP,
        timeout=10,
    )


def _snapshot_vehicle(server: BackgroundServer) -> dict[str, Any]:
    snapshot = requests.get(f"{server.url}/supervisor/api/state", headers=SUP, timeout=10).json()
    (vehicle,) = [v for v in snapshot["vehicles"] if v["id"] == "drone-1"]
    return dict(vehicle)


def _exported(server: BackgroundServer, mission: str) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Per candidate: its GeoJSON properties, and its KML description."""
    geo = requests.get(f"{server.url}/v1/missions/{mission}/finds.geojson", headers=SUP, timeout=30).json()
    props = {
        f["properties"]["candidate_id"]: f["properties"]
        for f in geo["features"]
        if f["properties"]["kind"] == "find"
    }
    kml = requests.get(f"{server.url}/v1/missions/{mission}/finds.kml", headers=SUP, timeout=30)
    document = etree.fromstring(kml.content, etree.XMLParser(recover=False))
    descriptions = {
        p.findtext(f"{KML}ExtendedData/{KML}Data[@name='candidate_id']/{KML}value") or "": p.findtext(
            f"{KML}description"
        )
        or ""
        for p in document.iter(f"{KML}Placemark")
        if p.find(f"{KML}Point") is not None
    }
    return props, descriptions


def _remarks(tak: TakStandIn, count: int) -> list[str]:
    tak.messages(count)
    return [etree.fromstring(data).findtext("detail/remarks") or "" for data in tak.received]


def test_provenance_a_vehicles_claim_is_its_report_and_the_supervisors_reject_is_taken(
    server: BackgroundServer, tak: TakStandIn
) -> None:
    _claim(server, "m-6", "c-1")  # the input: the vehicle says "supervisor page" confirmed it
    # TAK hears of the find as the vehicle's report, never as a confirmation on the page.
    (remarks,) = _remarks(tak, 1)
    assert f"confirmed by {CLAIM}" in remarks and "confirmed by supervisor page;" not in remarks, remarks
    vehicle = _snapshot_vehicle(server)
    (candidate,) = vehicle["candidates"]
    assert candidate["status"] == "awaiting" and candidate["reported"] == f"confirmed by {CLAIM}", candidate
    (find,) = vehicle["finds"]
    assert find["decided_via"] == "GCS via the vehicle" and find["decided_by"] == CLAIM, find
    props, descriptions = _exported(server, "m-6")
    assert props["c-1"]["decided_via"] == "GCS via the vehicle" and props["c-1"]["decided_by"] == CLAIM
    assert "as reported by drone-1" in descriptions["c-1"]
    # The supervisor's own Reject on the page is taken: the vehicle's word blocks nothing.
    rejected = _decide(server, "c-1", "reject", operator="supervisor page", via="supervisor page")
    assert rejected.status_code == 201, rejected.text
    vehicle = _snapshot_vehicle(server)
    (candidate,) = vehicle["candidates"]
    assert candidate["status"] == "rejected" and candidate["decided_by"] == "supervisor page"
    (find,) = vehicle["finds"]
    assert find["decided_by"] == f"{CLAIM}; rejected by supervisor page", find
    # TAK hears the supervisor's word on it too (the same marker, its remarks updated).
    assert f"{CLAIM}; rejected by supervisor page" in _remarks(tak, 2)[-1]


def test_provenance_every_way_a_decision_comes_is_named(server: BackgroundServer, tak: TakStandIn) -> None:
    # Three people 111 m apart (one person confirmed again would be one find).
    for candidate, lat in (("c-page", 47.4), ("c-api", 47.401)):
        status = {"mission_id": "m-7", "state": "AWAITING_SUPERVISOR", "prompt": "a man in red",
                  "awaiting": {"candidate_id": candidate, "box": [0, 0, 10, 10], "position": [lat, 8.5]}}  # fmt: skip
        assert requests.post(
            f"{server.url}/v1/vehicles/drone-1/status", json=status, headers=DRONE, timeout=10
        ).ok
        extra = (
            {"operator": "supervisor page", "via": "supervisor page"}
            if candidate == "c-page"
            else {"operator": "Ops"}
        )
        assert _decide(server, candidate, "confirm", **extra).status_code == 201
    _claim(server, "m-7", "c-gcs", by="gcs", lat=47.402)  # the GCS operator confirmed over MAVLink
    expected = {
        "c-page": ("supervisor page", "supervisor page"),
        "c-api": ("back-end API", "Ops through the back-end API (supervisor token)"),
        "c-gcs": ("GCS via the vehicle", "the GCS operator, as reported by drone-1"),
    }
    finds = {f["candidate_id"]: f for f in _snapshot_vehicle(server)["finds"]}
    props, descriptions = _exported(server, "m-7")
    for candidate, (via, text) in expected.items():
        assert (finds[candidate]["decided_via"], finds[candidate]["decided_by"]) == (via, text)
        assert (props[candidate]["decided_via"], props[candidate]["decided_by"]) == (via, text)
        assert f"confirmed by {text}" in descriptions[candidate].replace("&quot;", '"')
    remarks = _remarks(tak, 3)
    for _, text in expected.values():
        assert any(f"confirmed by {text};" in r for r in remarks), (text, remarks)
    # A decision against one of the supervisor's standing ones is refused, naming who and through what.
    refused = requests.post(f"{server.url}/v1/vehicles/drone-1/decisions", headers=SUP, timeout=10,
                            json={"candidate_id": "c-api", "action": "reject"})  # fmt: skip
    assert refused.status_code == 409
    assert "confirmed by Ops through the back-end API (supervisor token)" in refused.json()["detail"]


def test_provenance_the_gcs_line_names_who_and_through_what() -> None:
    assert gcs_text("supervisor page", "supervisor page") == "supervisor page"
    assert gcs_text("back-end API", "Ops") == "Ops via back-end API"
    assert gcs_text("back-end API", "") == "supervisor via back-end API"
    assert gcs_text("GCS via the vehicle", "gcs") == "gcs"
    assert decision_text("GCS via the vehicle", "supervisor page", "drone-1") == CLAIM


# Item 8: the decision history past 1,000 decisions per vehicle


def test_history_past_the_kept_decisions_says_which_were_dropped_and_the_standing_ones_hold(
    models_dir: Path,
) -> None:
    store = SessionStore(SqliteStore(":memory:"))
    store.set_status("drone-1", VehicleStatusIn(mission_id="m-8", state="SEARCH"))
    extra = 5
    for i in range(DECISIONS_KEPT_PER_VEHICLE + extra):
        action = "confirm" if i % 2 else "reject"
        store.state.add_decision("drone-1", "m-8", DecisionIn(candidate_id=f"c-{i}", action=action), 1.0 + i)
    first = store.standing_decision("drone-1", "m-8", "c-0")
    assert first is not None
    with BackgroundServer(create_app(backend_config(models_dir), sessions=store)) as running:
        polled = requests.get(
            f"{running.url}/v1/vehicles/drone-1/decisions?after=0", headers=DRONE, timeout=30
        )
        assert polled.status_code == 200
        listed = polled.json()
        assert len(listed) == DECISIONS_KEPT_PER_VEHICLE and listed[0]["candidate_id"] == f"c-{extra}"
        dropped = int(polled.headers["X-Decisions-Dropped-Through"])
        assert dropped == listed[0]["decision_id"] - 1 and dropped >= first.decision_id
        # The oldest decision left the list, not the store: it still stands.
        contrary = requests.post(f"{running.url}/v1/vehicles/drone-1/decisions", headers=SUP, timeout=10,
                                 json={"candidate_id": "c-0", "action": "confirm"})  # fmt: skip
        assert contrary.status_code == 409 and "stands" in contrary.json()["detail"]
        other = requests.get(
            f"{running.url}/v1/vehicles/drone-2/decisions",
            headers={"Authorization": f"Bearer {TOKENS['drone-2']}"},
            timeout=10,
        )
        assert other.headers["X-Decisions-Dropped-Through"] == "0" and other.json() == []
        schema = json.dumps(requests.get(f"{running.url}/openapi.json", timeout=10).json())
        assert "X-Decisions-Dropped-Through" in schema  # documented in the API reference
