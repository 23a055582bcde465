"""Bearer tokens: one per vehicle and one for the supervisor, all from configuration.

Missing or unknown token -> 401; a valid token used for another vehicle's data -> 403. Tokens are
compared in constant time. The routes get the caller through `backend.dependencies` (`Caller`,
`SupervisorCaller`), which reads the Authorization header and asks `principal_for` here.
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass

from fastapi import HTTPException

from backend.config import AuthConfig

CHALLENGE = {"WWW-Authenticate": "Bearer"}


class UnknownTokenError(HTTPException):
    """401 for a well-formed bearer token that matches nobody's (a wrong or rotated one), told apart from a
    missing or malformed header: only this one can be a vehicle's own credentials gone wrong."""

    def __init__(self) -> None:
        super().__init__(401, "invalid bearer token", headers=CHALLENGE)


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
        raise HTTPException(
            401, "malformed Authorization header; expected 'Bearer <token>'", headers=CHALLENGE
        )
    match: Principal | None = None
    for vehicle_id, expected in auth.tokens.items():
        if expected and hmac.compare_digest(token.encode(), expected.encode()):
            match = Principal(vehicle_id)
    if auth.supervisor_token and hmac.compare_digest(token.encode(), auth.supervisor_token.encode()):
        match = Principal(None)
    if match is None:
        raise UnknownTokenError()
    return match


def require_vehicle_access(principal: Principal, vehicle_id: str) -> None:
    if not principal.may_act_for(vehicle_id):
        raise HTTPException(403, f"this token is not valid for vehicle {vehicle_id!r}")
