"""Issue 44 items 3 and 5, against a real server on loopback (select: -k hostile).

3. Every layer reads one value of a header: a request carrying a single-valued header twice (Content-Type,
   Authorization, Content-Length, Host) is refused with 400 before its body is read, and a JSON route
   bounds the shape of any body it could parse as JSON, whatever its Content-Type says.
5. The page's "token refused" alarm is raised only by a request that presented a bearer token on a vehicle's
   own route and was refused it; no token, a malformed header, a route that does not exist or another
   vehicle's valid token raise nothing, and the vehicle's next accepted request clears it.
"""

from __future__ import annotations

import contextlib
import json
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
import requests

from backend.app import create_app
from backend.serving import BackgroundServer
from tests.backend_fixtures import SUPERVISOR, TOKENS, backend_config

SUP = {"Authorization": f"Bearer {SUPERVISOR}"}


@pytest.fixture(scope="module")
def server(models_dir: Path) -> Iterator[BackgroundServer]:
    app = create_app(backend_config(models_dir, "sessions.rate_limit_requests=100000"))
    with BackgroundServer(app) as running:
        yield running


def _raw(server: BackgroundServer, head: list[tuple[str, str]], body: bytes, path: str) -> tuple[int, bytes]:
    """One POST with exactly these header lines (repeats kept), over a socket: the status code and body."""
    port = int(server.url.rsplit(":", 1)[1])
    lines = [f"POST {path} HTTP/1.1", "Host: 127.0.0.1", "Connection: close"]
    lines += [f"{name}: {value}" for name, value in head]
    lines.append(f"Content-Length: {len(body)}")
    answer = b""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as conn:
        conn.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        with contextlib.suppress(OSError):  # refused from its headers: answered, closed on the body
            conn.sendall(body)
        try:
            while chunk := conn.recv(65536):
                answer += chunk
        except ConnectionResetError:
            pass  # the close, after the answer, of a connection whose body the server did not read
    status_line, _, rest = answer.partition(b"\r\n")
    return int(status_line.split()[1]), rest.partition(b"\r\n\r\n")[2]


STATUS = "/v1/vehicles/drone-1/status"
SIXTY_THOUSAND_KEYS = json.dumps({"state": "SEARCH", **{f"k{i}": 0 for i in range(60_000)}}).encode()


@pytest.mark.parametrize(
    "content_types",
    [("application/json", "text/plain"), ("text/plain", "application/json")],
    ids=["json-then-text", "text-then-json"],
)
def test_hostile_a_duplicate_content_type_is_refused_before_the_body(
    server: BackgroundServer, content_types: tuple[str, str]
) -> None:
    """The issue's input: 60,000 keys with two Content-Type headers (the limits read one, the route the other)."""
    head = [("Authorization", f"Bearer {TOKENS['drone-1']}"), *(("Content-Type", t) for t in content_types)]
    code, body = _raw(server, head, SIXTY_THOUSAND_KEYS, STATUS)
    assert code == 400, body[:300]
    detail = json.loads(body)["detail"]
    assert "content-type" in detail.lower() and "\n" not in detail, detail


def test_hostile_a_duplicate_authorization_is_refused(server: BackgroundServer) -> None:
    """Two tokens: the quota would count one vehicle while the route acts as the other."""
    head = [
        ("Authorization", f"Bearer {TOKENS['drone-2']}"),
        ("Authorization", f"Bearer {TOKENS['drone-1']}"),
        ("Content-Type", "application/json"),
    ]
    code, body = _raw(server, head, json.dumps({"state": "SEARCH"}).encode(), STATUS)
    assert code == 400, body[:300]
    assert "authorization" in json.loads(body)["detail"].lower()


def test_hostile_a_json_route_bounds_a_body_whatever_its_content_type(server: BackgroundServer) -> None:
    """One Content-Type that the limits and the route might read apart ("text/plain" with JSON inside, an
    odd spelling of JSON): the shape is bounded all the same, and a valid status still goes through."""
    auth = [("Authorization", f"Bearer {TOKENS['drone-1']}")]
    for content_type in ("text/plain", "application/JSON; charset=utf-8", "application/x-anything+json"):
        code, body = _raw(server, [*auth, ("Content-Type", content_type)], SIXTY_THOUSAND_KEYS, STATUS)
        assert code == 413, (content_type, code, body[:200])
    code, body = _raw(server, [*auth, ("Content-Type", "application/json")], b'{"state": "SEARCH"}', STATUS)
    assert code == 200, body[:300]


# Item 5: the "token refused" alarm


def _auth_error(server: BackgroundServer, vehicle: str) -> str | None:
    snapshot = requests.get(f"{server.url}/supervisor/api/state", headers=SUP, timeout=10).json()
    found = [v for v in snapshot["vehicles"] if v["id"] == vehicle]
    return found[0]["auth_error"] if found else None


def test_hostile_only_a_refused_token_on_the_vehicles_own_route_raises_the_alarm(
    server: BackgroundServer,
) -> None:
    vehicle = "drone-2"
    status = f"{server.url}/v1/vehicles/{vehicle}/status"
    for path, headers in (
        (f"/v1/vehicles/{vehicle}/anything", {}),  # the input: no token, a route that does not exist
        (f"/v1/vehicles/{vehicle}/status", {}),  # no token at all
        (f"/v1/vehicles/{vehicle}/status", {"Authorization": "Basic dXNlcjpwdw=="}),  # not a bearer token
        (f"/v1/vehicles/{vehicle}/anything", {"Authorization": "Bearer wrong-token"}),  # no such route
        (f"/v1/vehicles/{vehicle}/status", {"Authorization": f"Bearer {TOKENS['drone-1']}"}),  # another's
    ):
        answer = requests.get(server.url + path, headers=headers, timeout=10)
        assert answer.status_code in (401, 403, 404), (path, answer.status_code)
        assert _auth_error(server, vehicle) is None, (path, headers)
    # The vehicle's own route with a bearer token the back-end does not know (a wrong or rotated one).
    refused = requests.post(
        status, json={"state": "SEARCH"}, headers={"Authorization": "Bearer old"}, timeout=10
    )
    assert refused.status_code == 401
    assert "refused" in (_auth_error(server, vehicle) or "")
    # Its next accepted request clears it: the vehicle reports, so its token is not what is wrong.
    accepted = requests.post(
        status, json={"state": "SEARCH"}, headers={"Authorization": f"Bearer {TOKENS[vehicle]}"}, timeout=10
    )
    assert accepted.status_code == 200
    assert _auth_error(server, vehicle) is None
