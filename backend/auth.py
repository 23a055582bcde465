"""Bearer tokens: one per vehicle and one for the supervisor, all from configuration.

Missing or unknown token -> 401; a valid token used for another vehicle's data -> 403. Tokens are
compared in constant time. FastAPI dependencies for routes: `authenticated`, `require_supervisor`.
They read the token through FastAPI's `HTTPBearer`, so the OpenAPI schema declares the bearer scheme and
/docs has an Authorize button; the 401 answers stay the service's own (auto_error=False).
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from backend.config import AuthConfig

CHALLENGE = {"WWW-Authenticate": "Bearer"}
bearer = HTTPBearer(
    auto_error=False,
    scheme_name="bearer",
    description="A vehicle's token (auth.tokens) or the supervisor's (auth.supervisor_token).",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


@dataclass(frozen=True)
class Principal:
    vehicle_id: str | None  # None for the supervisor

    @property
    def is_supervisor(self) -> bool:
        return self.vehicle_id is None

    def may_act_for(self, vehicle_id: str) -> bool:
        return self.is_supervisor or self.vehicle_id == vehicle_id


def principal_for(auth: AuthConfig, authorization: str | None) -> Principal:
    """Who presents this Authorization header; HTTPException(401) when nobody does."""
    if not authorization:
        raise HTTPException(401, "missing bearer token (Authorization: Bearer <token>)", headers=CHALLENGE)
    scheme, _, token = authorization.partition(" ")
    token = token.strip()
    if scheme.lower() != "bearer" or not token:
        raise HTTPException(401, "malformed Authorization header; expected 'Bearer <token>'", headers=CHALLENGE)
    match: Principal | None = None
    for vehicle_id, expected in auth.tokens.items():
        if expected and hmac.compare_digest(token.encode(), expected.encode()):
            match = Principal(vehicle_id)
    if auth.supervisor_token and hmac.compare_digest(token.encode(), auth.supervisor_token.encode()):
        match = Principal(None)
    if match is None:
        raise HTTPException(401, "invalid bearer token", headers=CHALLENGE)
    return match


def authenticated(request: Request, _credentials: Credentials) -> Principal:
    # The header is parsed here, not from `_credentials`, so that a malformed one gets this module's answer.
    return principal_for(request.app.state.config.auth, request.headers.get("authorization"))


def require_supervisor(request: Request, credentials: Credentials) -> Principal:
    principal = authenticated(request, credentials)
    if not principal.is_supervisor:
        raise HTTPException(403, "this endpoint needs the supervisor token")
    return principal


def require_vehicle_access(principal: Principal, vehicle_id: str) -> None:
    if not principal.may_act_for(vehicle_id):
        raise HTTPException(403, f"this token is not valid for vehicle {vehicle_id!r}")
