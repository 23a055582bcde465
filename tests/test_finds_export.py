"""A confirmed find reaches the rescuers' tools: GeoJSON and KML downloads read by the `geojson` and `fastkml`
libraries, and a Cursor-on-Target event received by a TAK stand-in on loopback (TCP, UDP and TLS with a
client certificate, as a TAK server asks) and read with the TAK library (`takproto`).
Select: pytest -k "cursor_on_target or geojson or kml".
"""

from __future__ import annotations

import json
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import geojson
import pytest
import takproto
from fastapi.testclient import TestClient
from fastkml import kml

from backend.app import create_app
from cloudtrack.cursor_on_target import COT_TYPE, CotSender, FindReport, find_event, find_uid, seen_text
from tests.backend_fixtures import SUPERVISOR, auth, backend_config

HOME = (47.3977, 8.5456)
AREA = [[47.3970, 8.5450], [47.3970, 8.5470], [47.3985, 8.5470], [47.3985, 8.5450]]  # clockwise as sent
FIND = {
    "candidate_id": "c-17",
    "position": [47.39781, 8.54567],
    "sigma_m": 2.5,
    "time": 1732200000.5,
    "seen_at": 1732199955.5,  # the position is 45 s older than the confirmation
    "prompt": "an injured man in a gray shirt",
    "confirmed_by": "gcs",
}
SEEN = "position as seen at 14:39:15 UTC, 45 s before the confirmation"


class TakStandIn:
    """A TAK server's streaming input on loopback: accepts CoT over TCP, UDP or TLS and keeps what came."""

    def __init__(self, kind: str, tls: ssl.SSLContext | None = None) -> None:
        self.kind = kind
        self.received: list[bytes] = []
        family = socket.SOCK_DGRAM if kind == "udp" else socket.SOCK_STREAM
        self._sock = socket.socket(socket.AF_INET, family)
        self._sock.bind(("127.0.0.1", 0))
        self.port = self._sock.getsockname()[1]
        self._tls = tls
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    @property
    def url(self) -> str:
        return f"{self.kind}://127.0.0.1:{self.port}"

    def __enter__(self) -> TakStandIn:
        if self.kind != "udp":
            self._sock.listen()
        self._sock.settimeout(0.2)
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sock.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                if self.kind == "udp":
                    self.received.append(self._sock.recvfrom(65536)[0])
                    continue
                conn, _ = self._sock.accept()
            except (TimeoutError, OSError):
                continue
            if self._tls is not None:
                conn.settimeout(5)
                try:
                    conn = self._tls.wrap_socket(conn, server_side=True)
                except (ssl.SSLError, OSError):
                    conn.close()
                    continue
            conn.settimeout(0.2)
            buffer = b""
            with conn:
                while not self._stop.is_set():
                    try:
                        chunk = conn.recv(65536)
                    except (TimeoutError, OSError):
                        chunk = None
                    if chunk == b"":
                        break
                    if chunk:
                        buffer += chunk
                        # TAK's streaming protocol version 0: XML events one after another.
                        while b"</event>" in buffer:
                            event, _, buffer = buffer.partition(b"</event>")
                            self.received.append(event.strip() + b"</event>")

    def messages(self, count: int = 1, timeout_s: float = 15.0) -> list[Any]:
        deadline = time.monotonic() + timeout_s
        while len(self.received) < count and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(self.received) >= count, f"the TAK stand-in received {len(self.received)} events"
        return [takproto.parse_proto(bytearray(data)) for data in self.received]


@pytest.fixture
def client_factory(models_dir: Path) -> Iterator[Any]:
    clients: list[TestClient] = []

    def make(*settings: str) -> TestClient:
        client = TestClient(create_app(backend_config(models_dir, *settings)))
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.__exit__(None, None, None)


def _fly_and_find(client: TestClient, crop_b64: str | None = None) -> None:
    """drone-1 flies a little of its survey (positions, area, coverage) and reports a find, as it does with
    every status once its GCS confirmed; and a second candidate the supervisor confirms on the page."""
    for i in range(6):
        status = {
            "mission_id": "m-7",
            "state": "SEARCHING",
            "prompt": FIND["prompt"],
            "position": [HOME[0] + i * 0.0001, HOME[1]],
            "search": {
                "area": AREA,
                "coverage": 0.1 * i,
                "covered": [[[47.3970, 8.5450], [47.3970 + 0.0001 * (i + 1), 8.5450], [47.3970, 8.5460]]],
            },
        }
        assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=status).status_code == 200
    awaiting = {
        "candidate_id": "c-9",
        "box": [1.0, 2.0, 30.0, 60.0],
        "position": [47.3980, 8.5462],
        "seen_at": 1732199990.0,
    }
    if crop_b64:
        awaiting["crop_jpeg_b64"] = crop_b64
    body = {
        "mission_id": "m-7",
        "state": "AWAITING_SUPERVISOR",
        "prompt": FIND["prompt"],
        "awaiting": awaiting,
    }
    assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body).status_code == 200
    decision = {"candidate_id": "c-9", "action": "confirm", "operator": "supervisor page"}
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    assert client.post("/v1/vehicles/drone-1/decisions", headers=supervisor, json=decision).status_code == 201
    for _ in range(3):  # the find rides every status: it is stored once
        body = {"mission_id": "m-7", "state": "CONFIRMED", "prompt": FIND["prompt"], "find": FIND}
        assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body).status_code == 200


def test_geojson_download_holds_finds_track_and_areas(client_factory: Any) -> None:
    client = client_factory()
    _fly_and_find(client)
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    assert client.get("/v1/missions/m-7/finds.geojson").status_code == 401
    assert client.get("/v1/missions/m-7/finds.geojson", headers=auth()).status_code == 403
    assert client.get("/v1/missions/m-8/finds.geojson", headers=supervisor).status_code == 404
    response = client.get(
        "/v1/missions/m-7/finds.geojson", params={"vehicle_id": "drone-1"}, headers=supervisor
    )
    assert response.status_code == 200 and response.headers["content-type"].startswith("application/geo+json")
    assert "attachment" in response.headers["content-disposition"]
    document = geojson.loads(response.text)
    assert isinstance(document, geojson.FeatureCollection) and document.is_valid, document.errors()
    by_kind: dict[str, list[Any]] = {}
    for feature in document["features"]:
        by_kind.setdefault(feature["properties"]["kind"], []).append(feature)
    finds = {f["properties"]["candidate_id"]: f for f in by_kind["find"]}
    assert sorted(finds) == ["c-17", "c-9"]  # once each, however often reported
    vehicle_find = finds["c-17"]
    assert vehicle_find["geometry"]["coordinates"] == [FIND["position"][1], FIND["position"][0]]  # [lon, lat]
    expected = {
        "sigma_m": 2.5, "confirmed_by": "gcs", "prompt": FIND["prompt"], "time": "2024-11-21T14:40:00Z",
        "seen_at": "2024-11-21T14:39:15Z", "vehicle_id": "drone-1", "mission_id": "m-7",
    }  # fmt: skip
    assert {k: vehicle_find["properties"][k] for k in expected} == expected
    page_find = finds["c-9"]["properties"]
    assert page_find["confirmed_by"] == "supervisor page" and page_find["sigma_m"] is None
    assert page_find["seen_at"] == "2024-11-21T14:39:50Z"  # made at the page's confirm, from the candidate
    (track,) = by_kind["track"]
    assert track["geometry"]["type"] == "LineString" and len(track["geometry"]["coordinates"]) == 6
    (area,) = by_kind["search_area"]
    ring = area["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1] and len(ring) == 5  # closed
    signed = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(ring, ring[1:], strict=False))
    assert signed > 0  # RFC 7946: exterior rings counter-clockwise
    (covered,) = by_kind["covered"]
    assert covered["geometry"]["type"] == "MultiPolygon" and covered["properties"][
        "coverage"
    ] == pytest.approx(0.5)


def test_kml_download_holds_finds_track_and_areas(client_factory: Any) -> None:
    client = client_factory()
    _fly_and_find(client)
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    response = client.get("/v1/missions/m-7/finds.kml", headers=supervisor)
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("application/vnd.google-earth.kml+xml")
    document = kml.KML.from_string(response.content)
    placemarks: dict[str, Any] = {}

    def walk(feature: Any) -> None:
        for child in getattr(feature, "features", []) or []:
            if type(child).__name__ == "Placemark":
                placemarks[child.name] = child
            walk(child)

    walk(document)
    found = {name: p for name, p in placemarks.items() if name.startswith("FOUND")}
    assert len(found) == 2
    points = sorted((p.geometry.x, p.geometry.y) for p in found.values())
    assert (FIND["position"][1], FIND["position"][0]) in [
        (pytest.approx(x), pytest.approx(y)) for x, y in points
    ]
    assert any(
        "confirmed by the GCS operator, as reported by drone-1" in (p.description or "")
        and "±2.5 m" in p.description
        and SEEN in p.description
        for p in found.values()
    )
    assert len(placemarks["drone-1 track"].geometry.coords) == 6
    assert len(placemarks["drone-1 search area"].geometry.exterior.coords) == 5


def _vehicle_find(client: TestClient, candidate: str = "c-17") -> None:
    body = {
        "mission_id": "m-7",
        "state": "CONFIRMED",
        "prompt": FIND["prompt"],
        "find": {**FIND, "candidate_id": candidate},
    }
    assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=body).status_code == 200


def _assert_find_event(message: Any, candidate: str = "c-17") -> None:
    event = message.cotEvent
    assert event.type == COT_TYPE and event.uid == f"cloudtrack-find-drone-1-m-7-{candidate}"
    assert (event.lat, event.lon) == (
        pytest.approx(FIND["position"][0], abs=1e-7),
        pytest.approx(FIND["position"][1], abs=1e-7),
    )
    assert event.ce == pytest.approx(2.5)
    assert event.detail.contact.callsign == f"FOUND: {FIND['prompt']}"
    assert "confirmed by the GCS operator, as reported by drone-1" in event.detail.xmlDetail
    assert SEEN in event.detail.xmlDetail  # the rescuers' map says how old the position is


@pytest.mark.parametrize("kind", ["tcp", "udp"])
def test_cursor_on_target_find_reaches_a_tak_server(client_factory: Any, kind: str) -> None:
    with TakStandIn(kind) as tak:
        client = client_factory(f'tak.url="{tak.url}"')
        _vehicle_find(client)
        _vehicle_find(client)  # reported again with the next status: sent once
        (message,) = tak.messages(1)
        _assert_find_event(message)
        time.sleep(0.5)
        assert len(tak.received) == 1


def _openssl(*args: str) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=60)


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA, a server certificate for 127.0.0.1 and a client certificate, as a TAK server's admin makes."""
    folder = tmp_path_factory.mktemp("tak-tls")
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=test-ca",
             "-keyout", str(folder / "ca.key"), "-out", str(folder / "ca.pem"))  # fmt: skip
    (folder / "server.ext").write_text("subjectAltName=IP:127.0.0.1\n")
    for name in ("server", "client"):
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={name}",
                 "-keyout", str(folder / f"{name}.key"), "-out", str(folder / f"{name}.csr"))  # fmt: skip
        extra = ["-extfile", str(folder / "server.ext")] if name == "server" else []
        _openssl("x509", "-req", "-in", str(folder / f"{name}.csr"), "-CA", str(folder / "ca.pem"),
                 "-CAkey", str(folder / "ca.key"), "-CAcreateserial", "-days", "2",
                 "-out", str(folder / f"{name}.pem"), *extra)  # fmt: skip
    return folder


def test_cursor_on_target_find_reaches_a_tak_server_over_tls_with_a_client_certificate(
    client_factory: Any, certificates: Path
) -> None:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(certificates / "server.pem", certificates / "server.key")
    context.load_verify_locations(certificates / "ca.pem")
    context.verify_mode = ssl.CERT_REQUIRED  # no client certificate, no connection
    with TakStandIn("tcp", tls=context) as tak:
        url = f"tls://127.0.0.1:{tak.port}"
        client = client_factory(
            f'tak.url="{url}"',
            f'tak.tls_cert="{certificates / "client.pem"}"',
            f'tak.tls_key="{certificates / "client.key"}"',
            f'tak.tls_ca="{certificates / "ca.pem"}"',
        )
        _vehicle_find(client)
        (message,) = tak.messages(1)
        _assert_find_event(message)


def test_cursor_on_target_sender_keeps_a_find_until_the_server_answers() -> None:
    """The TAK server is down when the find is made: it is delivered once the server is up."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    report = FindReport("c-1", 47.0, 8.0, None, 1.0, "a red jacket", "gcs", "drone-1", "m-1")
    sender = CotSender(f"tcp://127.0.0.1:{port}", retry_s=0.2).start()
    try:
        sender.send(find_event(report))
        time.sleep(0.6)
        assert sender.pending() == 1 and "connect call failed" in sender.last_error.lower()
        tak = TakStandIn("tcp")
        tak._sock.close()
        tak._sock = socket.socket()
        tak._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        tak._sock.bind(("127.0.0.1", port))
        tak.port = port
        with tak:
            (message,) = tak.messages(1)
            assert message.cotEvent.uid == find_uid(report) and message.cotEvent.ce == pytest.approx(
                9999999.0
            )
    finally:
        sender.close()
    assert sender.pending() == 0


def test_cursor_on_target_event_is_what_takproto_reads() -> None:
    report = FindReport(
        "c-2",
        -33.8568,
        151.2153,
        4.0,
        1732200000.0,
        "a child in a yellow raincoat",
        "supervisor page",
        "drone-2",
        "m-9",
    )
    message = takproto.parse_proto(bytearray(find_event(report, callsign="Team Alpha", stale_s=600)))
    event = message.cotEvent
    assert (event.lat, event.lon, event.ce) == (pytest.approx(-33.8568), pytest.approx(151.2153), 4.0)
    assert event.how == "h-e" and event.staleTime - event.startTime == 600_000
    assert "Team Alpha" in event.detail.xmlDetail and "2024-11-21 14:40:00 UTC" in event.detail.xmlDetail
    assert "when the position was seen is not known" in event.detail.xmlDetail
    json.dumps(str(message))  # printable


@pytest.mark.parametrize(
    ("seen_at", "text"),
    [
        (None, "when the position was seen is not known"),
        (float("nan"), "when the position was seen is not known"),
        (-float("inf"), "when the position was seen is not known"),
        (1732200000.0, "position as seen at 14:40:00 UTC, at the confirmation"),
        (1732199999.5, "position as seen at 14:39:59 UTC, at the confirmation"),
        (1732199955.0, "position as seen at 14:39:15 UTC, 45 s before the confirmation"),
        (1732199881.0, "position as seen at 14:38:01 UTC, 119 s before the confirmation"),
        (1732199700.0, "position as seen at 14:35:00 UTC, 5 min before the confirmation"),
        (1732200030.0, "position as seen at 14:40:30 UTC, 30 s after the confirmation"),
    ],
)
def test_a_find_says_how_old_its_position_is(seen_at: float | None, text: str) -> None:
    assert seen_text(1732200000.0, seen_at) == text
