"""Running the app under uvicorn: in the foreground (`serve`) or on a background thread (bench, tests).

uvicorn bounds a body's time (backend.request_limits) and an idle kept-alive connection (5 s), but not
the request line and headers: a client trickling one header line every few seconds held its connection
for as long as it liked (90 such clients, none closed after 30 s). `header_timeout_protocol` is uvicorn's
own h11 protocol with that deadline added: `[server] header_timeout_s` after the connection opens, or
after the previous answer on a kept-alive one, a request whose headers are not complete is answered 408
and the connection closed. In deployment nginx in front does the same (`client_header_timeout`,
docs/backend.md).
"""

from __future__ import annotations

import asyncio
import threading
import time
from types import TracebackType
from typing import Any

import h11
import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.h11_impl import H11Protocol

_LATE = b"HTTP/1.1 408 Request Timeout\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"


class _HeaderDeadline(H11Protocol):
    header_timeout_s = 10.0

    _header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._watch_headers()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._watch_headers()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._watch_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_timer()
        super().connection_lost(exc)

    def _watch_headers(self) -> None:
        """Armed while the next request's headers are awaited (h11's IDLE), from then on, never re-armed
        by a trickle of bytes; cancelled once they are complete."""
        waiting = self.conn.their_state is h11.IDLE and not self.transport.is_closing()
        if not waiting:
            self._stop_timer()
        elif self._header_timer is None:
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)

    def _stop_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.write(_LATE)
            self.transport.close()


def header_timeout_protocol(timeout_s: float) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a deadline for the request line and headers (`http=` of uvicorn)."""
    return type("HeaderDeadlineH11Protocol", (_HeaderDeadline,), {"header_timeout_s": timeout_s})


def _header_timeout(app: FastAPI) -> float:
    config: Any = getattr(app.state, "config", None)
    return float(config.server.header_timeout_s) if config is not None else 10.0


def serve(app: FastAPI, host: str, port: int, log_level: str = "info") -> None:
    """Serve until interrupted. TLS is the reverse proxy's job (docs/backend.md)."""
    uvicorn.run(
        app,
        host=host,
        port=port,
        log_level=log_level.lower(),
        proxy_headers=True,
        server_header=False,
        http=header_timeout_protocol(_header_timeout(app)),
    )


class BackgroundServer:
    """A real uvicorn server on a loopback port in a daemon thread; `url` once started.

    with BackgroundServer(app) as server:
        requests.get(server.url + "/health")
    """

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", port: int = 0) -> None:
        config = uvicorn.Config(
            app,
            host=host,
            port=port,
            log_level="warning",
            lifespan="on",
            server_header=False,
            http=header_timeout_protocol(_header_timeout(app)),
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="uvicorn", daemon=True)
        self.url = ""

    def start(self, timeout_s: float = 20.0) -> BackgroundServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the back-end server did not start")
            time.sleep(0.02)
        host, port = self._server.servers[0].sockets[0].getsockname()[:2]
        self.url = f"http://{host}:{port}"
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=10)

    def __enter__(self) -> BackgroundServer:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
