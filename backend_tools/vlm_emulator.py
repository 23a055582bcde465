"""EMULATOR - not a VLM. An OpenAI-compatible chat-completions server on loopback for tests and bench.

It speaks the real protocol (`POST /v1/chat/completions` with a base64 `image_url` part, `GET
/v1/models`), waits a fixed latency L per request (many requests wait at once, like a batching VLM
server), and answers from the local colour verifier run on the image it was sent, so its answers follow
the pixels rather than a script. Modes for tests: "pixels" (default), "garbage" (unparseable prose),
"yes", "no"; `fail_first` makes the first n requests fail with a given HTTP status (retry tests).
"""

from __future__ import annotations

import base64
import json
import re
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from types import TracebackType
from typing import Any

import cv2
import numpy as np

from backend.verifiers.attributes import AttributeVerifier
from backend.verifiers.interface import VerifierAnswer
from behaviors.detection import Verdict

MODEL_NAME = "cloudtrack-vlm-emulator"


def answer_for(image_bgr: np.ndarray | None, text: str, mode: str) -> str:
    """The emulated model's reply to one task text and image."""
    if mode == "garbage":
        return "The quick brown fox considers the image thoughtfully and declines to commit either way."
    if mode in ("yes", "no"):
        return f"Emulated fixed answer.\nAnswer: {mode.capitalize()}."
    quoted = re.findall(r'"([^"]+)"', text)
    description = quoted[0] if quoted else text
    if image_bgr is None:
        return "I received no image.\nAnswer: No."
    h, w = image_bgr.shape[:2]
    # The crop carries the candidate in the middle with the pipeline's 50 px context margin around it.
    mx, my = min(50.0, 0.25 * w), min(50.0, 0.25 * h)
    answer: VerifierAnswer = AttributeVerifier().verify(
        image_bgr, (mx, my, w - 2 * mx, h - 2 * my), description, "person"
    )
    # "If in doubt, rather say yes", as the prompt asks.
    word = "No" if answer.verdict is Verdict.NO else "Yes"
    return f"Emulated from pixels: {answer.justification}.\nAnswer: {word}."


def _image_from(messages: list[Any]) -> tuple[np.ndarray | None, str]:
    text, image = "", None
    for message in messages:
        content = message.get("content") if isinstance(message, dict) else None
        parts = content if isinstance(content, list) else [{"type": "text", "text": content or ""}]
        for part in parts:
            if not isinstance(part, dict):
                continue
            if part.get("type") == "text":
                text += str(part.get("text", "")) + "\n"
            elif part.get("type") == "image_url":
                url = str((part.get("image_url") or {}).get("url", ""))
                if url.startswith("data:") and "," in url:
                    data = base64.b64decode(url.split(",", 1)[1])
                    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return image, text


class _QuietServer(ThreadingHTTPServer):
    def handle_error(self, request: Any, client_address: Any) -> None:
        # A client that went away (a back-end replica killed mid-request) is not an emulator error.
        if not isinstance(sys.exc_info()[1], ConnectionError):
            super().handle_error(request, client_address)


class VlmEmulator:
    """with VlmEmulator(latency_s=1.0) as vlm: ... base_url = vlm.base_url ..."""

    def __init__(
        self,
        latency_s: float = 0.0,
        mode: str = "pixels",
        fail_first: int = 0,
        fail_status: int = 503,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        self.latency_s = latency_s
        self.mode = mode
        self.fail_first = fail_first
        self.fail_status = fail_status
        self.requests = 0
        self.max_in_flight = 0
        self._in_flight = 0
        self._lock = threading.Lock()
        emulator = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args: Any) -> None:  # quiet: tests and bench print their own figures
                pass

            def _send(self, status: int, payload: dict[str, Any]) -> None:
                body = json.dumps(payload).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self) -> None:
                if self.path.rstrip("/").endswith("/models"):
                    self._send(200, {"object": "list", "data": [{"id": MODEL_NAME, "object": "model"}]})
                else:
                    self._send(404, {"error": {"message": "not found"}})

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length") or 0)
                raw = self.rfile.read(length)
                if not self.path.rstrip("/").endswith("/chat/completions"):
                    self._send(404, {"error": {"message": "not found"}})
                    return
                with emulator._lock:
                    emulator.requests += 1
                    number = emulator.requests
                    emulator._in_flight += 1
                    emulator.max_in_flight = max(emulator.max_in_flight, emulator._in_flight)
                try:
                    time.sleep(emulator.latency_s)
                    if number <= emulator.fail_first:
                        self._send(emulator.fail_status, {"error": {"message": "emulated failure"}})
                        return
                    try:
                        request = json.loads(raw)
                        image, text = _image_from(request["messages"])
                    except (ValueError, KeyError, TypeError):
                        self._send(400, {"error": {"message": "malformed chat-completions request"}})
                        return
                    reply = answer_for(image, text, emulator.mode)
                    self._send(200, {
                        "id": f"emulated-{number}", "object": "chat.completion", "created": int(time.time()),
                        "model": request.get("model", MODEL_NAME),
                        "choices": [{"index": 0, "finish_reason": "stop", "message": {"role": "assistant", "content": reply}}],
                        "usage": {"prompt_tokens": 0, "completion_tokens": 0, "total_tokens": 0},
                    })  # fmt: skip
                finally:
                    with emulator._lock:
                        emulator._in_flight -= 1

        self._server = _QuietServer((host, port), Handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, name="vlm-emulator", daemon=True)
        bound_host, bound_port = self._server.server_address[:2]
        self.base_url = f"http://{bound_host!s}:{bound_port}/v1"

    def start(self) -> VlmEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> VlmEmulator:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
