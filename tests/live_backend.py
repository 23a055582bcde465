"""The real back-end (`backend.app.create_app`) served by uvicorn on a loopback port, for end-to-end tests."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import uvicorn

from backend.app import create_app
from backend.config import (
    AuthConfig,
    BackendConfig,
    DetectorConfig,
    FleetConfig,
    SessionConfig,
    VerifierConfig,
)

SUPERVISOR_TOKEN = "supervisor-test-token"
VEHICLE_TOKENS = {"drone-1": "drone-1-test-token", "drone-2": "drone-2-test-token"}


@dataclass(frozen=True)
class LiveBackend:
    url: str
    app: object  # the FastAPI app, for its `state.sessions`


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def serve(app: object, port: int | None = None) -> Iterator[str]:
    """Any ASGI app on a loopback port (`port`, else a free one), served by uvicorn in a thread; yields its
    base URL. Served again on the same port, the same app is a back-end that went away and came back."""
    port = port or free_port()
    # A short graceful-shutdown timeout: an open Server-Sent Event stream must not hold the test up.
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", timeout_graceful_shutdown=1)  # type: ignore[arg-type]
    )
    thread = threading.Thread(target=server.run, name="live-backend", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the back-end did not start")
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=15)


@contextmanager
def live_backend(
    models_dir: Path, verifier: str = "none", dropout_s: float | None = None
) -> Iterator[LiveBackend]:
    """The back-end with YOLOX-nano from the shared models, the test tokens and `verifier` ("local": the
    colour verifier that runs here; "none": detector only); `dropout_s`: [fleet] dropout_s (None: default)."""
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        verifier=VerifierConfig(kind=verifier),
        sessions=SessionConfig(sqlite_path=":memory:"),
        **({} if dropout_s is None else {"fleet": FleetConfig(dropout_s=dropout_s)}),
    )
    app = create_app(config)
    with serve(app) as url:
        yield LiveBackend(url, app)
