"""ASGI middleware bounding the work of every request before anything parses or validates it.

In this order, each step refusing with a short JSON answer:
0. One header parse for every layer: a header that takes one value (`SINGLE_VALUED`: Authorization,
   Content-Type, Content-Length, Host) sent twice -> 400, so the limits here, the quota and the route
   can never read two different values of it (Starlette reads the first, a dict of the list the last).
1. The route's body limit (`route_limit`): a declared Content-Length over it -> 413 at once.
2. Who is calling (/v1/ routes): a missing or unknown bearer token -> 401; a vehicle over its request-rate
   quota -> 429 with Retry-After. Counted here, before the body is read: a request that later fails
   validation still counts, so a flood of invalid posts is cut like any other.
3. The body, read within `timeout_s` of the request's start (a client that stalls gets 408 and the
   connection is closed) and counted as it arrives (413 beyond the route's limit, chunked too).
4. Its shape, before FastAPI parses it: on a route that takes JSON, any body but a multipart one is
   bounded as JSON whatever its Content-Type says (one that is not JSON passes to the validator), so no
   spelling of the header lets a body skip the limits: more values, more keys in one object or deeper
   nesting than `JsonLimits` allows -> 413; a multipart body with more parts than the route takes -> 413.
   The counts are made on the bytes first (C-speed), so a refused body is never parsed in Python, and a
   body over `SHAPE_ON_LOOP_BYTES` is parsed for its shape on a worker thread, off the event loop.
Only then does the app see the (buffered) body. What is left for FastAPI and pydantic is bounded by the
route's limits, so no request holds the event loop for more than a few milliseconds; validation errors
are summarised by `backend.app` (the first few and how many).
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import anyio
from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from backend.auth import UnknownTokenError, principal_for
from backend.config import AuthConfig, ServerConfig, SessionConfig
from cloudtrack.api_models import CROP_B64_MAX_CHARS

# A rate check: (vehicle, now, limit, window_s) -> None within the quota, else seconds until it reopens.
RateCheck = Callable[[str, float, int, float], "float | None"]


@dataclass(frozen=True)
class JsonLimits:
    """The shape a JSON body may have. Every value counts (numbers, strings, arrays, objects...)."""

    max_values: int = 10_000  # a status at the contract's bounds holds about 2,300
    max_keys: int = 64  # in one object: no API model has more than 20 fields
    max_depth: int = 8  # containers around a value: a status's covered area is 5 deep


@dataclass(frozen=True)
class RouteLimit:
    max_bytes: int
    json: JsonLimits | None = JsonLimits()  # checked when the body is JSON
    max_parts: int = 0  # multipart bodies: most parts (0: none expected)


SMALL_BODY = 16_384  # a decision, a GET: nothing more to send
SHAPE_ON_LOOP_BYTES = 32_768  # a smaller body's shape is checked on the event loop (well under 1 ms)
# Headers a request carries once (RFC 9110): two of them would let two layers read two different values.
SINGLE_VALUED = (b"authorization", b"content-type", b"content-length", b"host")
DETECT_META = JsonLimits(max_values=100, max_keys=32, max_depth=3)  # the `meta` part of /v1/detect

# (method, path pattern, limit); the first match wins, anything else gets SMALL_BODY.
_ROUTES: tuple[tuple[str, re.Pattern[str], Callable[[ServerConfig], RouteLimit]], ...] = (
    # The keyframe and its `meta` part (image + meta: two parts, a few more for a client's extras).
    ("POST", re.compile(r"^/v1/detect$"), lambda s: RouteLimit(s.max_request_bytes, None, max_parts=4)),
    # A status carries up to two crops (the awaited candidate's and the find's) and the search areas.
    ("POST", re.compile(r"^/v1/vehicles/[^/]+/status$"),
     lambda s: RouteLimit(2 * CROP_B64_MAX_CHARS + 200_000)),
    ("POST", re.compile(r"^/v1/missions/[^/]+/rejections$"),
     lambda s: RouteLimit(CROP_B64_MAX_CHARS + 20_000)),
)  # fmt: skip


def route_limit(method: str, path: str, server: ServerConfig | None = None) -> RouteLimit:
    """The body limit of one route (SMALL_BODY for every route without a larger one)."""
    server = server or ServerConfig()
    for route_method, pattern, limit in _ROUTES:
        if method == route_method and pattern.match(path):
            return limit(server)
    return RouteLimit(SMALL_BODY)


def json_shape_problem(body: bytes | str, limits: JsonLimits) -> str | None:
    """What is wrong with the shape of this JSON text (too many values or keys, too deep), or None.

    Invalid JSON is not a shape problem (None): the validator answers it. A cheap upper bound on the
    values (separators and brackets, counted in C) refuses a large document before it is parsed."""
    data = body.encode() if isinstance(body, str) else body
    upper = data.count(b",") + data.count(b"[") + data.count(b"{") + 1
    if upper > 2 * limits.max_values + 2:  # commas inside strings count too: bound it loosely
        return f"the JSON document holds more than {limits.max_values} values"
    try:
        document = json.loads(data)
    except RecursionError:
        return f"the JSON document is nested deeper than {limits.max_depth} levels"
    except ValueError:
        return None
    values = 0
    pending: list[tuple[Any, int]] = [(document, 0)]
    while pending:
        item, depth = pending.pop()
        values += 1
        if values > limits.max_values:
            return f"the JSON document holds more than {limits.max_values} values"
        if isinstance(item, (dict, list)):
            if depth >= limits.max_depth:
                return f"the JSON document is nested deeper than {limits.max_depth} levels"
            if isinstance(item, dict):
                if len(item) > limits.max_keys:
                    return f"a JSON object holds more than {limits.max_keys} keys"
                pending.extend((v, depth + 1) for v in item.values())
            else:
                pending.extend((v, depth + 1) for v in item)
    return None


def request_headers(scope: Scope) -> dict[bytes, bytes] | str:
    """The request's headers by lower-case name, read once for every layer; a one-line problem instead when
    a header of `SINGLE_VALUED` comes twice."""
    found: dict[bytes, bytes] = {}
    for name, value in scope.get("headers") or []:
        key = bytes(name).lower()
        if key in found:
            if key in SINGLE_VALUED:
                return f"the request carries more than one {key.decode('latin-1')} header; send it once"
            continue  # the first, as Starlette's Headers.get reads it
        found[key] = bytes(value)
    return found


def _multipart_parts(body: bytes, content_type: bytes) -> int:
    boundary = re.search(rb"boundary=\"?([^\";]+)", content_type)
    return body.count(b"--" + boundary.group(1)) - 1 if boundary else 0


class RequestLimits:
    def __init__(
        self,
        app: ASGIApp,
        server: ServerConfig,
        auth: AuthConfig,
        sessions: SessionConfig,
        rate_hit: RateCheck,
        on_refused: Callable[[str, str], None] | None = None,
        on_admitted: Callable[[str], None] | None = None,
    ) -> None:
        """`on_refused(path, detail)` hears each well-formed bearer token that matches nobody (a vehicle's
        wrong or rotated token: the supervisor's view shows a vehicle that cannot report); a missing or
        malformed header is nobody's credential and is not told. `on_admitted(vehicle_id)` hears each
        request a vehicle's token was accepted for (its alarm, if any, is over)."""
        self.on_refused = on_refused
        self.on_admitted = on_admitted
        self.app = app
        self.server = server
        self.auth = auth
        self.sessions = sessions
        self.rate_hit = rate_hit

    async def _refuse(
        self, send: Send, status: int, detail: str, headers: dict[str, str] | None = None
    ) -> None:
        body = json.dumps({"detail": detail}).encode()
        extra = [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    *extra,
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})

    async def _admitted(self, scope: Scope, headers: dict[bytes, bytes], send: Send) -> bool:
        """Authentication and the vehicle's rate quota, from the headers alone."""
        raw = headers.get(b"authorization")
        try:
            principal = principal_for(self.auth, raw.decode("latin-1") if raw is not None else None)
        except HTTPException as exc:
            if isinstance(exc, UnknownTokenError) and self.on_refused is not None:
                self.on_refused(scope["path"], str(exc.detail))
            await self._refuse(send, exc.status_code, str(exc.detail), dict(exc.headers or {}))
            return False
        if principal.vehicle_id is None:
            return True  # the supervisor has no rate quota
        if self.on_admitted is not None:
            self.on_admitted(principal.vehicle_id)
        s = self.sessions
        wait = await anyio.to_thread.run_sync(
            self.rate_hit, principal.vehicle_id, time.time(), s.rate_limit_requests, s.rate_limit_window_s
        )
        if wait is None:
            return True
        retry = max(1, int(-(-wait // 1)))
        await self._refuse(
            send,
            429,
            f"vehicle {principal.vehicle_id!r} sent more than {s.rate_limit_requests} requests in "
            f"{s.rate_limit_window_s:g} s",
            {"Retry-After": str(retry)},
        )
        return False

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = request_headers(scope)
        if isinstance(headers, str):
            await self._refuse(send, 400, headers, {"Connection": "close"})
            return
        limit = route_limit(scope["method"], scope["path"], self.server)
        too_large = f"request body exceeds the limit of {limit.max_bytes} bytes for this route"
        declared = headers.get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit.max_bytes):
            await self._refuse(send, 413, too_large, {"Connection": "close"})
            return
        if scope["path"].startswith("/v1/") and not await self._admitted(scope, headers, send):
            return
        deadline = time.monotonic() + self.server.body_timeout_s
        chunks: list[bytes] = []
        received = 0
        more = True
        while more:
            try:
                message = await asyncio.wait_for(receive(), max(0.0, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                await self._refuse(
                    send,
                    408,
                    f"the request body did not arrive within {self.server.body_timeout_s:g} s",
                    {"Connection": "close"},
                )
                return
            if message["type"] != "http.request":
                return  # the client went away
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > limit.max_bytes:
                await self._refuse(send, 413, too_large, {"Connection": "close"})
                return
            chunks.append(chunk)
            more = message.get("more_body", False)
        body = b"".join(chunks)
        content_type = headers.get(b"content-type", b"")
        if len(body) > SHAPE_ON_LOOP_BYTES and limit.json is not None:  # a JSON parse: off the loop
            problem = await anyio.to_thread.run_sync(self._shape_problem, body, content_type, limit)
        else:
            problem = self._shape_problem(body, content_type, limit)
        if problem is not None:
            await self._refuse(send, 413, problem)
            return
        await self.app(scope, _replay(body, receive), send)

    @staticmethod
    def _shape_problem(body: bytes, content_type: bytes, limit: RouteLimit) -> str | None:
        if not body:
            return None
        kind = content_type.split(b";")[0].strip().lower()
        if kind == b"multipart/form-data":
            parts = _multipart_parts(body, content_type)
            if parts > limit.max_parts:
                return f"the multipart body holds {parts} parts; this route takes at most {limit.max_parts}"
            return None
        # Any other body of a JSON route is bounded as JSON: which types FastAPI parses is its business.
        return json_shape_problem(body, limit.json) if limit.json is not None else None


def _replay(body: bytes, receive: Receive) -> Receive:
    """The buffered body as one message, then whatever the client sends next (its disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay
