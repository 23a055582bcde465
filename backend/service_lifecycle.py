"""The back-end's side of systemd's `Type=notify` (config/cloudtrack-backend.service), as a router lifespan.

READY=1 once the app is built (detector and verifier loaded) and uvicorn starts serving it; WATCHDOG=1 from
a task on the server's event loop, so a blocked loop stops the pings and systemd restarts the service;
STOPPING=1 when uvicorn shuts down. Outside systemd (no NOTIFY_SOCKET) it does nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter

from cloudtrack.service_notify import ServiceNotifier, ping_while_healthy


def lifecycle_router(notifier: ServiceNotifier | None = None) -> APIRouter:
    """No routes, only a lifespan; `app.include_router(lifecycle_router())` merges it into the app's."""

    @contextlib.asynccontextmanager
    async def lifespan(_app: Any) -> AsyncIterator[None]:
        service = notifier or ServiceNotifier.from_environment()
        service.ready("serving")
        pinger = asyncio.create_task(ping_while_healthy(service))
        try:
            yield
        finally:
            service.stopping("shutting down")
            pinger.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await pinger
            service.close()

    return APIRouter(lifespan=lifespan)
